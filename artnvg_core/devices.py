"""The torch device to run on: CUDA when present, then Apple's MPS, then the CPU; whether Triton is there.

MPS (Apple silicon and AMD GPUs on macOS) has no float64: the core runs float64 maths (camera
poses, activated-form conversions, metric sums) on the CPU and keeps device work in float32.
"""

from __future__ import annotations

import importlib.util
import os

import torch

DEVICE_CHOICES = ("auto", "cpu", "cuda", "mps")


def mps_available() -> bool:
    """Whether Apple's Metal (MPS) backend can run here."""
    return torch.backends.mps.is_available()


def triton_available() -> bool:
    """True when the ``triton`` package can be imported (torch's CUDA builds bring it)."""
    return importlib.util.find_spec("triton") is not None


def available_memory() -> int | None:
    """Bytes of main memory available to a new allocation without swapping (Linux's MemAvailable, else the
    free pages); None where the system does not say."""
    try:
        with open("/proc/meminfo") as info:
            for line in info:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def best_device() -> torch.device:
    """CUDA when available, else MPS when available, else the CPU."""
    if torch.cuda.is_available():
        return torch.device("cuda")
    if mps_available():
        return torch.device("mps")
    return torch.device("cpu")


def device_for(name: str) -> torch.device:
    """The device ``name`` (one of :data:`DEVICE_CHOICES`, or e.g. ``cuda:1``); ``auto`` is :func:`best_device`.

    Raises ValueError when the named kind of device is not present.
    """
    if name == "auto":
        return best_device()
    try:
        device = torch.device(name)
    except RuntimeError as error:
        raise ValueError(f"{name!r} is not a device (expected one of {', '.join(DEVICE_CHOICES)})") from error
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{name}: no CUDA device is available")
    if device.type == "mps" and not mps_available():
        raise ValueError(f"{name}: Apple's MPS backend is not available (it needs macOS on Apple silicon or an AMD GPU)")
    return device
