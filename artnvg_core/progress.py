"""Progress reporting and cancellation shared by long-running core functions.

A long function takes ``progress: ProgressFn | None`` and ``should_stop: StopFn | None``.
It calls ``progress(step, total, info)`` after each unit of work (and ``progress(0, total, info)`` as the
work starts where a unit takes seconds, such as a render call: a bar then shows from the start, not once the
first unit is done) and raises :class:`Cancelled` as soon as ``should_stop()`` returns True, before writing
anything. A unit that takes seconds asks within itself too, its backward pass included (:func:`stop_in_backward`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    import torch

ProgressFn = Callable[[int, int, dict], None]
StopFn = Callable[[], bool]


class Cancelled(RuntimeError):
    """Raised when a caller's stop check asked a long-running function to stop."""


def staged(progress: ProgressFn | None, stage: str) -> ProgressFn | None:
    """``progress`` with ``info["stage"]`` set to ``stage``: one callback following a function's parts in turn
    (a command-line bar or a node's text names each)."""
    return None if progress is None else lambda step, total, info: progress(step, total, {**info, "stage": stage})


class Stages:
    """One progress over work done in consecutive stages (a scene file's reading, decoding and checking), so that
    one bar fills once, evenly: each stage of ``weights`` (its measured time, any unit) fills its share of ``whole``
    steps. ``progress(0, whole, {})`` is called first; then ``stages[name]`` is the callback that stage reports its
    own ``(step, total, info)`` to; it calls ``progress(done, whole, info)``, ``done`` the steps of the stages before
    it plus its share of step / total (rounded down). None where ``progress`` is None."""

    def __init__(self, progress: ProgressFn | None, whole: int, weights: dict[str, float]):
        self.progress, self.whole, self.spans, start = progress, whole, {}, 0.0
        for name, weight in weights.items():
            share = weight / sum(weights.values())
            self.spans[name], start = (start, share), start + share
        if progress is not None:
            progress(0, whole, {})

    def __getitem__(self, name: str) -> ProgressFn | None:
        if self.progress is None:
            return None
        start, share = self.spans[name]

        def report(step: int, total: int, info: dict) -> None:
            done = start + share * (step / total if total else 1)
            self.progress(min(self.whole, int(self.whole * done)), self.whole, info)

        return report


def check_stop(should_stop: StopFn | None) -> None:
    """Raise :class:`Cancelled` if ``should_stop`` says so."""
    if should_stop is not None and should_stop():
        raise Cancelled("stopped by request")


def stop_in_backward(tensor: torch.Tensor, should_stop: StopFn | None) -> torch.Tensor:
    """``tensor``, made to call :func:`check_stop` when a backward pass reaches it (before the work that
    back-propagates through what made it): the :class:`Cancelled` ends that ``backward()``. Nothing changes
    where ``should_stop`` is None or ``tensor`` has no gradient."""
    if should_stop is not None and tensor.requires_grad:
        tensor.register_hook(lambda grad: check_stop(should_stop))
    return tensor
