"""What every scene file reader and writer shares: file checks, the scene check before writing, notes for the user
on what a format changes, 8-bit opacities, work done a chunk of Gaussians at a time (progress and cancellation)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ..fileio import require_regular_file
from ..notes import NoteFn, tell
from ..progress import ProgressFn, StopFn, check_stop
from ..scene import GaussianScene, describe_invalid, invalid_gaussians, logit

# Gaussians per chunk: at 3M Gaussians of SH degree 3 on a 2-core CPU a chunk's SPZ quantisation and deflate take
# about 0.15 s, a PLY's rows 0.02 s (a stop waits at most that long), and a 3M file's 46 chunks cost no measurable time.
CHUNK_GAUSSIANS = 1 << 16


class ChunkedWork:
    """A reader's or writer's work on ``count`` Gaussians in ``passes`` passes over them (an SPZ writer's one per
    attribute array, a PLY reader's copy then decode), :data:`CHUNK_GAUSSIANS` at a time: :meth:`chunks` yields
    one pass's slices, raising :class:`~artnvg_core.progress.Cancelled` before any whose ``should_stop()`` is
    True and calling ``progress(done, count, {})`` after each (and ``progress(0, count, {})`` first): ``done``
    the Gaussians done over all passes so far, divided by ``passes`` (a bar counts the scene's Gaussians)."""

    def __init__(self, count: int, passes: int = 1, progress: ProgressFn | None = None,
                 should_stop: StopFn | None = None):
        self.count, self.passes, self.done = count, passes, 0
        self.progress, self.should_stop = progress, should_stop
        check_stop(should_stop)
        if progress is not None:
            progress(0, count, {})

    def chunks(self, start: int = 0, stop: int | None = None) -> Iterator[slice]:
        """One pass's slices of the Gaussians, in order (of those from ``start`` to ``stop`` only: a pass made
        of parts, such as a file's sections)."""
        size, stop = CHUNK_GAUSSIANS, self.count if stop is None else stop
        for first in range(start, stop, size):
            check_stop(self.should_stop)
            rows = slice(first, min(first + size, stop))
            yield rows
            self.done += rows.stop - rows.start
            if self.progress is not None:
                self.progress(self.done // self.passes, self.count, {})

    def check_stop(self) -> None:
        """Raise :class:`~artnvg_core.progress.Cancelled` if ``should_stop`` says so (between passes)."""
        check_stop(self.should_stop)


def require_file(path: Path) -> None:
    """ValueError naming ``path`` unless it is a regular file (a FIFO would block the read)."""
    require_regular_file(path, "scene file")


def tell_filter_change(notes: NoteFn | None, path: Path, cpu: GaussianScene, kind: str, blur_px2: float,
                       antialiased: bool) -> None:
    """A note (:func:`~artnvg_core.notes.tell`) when a file of format ``kind`` reads back with another 2D filter
    (``blur_px2``, ``antialiased``: what it records, at most the antialiased flag) than ``cpu``'s."""
    if (cpu.blur_px2, cpu.antialiased) != (blur_px2, antialiased):
        tell(notes, path, f"{kind} cannot record the scene's 2D filter ({_filter(cpu.blur_px2, cpu.antialiased)}); "
                          f"it reads back with {_filter(blur_px2, antialiased)}")


def _filter(blur_px2: float, antialiased: bool) -> str:
    return f"{blur_px2:g} px^2 blur, {'antialiased' if antialiased else 'classic'}"


def scene_to_write(scene: GaussianScene, path: Path, should_stop: StopFn | None = None) -> GaussianScene:
    """``scene`` as detached float32 CPU tensors; a ValueError naming ``path`` and the field when
    any Gaussian is non-finite (after the float32 cast) or has a zero quaternion, before anything is written.
    ``should_stop``: as :func:`~artnvg_core.scene.invalid_gaussians`'s."""
    cpu = scene.map(lambda t: t.detach().to("cpu", torch.float32))
    if len(cpu) == 0:
        raise ValueError(f"{path}: not written: the scene contains no Gaussians")
    for name, problem, bad in invalid_gaussians(cpu, should_stop):
        if bad.any():
            raise ValueError(f"{path}: not written: {describe_invalid(name, bad, f'have {problem}')}")
    return cpu


# An 8-bit opacity byte b stands for b / 255; the two end bytes are read as b / 255 moved 0.25/255
# inwards (finite logits) and written back as the same byte.
_OPACITY_EDGE = 0.25 / 255


def opacity_logits_from_bytes(values: np.ndarray) -> np.ndarray:
    """Opacity logits [N] (float64) of 8-bit opacities (0..255 for 0..1)."""
    opacities = np.clip(np.asarray(values, np.float64) / 255, _OPACITY_EDGE, 1 - _OPACITY_EDGE)
    return logit(torch.from_numpy(opacities)).numpy()


def opacity_bytes(logits: torch.Tensor) -> np.ndarray:
    """8-bit opacities [N] (0..255 for 0..1, rounded half up) of opacity logits [N] (sigmoid in float64)."""
    return to_bytes(torch.sigmoid(logits.double()).numpy() * 255)


def to_bytes(values: np.ndarray) -> np.ndarray:
    """Values on the 0..255 scale rounded half up and clamped to uint8."""
    return np.clip(np.floor(np.asarray(values, np.float64) + 0.5), 0, 255).astype(np.uint8)
