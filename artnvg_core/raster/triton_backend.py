"""Triton backend: front-to-back compositing over tile lists, forward and backward, in Triton kernels
(JIT-compiled on first use, cached by Triton; no native build).

It takes the fused projection and colours (:mod:`.triton_projection`, or the reference's) and replaces the
reference's per-pixel compositing (:func:`~.torch_backend.rasterize`) with the same semantics:
alpha = min(0.999, o * exp(-sigma)), samples with sigma < 0 or alpha < 1/255 skipped, compositing
in depth order (ties in projection order) stopping before the first Gaussian that would bring the
transmittance to <= 1e-4.

Tile lists: :mod:`.triton_tiles` (each tile's Gaussians in depth order). Compositing: each Triton
program owns a few pixel rows of one ``tile`` x ``tile`` tile (:class:`Pass`) and walks the tile's list
``chunk`` Gaussians at a time as a [pixels, chunk] block, passing over blocks none of its pixels uses. The forward pass keeps per pixel
the final transmittance and the end of the list prefix that contributed; the backward pass replays
the list back to front from there (as gsplat does): the transmittance before each Gaussian is
recovered by division from the final one (a reversed scan along the chunk), and the colour still to
come is a suffix sum, so no difference of large sums loses precision. Per-Gaussian gradients are
summed over the program's pixels, then added with relaxed atomics (in no fixed order; nothing reads them
back in the kernel, so no add waits for its result, as with CUDA's atomicAdd: Triton's default order,
acq_rel, made each wait and the kernel take twice the time).

The kernels run on CUDA tensors, or on the CPU in Triton's interpreter (``TRITON_INTERPRET=1`` set
before this module is imported), which is how the tests check them where no GPU is.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import triton
import triton.language as tl

from ..triton_runtime import Warmup, stand_in
from .projection import ALPHA_MIN, Projection
from .torch_backend import ALPHA_MAX, T_MIN
from .triton_tiles import TILE, ListCapacity, tile_lists
from .triton_tiles import warmups as tile_warmups


class Pass(NamedTuple):
    """How a compositing kernel is launched: each program owns ``rows`` pixel rows of a tile (powers of
    two up to the tile's side), walks its list ``chunk`` Gaussians at a time and runs ``warps`` warps."""

    rows: int
    chunk: int
    warps: int


# forward, backward: among the fastest on an H100 (bench/raster_kernels.py). The backward's 4 pixel-Gaussian
# pairs a thread keep it under 100 registers (16 pairs took 255 and spilled), so 2.5x the warps stay resident.
PASSES = (Pass(2, 8, 1), Pass(2, 4, 1))


@triton.jit
def _chunk_alpha(params_ptr, ids_ptr, j, valid, px, py, ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr):
    """One [pixels, chunk] block: ids, parameters, offsets from the means, sigma, exp(-sigma) and
    alpha (clamped at ALPHA_MAX, 0 where skipped: sigma < 0 or alpha < ALPHA_MIN)."""
    gid = tl.load(ids_ptr + j, mask=valid, other=0).to(tl.int64)
    base = params_ptr + gid * 6
    mx = tl.load(base + 0, mask=valid, other=0.0)
    my = tl.load(base + 1, mask=valid, other=0.0)
    ca = tl.load(base + 2, mask=valid, other=0.0)
    cb = tl.load(base + 3, mask=valid, other=0.0)
    cc = tl.load(base + 4, mask=valid, other=0.0)
    op = tl.load(base + 5, mask=valid, other=0.0)
    dx = px[:, None] - mx[None, :]
    dy = py[:, None] - my[None, :]
    sigma = 0.5 * (ca[None, :] * dx * dx + cc[None, :] * dy * dy) + cb[None, :] * dx * dy
    vis = tl.exp(-sigma)
    raw = op[None, :] * vis
    alpha = tl.minimum(raw, ALPHA_MAX)
    hit = valid[None, :] & (sigma >= 0) & (alpha >= ALPHA_MIN)
    alpha = tl.where(hit, alpha, 0.0)
    return gid, ca, cb, cc, dx, dy, vis, raw, alpha


@triton.jit
def _features(feat_ptr, gid, valid, F: tl.constexpr):
    """Rows ``gid`` of a [rows, F] tensor (a chunk's features, or pixels' output gradients), channels
    0..3 (one block each; channel 3 zero unless F == 4)."""
    base = feat_ptr + gid * F
    f0 = tl.load(base + 0, mask=valid, other=0.0)
    f1 = tl.load(base + 1, mask=valid, other=0.0)
    f2 = tl.load(base + 2, mask=valid, other=0.0)
    if F == 4:
        f3 = tl.load(base + 3, mask=valid, other=0.0)
    else:
        f3 = tl.zeros_like(f0)
    return f0, f1, f2, f3


@triton.jit
def _pixels(width, height, tiles_x, TILE: tl.constexpr, ROWS: tl.constexpr):
    """This program's pixels: ``ROWS`` rows of one tile (TILE // ROWS programs share a tile and its
    list). Returns the tile, pixel indices, centres (x, y) and which pixels lie in the image."""
    pid = tl.program_id(0)
    tile = pid // (TILE // ROWS)
    local = tl.arange(0, TILE * ROWS)
    x = (tile % tiles_x) * TILE + local % TILE
    y = (tile // tiles_x) * TILE + (pid % (TILE // ROWS)) * ROWS + local // TILE
    inside = (x < width) & (y < height)
    return tile, y * width + x, x.to(tl.float32) + 0.5, y.to(tl.float32) + 0.5, inside


@triton.jit
def _forward_kernel(params_ptr, feat_ptr, ids_ptr, offsets_ptr, out_ptr, trans_ptr, last_ptr,
                    width, height, tiles_x, F: tl.constexpr, TILE: tl.constexpr, ROWS: tl.constexpr,
                    CHUNK: tl.constexpr, ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr, T_MIN: tl.constexpr,
                    SKIP: tl.constexpr):
    """The tile's list ``CHUNK`` Gaussians at a time as a [pixels, chunk] block (their parameters
    loaded together), until every pixel of the program is finished; with SKIP, blocks no open pixel
    uses are passed over. Within a block the transmittance after each Gaussian is a running product
    along the chunk; a Gaussian is used while that product stays above T_MIN (it only falls, so the
    used ones are the list prefix before the stop). Stores blended features, final transmittance
    and, per pixel, one past the list position of the last Gaussian that contributed (``start``
    when none)."""
    tile, pix, px, py, inside = _pixels(width, height, tiles_x, TILE, ROWS)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    cols = tl.arange(0, CHUNK)
    trans = tl.full([TILE * ROWS], 1.0, tl.float32)
    acc0 = tl.zeros([TILE * ROWS], tl.float32)
    acc1 = tl.zeros([TILE * ROWS], tl.float32)
    acc2 = tl.zeros([TILE * ROWS], tl.float32)
    acc3 = tl.zeros([TILE * ROWS], tl.float32)
    last = tl.zeros([TILE * ROWS], tl.int32) + start
    done = ~inside
    cur = start
    alive = end > start
    while alive:
        j = cur + cols
        valid = j < end
        gid, ca, cb, cc, dx, dy, vis, raw, alpha = _chunk_alpha(params_ptr, ids_ptr, j, valid, px, py,
                                                                ALPHA_MIN, ALPHA_MAX)
        alpha = tl.where(done[:, None], 0.0, alpha)
        hit = alpha > 0
        if SKIP:  # a block no open pixel sees changes nothing
            go = tl.max(tl.max(hit.to(tl.int32), axis=1), axis=0) > 0
        else:
            go = True
        if go:
            keep = 1.0 - alpha
            after = trans[:, None] * tl.cumprod(keep, axis=1)  # transmittance after each Gaussian
            used = hit & (after > T_MIN)
            weight = tl.where(used, alpha * tl.fdiv(after, keep), 0.0)  # alpha * transmittance before it
            f0, f1, f2, f3 = _features(feat_ptr, gid, valid, F)
            acc0 += tl.sum(weight * f0[None, :], axis=1)
            acc1 += tl.sum(weight * f1[None, :], axis=1)
            acc2 += tl.sum(weight * f2[None, :], axis=1)
            if F == 4:
                acc3 += tl.sum(weight * f3[None, :], axis=1)
            trans = tl.minimum(trans, tl.min(tl.where(used, after, 1.0), axis=1))
            last = tl.maximum(last, tl.max(tl.where(used, j[None, :] + 1, 0), axis=1))
            done = done | (tl.max((hit & ~used).to(tl.int32), axis=1) > 0)
        cur += CHUNK
        alive = (cur < end) & (tl.min(done.to(tl.int32), axis=0) == 0)
    base = out_ptr + pix.to(tl.int64) * F
    tl.store(base + 0, acc0, mask=inside)
    tl.store(base + 1, acc1, mask=inside)
    tl.store(base + 2, acc2, mask=inside)
    if F == 4:
        tl.store(base + 3, acc3, mask=inside)
    tl.store(trans_ptr + pix, trans, mask=inside)
    tl.store(last_ptr + pix, last, mask=inside)


@triton.jit
def _backward_kernel(params_ptr, feat_ptr, ids_ptr, offsets_ptr, trans_ptr, last_ptr, grad_out_ptr, grad_trans_ptr,
                     grad_params_ptr, grad_feat_ptr, width, height, tiles_x,
                     F: tl.constexpr, TILE: tl.constexpr, ROWS: tl.constexpr, CHUNK: tl.constexpr,
                     ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr, SKIP: tl.constexpr):
    """Gradients of the forward's outputs back to params [M, 6] (means2d, conics, opacity) and
    features [M, F], replaying each pixel's contributing prefix back to front (see the module)."""
    tile, pix, px, py, inside = _pixels(width, height, tiles_x, TILE, ROWS)
    start = tl.load(offsets_ptr + tile)
    cols = tl.arange(0, CHUNK)
    final = tl.load(trans_ptr + pix, mask=inside, other=1.0)
    last = tl.load(last_ptr + pix, mask=inside, other=0)
    last = tl.where(inside, last, start)
    g0, g1, g2, g3 = _features(grad_out_ptr, pix.to(tl.int64), inside, F)
    # d(loss)/d(final transmittance) times the final transmittance: what every alpha scales
    through = tl.load(grad_trans_ptr + pix, mask=inside, other=0.0) * final
    later = tl.zeros([TILE * ROWS], tl.float32)  # sum over later Gaussians of weight * (grad . feature)
    trans = final  # transmittance after the current chunk
    top = tl.max(last, axis=0)
    chunks = tl.cdiv(top - start, CHUNK)
    for k in range(chunks):
        j = start + (chunks - 1 - k) * CHUNK + cols
        valid = j < top
        gid, ca, cb, cc, dx, dy, vis, raw, alpha = _chunk_alpha(params_ptr, ids_ptr, j, valid, px, py,
                                                                ALPHA_MIN, ALPHA_MAX)
        alpha = tl.where(j[None, :] < last[:, None], alpha, 0.0)
        used = alpha > 0
        if SKIP:  # a block no pixel used changes nothing
            go = tl.max(tl.max(used.to(tl.int32), axis=1), axis=0) > 0
        else:
            go = True
        if go:
            keep = 1.0 - alpha
            before = tl.fdiv(trans[:, None], tl.cumprod(keep, axis=1, reverse=True))  # transmittance before each
            f0, f1, f2, f3 = _features(feat_ptr, gid, valid, F)
            gf = g0[:, None] * f0[None, :] + g1[:, None] * f1[None, :] + g2[:, None] * f2[None, :] \
                + g3[:, None] * f3[None, :]
            weight = alpha * before
            wg = weight * gf
            after_j = later[:, None] + (tl.cumsum(wg, axis=1, reverse=True) - wg)
            grad_alpha = before * gf - tl.fdiv(after_j + through[:, None], keep)
            grad_alpha = tl.where(used & (raw <= ALPHA_MAX), grad_alpha, 0.0)
            grad_sigma = -grad_alpha * raw
            touched = valid & (tl.max(used.to(tl.int32), axis=0) > 0)
            gp = grad_params_ptr + gid * 6
            tl.atomic_add(gp + 0, tl.sum(-grad_sigma * (ca[None, :] * dx + cb[None, :] * dy), axis=0), mask=touched,
                          sem="relaxed")
            tl.atomic_add(gp + 1, tl.sum(-grad_sigma * (cb[None, :] * dx + cc[None, :] * dy), axis=0), mask=touched,
                          sem="relaxed")
            tl.atomic_add(gp + 2, tl.sum(0.5 * grad_sigma * dx * dx, axis=0), mask=touched, sem="relaxed")
            tl.atomic_add(gp + 3, tl.sum(grad_sigma * dx * dy, axis=0), mask=touched, sem="relaxed")
            tl.atomic_add(gp + 4, tl.sum(0.5 * grad_sigma * dy * dy, axis=0), mask=touched, sem="relaxed")
            tl.atomic_add(gp + 5, tl.sum(grad_alpha * vis, axis=0), mask=touched, sem="relaxed")
            gfeat = grad_feat_ptr + gid * F
            tl.atomic_add(gfeat + 0, tl.sum(weight * g0[:, None], axis=0), mask=touched, sem="relaxed")
            tl.atomic_add(gfeat + 1, tl.sum(weight * g1[:, None], axis=0), mask=touched, sem="relaxed")
            tl.atomic_add(gfeat + 2, tl.sum(weight * g2[:, None], axis=0), mask=touched, sem="relaxed")
            if F == 4:
                tl.atomic_add(gfeat + 3, tl.sum(weight * g3[:, None], axis=0), mask=touched, sem="relaxed")
            later += tl.sum(wg, axis=1)
            trans = tl.max(before, axis=1)



def _forward_options(channels: int, tile: int, forward: Pass, skip: bool) -> dict:
    """The forward kernel's constants and warps for ``channels`` features (the backward's below)."""
    return dict(F=channels, TILE=tile, ROWS=forward.rows, CHUNK=forward.chunk, ALPHA_MIN=ALPHA_MIN,
                ALPHA_MAX=ALPHA_MAX, T_MIN=T_MIN, SKIP=skip, num_warps=forward.warps)


def _backward_options(channels: int, tile: int, backward: Pass, skip: bool) -> dict:
    return dict(F=channels, TILE=tile, ROWS=backward.rows, CHUNK=backward.chunk, ALPHA_MIN=ALPHA_MIN,
                ALPHA_MAX=ALPHA_MAX, SKIP=skip, num_warps=backward.warps)


def warmups(device: torch.device | str, channels: int, width: int, height: int, gradients: bool, *,
            tile: int = TILE, passes: tuple[Pass, Pass] = PASSES, skip: bool = True) -> list[Warmup]:
    """The launches :func:`rasterize_triton` makes (its tile lists' included) for ``channels`` features and a
    ``width`` x ``height`` image (with ``gradients``: its backward's too), as
    :class:`~artnvg_core.triton_runtime.Warmup`."""
    f32, i32 = stand_in(torch.float32, device), stand_in(torch.int32, device)
    sizes = (width, height, -(-width // tile))  # width, height, tiles across
    found = [*tile_warmups(device, width, height, tile),
             Warmup(_forward_kernel, (f32, f32, i32, i32, f32, f32, i32, *sizes),
                    _forward_options(channels, tile, passes[0], skip))]
    if gradients:
        found.append(Warmup(_backward_kernel, (f32, f32, i32, i32, f32, i32, f32, f32, f32, f32, *sizes),
                            _backward_options(channels, tile, passes[1], skip)))
    return found


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, ids, offsets, width, height, tile, passes, skip):
        params = torch.cat([means2d, conics, opacities[:, None]], 1).contiguous()
        features = features.contiguous()
        channels = features.shape[1]
        out = features.new_empty(height, width, channels)
        trans = features.new_empty(height, width)
        last = torch.empty(height, width, dtype=torch.int32, device=features.device)
        tiles_x = -(-width // tile)
        forward = passes[0]
        grid = (tiles_x * -(-height // tile) * (tile // forward.rows),)
        _forward_kernel[grid](params, features, ids, offsets, out, trans, last, width, height, tiles_x,
                              **_forward_options(channels, tile, forward, skip))
        ctx.save_for_backward(params, features, ids, offsets, trans, last)
        ctx.settings = (width, height, tile, passes[1], skip)
        return out, trans

    @staticmethod
    def backward(ctx, grad_out, grad_trans):
        params, features, ids, offsets, trans, last = ctx.saved_tensors
        width, height, tile, backward, skip = ctx.settings
        grad_params = torch.zeros_like(params)
        grad_features = torch.zeros_like(features)
        grad_out = torch.zeros_like(features[:1, :1]).expand(height, width, -1) if grad_out is None else grad_out
        grad_trans = torch.zeros_like(trans) if grad_trans is None else grad_trans
        tiles_x = -(-width // tile)
        grid = (tiles_x * -(-height // tile) * (tile // backward.rows),)
        _backward_kernel[grid](params, features, ids, offsets, trans, last, grad_out.contiguous(),
                               grad_trans.contiguous(), grad_params, grad_features, width, height, tiles_x,
                               **_backward_options(features.shape[1], tile, backward, skip))
        return (grad_params[:, :2], grad_params[:, 2:5], grad_params[:, 5], grad_features,
                None, None, None, None, None, None, None)


def rasterize_triton(proj: Projection, features: torch.Tensor, width: int, height: int, *, tile: int = TILE,
                     passes: tuple[Pass, Pass] = PASSES, skip: bool = True, capacity: ListCapacity | None = None):
    """Composite one camera's projected Gaussians with the Triton kernels; the reference
    :func:`~.torch_backend.rasterize`'s contract (features [M, F] float32 with F 3 or 4, on CUDA or
    interpreted on the CPU). ``tile``: pixels per tile side (8 or 16); ``passes``: the forward and the
    backward kernel's :class:`Pass` (rows at most ``tile``); ``skip``: pass over blocks of Gaussians no
    pixel uses; ``capacity``: the tile lists' room (:class:`ListCapacity`; None: sized by waiting for the
    count). Returns blended features [H, W, F] (no background) and transmittance [H, W].
    """
    if features.shape[1] not in (3, 4):
        raise ValueError(f"rasterize_triton: features must have 3 or 4 channels, got {features.shape[1]}")
    ids, offsets = tile_lists(proj, width, height, tile, capacity)
    return _Composite.apply(proj.means2d, proj.conics, proj.opacities, features, ids, offsets,
                            width, height, tile, passes, skip)
