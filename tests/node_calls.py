"""Nodes called as ComfyUI calls them, and the shared bear scene the node tests run them on.

:func:`call` runs a node's function under ``torch.inference_mode()``, as ComfyUI runs every node. The
fixtures (import them by name): ``bear`` (the shared bear capture: its folder, scene and cameras),
``small_bear`` (every 25th of its Gaussians: renders stay fast on a CPU) and ``comfy_dirs`` (a working
directory whose input folder holds the bear capture; without ComfyUI the input and output folders are
``./input`` and ``./output`` of the working directory).
"""

import shutil

import pytest
import torch

from artnvg_core.cameras import load_cameras
from artnvg_core.formats import load_scene

SCALE = 0.125  # the bear's 512 x 512 views -> 64 x 64


def call(node_class, **inputs):
    """Run a node's function as ComfyUI does."""
    with torch.inference_mode():
        return getattr(node_class(), node_class.FUNCTION)(**inputs)


def same_scene(a, b) -> bool:
    """Whether two scenes hold equal tensors."""
    return all(torch.equal(x, y) for x, y in zip(a.tensors().values(), b.tensors().values()))


@pytest.fixture(scope="module")
def bear(shared_data):
    folder = shared_data / "scenes" / "bear"
    return {"folder": folder, "scene": load_scene(folder / "scene.ply"), "cameras": load_cameras(folder)}


@pytest.fixture(scope="module")
def small_bear(bear):
    """Every 25th Gaussian of the bear (4,000)."""
    scene = bear["scene"]
    return scene.select(torch.arange(0, len(scene), 25))


@pytest.fixture
def comfy_dirs(tmp_path, monkeypatch, bear):
    """A working directory whose input folder holds the bear capture (as ComfyUI users lay it out; copies, since
    a link that leads out of ComfyUI's folders is not read)."""
    monkeypatch.chdir(tmp_path)
    capture = tmp_path / "input" / "bear"
    capture.mkdir(parents=True)
    for name in ("scene.ply", "transforms.json"):
        shutil.copyfile(bear["folder"] / name, capture / name)
    return tmp_path
