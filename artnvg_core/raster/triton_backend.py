"""Triton backend: tile intersection and sort with PyTorch operations, front-to-back compositing
forward and backward in Triton kernels (JIT-compiled on first use, cached by Triton; no native build).

It takes the fused projection and colours (:mod:`.triton_projection`, or the reference's) and replaces the
reference's per-pixel compositing (:func:`~.torch_backend.rasterize`) with the same semantics:
alpha = min(0.999, o * exp(-sigma)), samples with sigma < 0 or alpha < 1/255 skipped, compositing
in depth order (ties in projection order) stopping before the first Gaussian that would bring the
transmittance to <= 1e-4.

Each Triton program owns one ``tile`` x ``tile`` pixel tile. The forward pass walks the tile's
depth-sorted list one Gaussian at a time over the tile's pixels, keeping per pixel the final
transmittance and the end of the list prefix that contributed. The backward pass replays the lists
back to front from there (as gsplat does), ``chunk`` Gaussians at a time as a [pixels, chunk] block:
the transmittance before each Gaussian is recovered by division from the final one (a reversed
scan along the chunk), and the colour still to come is a suffix sum, so no difference of large sums
loses precision. Per-Gaussian gradients are summed over the tile's pixels, then added with atomics.

The kernels run on CUDA tensors, or on the CPU in Triton's interpreter (``TRITON_INTERPRET=1`` set
before this module is imported), which is how the tests check them where no GPU is.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from .projection import ALPHA_MIN, Projection
from .torch_backend import ALPHA_MAX, T_MIN

TILE = 16  # pixels per tile side
CHUNK = 8  # Gaussians per [pixels, chunk] block of the backward pass
CHECK = 32  # Gaussians between the forward pass's checks for a finished tile
WARPS = 4  # per program (a tile): with CHUNK, the fastest backward tried on an H100 (2-8 warps, chunks 8-32)


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
def _pixels(width, height, tiles_x, TILE: tl.constexpr):
    """This program's tile: pixel indices, centres (x, y) and which pixels lie in the image."""
    tile = tl.program_id(0)
    local = tl.arange(0, TILE * TILE)
    x = (tile % tiles_x) * TILE + local % TILE
    y = (tile // tiles_x) * TILE + local // TILE
    inside = (x < width) & (y < height)
    return tile, y * width + x, x.to(tl.float32) + 0.5, y.to(tl.float32) + 0.5, inside


@triton.jit
def _forward_kernel(params_ptr, feat_ptr, ids_ptr, offsets_ptr, out_ptr, trans_ptr, last_ptr,
                    width, height, tiles_x, F: tl.constexpr, TILE: tl.constexpr, CHECK: tl.constexpr,
                    ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr, T_MIN: tl.constexpr):
    """One Gaussian at a time over the tile's pixels; whether any pixel is still open is checked
    every CHECK Gaussians. Stores blended features, final transmittance and, per pixel, one past
    the list position of the last Gaussian that contributed (``start`` when none)."""
    tile, pix, px, py, inside = _pixels(width, height, tiles_x, TILE)
    start = tl.load(offsets_ptr + tile)
    end = tl.load(offsets_ptr + tile + 1)
    trans = tl.full([TILE * TILE], 1.0, tl.float32)
    acc0 = tl.zeros([TILE * TILE], tl.float32)
    acc1 = tl.zeros([TILE * TILE], tl.float32)
    acc2 = tl.zeros([TILE * TILE], tl.float32)
    acc3 = tl.zeros([TILE * TILE], tl.float32)
    last = tl.zeros([TILE * TILE], tl.int32) + start
    done = ~inside
    cur = start
    alive = end > start
    while alive:
        until = tl.minimum(cur + CHECK, end)
        for j in range(cur, until):
            gid = tl.load(ids_ptr + j).to(tl.int64)
            base = params_ptr + gid * 6
            dx = px - tl.load(base + 0)
            dy = py - tl.load(base + 1)
            sigma = 0.5 * (tl.load(base + 2) * dx * dx + tl.load(base + 4) * dy * dy) + tl.load(base + 3) * dx * dy
            alpha = tl.minimum(tl.load(base + 5) * tl.exp(-sigma), ALPHA_MAX)
            hit = (sigma >= 0) & (alpha >= ALPHA_MIN) & ~done
            after = trans * (1.0 - alpha)
            stop = hit & (after <= T_MIN)
            used = hit & ~stop
            weight = tl.where(used, alpha * trans, 0.0)
            feat = feat_ptr + gid * F
            acc0 += weight * tl.load(feat + 0)
            acc1 += weight * tl.load(feat + 1)
            acc2 += weight * tl.load(feat + 2)
            if F == 4:
                acc3 += weight * tl.load(feat + 3)
            trans = tl.where(used, after, trans)
            last = tl.where(used, j + 1, last)
            done = done | stop
        cur = until
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
                     F: tl.constexpr, TILE: tl.constexpr, CHUNK: tl.constexpr,
                     ALPHA_MIN: tl.constexpr, ALPHA_MAX: tl.constexpr):
    tile, pix, px, py, inside = _pixels(width, height, tiles_x, TILE)
    start = tl.load(offsets_ptr + tile)
    cols = tl.arange(0, CHUNK)
    final = tl.load(trans_ptr + pix, mask=inside, other=1.0)
    last = tl.load(last_ptr + pix, mask=inside, other=0)
    last = tl.where(inside, last, start)
    g0, g1, g2, g3 = _features(grad_out_ptr, pix.to(tl.int64), inside, F)
    # d(loss)/d(final transmittance) times the final transmittance: what every alpha scales
    through = tl.load(grad_trans_ptr + pix, mask=inside, other=0.0) * final
    later = tl.zeros([TILE * TILE], tl.float32)  # sum over later Gaussians of weight * (grad . feature)
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
        keep = 1.0 - alpha
        before = trans[:, None] / tl.cumprod(keep, axis=1, reverse=True)  # transmittance before each
        f0, f1, f2, f3 = _features(feat_ptr, gid, valid, F)
        gf = g0[:, None] * f0[None, :] + g1[:, None] * f1[None, :] + g2[:, None] * f2[None, :] \
            + g3[:, None] * f3[None, :]
        weight = alpha * before
        wg = weight * gf
        after_j = later[:, None] + (tl.cumsum(wg, axis=1, reverse=True) - wg)
        grad_alpha = before * gf - (after_j + through[:, None]) / keep
        grad_alpha = tl.where(used & (raw <= ALPHA_MAX), grad_alpha, 0.0)
        grad_sigma = -grad_alpha * raw
        touched = valid & (tl.max(used.to(tl.int32), axis=0) > 0)
        gp = grad_params_ptr + gid * 6
        tl.atomic_add(gp + 0, tl.sum(-grad_sigma * (ca[None, :] * dx + cb[None, :] * dy), axis=0), mask=touched)
        tl.atomic_add(gp + 1, tl.sum(-grad_sigma * (cb[None, :] * dx + cc[None, :] * dy), axis=0), mask=touched)
        tl.atomic_add(gp + 2, tl.sum(0.5 * grad_sigma * dx * dx, axis=0), mask=touched)
        tl.atomic_add(gp + 3, tl.sum(grad_sigma * dx * dy, axis=0), mask=touched)
        tl.atomic_add(gp + 4, tl.sum(0.5 * grad_sigma * dy * dy, axis=0), mask=touched)
        tl.atomic_add(gp + 5, tl.sum(grad_alpha * vis, axis=0), mask=touched)
        gfeat = grad_feat_ptr + gid * F
        tl.atomic_add(gfeat + 0, tl.sum(weight * g0[:, None], axis=0), mask=touched)
        tl.atomic_add(gfeat + 1, tl.sum(weight * g1[:, None], axis=0), mask=touched)
        tl.atomic_add(gfeat + 2, tl.sum(weight * g2[:, None], axis=0), mask=touched)
        if F == 4:
            tl.atomic_add(gfeat + 3, tl.sum(weight * g3[:, None], axis=0), mask=touched)
        later += tl.sum(wg, axis=1)
        trans = tl.max(before, axis=1)


@triton.jit
def _emit_kernel(x0_ptr, y0_ptr, span_x_ptr, counts_ptr, ends_ptr, gauss_ptr, tile_ptr, id_ptr, n, tiles_x,
                 BLOCK_G: tl.constexpr, BLOCK_T: tl.constexpr):
    """Gaussian i's (tile id, Gaussian id) pairs go to ends[i] - counts[i]..ends[i]; one program
    writes those of BLOCK_G Gaussians, BLOCK_T tiles of each at a time."""
    i = tl.program_id(0) * BLOCK_G + tl.arange(0, BLOCK_G)
    inside = i < n
    x0 = tl.load(x0_ptr + i, mask=inside, other=0)
    y0 = tl.load(y0_ptr + i, mask=inside, other=0)
    span_x = tl.maximum(tl.load(span_x_ptr + i, mask=inside, other=1), 1)
    count = tl.load(counts_ptr + i, mask=inside, other=0)
    start = tl.load(ends_ptr + i, mask=inside, other=0) - count
    gauss = tl.load(gauss_ptr + i, mask=inside, other=0).to(tl.int32)
    for k in range(0, tl.max(count, axis=0), BLOCK_T):
        local = k + tl.arange(0, BLOCK_T)[None, :]
        tile = (y0[:, None] + local // span_x[:, None]) * tiles_x + x0[:, None] + local % span_x[:, None]
        where = start[:, None] + local
        mask = local < count[:, None]
        tl.store(tile_ptr + where, tile.to(tl.int32), mask=mask)
        tl.store(id_ptr + where, gauss[:, None] + tl.zeros_like(local).to(tl.int32), mask=mask)


def tile_lists(proj: Projection, width: int, height: int, tile: int = TILE):
    """Depth-sorted Gaussian lists per tile, as the reference's ``_tile_lists`` orders them.

    Gaussians with negative radii (culled by :mod:`.triton_projection`, which keeps all N) get no tiles.
    Returns (ids [I] int32 indices into the projection, grouped by tile, depth-sorted within one,
    ties in projection order; offsets [tiles + 1] int32, tile t's run is ids[offsets[t]:offsets[t+1]]).
    One host synchronisation (the number of intersections sizes the lists); a Triton kernel writes
    the (tile, Gaussian) pairs, one stable radix sort by tile groups them.
    """
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    device = proj.means2d.device
    with torch.no_grad():
        by_depth = torch.argsort(proj.depths, stable=True)
        center = proj.means2d[by_depth].double()  # exact bounds for centres far off the image
        radii = proj.radii[by_depth].double()
        x0 = torch.floor((center[:, 0] - radii[:, 0]) / tile).clamp(0, tiles_x).long()
        x1 = torch.ceil((center[:, 0] + radii[:, 0]) / tile).clamp(0, tiles_x).long()
        y0 = torch.floor((center[:, 1] - radii[:, 1]) / tile).clamp(0, tiles_y).long()
        y1 = torch.ceil((center[:, 1] + radii[:, 1]) / tile).clamp(0, tiles_y).long()
        span_x = x1 - x0
        counts = torch.where(radii[:, 0] < 0, 0, span_x * (y1 - y0))  # radii -1: culled, no tiles
        ends = torch.cumsum(counts, 0)
        total = int(ends[-1])
        tile_id = torch.empty(total, dtype=torch.int32, device=device)
        ids = torch.empty(total, dtype=torch.int32, device=device)
        grid = (triton.cdiv(len(by_depth), 32),)
        _emit_kernel[grid](x0, y0, span_x, counts, ends, by_depth, tile_id, ids, len(by_depth), tiles_x,
                           BLOCK_G=32, BLOCK_T=32, num_warps=4)
        tile_id, order = torch.sort(tile_id, stable=True)
        ids = ids[order]
        bounds = torch.arange(tiles_x * tiles_y + 1, device=device, dtype=torch.int32)
        offsets = torch.searchsorted(tile_id, bounds, out_int32=True)
    return ids, offsets


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, ids, offsets, width, height, tile, chunk):
        params = torch.cat([means2d, conics, opacities[:, None]], 1).contiguous()
        features = features.contiguous()
        channels = features.shape[1]
        out = features.new_empty(height, width, channels)
        trans = features.new_empty(height, width)
        last = torch.empty(height, width, dtype=torch.int32, device=features.device)
        tiles_x = -(-width // tile)
        grid = (tiles_x * -(-height // tile),)
        _forward_kernel[grid](params, features, ids, offsets, out, trans, last, width, height, tiles_x,
                              F=channels, TILE=tile, CHECK=CHECK, ALPHA_MIN=ALPHA_MIN, ALPHA_MAX=ALPHA_MAX,
                              T_MIN=T_MIN, num_warps=WARPS)
        ctx.save_for_backward(params, features, ids, offsets, trans, last)
        ctx.shape = (width, height, tile, chunk)
        return out, trans

    @staticmethod
    def backward(ctx, grad_out, grad_trans):
        params, features, ids, offsets, trans, last = ctx.saved_tensors
        width, height, tile, chunk = ctx.shape
        grad_params = torch.zeros_like(params)
        grad_features = torch.zeros_like(features)
        grad_out = torch.zeros_like(features[:1, :1]).expand(height, width, -1) if grad_out is None else grad_out
        grad_trans = torch.zeros_like(trans) if grad_trans is None else grad_trans
        tiles_x = -(-width // tile)
        grid = (tiles_x * -(-height // tile),)
        _backward_kernel[grid](params, features, ids, offsets, trans, last, grad_out.contiguous(),
                               grad_trans.contiguous(), grad_params, grad_features, width, height, tiles_x,
                               F=features.shape[1], TILE=tile, CHUNK=chunk, ALPHA_MIN=ALPHA_MIN,
                               ALPHA_MAX=ALPHA_MAX, num_warps=WARPS)
        return (grad_params[:, :2], grad_params[:, 2:5], grad_params[:, 5], grad_features,
                None, None, None, None, None, None)


def rasterize_triton(proj: Projection, features: torch.Tensor, width: int, height: int, *,
                     tile: int = TILE, chunk: int = CHUNK):
    """Composite one camera's projected Gaussians with the Triton kernels; the reference
    :func:`~.torch_backend.rasterize`'s contract (features [M, F] float32 with F 3 or 4, on CUDA or
    interpreted on the CPU). ``tile``: pixels per tile side (8 or 16); ``chunk``: Gaussians per block
    (a power of two). Returns blended features [H, W, F] (no background) and transmittance [H, W].
    """
    if features.shape[1] not in (3, 4):
        raise ValueError(f"rasterize_triton: features must have 3 or 4 channels, got {features.shape[1]}")
    ids, offsets = tile_lists(proj, width, height, tile)
    return _Composite.apply(proj.means2d, proj.conics, proj.opacities, features, ids, offsets,
                            width, height, tile, chunk)

