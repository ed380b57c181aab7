"""Parsing of command-line values shared by the ``python -m artnvg_core`` commands."""

from __future__ import annotations

import torch


def parse_device(name: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu; ``cuda`` without a GPU is a ValueError."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: no CUDA device is available")
    return torch.device(name)


def parse_devices(text: str | None) -> list[torch.device] | None:
    """Devices from ``--devices`` text such as ``cuda:0,cuda:1`` (None when not given)."""
    if not text:
        return None
    devices = []
    for part in text.split(","):
        try:
            devices.append(torch.device(part.strip()))
        except RuntimeError as error:
            raise ValueError(f"--devices: {part.strip()!r} is not a device (expected e.g. cuda:0,cuda:1)") from error
    return devices


def parse_view_indices(text: str | None, count: int) -> list[int]:
    """Indices from ``--views`` text such as ``0,5,9`` (default: all ``count`` views)."""
    if not text:
        return list(range(count))
    try:
        indices = [int(part) for part in text.split(",") if part.strip()]
    except ValueError as error:
        raise ValueError(f"--views: expected comma-separated integers such as 0,5,9, got {text!r}") from error
    bad = [i for i in indices if not 0 <= i < count]
    if bad or not indices:
        raise ValueError(f"--views: indices {bad or text!r} out of range for {count} cameras")
    return indices
