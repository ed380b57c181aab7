"""torch's CPU threads while a node computes (nodes/cpu_threads.py)."""

import pytest
import torch

from nodes import cpu_threads as module
from nodes.cpu_threads import cpu_threads, threads_for, usable_cores


@pytest.mark.parametrize(("cores", "load", "threads"), [
    (2, 0.0, 2), (2, 0.4, 1), (2, 1.0, 1), (2, 6.5, 1), (8, 2.5, 5), (8, 0.0, 8), (4, float("nan"), 1),
])
def test_threads_are_the_idle_cores_at_least_one(cores, load, threads):
    assert threads_for(cores, load) == threads


def test_threads_are_set_for_the_block_on_the_cpu_only_and_restored(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(module, "usable_cores", lambda: 4)
    monkeypatch.setattr(module, "machine_load", lambda: 2.2)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        with cpu_threads(torch.device("cpu")):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 3
        with cpu_threads(torch.device("meta")):  # not the CPU (a GPU in practice): unchanged
            assert torch.get_num_threads() == 3
        monkeypatch.setenv("OMP_NUM_THREADS", "3")  # the user chose
        with cpu_threads(torch.device("cpu")):
            assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


def test_usable_cores_is_within_the_machine():
    assert 1 <= usable_cores() <= (__import__("os").cpu_count() or 1)


@pytest.mark.parametrize(("cores", "load", "said"), [(4, 2.2, "1 CPU thread on 4 cores (load 2.2;"),
                                                    (4, 0.0, "4 CPU threads on 4 cores (load 0.0;")])
def test_the_count_is_said_once_in_words(monkeypatch, caplog, cores, load, said):
    """It said '1 CPU thread(s) on 2 core(s)' (seen on ComfyUI 0.3.64's console)."""
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(module, "usable_cores", lambda: cores)
    monkeypatch.setattr(module, "machine_load", lambda: load)
    monkeypatch.setattr(module, "_announced", set())
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        for _ in range(2):
            with cpu_threads(torch.device("cpu")):
                pass
    finally:
        torch.set_num_threads(before)
    assert [r.getMessage() for r in caplog.records] == [
        f"ArtNVG: torch computes with {said} set OMP_NUM_THREADS to choose yourself)"]
