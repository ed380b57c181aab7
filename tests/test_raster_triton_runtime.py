"""raster/triton_runtime.py: Triton's key hashed once a process, in a thread of its own, only where it has not run."""

import functools
import sys
import threading

import pytest

triton_cache = pytest.importorskip("triton.runtime.cache")

from artnvg_core.background import SWITCH_INTERVAL  # noqa: E402
from artnvg_core.raster import triton_runtime  # noqa: E402


@pytest.fixture
def fake_key(monkeypatch):
    """triton_key replaced by a cached function that records the thread it runs in (and the switch interval
    then, in ``intervals``)."""
    threads, intervals = [], []

    @functools.lru_cache(None)
    def triton_key():
        threads.append(threading.current_thread())
        intervals.append(sys.getswitchinterval())
        return "key"

    triton_key.intervals = intervals

    monkeypatch.setattr(triton_cache, "triton_key", triton_key)
    monkeypatch.setattr(triton_runtime, "_started", None)
    return triton_key, threads


def test_the_key_is_hashed_once_in_a_thread_of_its_own(fake_key):
    triton_key, threads = fake_key
    thread = triton_runtime.hash_triton_in_background()
    assert thread is not None and thread.daemon
    thread.join(10)
    assert threads == [thread] and thread is not threading.current_thread()
    assert triton_key.intervals == [pytest.approx(SWITCH_INTERVAL)]  # the lock handed back often beside the main thread
    assert triton_key.cache_info().currsize == 1  # the process's later callers find it
    assert triton_runtime.hash_triton_in_background() is None and threads == [thread]


def test_nothing_where_the_key_is_known_or_triton_has_no_such_function(fake_key, monkeypatch):
    triton_key, threads = fake_key
    triton_key()
    assert triton_runtime.hash_triton_in_background() is None and len(threads) == 1
    monkeypatch.setattr(triton_runtime, "_started", None)
    monkeypatch.delattr(triton_cache, "triton_key")
    assert triton_runtime.hash_triton_in_background() is None
