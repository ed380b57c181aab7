"""Shared pytest fixtures, and the ``cuda`` marker's skip where no CUDA GPU is present."""

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
# Triton's kernels run in its CPU interpreter where no GPU is; the variable must be set before the
# first import of a kernel module, whichever test imports it first ("auto" still renders with torch on the CPU)
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")
SHARED_DATA = Path(os.environ.get("ARTNVG_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The project's shared test data folder: $ARTNVG_SHARED_DATA, else ../shared/data beside the
    checkout; skips the test when it is missing."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture
def npm_tools() -> None:
    """Skips the test unless the npm tools of tests/npm_tools.py are installed (installing them first
    where npm and its registry can)."""
    from tests.npm_tools import unavailable

    reason = unavailable()
    if reason is not None:
        pytest.skip(reason)


@pytest.fixture(autouse=True)
def fixed_cpu_threads(monkeypatch):
    """The nodes choose torch's CPU threads from the machine's load unless OMP_NUM_THREADS is set
    (nodes/cpu_threads.py); tests that compare a node's result with the core's bit for bit need the same
    threads in both, whatever the load: the variable names the threads torch already uses."""
    if not os.environ.get("OMP_NUM_THREADS"):
        monkeypatch.setenv("OMP_NUM_THREADS", str(torch.get_num_threads()))


@pytest.hookimpl(tryfirst=True)  # before ``-m`` selects: it must see the ``slow`` marks added here
def pytest_collection_modifyitems(config, items):
    """Tests in tests/integration (a real ComfyUI server) and tests on the local Ray instance (its workers
    start in tens of seconds) are marked ``slow``; tests marked ``cuda`` are skipped where torch sees no
    CUDA GPU."""
    integration = REPO / "tests" / "integration"
    skip = None if torch.cuda.is_available() else pytest.mark.skip(reason="needs a CUDA GPU (marker 'cuda')")
    for item in items:
        if integration in item.path.parents or "ray_local" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.slow)
        if skip is not None and item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def ray_local():
    """One new local Ray instance for the whole test session (its start-up is paid once; not a cluster
    that ``ray start`` or RAY_ADDRESS points Ray to), with three CPU slots: a module's pool of two workers
    and a test's own worker beside it, in whatever order the tests run; skips the test when Ray is not
    installed. Its workers import this checkout and its tests/ helpers (PYTHONPATH) and run
    ``ray_workers.setup_worker``."""
    import logging

    ray = pytest.importorskip("ray")
    from ray_workers import setup_worker

    paths = [str(REPO), str(REPO / "tests"), *filter(None, [os.environ.get("PYTHONPATH")])]
    ray.init(address="local", num_cpus=3, num_gpus=0, include_dashboard=False, logging_level=logging.WARNING,
             runtime_env={"env_vars": {"PYTHONPATH": os.pathsep.join(paths)}, "worker_process_setup_hook": setup_worker})
    yield ray
    ray.shutdown()
