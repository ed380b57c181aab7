"""Optional gsplat backend (CUDA only): gsplat's tile compositor over the reference's projection.

gsplat's own pipeline projects in float32 with the raw scales: ``exp(log-scale)`` squared
overflows from log-scale 44 on, the 2D determinant ``a*c - b^2`` cancels for needle-thin
Gaussians, footprints overflow its int32 radii, and SH it evaluates itself can reach inf. Such
Gaussians (all finite, all accepted by the loaders) rendered as nothing with non-finite gradients
(gsplat 1.5.3; its issue #248). So gsplat is handed what it handles, with the reference's meaning:
the reference projection (:mod:`.projection`: largest scale factored out, determinant from 2x2
minors, opacity culling, footprints cut to the image) and colours (:mod:`.sh`, capped at
``COLOR_MAX``), and its CUDA kernels do the per-pixel work: tile intersection, depth sort and
front-to-back compositing, forward and backward (``isect_tiles``, ``rasterize_to_pixels``).

gsplat builds its CUDA kernels the first time they are used after installing it (minutes; the measured
time is in BENCHMARKS.md, "First look"); :func:`load_kernels` announces that build before it starts.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import time
from typing import Callable

import torch

from .projection import Projection

_log = logging.getLogger(__name__)

TILE = 16  # gsplat's tile size, pixels
BUILD_NOTICE = ("gsplat: building its CUDA kernels, once after installing it (a matter of minutes, measured in "
                "BENCHMARKS.md, \"First look\"); later runs start at once")
_INT32_MAX = 2**31 - 1
_loaded = False


def gsplat_available() -> bool:
    """True when the ``gsplat`` package can be imported."""
    return importlib.util.find_spec("gsplat") is not None


def build_pending() -> bool:
    """True when loading gsplat's kernels will compile them first: no prebuilt ``gsplat.csrc`` and no
    earlier build in torch's extension folder (the test gsplat 1.x itself makes)."""
    if importlib.util.find_spec("gsplat.csrc") is not None:
        return False
    from torch.utils.cpp_extension import _get_build_directory

    return not os.path.exists(os.path.join(_get_build_directory("gsplat_cuda", verbose=False), "gsplat_cuda.so"))


def _import_kernels():
    """gsplat's compiled kernels (None when it found no CUDA toolkit to build them with)."""
    from gsplat.cuda._backend import _C

    return _C


def load_kernels(announce: Callable[[str], None] | None = None) -> None:
    """Load gsplat's CUDA kernels once per process. A first-use build is announced through
    ``announce`` (default: a warning on this module's logger) before it starts, and its time after.
    RuntimeError when gsplat cannot build them (no CUDA toolkit)."""
    global _loaded
    if _loaded:
        return
    announce = announce or _log.warning
    building = build_pending()
    if building:
        announce(BUILD_NOTICE)
    start = time.perf_counter()
    if _import_kernels() is None:
        raise RuntimeError("gsplat could not build its CUDA kernels (no CUDA toolkit, nvcc, found); "
                           "install the CUDA toolkit or render with backend 'torch'")
    if building:
        announce(f"gsplat: CUDA kernels built in {time.perf_counter() - start:.0f} s")
    _loaded = True


def rasterize_gsplat(proj: Projection, features: torch.Tensor, width: int, height: int):
    """Composite one camera's projected Gaussians with gsplat's kernels; the reference
    :func:`~.torch_backend.rasterize`'s contract (features [M, F], float32, CUDA).

    Footprints cut to the image get two tiles of margin, so gsplat's float32 tile bounds still
    reach past the image for centres up to about 1e8 pixels off it.
    Returns blended features [H, W, F] (no background) and transmittance [H, W].
    """
    from gsplat import isect_offset_encode, isect_tiles, rasterize_to_pixels

    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    with torch.no_grad():
        size = torch.tensor([width, height], dtype=proj.means2d.dtype, device=proj.means2d.device)
        reach = torch.maximum(proj.means2d.abs(), (proj.means2d - size).abs()).ceil()
        cut = proj.radii >= reach
        radii = torch.where(cut, reach + 2 * TILE, proj.radii).clamp_max(_INT32_MAX).to(torch.int32)
        _, isect_ids, flatten_ids = isect_tiles(proj.means2d[None], radii[None], proj.depths[None], TILE,
                                                tiles_x, tiles_y)
        offsets = isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    blended, alpha = rasterize_to_pixels(proj.means2d[None], proj.conics[None], features[None],
                                         proj.opacities[None], width, height, TILE, offsets, flatten_ids)
    return blended[0], 1 - alpha[0, ..., 0]
