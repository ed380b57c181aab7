""":class:`~artnvg_core.finetune.finite_steps.FiniteAdam`'s step in two Triton kernels per parameter.

FiniteAdam's PyTorch step queues about twenty small kernels per parameter; a GPU finetune step is
bound by launching kernels (BENCHMARKS.md, "Finetune"), so on CUDA the step launches two per parameter:
:func:`mark_held_rows` sets ``held[i]`` for every row ``i`` (Gaussian) whose gradient has a value that
is not finite or is >= the limit, and :func:`adam_rows` takes Adam's step on every row, holding back
the held rows and skipping the whole step when the device flag says so. The arithmetic is the PyTorch
step's, in float32, in the same order (the compiler may fuse a multiply and an add: results agree to
float32 rounding). Each tensor is seen as its N x D values (D: the values of one row), so one compiled
kernel serves every parameter shape. They run on CUDA tensors, or on the CPU in Triton's interpreter
(``TRITON_INTERPRET=1`` set before this module is imported).
"""

from __future__ import annotations

import torch
import triton
import triton.language as tl

from ..triton_runtime import Warmup, stand_in

BLOCK = 1024  # values per program


@triton.jit(do_not_specialize=["count", "D"])
def _held_kernel(grad, held, count, D, limit, BLOCK: tl.constexpr):
    offsets = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    inside = offsets < count
    g = tl.load(grad + offsets, mask=inside, other=0.0)
    unusable = inside & ~(tl.abs(g) < limit)  # NaN compares false: held too
    tl.store(held + offsets // D, tl.full((BLOCK,), 1, tl.uint8), mask=unusable)  # same byte, same value: no race


@triton.jit(do_not_specialize=["count", "D", "step_size"])  # step_size: a parameter's entry of a vector
def _adam_kernel(param, grad, exp_avg, exp_avg_sq, held, skipped, step_size, correction2_sqrt, count, D,
                 one_minus_beta1, beta2, one_minus_beta2, eps, BLOCK: tl.constexpr):
    offsets = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
    inside = offsets < count
    skip = tl.load(skipped) != 0
    zero = tl.load(held + offsets // D, mask=inside, other=0) != 0
    p = tl.load(param + offsets, mask=inside)
    g = tl.load(grad + offsets, mask=inside)
    m = tl.load(exp_avg + offsets, mask=inside)
    v = tl.load(exp_avg_sq + offsets, mask=inside)
    m_new = m + one_minus_beta1 * (g - m)  # torch.lerp with a weight < 0.5
    v_new = v * beta2 + one_minus_beta2 * g * g
    update = tl.load(step_size) * m_new / (tl.sqrt_rn(v_new) / tl.load(correction2_sqrt) + eps)
    tl.store(param + offsets, tl.where(skip | zero, p, p - update), mask=inside)
    tl.store(exp_avg + offsets, tl.where(skip, m, tl.where(zero, 0.0, m_new)), mask=inside)
    tl.store(exp_avg_sq + offsets, tl.where(skip, v, tl.where(zero, 0.0, v_new)), mask=inside)


def warmups(device: torch.device | str) -> list[Warmup]:
    """The launches :func:`mark_held_rows` and :func:`adam_rows` make, as
    :class:`~artnvg_core.triton_runtime.Warmup`."""
    f32, u8 = stand_in(torch.float32, device), stand_in(torch.uint8, device)
    return [Warmup(_held_kernel, (f32, u8, 0, 0, 0.0), dict(BLOCK=BLOCK)),
            Warmup(_adam_kernel, (f32, f32, f32, f32, u8, u8, f32, f32, 0, 0, 0.0, 0.0, 0.0, 0.0), dict(BLOCK=BLOCK))]


def _grid(tensor: torch.Tensor) -> tuple[int]:
    return (triton.cdiv(tensor.numel(), BLOCK),)


def mark_held_rows(grad: torch.Tensor, held: torch.Tensor, limit: float) -> None:
    """Set ``held`` [N] (uint8) to 1 at every row of ``grad`` [N, ...] (float32, contiguous) holding a
    value that is not finite or whose magnitude is >= ``limit``; other entries are left as they are."""
    if grad.numel():
        _held_kernel[_grid(grad)](grad, held, grad.numel(), grad.numel() // len(grad), limit, BLOCK=BLOCK)


def adam_rows(param: torch.Tensor, grad: torch.Tensor, exp_avg: torch.Tensor, exp_avg_sq: torch.Tensor,
              held: torch.Tensor, skipped: torch.Tensor, step_size: torch.Tensor, correction2_sqrt: torch.Tensor,
              betas: tuple[float, float], eps: float) -> None:
    """Adam's step in place on ``param`` [N, ...] and its moments (float32, contiguous, ``grad``'s shape).

    held [N] uint8: rows that keep their values and get zeroed moments; skipped: uint8 scalar, nonzero
    keeps everything; step_size: float32 scalar (learning rate over the first moment's bias correction);
    correction2_sqrt: float32 scalar (square root of the second moment's bias correction)."""
    if param.numel():
        beta1, beta2 = betas
        _adam_kernel[_grid(param)](param, grad, exp_avg, exp_avg_sq, held, skipped, step_size, correction2_sqrt,
                                   param.numel(), param.numel() // len(param), 1 - beta1, beta2, 1 - beta2, eps,
                                   BLOCK=BLOCK)
