"""Triton's start-up, begun before the first kernel waits for it: its key hashed and a run's kernels compiled
in background threads.

Before it loads or compiles its first kernel, a process hashes Triton's own compiler sources and its shared
library (``triton.runtime.cache.triton_key``): the key its cached kernels are found under, 0.5 s of a warm
first look's process on an H200 host under cProfile (BENCHMARKS.md, "First look").
:func:`hash_triton_in_background` starts that hashing in a thread of its own as soon as the caller knows
Triton will render; reading files and hashing release the interpreter lock, so it goes on beside the work
before the first render (the style's features, say), within :func:`~artnvg_core.background.brief_switches`
(with the default switch interval each of its hundreds of reads waits for the main thread's turn to end: on
the 2-core CPU here 5.9-6.1 s beside a thread spinning in Python, 0.5-0.6 s within it, 0.3-0.5 s alone).
Triton keeps the key for the rest of the process. A Triton without that function is left as it is.

A process that finds no cached build of a kernel compiles it at its first launch, one kernel after another
(a first look's 11 compilations took 6.5 s on an H200 host, their launchers' builds with the C compiler besides).
:func:`compile_in_background` compiles the launches a run will make (:class:`Warmup`, each module of kernels
says which its work makes) in threads, side by side (the compiler's passes, ``ptxas`` and the C compiler run
without the interpreter lock), while the caller goes on; :func:`wait_for_compilation`, which the renders call
before their first launch, waits for them, so that no kernel is compiled twice. Where a warm-up's arguments
are not quite those of the launch (another specialization), the launch compiles its own, as without it.
Once a process has compiled a set of warm-ups, a file in Triton's cache says so (named by the kernels' own
source keys, the launches, Triton's version and the GPU's architecture): later processes find their kernels
cached and load them as they launch, in milliseconds, without the threads (which, loading beside a model
load, made a warm `fast` run's first render wait 1.8 s longer on an H200 host).
"""

from __future__ import annotations

import hashlib
import os
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import torch

from .background import brief_switches

_started: threading.Thread | None = None
_lock = threading.Lock()
_compiling: list[tuple[list[Future], Path | None]] = []  # warm-ups not waited for yet, and their done file


class Warmup(NamedTuple):
    """One launch of a Triton kernel, compiled before it is made: the kernel (``triton.jit``) and the positional
    and keyword arguments the launch passes, a tensor standing for its dtype, device and alignment only
    (:func:`stand_in`)."""

    kernel: Any
    args: tuple
    kwargs: dict


def stand_in(dtype: torch.dtype, device: torch.device | str) -> torch.Tensor:
    """An empty ``dtype`` tensor on ``device``: a warm-up's argument for a launch's (16-byte aligned) tensor."""
    return torch.empty(0, dtype=dtype, device=device)


def compile_in_background(warmups: Sequence[Warmup], device: torch.device | str) -> None:
    """Compile (or load from Triton's cache) each of ``warmups``' kernels for CUDA ``device``, with its launcher,
    in threads of their own (one a CPU core), within :func:`~artnvg_core.background.brief_switches`; returns
    at once. Nothing on other devices (Triton's interpreter compiles nothing). A warm-up that fails is left to
    its launch, which compiles it again and reports the error there."""
    device = torch.device(device)
    if device.type != "cuda" or not warmups:
        return
    done = _done_file(warmups, device)
    if done is not None and done.exists():
        return
    pool = ThreadPoolExecutor(min(len(warmups), os.cpu_count() or 1), thread_name_prefix="triton-compile")
    with _lock:
        _compiling.append(([pool.submit(_compile, warmup, device) for warmup in warmups], done))
    pool.shutdown(wait=False)


def wait_for_compilation() -> None:
    """Wait for the warm-ups :func:`compile_in_background` started (none: returns at once); where all of a
    set compiled, write the file that spares later processes the set."""
    with _lock:
        pending = list(_compiling)
        _compiling.clear()
    for futures, done in pending:
        failed = [future.exception() for future in futures]  # waits; a failure is the launch's to report
        if done is not None and not any(failed):
            try:
                done.parent.mkdir(parents=True, exist_ok=True)
                done.touch()
            except OSError:  # a cache folder it cannot write to: the threads again next time
                pass


def _done_file(warmups: Sequence[Warmup], device: torch.device) -> Path | None:
    """The file in Triton's cache that says a process compiled ``warmups`` for ``device``'s architecture
    (cleared with the cache); None where this Triton does not say where its cache is."""
    try:
        import triton
        from triton import knobs

        folder = knobs.cache.dir
    except (ImportError, AttributeError):
        return None
    digest = hashlib.sha256(f"{triton.__version__} {torch.cuda.get_device_capability(device)}".encode())
    for warmup in warmups:
        args = [str(arg.dtype) if isinstance(arg, torch.Tensor) else repr(arg) for arg in warmup.args]
        digest.update(repr((warmup.kernel.cache_key, args, sorted(warmup.kwargs.items()))).encode())
    return Path(folder) / "artnvg-compiled" / digest.hexdigest()


def _compile(warmup: Warmup, device: torch.device) -> None:
    torch.cuda.set_device(device)  # the thread's device: the kernel's cache and its binary's context
    with brief_switches():
        if _started is not None:
            _started.join()  # the key it hashes: once, not in every thread
        compiled = warmup.kernel.warmup(*warmup.args, grid=(1,), **warmup.kwargs)
        init_handles = getattr(compiled, "_init_handles", None)  # loads the binary and builds its launcher
        if init_handles is not None:
            init_handles()


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
