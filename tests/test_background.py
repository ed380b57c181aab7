"""brief_switches: the short switch interval while any block runs, in any thread, the process's after the last."""

import sys
import threading

import pytest

from artnvg_core.background import SWITCH_INTERVAL, brief_switches


def test_overlapping_blocks_in_two_threads_restore_the_interval_after_the_last():
    before = sys.getswitchinterval()
    entered, leave = threading.Event(), threading.Event()
    seen = []

    def other() -> None:
        with brief_switches():
            entered.set()
            leave.wait()
            seen.append(sys.getswitchinterval())

    thread = threading.Thread(target=other, daemon=True)
    try:
        with brief_switches():
            assert sys.getswitchinterval() == pytest.approx(SWITCH_INTERVAL)
            thread.start()
            entered.wait()
        assert sys.getswitchinterval() == pytest.approx(SWITCH_INTERVAL)  # the other thread's block still runs
    finally:
        leave.set()
        thread.join()
    assert seen == [pytest.approx(SWITCH_INTERVAL)] and sys.getswitchinterval() == before


def test_a_failing_block_restores_the_interval_too():
    before = sys.getswitchinterval()
    try:
        with brief_switches():
            raise KeyError("x")
    except KeyError:
        pass
    assert sys.getswitchinterval() == before
