"""Parsing of command-line values shared by the ``python -m artnvg_core`` commands."""

from __future__ import annotations

import torch

from .devices import device_for


def parse_device(name: str) -> torch.device:
    """``--device``: ``auto`` -> CUDA, else MPS, else the CPU; a device that is not present is a ValueError."""
    try:
        return device_for(name)
    except ValueError as error:
        raise ValueError(f"--device {error}") from error


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
