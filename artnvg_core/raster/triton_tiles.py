"""Triton tile lists: for each ``tile`` x ``tile`` tile of an image, the Gaussians that reach its pixels, in
depth order (:func:`tile_lists`), for :mod:`.triton_backend`'s compositing.

Kernels count and write each Gaussian's (tile, Gaussian) pairs in depth order, one per tile of its
footprint box whose pixel centres it reaches at alpha >= 1/255 (found tile row by tile row,
conservatively: the samples left out are ones the compositing skips), and one stable radix sort by
tile groups them. Renders made one after another can share a :class:`ListCapacity`, so that none waits
for its intersection count.

The kernels run on CUDA tensors, or on the CPU in Triton's interpreter (``TRITON_INTERPRET=1`` set
before this module is imported).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from ..triton_runtime import Warmup, stand_in
from .projection import ALPHA_MIN, Projection

TILE = 16  # pixels per tile side
# The tile test's margins (:func:`_gaussian_level`, :func:`_row_tiles`): the compositing's float32 sigma
# falls short of the exact one by under 1e-6 of the quadratic form's diagonal terms (slack 1e-5 of
# them); its float32 pixel offsets are within 1e-7 of their size of the exact ones (margin 1e-6 and
# 1e-3 px, where float64 rounding needs 1e-12).
_TILE_SLACK, _REL_MARGIN, _PX_MARGIN = tl.constexpr(1e-5), tl.constexpr(1e-6), tl.constexpr(1e-3)
_ALPHA_MIN = tl.constexpr(ALPHA_MIN)


@triton.jit
def _tile_rect(means2d_ptr, radii_ptr, order_ptr, i, inside, tiles_x, tiles_y, TILE: tl.constexpr):
    """The footprint boxes of depth-ranked Gaussians ``i``: Gaussian ids, the box's first tile (x0, y0),
    its width in tiles and its tile count (0 when culled: radii -1). Bounds in float64, exact for
    centres far off the image."""
    gauss = tl.load(order_ptr + i, mask=inside, other=0)
    cx = tl.load(means2d_ptr + gauss * 2 + 0, mask=inside, other=0.0).to(tl.float64)
    cy = tl.load(means2d_ptr + gauss * 2 + 1, mask=inside, other=0.0).to(tl.float64)
    rx = tl.load(radii_ptr + gauss * 2 + 0, mask=inside, other=-1)
    ry = tl.load(radii_ptr + gauss * 2 + 1, mask=inside, other=-1)
    fx, fy = rx.to(tl.float64), ry.to(tl.float64)
    x0 = tl.minimum(tl.maximum(tl.math.floor((cx - fx) / TILE), 0.0), tiles_x).to(tl.int32)
    x1 = tl.minimum(tl.maximum(tl.math.ceil((cx + fx) / TILE), 0.0), tiles_x).to(tl.int32)
    y0 = tl.minimum(tl.maximum(tl.math.floor((cy - fy) / TILE), 0.0), tiles_y).to(tl.int32)
    y1 = tl.minimum(tl.maximum(tl.math.ceil((cy + fy) / TILE), 0.0), tiles_y).to(tl.int32)
    span_x = x1 - x0
    count = tl.where(rx < 0, 0, span_x * (y1 - y0))
    return gauss, x0, y0, span_x, count


@triton.jit
def _gaussian_level(conics_ptr, opac_ptr, means2d_ptr, gauss):
    """Float64 footprint data of Gaussians ``gauss``: the conic (a, b, c) shrunk on its diagonal by
    _TILE_SLACK (more than the compositing's float32 sigma can fall short of the exact one, relative to
    the diagonal terms), its determinant, the sigma level log(255 o) (+1e-4: the compositing's exp and
    products) below which alpha reaches 1/255, and the centre (x, y)."""
    a = tl.load(conics_ptr + gauss * 3 + 0).to(tl.float64) * (1.0 - _TILE_SLACK)
    b = tl.load(conics_ptr + gauss * 3 + 1).to(tl.float64)
    c = tl.load(conics_ptr + gauss * 3 + 2).to(tl.float64) * (1.0 - _TILE_SLACK)
    level = tl.log(tl.load(opac_ptr + gauss).to(tl.float64) * (1.0 / _ALPHA_MIN)) + 1e-4
    cx = tl.load(means2d_ptr + gauss * 2 + 0).to(tl.float64)
    cy = tl.load(means2d_ptr + gauss * 2 + 1).to(tl.float64)
    return a, b, c, a * c - b * b, level, cx, cy


@triton.jit
def _row_tiles(a, b, c, det, level, cx, cy, row, x0, span_x, TILE: tl.constexpr):
    """The first and last tile columns (within the box's columns x0..x0 + span_x - 1; last < first: none)
    of tile row ``row`` whose pixel centres reach the Gaussian's {sigma <= level} (see
    :func:`_gaussian_level`). Where that set is an ellipse, its part within the row's band of pixel
    centres is convex, so a tile's centres reach it exactly where their x range meets the part's x
    range: the ellipse's x at the band's y nearest the ellipse's right- and leftmost points, widened by
    _PX_MARGIN px and _REL_MARGIN of the terms (float64 rounding, the compositing's float32 offsets).
    Elsewhere (a shrunk form that is not positive definite, non-finite values) the whole box row."""
    y_lo = (row * TILE).to(tl.float64) + 0.5 - cy
    y_hi = y_lo + (TILE - 1)
    widen_y = _PX_MARGIN + _REL_MARGIN * tl.maximum(tl.abs(y_lo), tl.abs(y_hi))
    reach = tl.sqrt(tl.maximum(2.0 * a * level, 0.0))  # a * the ellipse's x half width at dy = 0
    half_h = reach / tl.sqrt(det)  # the ellipse's y half height
    lo = tl.maximum(y_lo - widen_y, -half_h)
    hi = tl.minimum(y_hi + widen_y, half_h)
    peak = -b * half_h / tl.sqrt(a * c)  # dy of the rightmost point (the leftmost at -peak)
    dy_r = tl.minimum(tl.maximum(peak, lo), hi)
    dy_l = tl.minimum(tl.maximum(-peak, lo), hi)
    right = (-b * dy_r + tl.sqrt(tl.maximum(reach * reach - det * dy_r * dy_r, 0.0))) / a
    left = (-b * dy_l - tl.sqrt(tl.maximum(reach * reach - det * dy_l * dy_l, 0.0))) / a
    widen_x = _PX_MARGIN + _REL_MARGIN * ((tl.abs(b) * tl.maximum(tl.abs(lo), tl.abs(hi)) + reach) / a
                                          + tl.abs(cx))
    first_x = tl.math.ceil((cx + left - widen_x - (TILE - 0.5)) / TILE)
    last_x = tl.math.floor((cx + right + widen_x - 0.5) / TILE)
    box_last = x0 + span_x - 1
    ellipse = (a > 0) & (c > 0) & (det > 0) & (level == level) & (tl.abs(cx) < 1e18) & (tl.abs(cy) < 1e18)
    empty = ellipse & ((level < 0) | (lo > hi))
    first = tl.where(ellipse, tl.minimum(tl.maximum(first_x, x0.to(tl.float64)), box_last + 1.0), x0)
    last = tl.where(ellipse, tl.minimum(tl.maximum(last_x, x0 - 1.0), box_last.to(tl.float64)), box_last)
    last = tl.where(empty, x0 - 1, last)
    return first.to(tl.int32), last.to(tl.int32)


@triton.jit(do_not_specialize=["n"])
def _count_kernel(means2d_ptr, radii_ptr, conics_ptr, opac_ptr, order_ptr, counts_ptr, n, tiles_x, tiles_y,
                  TILE: tl.constexpr, BLOCK_G: tl.constexpr, BLOCK_R: tl.constexpr):
    """counts[i]: the tiles whose pixel centres the i-th Gaussian in depth order reaches at alpha >=
    1/255 (:func:`_row_tiles`, box row by box row, BLOCK_R rows at a time)."""
    i = tl.program_id(0) * BLOCK_G + tl.arange(0, BLOCK_G)
    inside = i < n
    gauss, x0, y0, span_x, count = _tile_rect(means2d_ptr, radii_ptr, order_ptr, i, inside, tiles_x, tiles_y, TILE)
    span_y = tl.where(count > 0, count // tl.maximum(span_x, 1), 0)
    a, b, c, det, level, cx, cy = _gaussian_level(conics_ptr, opac_ptr, means2d_ptr, gauss)
    total = tl.zeros([BLOCK_G], tl.int32)
    for k in range(0, tl.max(span_y, axis=0), BLOCK_R):
        rows = k + tl.arange(0, BLOCK_R)[None, :]
        first, last = _row_tiles(a[:, None], b[:, None], c[:, None], det[:, None], level[:, None], cx[:, None],
                                 cy[:, None], y0[:, None] + rows, x0[:, None], span_x[:, None], TILE)
        total += tl.sum(tl.where(rows < span_y[:, None], tl.maximum(last - first + 1, 0), 0), axis=1)
    tl.store(counts_ptr + i, total, mask=inside)


@triton.jit(do_not_specialize=["n", "room"])
def _emit_kernel(means2d_ptr, radii_ptr, conics_ptr, opac_ptr, order_ptr, ends_ptr, tile_ptr, id_ptr, n,
                 tiles_x, tiles_y, room, TILE: tl.constexpr, BLOCK_G: tl.constexpr, BLOCK_T: tl.constexpr):
    """The i-th Gaussian in depth order writes its (tile id, Gaussian id) pairs, row by row of its box
    (the tiles :func:`_count_kernel` counted), to ends[i - 1]..ends[i] (ends: the counts' inclusive
    sums), those below ``room`` (the lists' length); one program writes those of BLOCK_G Gaussians,
    BLOCK_T tiles of a row at a time."""
    i = tl.program_id(0) * BLOCK_G + tl.arange(0, BLOCK_G)
    inside = i < n
    gauss, x0, y0, span_x, count = _tile_rect(means2d_ptr, radii_ptr, order_ptr, i, inside, tiles_x, tiles_y, TILE)
    span_y = tl.where(count > 0, count // tl.maximum(span_x, 1), 0)
    a, b, c, det, level, cx, cy = _gaussian_level(conics_ptr, opac_ptr, means2d_ptr, gauss)
    where = tl.load(ends_ptr + i - 1, mask=inside & (i > 0), other=0)  # the pairs of earlier Gaussians
    cols = tl.arange(0, BLOCK_T)[None, :]
    for r in range(0, tl.max(span_y, axis=0)):
        first, last = _row_tiles(a, b, c, det, level, cx, cy, y0 + r, x0, span_x, TILE)
        width = tl.where(r < span_y, tl.maximum(last - first + 1, 0), 0)
        for k in range(0, tl.max(width, axis=0), BLOCK_T):
            local = k + cols
            at = where[:, None] + local
            mask = (local < width[:, None]) & (at < room)
            tile = (y0 + r)[:, None] * tiles_x + first[:, None] + local
            tl.store(tile_ptr + at, tile.to(tile_ptr.dtype.element_ty), mask=mask)
            tl.store(id_ptr + at, gauss[:, None].to(tl.int32) + tl.zeros_like(local), mask=mask)
        where += width


class ListCapacity:
    """Room for the tile lists of renders made one after another (a finetune's steps), so that none of them
    waits for its intersection count: the first render counts and waits, as one without a capacity does,
    and sets the room to MARGIN times its count (SLACK more at least); each later render is given that
    room and records its count where the host can read it once the count is done (a copy queued right
    after it), and whether it overflowed as a device flag. A render that overflowed was truncated;
    :meth:`overflowed` (the host check, which waits for the recorded counts only) then says so and grows
    the room, and the caller repeats that render's step, which it skipped on the device
    (:meth:`take_overflow`)."""

    MARGIN, SLACK = 1.1, 1024  # room: the count times MARGIN, at least SLACK more (less room: more steps taken again)

    def __init__(self):
        self.room: int | None = None
        self._counts: list[tuple[torch.Tensor, torch.cuda.Event | None]] = []
        self._overflow: torch.Tensor | None = None

    def size_for(self, total: int) -> None:
        """Room for ``total`` intersections and a margin."""
        self.room = max(int(total * self.MARGIN), total + self.SLACK)

    def record(self, total: torch.Tensor) -> None:
        """A render's count (a device tensor [1]) given :attr:`room` entries."""
        flag = total[0] > self.room
        self._overflow = flag if self._overflow is None else self._overflow | flag
        if total.is_cuda:
            host = torch.empty(1, dtype=total.dtype, pin_memory=True)
            host.copy_(total, non_blocking=True)
            event = torch.cuda.Event()
            event.record()
            self._counts.append((host, event))
        else:
            self._counts.append((total, None))

    def take_overflow(self) -> torch.Tensor | None:
        """Whether any render since the last call overflowed (a device bool scalar; None: no render)."""
        flag, self._overflow = self._overflow, None
        return flag

    def overflowed(self) -> bool:
        """Whether a render recorded since the last call had more intersections than its room (the room
        then grows to fit it); waits for those renders' counts, not for anything queued after them."""
        largest = 0
        for host, event in self._counts:
            if event is not None:
                event.synchronize()
            largest = max(largest, int(host[0]))
        self._counts.clear()
        if self.room is not None and largest > self.room:
            self.size_for(largest)
            return True
        return False


COUNT_BLOCK, EMIT_BLOCK = 64, 32  # Gaussians per program of the kernels that count and write the pairs


def _count_options(tile: int) -> dict:
    return dict(TILE=tile, BLOCK_G=COUNT_BLOCK, BLOCK_R=4, num_warps=4)


def _emit_options(tile: int) -> dict:
    return dict(TILE=tile, BLOCK_G=EMIT_BLOCK, BLOCK_T=8, num_warps=1)


def _sizes(width: int, height: int, tile: int) -> tuple[int, int, torch.dtype]:
    """Tiles across and down a ``width`` x ``height`` image, and the dtype of their ids with room for the bound
    ``tiles`` (16-bit keys while they fit: half the radix sort's passes of 32-bit ones)."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    return tiles_x, tiles_y, torch.int16 if tiles_x * tiles_y < 2**15 else torch.int32


def warmups(device: torch.device | str, width: int, height: int, tile: int = TILE) -> list[Warmup]:
    """The launches :func:`tile_lists` makes for a ``width`` x ``height`` image, as
    :class:`~artnvg_core.triton_runtime.Warmup`."""
    tiles_x, tiles_y, key = _sizes(width, height, tile)
    f32, i64, i32 = (stand_in(dtype, device) for dtype in (torch.float32, torch.int64, torch.int32))
    footprints = (f32, i64, f32, f32, i64)  # _footprint_inputs, the depth order
    return [Warmup(_count_kernel, (*footprints, i32, 0, tiles_x, tiles_y), _count_options(tile)),
            Warmup(_emit_kernel, (*footprints, i64, stand_in(key, device), i32, 0, tiles_x, tiles_y, 0),
                   _emit_options(tile))]


def _footprint_inputs(proj: Projection) -> tuple[torch.Tensor, ...]:
    """What the tile kernels read of a projection: means2d, radii, conics, opacities (detached, contiguous)."""
    return (proj.means2d.detach().contiguous(), proj.radii.contiguous(), proj.conics.detach().contiguous(),
            proj.opacities.detach().contiguous())


def _count_tiles(proj: Projection, by_depth: torch.Tensor, tiles_x: int, tiles_y: int, tile: int) -> torch.Tensor:
    """counts [max(N, 1)] int32: the tiles each Gaussian in depth order ``by_depth`` reaches."""
    n = len(by_depth)
    counts = torch.zeros(max(n, 1), dtype=torch.int32, device=by_depth.device)
    if n:
        _count_kernel[(triton.cdiv(n, COUNT_BLOCK),)](*_footprint_inputs(proj), by_depth, counts, n, tiles_x,
                                                      tiles_y, **_count_options(tile))
    return counts


def _write_pairs(proj: Projection, by_depth: torch.Tensor, ends: torch.Tensor, room: int, tiles_x: int, tiles_y: int,
                 tile: int, key: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The (tile id [room] ``key``, Gaussian id [room] int32) pairs in depth order, the Gaussians'
    counts' inclusive sums ``ends`` locating each one's; entries past the last hold the tile id
    ``tiles_x * tiles_y`` and Gaussian 0."""
    tile_id = torch.full((room,), tiles_x * tiles_y, dtype=key, device=by_depth.device)
    ids = torch.zeros(room, dtype=torch.int32, device=by_depth.device)
    n = len(by_depth)
    if room and n:
        _emit_kernel[(triton.cdiv(n, EMIT_BLOCK),)](*_footprint_inputs(proj), by_depth, ends, tile_id, ids, n,
                                                    tiles_x, tiles_y, room, **_emit_options(tile))
    return tile_id, ids


def tile_lists(proj: Projection, width: int, height: int, tile: int = TILE, capacity: ListCapacity | None = None):
    """Depth-sorted Gaussian lists per tile: the reference's ``_tile_lists`` (footprint boxes) less the
    tiles whose pixel centres a Gaussian cannot reach at alpha >= 1/255 (:func:`_row_tiles`).

    Gaussians with negative radii (culled by :mod:`.triton_projection`, which keeps all N) get no tiles.
    Returns (ids [I] int32 indices into the projection, grouped by tile, depth-sorted within one,
    ties in projection order; offsets [tiles + 1] int32, tile t's run is ids[offsets[t]:offsets[t+1]]).
    Triton kernels count and write the (tile, Gaussian) pairs in depth order, one stable radix sort by
    tile groups them (16-bit keys while the tiles fit: half the passes of 32-bit ones). The lists'
    length I is the count, which the host waits for, or, with a sized ``capacity``, its room (no wait;
    entries past the count hold the key ``tiles``, so they sort last and no tile's run includes them).
    """
    tiles_x, tiles_y, key = _sizes(width, height, tile)
    tiles = tiles_x * tiles_y
    with torch.no_grad():
        by_depth = torch.argsort(proj.depths, stable=True)
        ends = torch.cumsum(_count_tiles(proj, by_depth, tiles_x, tiles_y, tile), 0)
        if capacity is None or capacity.room is None:
            room = int(ends[-1])
            if capacity is not None:
                capacity.size_for(room)
        else:
            room = capacity.room
            capacity.record(ends[-1:])
        tile_id, ids = _write_pairs(proj, by_depth, ends, room, tiles_x, tiles_y, tile, key)
        tile_id, order = torch.sort(tile_id, stable=True)
        ids = ids[order]
        offsets = torch.searchsorted(tile_id, torch.arange(tiles + 1, device=ids.device, dtype=key), out_int32=True)
    return ids, offsets
