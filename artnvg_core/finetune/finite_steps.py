"""Adam steps that never write a non-finite value into a Gaussian, without waiting for the GPU.

A finetune step can go wrong for a few Gaussians (a rasterizer's gradient of an extreme
Gaussian can be NaN or inf) or for all of them (a non-finite loss). Adam would spread such a
value into its moments and from there into the parameters, and a scene with one NaN can no
longer be saved. :class:`FiniteAdam` is Adam (Kingma & Ba, as ``torch.optim.Adam`` computes it:
no weight decay, no AMSGrad) over per-Gaussian parameters (dimension 0 indexes the N Gaussians)
that applies only finite updates:

- a non-finite loss skips the whole step (no update, moments and step count unchanged); so does
  a step the caller marks as skipped (e.g. a view that sees no Gaussian);
- a Gaussian with a non-finite gradient, or one of magnitude >= ``GRAD_LIMIT`` (whose square
  overflows Adam's float32 second moment), in any parameter is held back: its Adam moments are
  zeroed in every parameter and its values are kept; every other Gaussian steps as it would have.

With every gradient finite and below ``GRAD_LIMIT``, Adam's moments stay finite and its update is
at most about 30 x the learning rate, so no finite parameter becomes non-finite.

Every decision is made on the parameters' device (``torch.where`` on masks, the step count a
device tensor), so a step never waits for the GPU: the CPU queues the next step while the GPU
runs this one. On CUDA the per-parameter arithmetic runs as two Triton kernels per parameter
(:mod:`artnvg_core.finetune.finite_steps_triton`) instead of about twenty PyTorch ones. What was skipped or
held back is recorded on the device and logged by :meth:`FiniteAdam.report` (one wait; the step
and the Gaussians' first indices, the first time each Gaussian is held back) and summed up by
:meth:`FiniteAdam.summary`.
``torch.optim`` is not used: its first use imports ``torch._dynamo`` (seconds of start-up).
"""

from __future__ import annotations

import logging

import torch

from ..counted import counted
from ..devices import triton_available

_log = logging.getLogger(__name__)

GRAD_LIMIT = 1e18
_SHOWN = 8  # indices listed in a message


def _listed(indices: torch.Tensor) -> str:
    shown = ", ".join(str(i) for i in indices[:_SHOWN].tolist())
    return shown + (f", ... ({len(indices) - _SHOWN} more)" if len(indices) > _SHOWN else "")


class FiniteAdam:
    """Adam over ``params`` (name -> [N, ...] leaf tensor, one row per Gaussian; those without
    ``requires_grad`` or empty are left alone) with learning rates ``lrs`` (name -> rate), applying
    only finite updates (module docstring). ``label`` starts every message (e.g. ``finetune``).
    ``fused``: the Triton step (default: on CUDA when Triton imports and every parameter is a contiguous
    float32 tensor; True on the CPU needs ``TRITON_INTERPRET=1``)."""

    def __init__(self, params: dict[str, torch.Tensor], lrs: dict[str, float], label: str,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15, fused: bool | None = None):
        self.params = {name: p for name, p in params.items() if p.requires_grad and p.numel() > 0}
        self.lrs = {name: float(lrs[name]) for name in self.params}
        self.betas, self.eps, self.label = betas, eps, label
        first = next(iter(params.values()))
        count, device = first.shape[0], first.device
        self.exp_avg = {name: torch.zeros_like(p) for name, p in self.params.items()}
        self.exp_avg_sq = {name: torch.zeros_like(p) for name, p in self.params.items()}
        # steps applied (skipped ones not); float64 as torch.optim.Adam's Python floats, float32 on MPS (no float64)
        self.taken = torch.zeros((), dtype=torch.float32 if device.type == "mps" else torch.float64, device=device)
        self.first_held = torch.zeros(count, dtype=torch.long, device=device)  # step first held back; 0: never
        self.held_steps = torch.zeros((), dtype=torch.long, device=device)
        self.skipped_steps = torch.zeros((), dtype=torch.long, device=device)  # for a non-finite loss
        self.first_skipped = torch.zeros((), dtype=torch.long, device=device)
        self.first_skipped_terms: torch.Tensor | None = None  # the loss terms at that step
        self.term_names: tuple[str, ...] = ()
        self._logged = torch.zeros(count, dtype=torch.bool)  # host: Gaussians already named in a message
        self._skip_logged = False
        if fused is None:
            fused = device.type == "cuda" and triton_available() and all(
                p.dtype == torch.float32 and p.is_contiguous() for p in self.params.values())
        self.fused = fused
        if fused:
            self._rates = torch.tensor(list(self.lrs.values()), dtype=self.taken.dtype, device=device)
            self._held = torch.zeros(count, dtype=torch.uint8, device=device)

    @torch.no_grad()
    def step(self, step: int, loss: torch.Tensor, terms: dict[str, torch.Tensor],
             skip: torch.Tensor | None = None) -> None:
        """One Adam step from the gradients now in the parameters (then cleared); ``step`` numbers it in
        messages, ``loss``/``terms`` (scalars) decide and explain a skip, ``skip`` (a bool scalar on the
        device) skips it for the caller's own reason. Queues work only: never waits for the device."""
        nonfinite = ~torch.isfinite(loss.detach())
        skipped = nonfinite if skip is None else nonfinite | skip
        self._record_skip(step, nonfinite, terms)
        grads = {name: p.grad.contiguous() for name, p in self.params.items() if p.grad is not None}
        bad = self._held_back(grads) & ~skipped
        self.first_held.copy_(torch.where(bad & (self.first_held == 0), step, self.first_held))
        self.held_steps += bad.any()
        taken = self.taken + (~skipped).to(self.taken.dtype)
        beta1, beta2 = self.betas
        correction1 = 1 - beta1**taken  # in float64 (but on MPS), as torch.optim.Adam computes them in Python
        correction2_sqrt = (1 - beta2**taken).sqrt().float()
        update = self._fused_updates if self.fused else self._torch_updates
        update(grads, skipped, bad, correction1, correction2_sqrt)
        for name in grads:
            self.params[name].grad = None
        self.taken.copy_(taken)

    def _held_back(self, grads: dict[str, torch.Tensor]) -> torch.Tensor:
        """[N] bool: the Gaussians with a non-finite (or >= GRAD_LIMIT) gradient in any parameter."""
        if self.fused:
            from .finite_steps_triton import mark_held_rows

            self._held.zero_()
            for grad in grads.values():
                mark_held_rows(grad, self._held, GRAD_LIMIT)
            return self._held.view(torch.bool)
        bad = torch.zeros_like(self.first_held, dtype=torch.bool)
        for grad in grads.values():
            grad = grad.reshape(len(bad), -1)
            bad |= ~(torch.isfinite(grad) & (grad.abs() < GRAD_LIMIT)).all(1)
        return bad

    def _torch_updates(self, grads: dict[str, torch.Tensor], skipped: torch.Tensor, bad: torch.Tensor,
                       correction1: torch.Tensor, correction2_sqrt: torch.Tensor) -> None:
        """Every parameter's step in PyTorch: ``skipped`` keeps everything, ``bad`` [N] rows keep their
        values and get zeroed moments."""
        beta1, beta2 = self.betas
        for name, grad in grads.items():
            p = self.params[name]
            rows = (len(bad),) + (1,) * (p.dim() - 1)
            keep, zero = skipped.expand(rows), bad.view(rows)
            exp_avg = self.exp_avg[name].lerp(grad, 1 - beta1)
            exp_avg_sq = self.exp_avg_sq[name] * beta2 + (1 - beta2) * grad * grad
            step_size = (self.lrs[name] / correction1).float()
            update = step_size * exp_avg / (exp_avg_sq.sqrt() / correction2_sqrt + self.eps)
            p.copy_(torch.where(keep | zero, p, p - update))
            self.exp_avg[name].copy_(torch.where(keep, self.exp_avg[name], exp_avg.masked_fill(zero, 0)))
            self.exp_avg_sq[name].copy_(torch.where(keep, self.exp_avg_sq[name], exp_avg_sq.masked_fill(zero, 0)))

    def _fused_updates(self, grads: dict[str, torch.Tensor], skipped: torch.Tensor, bad: torch.Tensor,
                       correction1: torch.Tensor, correction2_sqrt: torch.Tensor) -> None:
        """The same by :func:`~artnvg_core.finetune.finite_steps_triton.adam_rows`, two launches per parameter
        (the held rows read from ``self._held``, which :meth:`_held_back` filled: ``bad`` is those
        rows less a skipped step's, which ``skipped`` keeps anyway)."""
        from .finite_steps_triton import adam_rows

        step_sizes = (self._rates / correction1).float()
        for index, name in enumerate(self.params):
            if name in grads:
                adam_rows(self.params[name], grads[name], self.exp_avg[name], self.exp_avg_sq[name],
                          self._held, skipped.view(torch.uint8), step_sizes[index], correction2_sqrt, self.betas,
                          self.eps)

    def _record_skip(self, step: int, nonfinite: torch.Tensor, terms: dict[str, torch.Tensor]) -> None:
        if not terms:
            return
        values = torch.stack([value.detach().float().reshape(()) for value in terms.values()])
        if self.first_skipped_terms is None or tuple(terms) != self.term_names:
            self.term_names, self.first_skipped_terms = tuple(terms), torch.zeros_like(values)
        first = nonfinite & (self.first_skipped == 0)
        self.first_skipped.copy_(torch.where(first, step, self.first_skipped))
        self.first_skipped_terms.copy_(torch.where(first, values, self.first_skipped_terms))
        self.skipped_steps += nonfinite

    def report(self) -> None:
        """Log (waiting for the device once) the Gaussians held back and the first skipped step since
        the last report, in step order."""
        first_held = self.first_held.cpu()
        new = (first_held > 0) & ~self._logged
        messages = []
        for step in first_held[new].unique().tolist():
            held = (new & (first_held == step)).nonzero()[:, 0]
            messages.append((step, "%s: step %d: non-finite (or >= %.0e) gradients in %s (%s), held at the last "
                             "finite values this step", (GRAD_LIMIT, counted(len(held), "Gaussian"), _listed(held))))
        self._logged |= new
        first_skipped = int(self.first_skipped)
        if first_skipped and not self._skip_logged:
            values = ", ".join(f"{name} {value:.4g}" for name, value in zip(self.term_names,
                                                                            self.first_skipped_terms.tolist()))
            messages.append((first_skipped, "%s: step %d: the loss is not finite (%s); the step is skipped", (values,)))
            self._skip_logged = True
        for step, message, args in sorted(messages, key=lambda m: m[0]):
            _log.warning(message, self.label, step, *args)

    def summary(self) -> None:
        """:meth:`report`, then how many steps were skipped or held Gaussians back, once the run is over."""
        self.report()
        skipped, held = int(self.skipped_steps), int(self.held_steps)
        if skipped:
            _log.warning("%s: %s skipped for a non-finite loss (first at step %d)", self.label, counted(skipped, "step"),
                         int(self.first_skipped))
        if held:
            _log.warning("%s: %s held back Gaussians with non-finite gradients, %s in all (%s)", self.label,
                         counted(held, "step"), counted(int(self._logged.sum()), "Gaussian"),
                         _listed(self._logged.nonzero()[:, 0]))
