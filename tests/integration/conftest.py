"""A real ComfyUI server with this pack installed, for the integration tests.

Skipped unless ARTNVG_COMFYUI_ROOT names a ComfyUI install made by
``../shared/tools/comfyui/setup.sh GITDIR ROOT`` (ROOT holds ComfyUI/ and venv/; the
pack's dependencies must be installed into that venv). The session starts its own server
on a free port with the shared start.sh / stop.sh, so no other server may run from ROOT
meanwhile. The project is linked as ROOT/ComfyUI/custom_nodes/artnvg (created if missing),
and test inputs are written under ROOT/ComfyUI/input/artnvg_test/.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from artnvg_core.scene import read_ply, write_ply

ROOT_ENV = "ARTNVG_COMFYUI_ROOT"
REPO = Path(__file__).resolve().parents[2]
TOOLS = REPO.parent / "shared" / "tools" / "comfyui"
TEST_FOLDER = "artnvg_test"
SCENE_STRIDE = 10  # the test scene keeps every 10th Gaussian of the bear (10,000): quick CPU renders


@dataclass
class ComfyServer:
    url: str
    root: Path
    input_dir: Path
    output_dir: Path
    log: Path
    test_folder: str = TEST_FOLDER  # under input_dir: scene.ply, transforms.json, style.jpg


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _link_pack(comfy: Path) -> None:
    link = comfy / "custom_nodes" / "artnvg"
    if link.is_symlink() or link.exists():
        if link.resolve() != REPO:
            pytest.fail(f"{link} exists but is not a link to {REPO}; remove it or point it here")
    else:
        link.symlink_to(REPO, target_is_directory=True)


def _write_inputs(input_dir: Path, shared_data: Path) -> None:
    """The bear capture, its scene thinned out, and a style image under input/artnvg_test/."""
    folder = input_dir / TEST_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    bear = shared_data / "scenes" / "bear"
    scene = read_ply(bear / "scene.ply")
    write_ply(scene.select(torch.arange(0, len(scene), SCENE_STRIDE)), folder / "scene.ply")
    shutil.copyfile(bear / "transforms.json", folder / "transforms.json")
    shutil.copyfile(shared_data / "styles" / "starry.jpg", folder / "style.jpg")


@pytest.fixture(scope="session")
def comfy_server(shared_data) -> ComfyServer:
    root = os.environ.get(ROOT_ENV)
    if not root:
        pytest.skip(f"set {ROOT_ENV} to a ComfyUI install made by ../shared/tools/comfyui/setup.sh")
    root = Path(root).resolve()
    comfy = root / "ComfyUI"
    if not (comfy / "main.py").is_file() or not (root / "venv").is_dir():
        pytest.fail(f"{ROOT_ENV}={root}: expected ComfyUI/main.py and venv/ there (run setup.sh)")
    _link_pack(comfy)
    _write_inputs(comfy / "input", shared_data)
    port = _free_port()
    subprocess.run(["bash", str(TOOLS / "start.sh"), str(root), str(port)], check=True, timeout=300)
    try:
        yield ComfyServer(f"http://127.0.0.1:{port}", root, comfy / "input", comfy / "output", root / "server.log")
    finally:
        subprocess.run(["bash", str(TOOLS / "stop.sh"), str(root)], check=False, timeout=60)
