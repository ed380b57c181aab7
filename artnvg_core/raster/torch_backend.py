"""Reference rasterizer in pure PyTorch: tile-based, differentiable by autograd.

Each camera's projected Gaussians are sorted by depth and binned into
8x8-pixel tiles. Tiles are composited in batches, walking each tile's
depth-sorted list ``chunk`` Gaussians at a time and dropping tiles whose
pixels are all saturated, so work follows what is visible and memory is
bounded by ``budget`` (elements per intermediate tensor). With autograd on,
each tile batch is checkpointed: its intermediates are recomputed in the
backward pass instead of being stored.

Per pixel (gsplat "classic"): alpha = min(0.999, o * exp(-sigma)), a
Gaussian is skipped where alpha < 1/255, and compositing stops
before the first Gaussian that would bring transmittance to <= 1e-4.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from ..progress import StopFn, check_stop, stop_in_backward
from .projection import ALPHA_MIN, Projection

TILE = 8
ALPHA_MAX = 0.999
T_MIN = 1e-4


def _tile_lists(proj: Projection, width: int, height: int, should_stop: StopFn | None = None):
    """Depth-sorted Gaussian lists per tile.

    Returns (order, starts, counts): ``order`` [I] indices into the
    projection for every (tile, Gaussian) intersection, grouped by tile and
    depth-sorted within a tile; ``starts``/``counts`` [tiles] locate each
    tile's run in ``order``. ``should_stop`` is asked between the steps over
    all intersections (each takes seconds for a 8192x8192 view on a CPU).
    """
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    device = proj.means2d.device
    with torch.no_grad():
        by_depth = torch.argsort(proj.depths, stable=True)  # ties keep scene order
        center = proj.means2d[by_depth]
        radii = proj.radii[by_depth]
        x0 = torch.floor((center[:, 0] - radii[:, 0]) / TILE).clamp(0, tiles_x).long()
        x1 = torch.ceil((center[:, 0] + radii[:, 0]) / TILE).clamp(0, tiles_x).long()
        y0 = torch.floor((center[:, 1] - radii[:, 1]) / TILE).clamp(0, tiles_y).long()
        y1 = torch.ceil((center[:, 1] + radii[:, 1]) / TILE).clamp(0, tiles_y).long()
        span_x, span_y = x1 - x0, y1 - y0
        per_gauss = span_x * span_y
        total = int(per_gauss.sum())
        owner = torch.repeat_interleave(torch.arange(len(by_depth), device=device), per_gauss)
        first = torch.cumsum(per_gauss, 0) - per_gauss
        check_stop(should_stop)
        local = torch.arange(total, device=device) - first[owner]
        tx = x0[owner] + local % span_x[owner]
        check_stop(should_stop)
        ty = y0[owner] + local // span_x[owner]
        tile_id = ty * tiles_x + tx
        check_stop(should_stop)
        tile_sort = torch.argsort(tile_id, stable=True)
        check_stop(should_stop)
        order = by_depth[owner[tile_sort]]
        counts = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
        starts = torch.cumsum(counts, 0) - counts
    return order, starts, counts


def _pixel_basis(device, dtype) -> torch.Tensor:
    """[P, 6] monomials (1, dx, dy, dx^2, dx*dy, dy^2) of the pixel offsets from the tile centre."""
    local = torch.arange(TILE * TILE, device=device)
    dx = (local % TILE).to(dtype) + 0.5 - TILE / 2
    dy = (local // TILE).to(dtype) + 0.5 - TILE / 2
    return torch.stack([torch.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy], -1)


def _power_coefficients(tile_center, means2d, conics, opacities) -> torch.Tensor:
    """[T, 6, K] coefficients of log(alpha) = log(o) - sigma in the pixel basis.

    sigma(p) = 1/2 (p - m)^T Q (p - m) is expanded around the tile centre c
    (d = c - m, p = c + delta), which keeps every term small where alpha is
    not negligible, so float32 stays accurate.
    tile_center: [T, 1, 2]; means2d, conics, opacities: [T, K, ...].
    """
    a, b, c = conics.unbind(-1)
    d = tile_center - means2d
    qd_x = a * d[..., 0] + b * d[..., 1]
    qd_y = b * d[..., 0] + c * d[..., 1]
    constant = torch.log(opacities) - 0.5 * (d[..., 0] * qd_x + d[..., 1] * qd_y)
    return torch.stack([constant, -qd_x, -qd_y, -0.5 * a, -b, -0.5 * c], -2)


def _composite_tiles(tiles, order, starts, counts, means2d, conics, opacities, features, width, chunk):
    """Composite a batch of tiles front to back.

    tiles: [T] tile ids. Per-Gaussian inputs are indexed through ``order``;
    ``features`` [M, F] are the values blended per pixel (colour, depth).
    Returns blended features [T, P, F] and transmittance [T, P] (P = TILE^2).
    """
    device, dtype = means2d.device, means2d.dtype
    tiles_x = -(-width // TILE)
    t = len(tiles)
    basis = _pixel_basis(device, dtype)
    center = torch.stack([tiles % tiles_x, tiles // tiles_x], -1).to(dtype) * TILE + TILE / 2
    blended = means2d.new_zeros(t, TILE * TILE, features.shape[-1])
    trans = means2d.new_ones(t, TILE * TILE)
    done = torch.zeros(t, TILE * TILE, dtype=torch.bool, device=device)
    active = torch.arange(t, device=device)
    offsets = torch.arange(chunk, device=device)
    step = 0
    while len(active) > 0:
        slot = step * chunk + offsets
        valid = slot[None] < counts[tiles[active]][:, None]
        g = order[(starts[tiles[active]][:, None] + slot[None]).clamp_max(len(order) - 1)]
        opac = torch.where(valid, opacities[g], torch.ones_like(opacities[g]))
        coeffs = _power_coefficients(center[active][:, None], means2d[g], conics[g], opac)
        alpha = torch.exp(torch.matmul(basis, coeffs)).clamp_max(ALPHA_MAX)
        hit = (alpha >= ALPHA_MIN) & valid[:, None, :]
        alpha = torch.where(hit, alpha, 0.0)
        t_in = trans[active]
        with torch.no_grad():
            # Transmittance only falls, so "stop before the first Gaussian that
            # brings it to <= T_MIN" marks a suffix of the list.
            stop = (t_in[..., None] * torch.cumprod(1 - alpha, -1) <= T_MIN) | done[active][..., None]
        alpha = torch.where(stop, 0.0, alpha)
        kept = torch.cumprod(1 - alpha, -1)
        t_before = t_in[..., None] * torch.cat([torch.ones_like(kept[..., :1]), kept[..., :-1]], -1)
        blended = blended.index_add(0, active, torch.bmm(alpha * t_before, features[g]))
        trans = trans.index_copy(0, active, t_in * kept[..., -1])
        done = done.index_copy(0, active, stop[..., -1])
        step += 1
        remaining = counts[tiles[active]] > step * chunk
        active = active[remaining & ~done[active].all(-1)]
    return blended, trans


def rasterize(
    proj: Projection,
    features: torch.Tensor,
    width: int,
    height: int,
    *,
    chunk: int = 64,
    budget: int | None = None,
    should_stop: StopFn | None = None,
):
    """Rasterize one camera's projected Gaussians.

    features: [M, F] values to blend per projected Gaussian (e.g. colour, depth).
    chunk: Gaussians per tile composited at once; budget: the most elements
    in one [tiles, pixels, chunk] intermediate (default 2^21 on CPU, 2^25 on CUDA); should_stop: asked before
    each batch of tiles, in the backward pass too (:class:`~artnvg_core.progress.Cancelled` when it says so).
    Returns blended features [H, W, F] (no background) and transmittance [H, W], in the autograd
    graph of the inputs even when no Gaussian reaches a tile (their gradients are then zero).
    """
    order, starts, counts = _tile_lists(proj, width, height, should_stop)
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    occupied = (counts > 0).nonzero()[:, 0]
    blended = features.new_zeros(tiles_x * tiles_y, TILE * TILE, features.shape[-1])
    trans = features.new_ones(tiles_x * tiles_y, TILE * TILE)
    inputs = (proj.means2d, proj.conics, proj.opacities, features)
    needs_grad = torch.is_grad_enabled() and any(x.requires_grad for x in inputs)
    if budget is None:
        budget = 1 << (25 if features.device.type == "cuda" else 21)
    batch = max(1, budget // (TILE * TILE * chunk))
    for i in range(0, len(occupied), batch):
        check_stop(should_stop)
        tiles = occupied[i : i + batch]
        args = (tiles, order, starts, counts, *inputs, width, chunk)
        out = checkpoint(_composite_tiles, *args, use_reentrant=False) if needs_grad else _composite_tiles(*args)
        if needs_grad:  # a new tensor each batch keeps autograd's saved values intact
            blended = blended.index_copy(0, tiles, stop_in_backward(out[0], should_stop))
            trans = trans.index_copy(0, tiles, out[1])
        else:  # in place: a copy of the whole view per batch made a 4096x4096 view spend half its time copying
            blended.index_copy_(0, tiles, out[0])
            trans.index_copy_(0, tiles, out[1])
    if needs_grad and len(occupied) == 0:  # nothing to composite: constant images, zero gradients
        zero = sum(x[:0].sum() for x in inputs)
        blended, trans = blended + zero, trans + zero

    def to_image(x):
        x = x.reshape(tiles_y, tiles_x, TILE, TILE, *x.shape[2:]).transpose(1, 2)
        return x.reshape(tiles_y * TILE, tiles_x * TILE, *x.shape[4:])[:height, :width]

    return to_image(blended), to_image(trans)
