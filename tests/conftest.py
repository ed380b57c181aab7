"""Shared pytest fixtures, and the ``cuda`` marker's skip where no CUDA GPU is present."""

import os
from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(os.environ.get("ARTNVG_SHARED_DATA") or Path(__file__).resolve().parents[2] / "shared" / "data")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The project's shared test data folder: $ARTNVG_SHARED_DATA, else ../shared/data beside the
    checkout; skips the test when it is missing."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared test data not found at {SHARED_DATA}")
    return SHARED_DATA


def pytest_collection_modifyitems(config, items):
    """Tests marked ``cuda`` are skipped where torch sees no CUDA GPU."""
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (marker 'cuda')")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)
