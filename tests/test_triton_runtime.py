"""triton_runtime.py: Triton's key hashed once a process, in a thread of its own, only where it has not run;
warm-ups compiled in threads, waited for before the first render."""

import functools
import sys
import threading

import pytest
import torch

triton_cache = pytest.importorskip("triton.runtime.cache")

from artnvg_core.background import SWITCH_INTERVAL  # noqa: E402
from artnvg_core import triton_runtime  # noqa: E402


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


class FakeKernel:
    """A kernel whose warm-up records its arguments, thread and device, after ``gate`` opens; fails when told."""

    def __init__(self, log, gate=None, fails=False, source="kernel source"):
        self.log, self.gate, self.fails, self.cache_key = log, gate, fails, source

    def warmup(self, *args, grid, **kwargs):
        if self.gate is not None:
            assert self.gate.wait(10)
        if self.fails:
            raise RuntimeError("does not compile")
        self.log.append(("compiled", args, grid, kwargs, threading.current_thread().name))
        return self

    def _init_handles(self):
        self.log.append(("launcher", threading.current_thread().name))


@pytest.fixture
def cuda_devices(monkeypatch, tmp_path):
    """torch.cuda.set_device recorded (thread, device) instead of called, so that the warm-ups' threads run on a
    CPU; an H100's architecture; Triton's cache in ``tmp_path``."""
    from triton import knobs

    chosen = []
    monkeypatch.setattr(triton_runtime.torch.cuda, "set_device",
                        lambda device: chosen.append((threading.current_thread().name, str(device))))
    monkeypatch.setattr(triton_runtime.torch.cuda, "get_device_capability", lambda device: (9, 0))
    monkeypatch.setattr(knobs.cache, "dir", str(tmp_path))
    monkeypatch.setattr(triton_runtime, "_started", None)
    return chosen


def test_warmups_compile_off_the_caller_thread_and_the_first_render_waits_for_them(cuda_devices):
    log, gate = [], threading.Event()
    warmups = [triton_runtime.Warmup(FakeKernel(log, gate), (index, 2.0), {"BLOCK": 8}) for index in range(3)]
    triton_runtime.compile_in_background(warmups, "cuda:1")
    assert log == []  # returned at once, the compilations still waiting for the gate
    threading.Timer(0.2, gate.set).start()
    triton_runtime.wait_for_compilation()
    compiled = sorted(entry[1] for entry in log if entry[0] == "compiled")
    assert compiled == [(0, 2.0), (1, 2.0), (2, 2.0)]  # each once, as given
    assert all(entry[2] == (1,) and entry[3] == {"BLOCK": 8} for entry in log if entry[0] == "compiled")
    assert sum(entry[0] == "launcher" for entry in log) == 3  # each one's launcher built there too
    threads = {entry[-1] for entry in log}
    assert threading.current_thread().name not in threads and all(t.startswith("triton-compile") for t in threads)
    assert {device for _, device in cuda_devices} == {"cuda:1"} and {t for t, _ in cuda_devices} == threads
    triton_runtime.wait_for_compilation()  # nothing left: at once


def test_a_failed_warmup_is_left_to_its_launch_and_other_devices_compile_nothing(cuda_devices):
    log = []
    triton_runtime.compile_in_background([triton_runtime.Warmup(FakeKernel(log, fails=True), (), {}),
                                          triton_runtime.Warmup(FakeKernel(log), (), {})], "cuda")
    triton_runtime.wait_for_compilation()  # no error here: the launch compiles it again and says why
    assert [entry[0] for entry in log] == ["compiled", "launcher"]
    triton_runtime.compile_in_background([triton_runtime.Warmup(FakeKernel(log), (), {})], "cpu")
    triton_runtime.wait_for_compilation()
    assert len(log) == 2 and len(cuda_devices) == 2


def test_warmups_wait_for_the_key_being_hashed(cuda_devices, monkeypatch):
    release, log = threading.Event(), []

    def slow_key():  # the key thread, still hashing when the warm-ups start
        assert release.wait(10)
        log.append("key hashed")

    key_thread = threading.Thread(target=slow_key)
    key_thread.start()
    monkeypatch.setattr(triton_runtime, "_started", key_thread)
    triton_runtime.compile_in_background([triton_runtime.Warmup(FakeKernel(log), (), {})], "cuda")
    threading.Timer(0.2, release.set).start()
    triton_runtime.wait_for_compilation()
    assert [entry if isinstance(entry, str) else entry[0] for entry in log] == ["key hashed", "compiled", "launcher"]


def test_a_set_compiled_once_is_not_compiled_again_by_later_processes(cuda_devices, tmp_path):
    log = []

    def compiled(warmups):
        triton_runtime.compile_in_background(warmups, "cuda")
        triton_runtime.wait_for_compilation()
        count = sum(entry[0] == "compiled" for entry in log)
        log.clear()
        return count

    kernels = [FakeKernel(log), FakeKernel(log, source="another kernel")]
    warmups = [triton_runtime.Warmup(kernel, (triton_runtime.stand_in(torch.float32, "cpu"), 16), {"BLOCK": 8})
               for kernel in kernels]
    assert compiled(warmups) == 2 and len(list((tmp_path / "artnvg-compiled").iterdir())) == 1
    assert compiled(warmups) == 0  # the file in Triton's cache says so: no threads, the launches load them
    changed = [warmups[0]._replace(args=(warmups[0].args[0], 17)), warmups[1]]  # another launch
    assert compiled(changed) == 2
    kernels[1].cache_key = "its source changed"
    assert compiled(warmups) == 2
    failing = [warmups[0]._replace(kernel=FakeKernel(log, fails=True, source="new")), warmups[1]]
    assert compiled(failing) == 1 and compiled(failing) == 1  # not all compiled: no file, tried again
