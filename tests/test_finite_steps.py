"""Finite optimizer steps: Gaussians with unusable gradients are held back exactly; others step as Adam does."""

import pytest
import torch

from artnvg_core.finite_steps import GRAD_LIMIT, FiniteSteps


def _params(seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"sh": torch.randn(6, 4, 3, generator=g).requires_grad_(True),
            "opacity": torch.randn(6, generator=g).requires_grad_(True),
            "frozen": torch.randn(6, 3, generator=g)}


def _grads(seed):
    g = torch.Generator().manual_seed(seed)
    return {"sh": torch.randn(6, 4, 3, generator=g), "opacity": torch.randn(6, generator=g)}


@pytest.mark.parametrize("poison", [float("nan"), float("inf"), -GRAD_LIMIT, 3e38])
def test_held_back_gaussians_keep_their_values_and_the_others_step_as_adam(poison, caplog):
    guarded, plain = _params(), _params()
    opt_g = torch.optim.Adam([guarded["sh"], guarded["opacity"]], lr=0.1)
    opt_p = torch.optim.Adam([plain["sh"], plain["opacity"]], lr=0.1)
    steps = FiniteSteps(opt_g, guarded, "test")
    for step in (1, 2, 3):
        grads = _grads(step)
        if step >= 2:
            grads["sh"][2, 1, 0] = poison  # Gaussian 2 from step 2 on
            grads["opacity"][4] = poison  # Gaussian 4 at step 2 only
            if step == 3:
                grads["opacity"][4] = 0.5
        for params, opt in ((guarded, opt_g), (plain, opt_p)):
            opt.zero_grad()
            for name, grad in grads.items():
                params[name].grad = grad.clone()
        with caplog.at_level("WARNING", logger="artnvg_core.finite_steps"):
            steps.step(step)
        for name in grads:  # the reference: plain Adam with those Gaussians' gradients zeroed
            plain[name].grad[[2, 4] if step == 2 else [2] if step == 3 else []] = 0
        opt_p.step()
        if step == 1:
            after_first = {k: v.detach().clone() for k, v in guarded.items()}
    keep = [0, 1, 3, 5]
    for name in ("sh", "opacity"):
        assert torch.isfinite(guarded[name]).all()
        assert torch.equal(guarded[name][keep], plain[name][keep]), name
        assert torch.equal(guarded[name][2], after_first[name][2]), name  # held back at steps 2 and 3
    assert not torch.equal(guarded["opacity"][4], after_first["opacity"][4])  # stepped again at step 3
    assert [r.message for r in caplog.records] == [
        "test: step 2: 2 Gaussians have non-finite (or >= 1e+18) gradients (2, 4); they keep their last "
        "finite values this step"]
    caplog.clear()
    with caplog.at_level("WARNING", logger="artnvg_core.finite_steps"):
        assert not steps.loss_is_finite(torch.tensor(float("nan")), 4, {"l1": torch.tensor(float("nan"))})
        assert steps.loss_is_finite(torch.tensor(1.0), 5, {})
        steps.summary()
    assert [r.message for r in caplog.records] == [
        "test: step 4: the loss is not finite (l1 nan); the step is skipped",
        "test: 1 steps skipped for a non-finite loss (first at step 4)",
        "test: 2 steps held back Gaussians with non-finite gradients, 2 Gaussians in all (2, 4)"]
