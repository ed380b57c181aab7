"""Triton's once-a-process start-up, begun before the first kernel waits for it.

Before it loads or compiles its first kernel, a process hashes Triton's own compiler sources and its shared
library (``triton.runtime.cache.triton_key``): the key its cached kernels are found under, 0.5 s of a warm
first look's process on an H200 host under cProfile (BENCHMARKS.md, "First look").
:func:`hash_triton_in_background` starts that hashing in a thread of its own as soon as the caller knows
Triton will render; reading files and hashing release the interpreter lock, so it goes on beside the work
before the first render (the style's features, say), within :func:`~artnvg_core.background.brief_switches`
(with the default switch interval each of its hundreds of reads waits for the main thread's turn to end: on
the 2-core CPU here 5.9-6.1 s beside a thread spinning in Python, 0.5-0.6 s within it, 0.3-0.5 s alone).
Triton keeps the key for the rest of the process. A Triton without that function is left as it is.
"""

from __future__ import annotations

import threading

from ..background import brief_switches

_started: threading.Thread | None = None
_lock = threading.Lock()


def hash_triton_in_background() -> threading.Thread | None:
    """Start ``triton.runtime.cache.triton_key`` in a daemon thread, once a process and only where it has
    not run yet; returns that thread (None where nothing was started)."""
    global _started
    try:
        from triton.runtime.cache import triton_key
    except ImportError:
        return None
    cache_info = getattr(triton_key, "cache_info", None)
    with _lock:
        if _started is not None or cache_info is None or cache_info().currsize:
            return None
        _started = threading.Thread(target=_hash, args=(triton_key,), name="triton-key", daemon=True)
        _started.start()
        return _started


def _hash(triton_key) -> None:
    with brief_switches():
        triton_key()
