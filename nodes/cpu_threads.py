"""How many CPU threads torch uses while a node computes on the CPU.

torch starts one thread per core. When other processes keep those cores busy, its threads wait on each
other and a step gets several times slower. So while a node runs on the CPU, :func:`cpu_threads` sets
torch's thread count to the cores this process may use less the machine's load (1-minute average of
runnable processes, which includes ComfyUI's own recent work), at least 1, and restores the previous
count afterwards. Nothing changes when ComfyUI computes on a GPU, or when ``OMP_NUM_THREADS`` is set: the
user chose then.
"""

from __future__ import annotations

import logging
import math
import os
from contextlib import contextmanager

import torch

from artnvg_core.counted import counted

_log = logging.getLogger("artnvg")
_announced: set[tuple[int, int]] = set()


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the system tells, else all)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def machine_load() -> float:
    """The 1-minute load average (runnable processes); 0 where the system does not tell."""
    try:
        return max(0.0, os.getloadavg()[0])
    except (AttributeError, OSError):
        return 0.0


def threads_for(cores: int, load: float) -> int:
    """Threads worth using on ``cores`` cores when ``load`` processes are runnable: the cores left idle
    (``cores - load``, rounded down), at least 1, at most ``cores``."""
    if not math.isfinite(load):
        return 1
    return max(1, min(cores, math.floor(cores - load)))


@contextmanager
def cpu_threads(device: torch.device):
    """Within the block, torch's CPU threads as the module docstring says (for work on ``device``)."""
    if torch.device(device).type != "cpu" or os.environ.get("OMP_NUM_THREADS"):
        yield
        return
    before = torch.get_num_threads()
    cores, load = usable_cores(), machine_load()
    threads = threads_for(cores, load)
    if threads != before and (threads, cores) not in _announced:
        _announced.add((threads, cores))
        _log.warning("ArtNVG: torch computes with %s on %s (load %.1f; set OMP_NUM_THREADS to choose yourself)",
                     counted(threads, "CPU thread"), counted(cores, "core"), load)
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
