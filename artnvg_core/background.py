"""Work in background threads beside Python-bound work: the interpreter lock handed over often.

A thread that calls into C (a torch operation, a file read) releases the interpreter lock and must get it
back. When another thread is running Python meanwhile, CPython hands the lock back only when that thread's
switch interval (5 ms by default) ends: a background model load makes thousands of such calls, so beside
a busy thread each costs up to 5 ms. Building the full-size models on the meta device beside a thread
spinning in Python took 75-108 s with the default interval, 3.9-7.2 s with 0.5 ms and 1.9-2.9 s with
0.1 ms, against 0.6-0.8 s alone (the 2-core development CPU). :func:`brief_switches` sets 0.1 ms while
any such block runs and restores the process's interval after the last one ends.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

SWITCH_INTERVAL = 1e-4  # seconds a thread may keep the interpreter lock while another waits for it

_lock = threading.Lock()
_active = 0  # blocks inside brief_switches, in all threads
_saved: float | None = None  # the interval before the first of them


@contextmanager
def brief_switches() -> Iterator[None]:
    """Within the block (in any thread), the interpreter's switch interval is :data:`SWITCH_INTERVAL`;
    blocks may overlap, in one thread or several: the interval the process had is back once the last
    ends."""
    global _active, _saved
    with _lock:
        if _active == 0:
            _saved = sys.getswitchinterval()
            sys.setswitchinterval(min(SWITCH_INTERVAL, _saved))
        _active += 1
    try:
        yield
    finally:
        with _lock:
            _active -= 1
            if _active == 0:
                sys.setswitchinterval(_saved)
