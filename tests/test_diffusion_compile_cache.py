"""Compile cache artifacts: written to the cache folder after compiling, loaded into a process whose
own compile caches are empty, where the same compile then finds its result instead of generating it."""

import shutil

import pytest
import torch
from torch._dynamo.utils import counters
from torch.compiler._cache import CacheArtifactManager

from artnvg_core.diffusion.compile_cache import compile_cache_file, load_compile_cache, save_compile_cache


@pytest.fixture
def fresh_compile_state(tmp_path, monkeypatch):
    """Empty Inductor and artifact caches in ``tmp_path`` for the test, restored afterwards."""
    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path / "inductor"))
    monkeypatch.setenv("ARTNVG_CACHE_DIR", str(tmp_path / "artnvg"))
    torch._dynamo.reset()
    with CacheArtifactManager.with_fresh_cache():
        yield tmp_path
    torch._dynamo.reset()


def _compile_and_run() -> dict:
    """Inductor compiles a product (an external matmul: no C++ kernel to build) and runs it; returns the
    Inductor counters of that compile."""
    counters.clear()
    with torch.no_grad():
        out = torch.compile(lambda x: x @ x.T)(torch.ones(3, 2))
    assert torch.equal(out, torch.full((3, 3), 2.0))
    return dict(counters["inductor"])


def test_artifacts_are_saved_and_hot_loaded(fresh_compile_state):
    folder = fresh_compile_state
    assert save_compile_cache("cpu") is None and load_compile_cache("cpu") == 0  # nothing compiled, no file
    assert _compile_and_run()["fxgraph_cache_miss"] == 1
    path = save_compile_cache("cpu")
    assert path == compile_cache_file("cpu") and path.parent == folder / "artnvg" / "compile"
    assert path.stat().st_size > 0
    assert not list(path.parent.glob("*.tmp*"))  # written atomically, no temporary left

    # another process's view: no compiled graph in memory, none in Inductor's or AOTAutograd's on-disk cache
    torch._dynamo.reset()
    for cache in ("fxgraph", "aotautograd"):
        shutil.rmtree(folder / "inductor" / cache)
    assert load_compile_cache("cpu") == 2  # the Inductor graph and the AOTAutograd entry
    assert _compile_and_run().get("fxgraph_cache_hit") == 1


def test_without_the_file_the_same_compile_generates_again(fresh_compile_state):
    """The control of the test above: with the on-disk caches emptied and nothing loaded, it misses."""
    folder = fresh_compile_state
    _compile_and_run()
    torch._dynamo.reset()
    for cache in ("fxgraph", "aotautograd"):
        shutil.rmtree(folder / "inductor" / cache)
    assert _compile_and_run().get("fxgraph_cache_miss") == 1


def test_cache_file_is_per_torch_version_and_device_kind(monkeypatch, tmp_path):
    monkeypatch.setenv("ARTNVG_CACHE_DIR", str(tmp_path))
    assert compile_cache_file("cpu") == tmp_path / "compile" / f"torch-{torch.__version__}-cpu.bin"
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device: "NVIDIA H100 80GB HBM3")
    assert compile_cache_file("cuda:0").name == f"torch-{torch.__version__}-NVIDIA_H100_80GB_HBM3.bin"
    monkeypatch.delenv("ARTNVG_CACHE_DIR")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compile_cache_file("cpu").parent == tmp_path / "home" / ".cache" / "artnvg" / "compile"
