"""A real ComfyUI server with this pack installed, for the integration tests.

Skipped unless ARTNVG_COMFYUI_ROOT names a ComfyUI install: either a ComfyUI checkout (the
folder holding main.py) or a folder holding one as ComfyUI/. The server runs on the CPU with
the Python of ARTNVG_COMFYUI_PYTHON, else of a venv/ beside or inside the checkout, else the one
running the tests; the pack's dependencies must be installed there. ARTNVG_COMFYUI_FRONTEND_ROOT,
when set, names another frontend's static folder (e.g. the ``static/`` of a newer
comfyui-frontend-package), passed to ComfyUI as ``--front-end-root``. The session starts its own
server on a free port and stops it at the end (log: ROOT/artnvg_server.log). The project is
linked as ComfyUI/custom_nodes/artnvg-comfyui (unless a link to it is there already), the demo
files the pack installs are removed from the input folder first (a fresh install), and test inputs are written under
ComfyUI/input/artnvg_test/: the bundled demo (artnvg_core/demo: the bear thinned out to 10,000
Gaussians for quick CPU renders, its 24 cameras and the style image).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

from artnvg_core.formats import read_ply, write_ply
from artnvg_core.stylize import DemoInputs
from nodes.demo_inputs import demo_files

ROOT_ENV, PYTHON_ENV, FRONTEND_ENV = "ARTNVG_COMFYUI_ROOT", "ARTNVG_COMFYUI_PYTHON", "ARTNVG_COMFYUI_FRONTEND_ROOT"
REPO = Path(__file__).resolve().parents[2]
TEST_FOLDER = "artnvg_test"
TEST_GAUSSIANS = 10_000
PACK_FOLDER = "artnvg-comfyui"  # the name a clone of the repository gets


@dataclass
class ComfyServer:
    url: str
    root: Path
    input_dir: Path
    output_dir: Path
    log: Path
    pack: str  # the pack's folder name in custom_nodes (the template browser's module name)
    test_folder: str = TEST_FOLDER  # under input_dir: scene.ply, transforms.json, style.jpg


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _comfy_checkout(root: Path) -> Path:
    for candidate in (root, root / "ComfyUI"):
        if (candidate / "main.py").is_file():
            return candidate
    pytest.fail(f"{ROOT_ENV}={root}: no ComfyUI main.py there or in {root / 'ComfyUI'}")


def _python(root: Path, comfy: Path) -> str:
    if os.environ.get(PYTHON_ENV):
        return os.environ[PYTHON_ENV]
    for venv in (root / "venv", comfy / "venv", comfy / ".venv"):
        if (venv / "bin" / "python").is_file():
            return str(venv / "bin" / "python")
    return sys.executable


def _link_pack(comfy: Path) -> str:
    """The pack's folder name in custom_nodes: an existing link to this checkout, else a new ``artnvg-comfyui``."""
    folder = comfy / "custom_nodes"
    for entry in sorted(folder.iterdir()):
        if entry.is_symlink() and entry.resolve() == REPO:
            return entry.name
    link = folder / PACK_FOLDER
    if link.is_symlink() or link.exists():
        pytest.fail(f"{link} exists but is not a link to {REPO}; remove it or point it here")
    link.symlink_to(REPO, target_is_directory=True)
    return link.name


def _remove_demo_inputs(input_dir: Path) -> None:
    """A fresh install's input folder: without the demo files the pack puts there when it loads."""
    for name in demo_files():
        (input_dir / name).unlink(missing_ok=True)


def _write_inputs(input_dir: Path) -> None:
    """The demo's bear thinned out, its cameras and its style image under input/artnvg_test/."""
    folder = input_dir / TEST_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    demo = DemoInputs()
    scene = read_ply(demo.scene)
    write_ply(scene.select(slice(0, None, max(1, len(scene) // TEST_GAUSSIANS))), folder / "scene.ply")
    shutil.copyfile(demo.cameras, folder / "transforms.json")
    shutil.copyfile(demo.style, folder / "style.jpg")


def _start(python: str, comfy: Path, port: int, log: Path) -> subprocess.Popen:
    frontend = os.environ.get(FRONTEND_ENV)
    with log.open("wb") as output:
        server = subprocess.Popen([python, "main.py", "--cpu", "--listen", "127.0.0.1", "--port", str(port),
                                   *(["--front-end-root", frontend] if frontend else [])],
                                  cwd=comfy, stdout=output, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if server.poll() is not None:
            pytest.fail(f"ComfyUI exited with status {server.returncode}; see {log}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/system_stats", timeout=5):
                return server
        except OSError:
            time.sleep(0.5)
    server.terminate()
    pytest.fail(f"ComfyUI did not answer within 300 s; see {log}")


@pytest.fixture(scope="session")
def comfy_checkout() -> tuple[Path, str]:
    """(ComfyUI checkout, its Python) for tests that run ComfyUI's modules in a process of their own."""
    root = os.environ.get(ROOT_ENV)
    if not root:
        pytest.skip(f"set {ROOT_ENV} to a ComfyUI checkout (docs/comfyui.md: Integration tests)")
    root = Path(root).resolve()
    comfy = _comfy_checkout(root)
    return comfy, _python(root, comfy)


@pytest.fixture(scope="session")
def comfy_server() -> ComfyServer:
    root = os.environ.get(ROOT_ENV)
    if not root:
        pytest.skip(f"set {ROOT_ENV} to a ComfyUI checkout (docs/comfyui.md: Integration tests)")
    root = Path(root).resolve()
    comfy = _comfy_checkout(root)
    pack = _link_pack(comfy)
    _remove_demo_inputs(comfy / "input")
    _write_inputs(comfy / "input")
    port, log = _free_port(), root / "artnvg_server.log"
    server = _start(_python(root, comfy), comfy, port, log)
    try:
        yield ComfyServer(f"http://127.0.0.1:{port}", root, comfy / "input", comfy / "output", log, pack)
    finally:
        server.terminate()
        try:
            server.wait(timeout=60)
        except subprocess.TimeoutExpired:
            server.kill()
