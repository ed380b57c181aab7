"""The environment of a test's child Python process."""

import os


def child_env() -> dict[str, str]:
    """This process's environment (what finds the installed packages, the GPU and its libraries: PYTHONPATH,
    CUDA_VISIBLE_DEVICES, LD_LIBRARY_PATH) with one CPU thread, so that a child runs as this test run does."""
    return dict(os.environ, OMP_NUM_THREADS="1")
