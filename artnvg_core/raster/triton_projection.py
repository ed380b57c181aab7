"""Fused per-Gaussian projection and SH colours for the Triton backend: one kernel computes, for all N
Gaussians at once, what :func:`.projection.project` and :func:`.sh.sh_to_color` compute (the
reference, kept for the torch and gsplat backends), and two more give the gradients (the colours',
then the geometry's), the vector-Jacobian products derived by hand (the module's comments give each
step). A Gaussian's SH coefficients (and their gradients) move as one contiguous row of all channels,
the channels told apart by column: one load and one store, coalesced, where a block per channel read
and wrote every third float. Triton's compile time grows with a kernel's memory operations faster
than linearly (its coalescing pass), so few operations and two small backward kernels compile in a
third of the time one large one took.

Same semantics as the reference: camera-space mean, culling (near plane, opacity >= 1/255, on
screen), means2d, conics, depth, opacity (antialiased compensation when asked), radii and colours
(SH up to ``degree``, capped as :mod:`.sh`). Every output has N rows; culled Gaussians get radii
-1 (which :func:`.triton_tiles.tile_lists` gives no tiles) and zero gradients, so no host sync
sizes anything here. Float32 throughout except the 2D covariance and its inverse (largest scale
factored out, determinant as a sum of squared 2x2 minors, the reference's formulation), kept in
float64: factored by the largest scale k in float32, a needle's thin axes square below float32's
normal range (the "needle 45 x 1e-2" hard case measured 56 dB against 123 dB); a float32 variant
with the determinant scaled by k^2 instead of k^4 was not tried. In a per-Gaussian kernel the
float64 arithmetic costs registers and FP64 throughput, not memory traffic.
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from ..triton_runtime import Warmup, stand_in
from .projection import ALPHA_MIN, MAX_EXTENT, MAX_RADIUS_PX, Projection
from .triton_sh import basis_grad, basis_rows, channel_sums, clamped_color, direction, sh_rows, unclamped_grad

BLOCK = 128  # Gaussians per program
COLOR_BLOCK = 32  # per program of the colours' backward (its seven [Gaussians, 3 K] blocks spill at 128)
# the kernels' constants (Triton reads globals only as constexpr)
TINY64 = tl.constexpr(2.2250738585072014e-308)  # float64's smallest normal: the determinant's floor, as the reference's
_ALPHA_MIN, _MAX_EXTENT, _MAX_RADIUS = tl.constexpr(ALPHA_MIN), tl.constexpr(MAX_EXTENT), tl.constexpr(MAX_RADIUS_PX)


@triton.jit
def _geometry(means_ptr, quats_ptr, scales_ptr, logits_ptr, cam_ptr, i, live, width, height, near, blur):
    """Everything the forward pass computes for Gaussians ``i`` (the backward pass recomputes it)."""
    w00 = tl.load(cam_ptr + 0)
    w01 = tl.load(cam_ptr + 1)
    w02 = tl.load(cam_ptr + 2)
    w10 = tl.load(cam_ptr + 3)
    w11 = tl.load(cam_ptr + 4)
    w12 = tl.load(cam_ptr + 5)
    w20 = tl.load(cam_ptr + 6)
    w21 = tl.load(cam_ptr + 7)
    w22 = tl.load(cam_ptr + 8)
    fx = tl.load(cam_ptr + 12)
    fy = tl.load(cam_ptr + 13)
    cx = tl.load(cam_ptr + 14)
    cy = tl.load(cam_ptr + 15)
    mx = tl.load(means_ptr + i * 3 + 0, mask=live, other=0.0)
    my = tl.load(means_ptr + i * 3 + 1, mask=live, other=0.0)
    mz = tl.load(means_ptr + i * 3 + 2, mask=live, other=0.0)
    x = w00 * mx + w01 * my + w02 * mz + tl.load(cam_ptr + 9)
    y = w10 * mx + w11 * my + w12 * mz + tl.load(cam_ptr + 10)
    zc = w20 * mx + w21 * my + w22 * mz + tl.load(cam_ptr + 11)
    op = 1.0 / (1.0 + tl.exp(-tl.load(logits_ptr + i, mask=live, other=0.0)))
    front = live & (zc > near)
    z = tl.where(front, zc, 1.0)  # culled lanes compute on a harmless depth
    # the perspective Jacobian with x/z and y/z clamped to 1.3x the field of view
    lim_xp = (width - cx) / fx + 0.15 * width / fx
    lim_xn = cx / fx + 0.15 * width / fx
    lim_yp = (height - cy) / fy + 0.15 * height / fy
    lim_yn = cy / fy + 0.15 * height / fy
    ratio_x = x / z
    ratio_y = y / z
    free_x = (ratio_x >= -lim_xn) & (ratio_x <= lim_xp)
    free_y = (ratio_y >= -lim_yn) & (ratio_y <= lim_yp)
    tx = z * tl.minimum(tl.maximum(ratio_x, -lim_xn), lim_xp)
    ty = z * tl.minimum(tl.maximum(ratio_y, -lim_yn), lim_yp)
    jx = fx / z
    jy = fy / z
    jxz = -fx * tx / (z * z)
    jyz = -fy * ty / (z * z)
    # unit quaternion: divided by its largest component (no square under- or overflows), then by its norm
    qw = tl.load(quats_ptr + i * 4 + 0, mask=live, other=1.0)
    qx = tl.load(quats_ptr + i * 4 + 1, mask=live, other=0.0)
    qy = tl.load(quats_ptr + i * 4 + 2, mask=live, other=0.0)
    qz = tl.load(quats_ptr + i * 4 + 3, mask=live, other=0.0)
    largest = tl.maximum(tl.maximum(tl.abs(qw), tl.abs(qx)), tl.maximum(tl.abs(qy), tl.abs(qz)))
    largest = tl.where(largest > 0, largest, 1.0)
    qw, qx, qy, qz = qw / largest, qx / largest, qy / largest, qz / largest
    qnorm = tl.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    qdiv = tl.maximum(qnorm, 1e-12)
    qw, qx, qy, qz = qw / qdiv, qx / qdiv, qy / qdiv, qz / qdiv
    # W R (camera rotation times the Gaussian's), float64
    r00 = (1 - 2 * (qy * qy + qz * qz)).to(tl.float64)
    r01 = (2 * (qx * qy - qw * qz)).to(tl.float64)
    r02 = (2 * (qx * qz + qw * qy)).to(tl.float64)
    r10 = (2 * (qx * qy + qw * qz)).to(tl.float64)
    r11 = (1 - 2 * (qx * qx + qz * qz)).to(tl.float64)
    r12 = (2 * (qy * qz - qw * qx)).to(tl.float64)
    r20 = (2 * (qx * qz - qw * qy)).to(tl.float64)
    r21 = (2 * (qy * qz + qw * qx)).to(tl.float64)
    r22 = (1 - 2 * (qx * qx + qy * qy)).to(tl.float64)
    a00 = w00.to(tl.float64) * r00 + w01.to(tl.float64) * r10 + w02.to(tl.float64) * r20
    a01 = w00.to(tl.float64) * r01 + w01.to(tl.float64) * r11 + w02.to(tl.float64) * r21
    a02 = w00.to(tl.float64) * r02 + w01.to(tl.float64) * r12 + w02.to(tl.float64) * r22
    a10 = w10.to(tl.float64) * r00 + w11.to(tl.float64) * r10 + w12.to(tl.float64) * r20
    a11 = w10.to(tl.float64) * r01 + w11.to(tl.float64) * r11 + w12.to(tl.float64) * r21
    a12 = w10.to(tl.float64) * r02 + w11.to(tl.float64) * r12 + w12.to(tl.float64) * r22
    a20 = w20.to(tl.float64) * r00 + w21.to(tl.float64) * r10 + w22.to(tl.float64) * r20
    a21 = w20.to(tl.float64) * r01 + w21.to(tl.float64) * r11 + w22.to(tl.float64) * r21
    a22 = w20.to(tl.float64) * r02 + w21.to(tl.float64) * r12 + w22.to(tl.float64) * r22
    # scales relative to the largest k = exp(top), top >= 0 (constant for the gradients)
    ls0 = tl.load(scales_ptr + i * 3 + 0, mask=live, other=0.0).to(tl.float64)
    ls1 = tl.load(scales_ptr + i * 3 + 1, mask=live, other=0.0).to(tl.float64)
    ls2 = tl.load(scales_ptr + i * 3 + 2, mask=live, other=0.0).to(tl.float64)
    top = tl.maximum(tl.maximum(tl.maximum(ls0, ls1), ls2), 0.0)
    s0 = tl.exp(ls0 - top)
    s1 = tl.exp(ls1 - top)
    s2 = tl.exp(ls2 - top)
    # rows of A' = J W R S / k: entry j scales with s_j only
    b00 = jx.to(tl.float64) * a00 + jxz.to(tl.float64) * a20
    b01 = jx.to(tl.float64) * a01 + jxz.to(tl.float64) * a21
    b02 = jx.to(tl.float64) * a02 + jxz.to(tl.float64) * a22
    b10 = jy.to(tl.float64) * a10 + jyz.to(tl.float64) * a20
    b11 = jy.to(tl.float64) * a11 + jyz.to(tl.float64) * a21
    b12 = jy.to(tl.float64) * a12 + jyz.to(tl.float64) * a22
    p0, p1, p2 = b00 * s0, b01 * s1, b02 * s2
    q0, q1, q2 = b10 * s0, b11 * s1, b12 * s2
    inv_k2 = tl.exp(-2 * top)
    bl = blur * inv_k2
    ca = p0 * p0 + p1 * p1 + p2 * p2 + bl
    cb = p0 * q0 + p1 * q1 + p2 * q2
    cc = q0 * q0 + q1 * q1 + q2 * q2 + bl
    m0 = p1 * q2 - p2 * q1  # r0 x r1: the 2x2 minors
    m1 = p2 * q0 - p0 * q2
    m2 = p0 * q1 - p1 * q0
    det_un = m0 * m0 + m1 * m1 + m2 * m2
    det = det_un + bl * (ca + cc - bl)
    return (x, y, z, zc, front, op, fx, fy, cx, cy, free_x, free_y, tx, ty, jx, jy, jxz, jyz,
            qw, qx, qy, qz, qnorm, qdiv, largest,
            r00, r01, r02, r10, r11, r12, r20, r21, r22, a00, a01, a02, a10, a11, a12, a20, a21, a22,
            top, s0, s1, s2, b00, b01, b02, b10, b11, b12, p0, p1, p2, q0, q1, q2,
            inv_k2, bl, ca, cb, cc, m0, m1, m2, det_un, det)



@triton.jit(do_not_specialize=["n"])
def _forward_kernel(means_ptr, quats_ptr, scales_ptr, logits_ptr, sh_ptr, cam_ptr,
                    means2d_ptr, conics_ptr, depths_ptr, opac_ptr, colors_ptr, radii_ptr,
                    n, width, height, near, blur,
                    K: tl.constexpr, W: tl.constexpr, DEGREE: tl.constexpr, AA: tl.constexpr,
                    BLOCK: tl.constexpr):
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = i < n
    i = i.to(tl.int64)
    (x, y, z, zc, front, op, fx, fy, cx, cy, free_x, free_y, tx, ty, jx, jy, jxz, jyz,
     qw, qx, qy, qz, qnorm, qdiv, largest,
     r00, r01, r02, r10, r11, r12, r20, r21, r22, a00, a01, a02, a10, a11, a12, a20, a21, a22,
     top, s0, s1, s2, b00, b01, b02, b10, b11, b12, p0, p1, p2, q0, q1, q2,
     inv_k2, bl, ca, cb, cc, m0, m1, m2, det_un, det) = _geometry(
        means_ptr, quats_ptr, scales_ptr, logits_ptr, cam_ptr, i, live, width, height, near, blur)
    det_c = tl.maximum(det, TINY64)
    opacity = op
    if AA:
        opacity = op * tl.sqrt(det_un / det_c).to(tl.float32)
    scale = inv_k2 / det_c
    u = fx * x / z + cx
    v = fy * y / z + cy
    # footprint: where alpha can reach 1/255, cut to the image
    extent = tl.minimum(tl.sqrt(2.0 * tl.maximum(tl.log(opacity / _ALPHA_MIN), 0.0)), _MAX_EXTENT)
    rad_x = tl.math.ceil(extent.to(tl.float64) * tl.exp(top + 0.5 * tl.log(ca))).to(tl.float32)
    rad_y = tl.math.ceil(extent.to(tl.float64) * tl.exp(top + 0.5 * tl.log(cc))).to(tl.float32)
    on_screen = (u + rad_x > 0) & (u - rad_x < width) & (v + rad_y > 0) & (v - rad_y < height)
    rad_x = tl.minimum(tl.minimum(rad_x, tl.math.ceil(tl.maximum(tl.abs(u), tl.abs(u - width)))), _MAX_RADIUS)
    rad_y = tl.minimum(tl.minimum(rad_y, tl.math.ceil(tl.maximum(tl.abs(v), tl.abs(v - height)))), _MAX_RADIUS)
    keep = front & (op >= _ALPHA_MIN) & on_screen
    tl.store(radii_ptr + i * 2 + 0, tl.where(keep, rad_x.to(tl.int64), -1), mask=live)
    tl.store(radii_ptr + i * 2 + 1, tl.where(keep, rad_y.to(tl.int64), -1), mask=live)
    tl.store(means2d_ptr + i * 2 + 0, u, mask=live)
    tl.store(means2d_ptr + i * 2 + 1, v, mask=live)
    tl.store(conics_ptr + i * 3 + 0, (cc * scale).to(tl.float32), mask=live)
    tl.store(conics_ptr + i * 3 + 1, (-cb * scale).to(tl.float32), mask=live)
    tl.store(conics_ptr + i * 3 + 2, (ca * scale).to(tl.float32), mask=live)
    tl.store(depths_ptr + i, zc, mask=live)
    tl.store(opac_ptr + i, opacity, mask=live)
    # colours: SH(dir) + 0.5, clamped to [0, COLOR_MAX]
    dx, dy, dz, _, _ = direction(means_ptr, cam_ptr, i, live)
    coefficients, k, channel = sh_rows(sh_ptr, i, live, K, W, DEGREE)
    r, g, b = channel_sums(basis_rows(dx, dy, dz, k, DEGREE) * coefficients, channel)
    tl.store(colors_ptr + i * 3 + 0, clamped_color(r), mask=live)
    tl.store(colors_ptr + i * 3 + 1, clamped_color(g), mask=live)
    tl.store(colors_ptr + i * 3 + 2, clamped_color(b), mask=live)


@triton.jit(do_not_specialize=["n"])
def _color_backward_kernel(means_ptr, sh_ptr, cam_ptr, radii_ptr, g_colors_ptr, g_means_ptr, g_sh_ptr, n,
                           K: tl.constexpr, W: tl.constexpr, DEGREE: tl.constexpr, BLOCK: tl.constexpr):
    """Gradients of the colours: all of the SH coefficients' (g_sh) and the means' through the viewing
    direction (g_means, which :func:`_backward_kernel` then completes); a kernel of its own, as two small
    kernels compile in far less time than their sum (Triton's coalescing pass grows faster than the
    kernel)."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = i < n
    i = i.to(tl.int64)
    keep = live & (tl.load(radii_ptr + i * 2, mask=live, other=-1) >= 0)
    dx, dy, dz, dlen, dfree = direction(means_ptr, cam_ptr, i, live)
    coefficients, k, channel = sh_rows(sh_ptr, i, keep, K, W, DEGREE)
    basis = basis_rows(dx, dy, dz, k, DEGREE)
    r, g, b = channel_sums(basis * coefficients, channel)
    g_r = unclamped_grad(g_colors_ptr + i * 3 + 0, r + 0.5, keep)
    g_g = unclamped_grad(g_colors_ptr + i * 3 + 1, g + 0.5, keep)
    g_b = unclamped_grad(g_colors_ptr + i * 3 + 2, b + 0.5, keep)
    g_color = tl.where(channel[None, :] == 0, g_r[:, None], tl.where(channel[None, :] == 1, g_g[:, None], g_b[:, None]))
    cols = tl.arange(0, W)
    tl.store(g_sh_ptr + i[:, None] * (K * 3) + cols[None, :], g_color * basis,
             mask=live[:, None] & (cols[None, :] < K * 3))
    weights = g_color * coefficients  # d loss / d basis value, per column
    ddx = tl.zeros_like(basis)  # d basis / d direction, as rows
    ddy = tl.zeros_like(basis)
    ddz = tl.zeros_like(basis)
    for basis_k in tl.static_range(1, (DEGREE + 1) * (DEGREE + 1)):
        kx, ky, kz = basis_grad(basis_k, dx, dy, dz)
        column = k[None, :] == basis_k
        ddx = tl.where(column, kx[:, None], ddx)
        ddy = tl.where(column, ky[:, None], ddy)
        ddz = tl.where(column, kz[:, None], ddz)
    gdx = tl.sum(weights * ddx, axis=1)
    gdy = tl.sum(weights * ddy, axis=1)
    gdz = tl.sum(weights * ddz, axis=1)
    # the unit direction d / max(|d|, eps), d = mean - camera centre
    radial_d = tl.where(dfree, dx * gdx + dy * gdy + dz * gdz, 0.0)
    tl.store(g_means_ptr + i * 3 + 0, (gdx - dx * radial_d) / dlen, mask=live)
    tl.store(g_means_ptr + i * 3 + 1, (gdy - dy * radial_d) / dlen, mask=live)
    tl.store(g_means_ptr + i * 3 + 2, (gdz - dz * radial_d) / dlen, mask=live)


@triton.jit(do_not_specialize=["n"])
def _backward_kernel(means_ptr, quats_ptr, scales_ptr, logits_ptr, cam_ptr, radii_ptr,
                     g_means2d_ptr, g_conics_ptr, g_depths_ptr, g_opac_ptr,
                     g_means_ptr, g_quats_ptr, g_scales_ptr, g_logits_ptr,
                     n, width, height, near, blur, AA: tl.constexpr, BLOCK: tl.constexpr):
    """Gradients of the geometry's outputs (means2d, conics, depths, opacities) back to means, quats, log
    scales and opacity logits; g_means holds the colours' part on entry."""
    i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    live = i < n
    i = i.to(tl.int64)
    keep = live & (tl.load(radii_ptr + i * 2, mask=live, other=-1) >= 0)
    (x, y, z, zc, front, op, fx, fy, cx, cy, free_x, free_y, tx, ty, jx, jy, jxz, jyz,
     qw, qx, qy, qz, qnorm, qdiv, largest,
     r00, r01, r02, r10, r11, r12, r20, r21, r22, a00, a01, a02, a10, a11, a12, a20, a21, a22,
     top, s0, s1, s2, b00, b01, b02, b10, b11, b12, p0, p1, p2, q0, q1, q2,
     inv_k2, bl, ca, cb, cc, m0, m1, m2, det_un, det) = _geometry(
        means_ptr, quats_ptr, scales_ptr, logits_ptr, cam_ptr, i, live, width, height, near, blur)
    gu = tl.load(g_means2d_ptr + i * 2 + 0, mask=keep, other=0.0)
    gv = tl.load(g_means2d_ptr + i * 2 + 1, mask=keep, other=0.0)
    gk0 = tl.load(g_conics_ptr + i * 3 + 0, mask=keep, other=0.0).to(tl.float64)
    gk1 = tl.load(g_conics_ptr + i * 3 + 1, mask=keep, other=0.0).to(tl.float64)
    gk2 = tl.load(g_conics_ptr + i * 3 + 2, mask=keep, other=0.0).to(tl.float64)
    g_opacity = tl.load(g_opac_ptr + i, mask=keep, other=0.0)
    # conic = (c, -b, a) * s with s = inv_k2 / max(det, tiny)
    det_ok = det >= TINY64
    det_c = tl.maximum(det, TINY64)
    scale = inv_k2 / det_c
    g_a = gk2 * scale
    g_b = -gk1 * scale
    g_c = gk0 * scale
    g_det = tl.where(det_ok, -(gk0 * cc - gk1 * cb + gk2 * ca) * scale / det_c, 0.0)
    g_det_un = tl.zeros_like(g_det)
    g_op = g_opacity
    if AA:  # opacity' = op * sqrt(det_un / det_c)
        ratio = det_un / det_c
        root = tl.sqrt(ratio)
        g_op = g_opacity * root.to(tl.float32)
        g_ratio = tl.where(root > 0, (g_opacity * op).to(tl.float64) * 0.5 / root, 0.0)
        g_det_un += g_ratio / det_c
        g_det += tl.where(det_ok, -g_ratio * ratio / det_c, 0.0)
    # det = det_un + bl * (a + c - bl)
    g_det_un += g_det
    g_a += g_det * bl
    g_c += g_det * bl
    # det_un = |m|^2, m = r0 x r1; a = |r0|^2 + bl, b = r0 . r1, c = |r1|^2 + bl
    gm0, gm1, gm2 = 2 * m0 * g_det_un, 2 * m1 * g_det_un, 2 * m2 * g_det_un
    gp0 = (q1 * gm2 - q2 * gm1) + 2 * p0 * g_a + q0 * g_b  # r1 x g_m
    gp1 = (q2 * gm0 - q0 * gm2) + 2 * p1 * g_a + q1 * g_b
    gp2 = (q0 * gm1 - q1 * gm0) + 2 * p2 * g_a + q2 * g_b
    gq0 = (gm1 * p2 - gm2 * p1) + 2 * q0 * g_c + p0 * g_b  # g_m x r0
    gq1 = (gm2 * p0 - gm0 * p2) + 2 * q1 * g_c + p1 * g_b
    gq2 = (gm0 * p1 - gm1 * p0) + 2 * q2 * g_c + p2 * g_b
    # r0_j = B0j s_j, r1_j = B1j s_j, s_j = exp(ls_j - top)
    g_ls0 = (gp0 * b00 + gq0 * b10) * s0
    g_ls1 = (gp1 * b01 + gq1 * b11) * s1
    g_ls2 = (gp2 * b02 + gq2 * b12) * s2
    gb00, gb01, gb02 = gp0 * s0, gp1 * s1, gp2 * s2
    gb10, gb11, gb12 = gq0 * s0, gq1 * s1, gq2 * s2
    # B0j = jx A0j + jxz A2j, B1j = jy A1j + jyz A2j (A = W R)
    g_jx = (gb00 * a00 + gb01 * a01 + gb02 * a02).to(tl.float32)
    g_jxz = (gb00 * a20 + gb01 * a21 + gb02 * a22).to(tl.float32)
    g_jy = (gb10 * a10 + gb11 * a11 + gb12 * a12).to(tl.float32)
    g_jyz = (gb10 * a20 + gb11 * a21 + gb12 * a22).to(tl.float32)
    ga00, ga01, ga02 = gb00 * jx.to(tl.float64), gb01 * jx.to(tl.float64), gb02 * jx.to(tl.float64)
    ga10, ga11, ga12 = gb10 * jy.to(tl.float64), gb11 * jy.to(tl.float64), gb12 * jy.to(tl.float64)
    ga20 = gb00 * jxz.to(tl.float64) + gb10 * jyz.to(tl.float64)
    ga21 = gb01 * jxz.to(tl.float64) + gb11 * jyz.to(tl.float64)
    ga22 = gb02 * jxz.to(tl.float64) + gb12 * jyz.to(tl.float64)
    # R's gradient: W^T g_A
    w00 = tl.load(cam_ptr + 0).to(tl.float64)
    w01 = tl.load(cam_ptr + 1).to(tl.float64)
    w02 = tl.load(cam_ptr + 2).to(tl.float64)
    w10 = tl.load(cam_ptr + 3).to(tl.float64)
    w11 = tl.load(cam_ptr + 4).to(tl.float64)
    w12 = tl.load(cam_ptr + 5).to(tl.float64)
    w20 = tl.load(cam_ptr + 6).to(tl.float64)
    w21 = tl.load(cam_ptr + 7).to(tl.float64)
    w22 = tl.load(cam_ptr + 8).to(tl.float64)
    gr00 = (w00 * ga00 + w10 * ga10 + w20 * ga20).to(tl.float32)
    gr01 = (w00 * ga01 + w10 * ga11 + w20 * ga21).to(tl.float32)
    gr02 = (w00 * ga02 + w10 * ga12 + w20 * ga22).to(tl.float32)
    gr10 = (w01 * ga00 + w11 * ga10 + w21 * ga20).to(tl.float32)
    gr11 = (w01 * ga01 + w11 * ga11 + w21 * ga21).to(tl.float32)
    gr12 = (w01 * ga02 + w11 * ga12 + w21 * ga22).to(tl.float32)
    gr20 = (w02 * ga00 + w12 * ga10 + w22 * ga20).to(tl.float32)
    gr21 = (w02 * ga01 + w12 * ga11 + w22 * ga21).to(tl.float32)
    gr22 = (w02 * ga02 + w12 * ga12 + w22 * ga22).to(tl.float32)
    # the rotation matrix of the unit quaternion (w, x, y, z)
    gqw = 2 * (-qz * gr01 + qy * gr02 + qz * gr10 - qx * gr12 - qy * gr20 + qx * gr21)
    gqx = 2 * (qy * gr01 + qz * gr02 + qy * gr10 - 2 * qx * gr11 - qw * gr12 + qz * gr20 + qw * gr21 - 2 * qx * gr22)
    gqy = 2 * (-2 * qy * gr00 + qx * gr01 + qw * gr02 + qx * gr10 + qz * gr12 - qw * gr20 + qz * gr21 - 2 * qy * gr22)
    gqz = 2 * (-2 * qz * gr00 - qw * gr01 + qx * gr02 + qw * gr10 - 2 * qz * gr11 + qy * gr12 + qx * gr20 + qy * gr21)
    # normalisation: q / max(|q|, eps) (the norm's part only where it was not clamped), then / largest
    radial = tl.where(qnorm >= 1e-12, qw * gqw + qx * gqx + qy * gqy + qz * gqz, 0.0)
    gqw = (gqw - qw * radial) / qdiv / largest
    gqx = (gqx - qx * radial) / qdiv / largest
    gqy = (gqy - qy * radial) / qdiv / largest
    gqz = (gqz - qz * radial) / qdiv / largest
    # camera-space mean: means2d, the Jacobian's entries (tx, ty clamped), depth
    z2 = z * z
    gx = gu * fx / z
    gy = gv * fy / z
    gz = -(gu * fx * x + gv * fy * y) / z2 - (g_jx * fx + g_jy * fy) / z2 \
        + 2 * (g_jxz * fx * tx + g_jyz * fy * ty) / (z2 * z) \
        + tl.load(g_depths_ptr + i, mask=keep, other=0.0)
    g_tx = -g_jxz * fx / z2
    g_ty = -g_jyz * fy / z2
    gx += tl.where(free_x, g_tx, 0.0)
    gy += tl.where(free_y, g_ty, 0.0)
    gz += tl.where(free_x, 0.0, g_tx * tx / z) + tl.where(free_y, 0.0, g_ty * ty / z)
    # mean_c = W m + t, beside the colours' part (from _color_backward_kernel)
    g_mx = tl.load(g_means_ptr + i * 3 + 0, mask=keep, other=0.0)
    g_my = tl.load(g_means_ptr + i * 3 + 1, mask=keep, other=0.0)
    g_mz = tl.load(g_means_ptr + i * 3 + 2, mask=keep, other=0.0)
    g_mx += w00.to(tl.float32) * gx + w10.to(tl.float32) * gy + w20.to(tl.float32) * gz
    g_my += w01.to(tl.float32) * gx + w11.to(tl.float32) * gy + w21.to(tl.float32) * gz
    g_mz += w02.to(tl.float32) * gx + w12.to(tl.float32) * gy + w22.to(tl.float32) * gz
    tl.store(g_means_ptr + i * 3 + 0, tl.where(keep, g_mx, 0.0), mask=live)
    tl.store(g_means_ptr + i * 3 + 1, tl.where(keep, g_my, 0.0), mask=live)
    tl.store(g_means_ptr + i * 3 + 2, tl.where(keep, g_mz, 0.0), mask=live)
    tl.store(g_quats_ptr + i * 4 + 0, tl.where(keep, gqw, 0.0), mask=live)
    tl.store(g_quats_ptr + i * 4 + 1, tl.where(keep, gqx, 0.0), mask=live)
    tl.store(g_quats_ptr + i * 4 + 2, tl.where(keep, gqy, 0.0), mask=live)
    tl.store(g_quats_ptr + i * 4 + 3, tl.where(keep, gqz, 0.0), mask=live)
    tl.store(g_scales_ptr + i * 3 + 0, tl.where(keep, g_ls0.to(tl.float32), 0.0), mask=live)
    tl.store(g_scales_ptr + i * 3 + 1, tl.where(keep, g_ls1.to(tl.float32), 0.0), mask=live)
    tl.store(g_scales_ptr + i * 3 + 2, tl.where(keep, g_ls2.to(tl.float32), 0.0), mask=live)
    tl.store(g_logits_ptr + i, tl.where(keep, g_op * op * (1 - op), 0.0), mask=live)


def _forward_options(coefficients: int, degree: int, antialiased: bool) -> dict:
    """The forward kernel's constants and warps for SH ``coefficients`` (K) per channel (the backward's below)."""
    return dict(K=coefficients, W=triton.next_power_of_2(3 * coefficients), DEGREE=degree, AA=antialiased,
                BLOCK=BLOCK, num_warps=4)


def _color_backward_options(coefficients: int, degree: int) -> dict:
    return dict(K=coefficients, W=triton.next_power_of_2(3 * coefficients), DEGREE=degree, BLOCK=COLOR_BLOCK,
                num_warps=4)


def _backward_options(antialiased: bool) -> dict:
    return dict(AA=antialiased, BLOCK=BLOCK, num_warps=4)


def warmups(device: torch.device | str, coefficients: int, width: int, height: int, degree: int, antialiased: bool,
            gradients: bool) -> list[Warmup]:
    """The launches :func:`project_color_triton` makes for SH ``coefficients`` per channel (K) at ``degree``
    and a ``width`` x ``height`` camera (with ``gradients``: its backward's too), as
    :class:`~artnvg_core.triton_runtime.Warmup`."""
    f32, i64 = stand_in(torch.float32, device), stand_in(torch.int64, device)
    bounds = (0, width, height, 0.0, 0.0)  # n, width, height, near plane, blur
    found = [Warmup(_forward_kernel, (f32,) * 11 + (i64, *bounds), _forward_options(coefficients, degree, antialiased))]
    if gradients:
        found += [Warmup(_color_backward_kernel, (f32, f32, f32, i64, f32, f32, f32, 0),
                         _color_backward_options(coefficients, degree)),
                  Warmup(_backward_kernel, (f32,) * 5 + (i64,) + (f32,) * 8 + bounds, _backward_options(antialiased))]
    return found


class _ProjectColor(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, log_scales, opacity_logits, sh, camera, settings):
        width, height, near, blur, degree, antialiased = settings
        n, k = len(means), sh.shape[1]
        inputs = [t.contiguous() for t in (means, quats, log_scales, opacity_logits, sh, camera)]
        means2d, conics = means.new_empty(n, 2), means.new_empty(n, 3)
        depths, opacities, colors = means.new_empty(n), means.new_empty(n), means.new_empty(n, 3)
        radii = torch.empty(n, 2, dtype=torch.long, device=means.device)
        _forward_kernel[(triton.cdiv(n, BLOCK),)](*inputs, means2d, conics, depths, opacities, colors, radii, n,
                                                  width, height, near, blur, **_forward_options(k, degree, antialiased))
        ctx.save_for_backward(*inputs, radii)
        ctx.settings = settings
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, opacities, colors, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_opacities, g_colors, _):
        means, quats, log_scales, logits, sh, camera, radii = ctx.saved_tensors
        width, height, near, blur, degree, antialiased = ctx.settings
        n = len(means)
        grads_in = [torch.zeros(shape, dtype=means.dtype, device=means.device) if g is None else g.contiguous()
                    for g, shape in ((g_means2d, (n, 2)), (g_conics, (n, 3)), (g_depths, (n,)),
                                     (g_opacities, (n,)), (g_colors, (n, 3)))]
        g_means, g_quats, g_scales, g_logits, g_sh = (torch.empty_like(t) for t in (means, quats, log_scales, logits, sh))
        _color_backward_kernel[(triton.cdiv(n, COLOR_BLOCK),)](
            means, sh, camera, radii, grads_in[4], g_means, g_sh, n, **_color_backward_options(sh.shape[1], degree))
        _backward_kernel[(triton.cdiv(n, BLOCK),)](
            means, quats, log_scales, logits, camera, radii, *grads_in[:4], g_means, g_quats, g_scales, g_logits, n,
            width, height, near, blur, **_backward_options(antialiased))
        return g_means, g_quats, g_scales, g_logits, g_sh, None, None


def project_color_triton(means, quats, log_scales, opacity_logits, sh, world_to_cam, intrinsics, center,
                         width: int, height: int, degree: int, near_plane: float = 0.01,
                         blur_px2: float = 0.3, antialiased: bool = False) -> tuple[Projection, torch.Tensor]:
    """:func:`.projection.project` and :func:`.sh.sh_to_color` of all N Gaussians in Triton kernels
    (float32 CUDA tensors, or the CPU under ``TRITON_INTERPRET=1``), differentiable in means [N, 3],
    quats [N, 4], log_scales [N, 3], opacity_logits [N] and sh [N, K, 3] (K >= (degree + 1)^2).
    ``center``: the camera centre [3] (colours are seen along mean - center).

    Returns (Projection of all N, index = arange(N), radii [N, 2] -1 where culled; colours [N, 3]).
    """
    # fx, fy, cx, cy by slices: an index list would be copied to the device, which waits for its queued work
    focal, principal = intrinsics[:2, :2].diagonal(), intrinsics[:2, 2]
    camera = torch.cat([world_to_cam[:3, :3].reshape(9), world_to_cam[:3, 3], focal, principal,
                        center]).to(torch.float32).detach()
    means2d, conics, depths, opacities, colors, radii = _ProjectColor.apply(
        means, quats, log_scales, opacity_logits, sh, camera,
        (width, height, float(near_plane), float(blur_px2), degree, bool(antialiased)))
    index = torch.arange(len(means), device=means.device)
    return Projection(index, means2d, conics, depths, opacities, radii), colors
