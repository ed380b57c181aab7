""":func:`~artnvg_core.losses.ssim.ssim` in two Triton kernels: one forward, one backward.

The PyTorch SSIM blurs six stacked maps with cuDNN's grouped convolutions (forward and backward about
1 ms at 512x512 on an H100) and queues some thirty elementwise kernels around them. Here one forward
kernel takes, for a tile of pixels of one channel, the five local statistics under the full 2D window
(mu_a, mu_b, E[a^2], E[b^2], E[(a - b)^2], zero padding), the SSIM map in :mod:`.ssim`'s form and its
tile's sum, and writes the map's partial derivatives by those statistics; the backward kernel blurs the
partial derivatives with the same window (a zero-padded blur with a symmetric window is its own
adjoint) and applies the chain rule per pixel:

    dSSIM/da(p) = sum_q w(q - p) [dS/dmu_a(q) + 2 a(p) dS/dE[a^2](q) + 2 (a - b)(p) dS/dE[(a-b)^2](q)]

(and for ``b`` with mu_b, E[b^2] and -2 (a - b)). For identical images every term is exactly zero, as in
the PyTorch form. Arithmetic in float32; the 2D window's sums run in another order than the separable
passes, so the two agree to float32 rounding. The inputs are read as contiguous [B, C, H, W] (a permuted
[B, H, W, 3] render is copied first: at 1024x1024 the copy and a contiguous read take 0.8 ms forward and
backward, strided reads 2.1 ms; BENCHMARKS.md, Finetune). They run on CUDA tensors, or on the CPU in
Triton's interpreter (``TRITON_INTERPRET=1`` set before this module is imported).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from ..triton_runtime import Warmup, stand_in

TILE_H, TILE_W = 16, 32  # pixels of a program


@triton.jit
def _tap(window_ptr, ys, xs, i, j, H, W, SIZE: tl.constexpr):
    """Window tap (i, j) around pixels (ys, xs) of a contiguous [H, W] plane: its weight, the offsets of the
    pixels it reads, and where they are inside (zero padding elsewhere)."""
    y = ys + (i - SIZE // 2)
    x = xs + (j - SIZE // 2)
    weight = tl.load(window_ptr + i) * tl.load(window_ptr + j)
    return weight, y * W + x, (y >= 0) & (y < H) & (x >= 0) & (x < W)


@triton.jit
def _statistics(a_ptr, b_ptr, window_ptr, ys, xs, H, W, SIZE: tl.constexpr):
    """The five windowed sums around pixels (ys, xs) of one channel: mu_a, mu_b, E[a^2], E[b^2], E[d^2]."""
    mu_a = tl.zeros(ys.shape, tl.float32) + tl.zeros(xs.shape, tl.float32)
    mu_b, e_aa, e_bb, e_dd = mu_a, mu_a, mu_a, mu_a
    for i in range(SIZE):
        for j in tl.static_range(SIZE):
            w, at, there = _tap(window_ptr, ys, xs, i, j, H, W, SIZE)
            av = tl.load(a_ptr + at, mask=there, other=0.0).to(tl.float32)
            bv = tl.load(b_ptr + at, mask=there, other=0.0).to(tl.float32)
            dv = av - bv
            mu_a += w * av
            mu_b += w * bv
            e_aa += w * av * av
            e_bb += w * bv * bv
            e_dd += w * dv * dv
    return mu_a, mu_b, e_aa, e_bb, e_dd


@triton.jit
def _forward_kernel(a_ptr, b_ptr, window_ptr, sums_ptr, maps_ptr, H, W, tiles_w, c1, c2,
                    SIZE: tl.constexpr, TH: tl.constexpr, TW: tl.constexpr, MAPS: tl.constexpr):
    """Per (tile, image x channel) program: the tile's sum of the SSIM map into ``sums [B*C, tiles]`` and, with
    ``MAPS``, the map's partial derivatives into ``maps [4, B*C, H, W]``: by mu_a, by mu_b, by E[a^2]
    (= by E[b^2]) and by E[d^2]."""
    tile, plane = tl.program_id(0), tl.program_id(1).to(tl.int64)
    ys = (tile // tiles_w) * TH + tl.arange(0, TH)[:, None]
    xs = (tile % tiles_w) * TW + tl.arange(0, TW)[None, :]
    inside = (ys < H) & (xs < W)
    mu_a, mu_b, e_aa, e_bb, e_dd = _statistics(a_ptr + plane * H * W, b_ptr + plane * H * W, window_ptr, ys, xs,
                                               H, W, SIZE)
    diff = mu_a - mu_b
    p = mu_a * mu_a + mu_b * mu_b + c1
    lum = 1.0 - diff * diff / p
    q = (e_aa - mu_a * mu_a) + (e_bb - mu_b * mu_b) + c2
    v = e_dd - diff * diff
    cs = 1.0 - v / q
    tl.store(sums_ptr + plane * tl.num_programs(0) + tile, tl.sum(tl.sum(tl.where(inside, lum * cs, 0.0), 1), 0))
    if MAPS:  # S = lum * cs, lum = 1 - diff^2 / p, cs = 1 - v / q; p, q and v as functions of the statistics
        by_v, by_q = -lum / q, lum * v / (q * q)  # dS/dv, dS/dq
        d_mu_a = cs * (-2.0 * diff * p + diff * diff * 2.0 * mu_a) / (p * p) - 2.0 * diff * by_v - 2.0 * mu_a * by_q
        d_mu_b = cs * (2.0 * diff * p + diff * diff * 2.0 * mu_b) / (p * p) + 2.0 * diff * by_v - 2.0 * mu_b * by_q
        at = maps_ptr + plane * H * W + ys * W + xs
        plane_stride = tl.num_programs(1).to(tl.int64) * H * W
        tl.store(at, d_mu_a, mask=inside)
        tl.store(at + plane_stride, d_mu_b, mask=inside)
        tl.store(at + 2 * plane_stride, by_q, mask=inside)  # dS/dE[a^2] = dS/dE[b^2] = dS/dq
        tl.store(at + 3 * plane_stride, by_v, mask=inside)  # dS/dE[d^2] = dS/dv


@triton.jit
def _blurred(maps_ptr, window_ptr, ys, xs, H, W, SIZE: tl.constexpr):
    """The windowed sum of one contiguous [H, W] map around pixels (ys, xs), zero outside."""
    total = tl.zeros(ys.shape, tl.float32) + tl.zeros(xs.shape, tl.float32)
    for i in range(SIZE):
        for j in tl.static_range(SIZE):
            w, at, there = _tap(window_ptr, ys, xs, i, j, H, W, SIZE)
            total += w * tl.load(maps_ptr + at, mask=there, other=0.0)
    return total


@triton.jit
def _backward_kernel(a_ptr, b_ptr, window_ptr, maps_ptr, scale_ptr, grad_a_ptr, grad_b_ptr, C, H, W, tiles_w,
                     SIZE: tl.constexpr, TH: tl.constexpr, TW: tl.constexpr, GRAD_A: tl.constexpr,
                     GRAD_B: tl.constexpr):
    """d(loss)/da with ``GRAD_A`` and d(loss)/db with ``GRAD_B`` of a tile of one channel: the blurred partial
    derivatives combined per pixel, times ``scale [B]`` (d(loss)/d(image's SSIM) over its values per channel)."""
    tile, plane = tl.program_id(0), tl.program_id(1).to(tl.int64)
    ys = (tile // tiles_w) * TH + tl.arange(0, TH)[:, None]
    xs = (tile % tiles_w) * TW + tl.arange(0, TW)[None, :]
    inside = (ys < H) & (xs < W)
    plane_stride = tl.num_programs(1).to(tl.int64) * H * W
    pixels = plane * H * W + ys * W + xs
    at = maps_ptr + plane * H * W
    scale = tl.load(scale_ptr + plane // C)
    av = tl.load(a_ptr + pixels, mask=inside, other=0.0).to(tl.float32)
    bv = tl.load(b_ptr + pixels, mask=inside, other=0.0).to(tl.float32)
    by_q = _blurred(at + 2 * plane_stride, window_ptr, ys, xs, H, W, SIZE)
    by_v = _blurred(at + 3 * plane_stride, window_ptr, ys, xs, H, W, SIZE)
    diff = av - bv
    if GRAD_A:
        grad_a = scale * (_blurred(at, window_ptr, ys, xs, H, W, SIZE) + 2.0 * av * by_q + 2.0 * diff * by_v)
        tl.store(grad_a_ptr + pixels, grad_a, mask=inside)
    if GRAD_B:
        grad_b = scale * (_blurred(at + plane_stride, window_ptr, ys, xs, H, W, SIZE) + 2.0 * bv * by_q
                          - 2.0 * diff * by_v)
        tl.store(grad_b_ptr + pixels, grad_b, mask=inside)


def _forward_options(size: int, maps: bool) -> dict:
    """The forward kernel's constants for a window of ``size`` taps (the backward's below)."""
    return dict(SIZE=size, TH=TILE_H, TW=TILE_W, MAPS=maps)


def _backward_options(size: int, grad_a: bool, grad_b: bool) -> dict:
    return dict(SIZE=size, TH=TILE_H, TW=TILE_W, GRAD_A=grad_a, GRAD_B=grad_b)


def warmups(device: torch.device | str, channels: int, height: int, width: int, size: int = 11,
            gradients: tuple[bool, bool] = (True, False)) -> list[Warmup]:
    """The launches :func:`fused_ssim` makes for float32 images of ``channels`` x ``height`` x ``width`` and a
    window of ``size`` taps, differentiable in (a, b) as ``gradients`` says (the finetune's: the render, not
    its target), as :class:`~artnvg_core.triton_runtime.Warmup`."""
    f32, tiles_w = stand_in(torch.float32, device), triton.cdiv(width, TILE_W)
    found = [Warmup(_forward_kernel, (f32,) * 5 + (height, width, tiles_w, 0.0, 0.0),
                    _forward_options(size, any(gradients)))]
    if any(gradients):
        found.append(Warmup(_backward_kernel, (f32,) * 7 + (channels, height, width, tiles_w),
                            _backward_options(size, *gradients)))
    return found


def _grid(a: torch.Tensor) -> tuple[int, int, int]:
    """(programs per image channel, programs per row of tiles, image channels) of [B, C, H, W] ``a``."""
    batch, channels, height, width = a.shape
    tiles_w = triton.cdiv(width, TILE_W)
    return triton.cdiv(height, TILE_H) * tiles_w, tiles_w, batch * channels


class _FusedSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, b, window, c1, c2, per_image, maps):
        batch, channels, height, width = a.shape
        tiles, tiles_w, planes = _grid(a)
        sums = torch.empty(planes, tiles, device=a.device, dtype=torch.float32)
        partials = torch.empty((4, planes, height, width) if maps else (0,), device=a.device, dtype=torch.float32)
        _forward_kernel[(tiles, planes)](a, b, window, sums, partials, height, width, tiles_w, c1, c2,
                                         **_forward_options(window.numel(), maps))
        ctx.save_for_backward(a, b, window, partials)
        ctx.per_image = per_image
        per = sums.view(batch, -1).sum(1) / (channels * height * width)
        return per if per_image else per.mean()

    @staticmethod
    def backward(ctx, grad):
        a, b, window, partials = ctx.saved_tensors
        batch, channels, height, width = a.shape
        tiles, tiles_w, planes = _grid(a)
        need_a, need_b = ctx.needs_input_grad[:2]
        per_image = grad if ctx.per_image else grad.expand(batch) / batch
        scale = (per_image / (channels * height * width)).float().contiguous()
        out_a = torch.empty_like(a, dtype=torch.float32) if need_a else a  # unneeded: a pointer never written
        out_b = torch.empty_like(b, dtype=torch.float32) if need_b else b
        _backward_kernel[(tiles, planes)](a, b, window, partials, scale, out_a, out_b, channels, height, width, tiles_w,
                                          **_backward_options(window.numel(), need_a, need_b))
        grads = (out_a.to(a.dtype) if need_a else None, out_b.to(b.dtype) if need_b else None)
        return (*grads, None, None, None, None, None)


def fused_ssim(a: torch.Tensor, b: torch.Tensor, window: torch.Tensor, c1: float, c2: float,
               per_image: bool = False) -> torch.Tensor:
    """SSIM of ``a, b [B, C, H, W]`` (checked by the caller; copied to contiguous ones where they are not) under
    the normalised odd ``window [size]`` (float32, on their device) with constants ``c1, c2``: a float32
    scalar, or ``[B]`` if ``per_image``; differentiable in both inputs."""
    maps = torch.is_grad_enabled() and (a.requires_grad or b.requires_grad)  # the backward's partial derivatives
    return _FusedSSIM.apply(a.contiguous(), b.contiguous(), window, c1, c2, per_image, maps)
