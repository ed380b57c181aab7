"""Every view of a camera set rendered without gradients, a chunk of views at a time: the one recipe
that the ``evaluate`` command, the render nodes and the benchmarks share."""

from __future__ import annotations

import torch

from ..cameras import CameraSet
from ..progress import ProgressFn, StopFn
from ..scene import GaussianScene
from . import RenderOutput, render

RENDER_CHUNK = 8  # views a render call: few enough to bound memory, enough to keep a GPU busy


@torch.no_grad()
def render_views(scene: GaussianScene, cameras: CameraSet, *, chunk: int = RENDER_CHUNK, depth: bool = False,
                 backend: str = "auto", cpu: bool = False, progress: ProgressFn | None = None,
                 should_stop: StopFn | None = None) -> RenderOutput:
    """:func:`~artnvg_core.raster.render` of every view of ``cameras``, ``chunk`` views a call.

    Returns rgb [C, H, W, 3] clamped to [0, 1], alpha [C, H, W, 1] and, with ``depth``, depth
    [C, H, W, 1] (else None), on the scene's device, or on the CPU with ``cpu`` (each chunk moved
    there as it is done, so the device holds one chunk). Calls ``progress(views done, C, {})``
    as it starts (0) and after each chunk and raises :class:`~artnvg_core.progress.Cancelled` as soon as ``should_stop()`` says
    so (checked inside each view, as :func:`~artnvg_core.raster.render` does).
    """
    if chunk < 1:
        raise ValueError(f"render_views: chunk must be >= 1, got {chunk}")
    parts = []
    if progress is not None:
        progress(0, len(cameras), {})
    for start in range(0, len(cameras), chunk) or [0]:  # cameras of no views: render's empty output
        views = range(start, min(start + chunk, len(cameras)))
        out = render(scene, cameras.subset(views), return_depth=depth, backend=backend, should_stop=should_stop)
        tensors = (out.rgb.clamp(0, 1), out.alpha, out.depth)
        parts.append(RenderOutput(*(t.cpu() if cpu and t is not None else t for t in tensors)))
        if progress is not None:
            progress(views.stop, len(cameras), {})
    return RenderOutput(
        rgb=torch.cat([p.rgb for p in parts]),
        alpha=torch.cat([p.alpha for p in parts]),
        depth=torch.cat([p.depth for p in parts]) if depth else None,
    )
