"""Optimizer steps that never write a non-finite value into a Gaussian.

A finetune step can go wrong for a few Gaussians (a rasterizer's gradient of an extreme
Gaussian can be NaN or inf) or for all of them (a non-finite loss). Adam would spread such a
value into its moments and from there into the parameters, and a scene with one NaN can no
longer be saved. :class:`FiniteSteps` wraps the optimizer of per-Gaussian parameters (dimension
0 indexes the N Gaussians):

- a non-finite loss skips the whole step (no backward, no update);
- a Gaussian with a non-finite gradient, or one of magnitude >= ``GRAD_LIMIT`` (whose square
  overflows Adam's float32 second moment), in any parameter is held back: its gradients and
  Adam moments are zeroed in every parameter, so its update is exactly zero and it keeps its last
  finite values; every other Gaussian steps as it would have.

With every gradient finite and below ``GRAD_LIMIT``, Adam's moments stay finite and its update is
at most about 30 x the learning rate, so no finite parameter becomes non-finite. What was held
back is logged (step, how many Gaussians, their first indices) the first time each Gaussian is
held back, and summed up by :meth:`FiniteSteps.summary`.
"""

from __future__ import annotations

import logging

import torch

_log = logging.getLogger(__name__)

GRAD_LIMIT = 1e18
_SHOWN = 8  # indices listed in a message


def _listed(indices: torch.Tensor) -> str:
    shown = ", ".join(str(i) for i in indices[:_SHOWN].tolist())
    return shown + (f", ... ({len(indices) - _SHOWN} more)" if len(indices) > _SHOWN else "")


class FiniteSteps:
    """Steps of ``optimizer`` over ``params`` (name -> [N, ...] tensor, one row per Gaussian) that apply
    only finite updates (module docstring). ``label`` starts every message (e.g. ``finetune``)."""

    def __init__(self, optimizer: torch.optim.Optimizer, params: dict[str, torch.Tensor], label: str):
        self.optimizer, self.label = optimizer, label
        self.params = {name: p for name, p in params.items() if p.requires_grad}
        count = next(iter(params.values())).shape[0]
        device = next(iter(params.values())).device
        self.reported = torch.zeros(count, dtype=torch.bool, device=device)
        self.held_steps = 0
        self.skipped_steps: list[int] = []

    def loss_is_finite(self, loss: torch.Tensor, step: int, terms: dict[str, torch.Tensor]) -> bool:
        """False (the step is to be skipped, and that is logged) when ``loss`` is not finite."""
        if torch.isfinite(loss):
            return True
        if not self.skipped_steps:
            values = ", ".join(f"{name} {float(value):.4g}" for name, value in terms.items())
            _log.warning("%s: step %d: the loss is not finite (%s); the step is skipped", self.label, step, values)
        self.skipped_steps.append(step)
        return False

    def step(self, step: int) -> None:
        """``optimizer.step()`` with the Gaussians whose gradients are not usable held back."""
        bad = torch.zeros_like(self.reported)
        for p in self.params.values():
            if p.grad is not None:
                grad = p.grad.reshape(len(bad), -1)
                bad |= ~(torch.isfinite(grad) & (grad.abs() < GRAD_LIMIT)).all(1)
        if bad.any():
            self._hold_back(bad, step)
        self.optimizer.step()

    def _hold_back(self, bad: torch.Tensor, step: int) -> None:
        for p in self.params.values():
            if p.grad is not None:
                p.grad[bad] = 0
            for moment in self.optimizer.state.get(p, {}).values():
                if isinstance(moment, torch.Tensor) and moment.shape == p.shape:
                    moment[bad] = 0
        self.held_steps += 1
        new = (bad & ~self.reported).nonzero()[:, 0]
        if len(new):
            _log.warning("%s: step %d: %d Gaussians have non-finite (or >= %.0e) gradients (%s); they keep their "
                         "last finite values this step", self.label, step, int(bad.sum()), GRAD_LIMIT, _listed(new))
            self.reported |= bad

    def summary(self) -> None:
        """Log, once the run is over, how many steps were skipped or held Gaussians back."""
        if self.skipped_steps:
            _log.warning("%s: %d steps skipped for a non-finite loss (first at step %d)", self.label,
                         len(self.skipped_steps), self.skipped_steps[0])
        if self.held_steps:
            _log.warning("%s: %d steps held back Gaussians with non-finite gradients, %d Gaussians in all (%s)",
                         self.label, self.held_steps, int(self.reported.sum()),
                         _listed(self.reported.nonzero()[:, 0]))
