"""The SH colours' Triton helpers for :mod:`.triton_projection`'s kernels: a Gaussian's viewing direction,
the SH basis and its derivatives (up to degree 3, the constants of :mod:`.sh`), and a Gaussian's SH
coefficients as one contiguous row of all channels (columns told apart by channel), summed per channel."""

from __future__ import annotations

import triton
import triton.language as tl

from ..scene import SH_C0
from .sh import COLOR_MAX, SH_C1, SH_C2, SH_C3

# the kernels' constants (Triton reads globals only as constexpr)
_COLOR_MAX, _C0, _C1 = tl.constexpr(COLOR_MAX), tl.constexpr(SH_C0), tl.constexpr(SH_C1)
_C2_0, _C2_1, _C2_2, _C2_3, _C2_4 = (tl.constexpr(c) for c in SH_C2)
_C3_0, _C3_1, _C3_2, _C3_3, _C3_4, _C3_5, _C3_6 = (tl.constexpr(c) for c in SH_C3)


@triton.jit
def direction(means_ptr, cam_ptr, i, live):
    """Unit viewing direction (camera centre -> mean), its length (clamped at 1e-12) and whether it
    was clamped."""
    dx = tl.load(means_ptr + i * 3 + 0, mask=live, other=1.0) - tl.load(cam_ptr + 16)
    dy = tl.load(means_ptr + i * 3 + 1, mask=live, other=0.0) - tl.load(cam_ptr + 17)
    dz = tl.load(means_ptr + i * 3 + 2, mask=live, other=0.0) - tl.load(cam_ptr + 18)
    length = tl.sqrt(dx * dx + dy * dy + dz * dz)
    div = tl.maximum(length, 1e-12)
    return dx / div, dy / div, dz / div, div, length >= 1e-12


@triton.jit
def basis(x, y, z, DEGREE: tl.constexpr):
    """The 16 real SH basis values (0 past ``DEGREE``), each formed as :func:`.sh.sh_to_color` forms it."""
    zero = tl.zeros_like(x)
    b1, b2, b3, b4, b5, b6, b7, b8 = zero, zero, zero, zero, zero, zero, zero, zero
    b9, b10, b11, b12, b13, b14, b15 = zero, zero, zero, zero, zero, zero, zero
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    if DEGREE > 0:
        b1, b2, b3 = -(y * _C1), z * _C1, -(x * _C1)
    if DEGREE > 1:
        b4 = xy * _C2_0
        b5 = yz * _C2_1
        b6 = (2 * zz - xx - yy) * _C2_2
        b7 = xz * _C2_3
        b8 = (xx - yy) * _C2_4
    if DEGREE > 2:
        b9 = y * (3 * xx - yy) * _C3_0
        b10 = xy * z * _C3_1
        b11 = y * (4 * zz - xx - yy) * _C3_2
        b12 = z * (2 * zz - 3 * xx - 3 * yy) * _C3_3
        b13 = x * (4 * zz - xx - yy) * _C3_4
        b14 = z * (xx - yy) * _C3_5
        b15 = x * (xx - 3 * yy) * _C3_6
    return b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15


@triton.jit
def basis_grad(k: tl.constexpr, x, y, z):
    """d basis_k / d (x, y, z) for k >= 1."""
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    zero = tl.zeros_like(x)
    if k == 1:
        out = (zero, zero - _C1, zero)
    elif k == 2:
        out = (zero, zero, zero + _C1)
    elif k == 3:
        out = (zero - _C1, zero, zero)
    elif k == 4:
        out = (y * _C2_0, x * _C2_0, zero)
    elif k == 5:
        out = (zero, z * _C2_1, y * _C2_1)
    elif k == 6:
        out = (x * (-2 * _C2_2), y * (-2 * _C2_2), z * (4 * _C2_2))
    elif k == 7:
        out = (z * _C2_3, zero, x * _C2_3)
    elif k == 8:
        out = (x * (2 * _C2_4), y * (-2 * _C2_4), zero)
    elif k == 9:
        out = (6 * xy * _C3_0, (3 * xx - 3 * yy) * _C3_0, zero)
    elif k == 10:
        out = (yz * _C3_1, xz * _C3_1, xy * _C3_1)
    elif k == 11:
        out = (xy * (-2 * _C3_2), (4 * zz - xx - 3 * yy) * _C3_2, yz * (8 * _C3_2))
    elif k == 12:
        out = (xz * (-6 * _C3_3), yz * (-6 * _C3_3), (6 * zz - 3 * xx - 3 * yy) * _C3_3)
    elif k == 13:
        out = ((4 * zz - 3 * xx - yy) * _C3_4, xy * (-2 * _C3_4), xz * (8 * _C3_4))
    elif k == 14:
        out = (xz * (2 * _C3_5), yz * (-2 * _C3_5), (xx - yy) * _C3_5)
    else:
        out = ((3 * xx - 3 * yy) * _C3_6, xy * (-6 * _C3_6), zero)
    return out


@triton.jit
def basis_rows(x, y, z, k, DEGREE: tl.constexpr):
    """The SH basis as rows [BLOCK, W]: a column of basis index ``k`` [W] holds SH_C0 (k = 0) or basis
    value k (0 past ``DEGREE`` and past 15)."""
    b1, b2, b3, b4, b5, b6, b7, b8, b9, b10, b11, b12, b13, b14, b15 = basis(x, y, z, DEGREE)
    k = k[None, :]
    rows = tl.where(k == 0, _C0, 0.0) + tl.zeros_like(x)[:, None]
    if DEGREE > 0:
        rows = tl.where(k == 1, b1[:, None], tl.where(k == 2, b2[:, None], tl.where(k == 3, b3[:, None], rows)))
    if DEGREE > 1:
        rows = tl.where(k == 4, b4[:, None], tl.where(k == 5, b5[:, None], tl.where(k == 6, b6[:, None], rows)))
        rows = tl.where(k == 7, b7[:, None], tl.where(k == 8, b8[:, None], rows))
    if DEGREE > 2:
        rows = tl.where(k == 9, b9[:, None], tl.where(k == 10, b10[:, None], tl.where(k == 11, b11[:, None], rows)))
        rows = tl.where(k == 12, b12[:, None], tl.where(k == 13, b13[:, None], rows))
        rows = tl.where(k == 14, b14[:, None], tl.where(k == 15, b15[:, None], rows))
    return rows


@triton.jit
def sh_rows(sh_ptr, i, live, K: tl.constexpr, W: tl.constexpr, DEGREE: tl.constexpr):
    """The SH coefficients of Gaussians ``i`` as rows [BLOCK, W] in memory order (column c: coefficient
    c // 3 of channel c % 3; 0 past ``DEGREE``), the basis index and channel of each column [W]: one
    contiguous load per Gaussian, whatever the degree (a kernel of few memory operations also
    compiles in a fraction of the time)."""
    cols = tl.arange(0, W)
    used = live[:, None] & (cols[None, :] < 3 * (DEGREE + 1) * (DEGREE + 1))
    return tl.load(sh_ptr + i[:, None] * (K * 3) + cols[None, :], mask=used, other=0.0), cols // 3, cols % 3


@triton.jit
def channel_sums(rows, channel):
    """Each channel's sum over its columns of ``rows`` [BLOCK, W] (column channels ``channel`` [W])."""
    return (tl.sum(tl.where(channel[None, :] == 0, rows, 0.0), axis=1),
            tl.sum(tl.where(channel[None, :] == 1, rows, 0.0), axis=1),
            tl.sum(tl.where(channel[None, :] == 2, rows, 0.0), axis=1))


@triton.jit
def clamped_color(value):
    """A colour from its SH sum: ``value + 0.5`` clamped to [0, COLOR_MAX] (:mod:`.sh`)."""
    return tl.minimum(tl.maximum(value + 0.5, 0.0), _COLOR_MAX)


@triton.jit
def unclamped_grad(g_ptr, color, keep):
    """A colour's gradient where the forward's clamp to [0, COLOR_MAX] let the colour through, else 0."""
    return tl.where((color >= 0) & (color <= _COLOR_MAX), tl.load(g_ptr, mask=keep, other=0.0), 0.0)
