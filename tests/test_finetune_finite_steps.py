"""FiniteAdam: Adam as torch.optim.Adam computes it; Gaussians with unusable gradients held back exactly;
non-finite losses and caller-skipped steps change nothing; what happened is logged when reported. Each
for the PyTorch step and the fused Triton step (compiled on a GPU, else in Triton's CPU interpreter:
tests/conftest.py sets TRITON_INTERPRET=1 there)."""

import pytest
import torch

from artnvg_core.finetune.finite_steps import GRAD_LIMIT, FiniteAdam

LRS = {"sh": 0.1, "opacity": 0.03}
DEVICES = {False: "cpu", True: "cuda" if torch.cuda.is_available() else "cpu"}


@pytest.fixture(params=[False, True], ids=["torch", "fused"])
def fused(request):
    if request.param:
        pytest.importorskip("triton")
    return request.param


def _params(seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    return {"sh": torch.randn(6, 4, 3, generator=g).to(device).requires_grad_(True),
            "opacity": torch.randn(6, generator=g).to(device).requires_grad_(True),
            "frozen": torch.randn(6, 3, generator=g).to(device)}


def _grads(seed, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    return {"sh": torch.randn(6, 4, 3, generator=g).to(device), "opacity": torch.randn(6, generator=g).to(device)}


def _torch_adam(params):
    return torch.optim.Adam([{"params": [params[name]], "lr": lr} for name, lr in LRS.items()], eps=1e-15,
                            foreach=False)


def _set(params, grads):
    for name, grad in grads.items():
        params[name].grad = grad.clone()


def test_finite_steps_are_torch_adam(fused):
    device = DEVICES[fused]
    ours, ref = _params(device=device), _params(device=device)
    adam, reference = FiniteAdam(ours, LRS, "test", fused=fused), _torch_adam(ref)
    for step in range(1, 8):
        grads = _grads(step, device)
        _set(ours, grads)
        _set(ref, grads)
        adam.step(step, torch.tensor(1.0, device=device), {"l1": torch.tensor(1.0, device=device)})
        reference.step()
        for name in LRS:
            torch.testing.assert_close(ours[name], ref[name], rtol=2e-6, atol=1e-7)
            assert ours[name].grad is None
    assert torch.equal(ours["frozen"], ref["frozen"])


@pytest.mark.parametrize("poison", [float("nan"), float("inf"), -GRAD_LIMIT, 3e38])
def test_held_back_gaussians_keep_their_values_and_the_others_step_as_adam(poison, fused, caplog):
    device = DEVICES[fused]
    guarded, plain = _params(device=device), _params(device=device)
    adam, reference = FiniteAdam(guarded, LRS, "test", fused=fused), _torch_adam(plain)
    for step in (1, 2, 3):
        grads = _grads(step, device)
        if step >= 2:
            grads["sh"][2, 1, 0] = poison  # Gaussian 2 from step 2 on
            grads["opacity"][4] = poison  # Gaussian 4 at step 2 only
            if step == 3:
                grads["opacity"][4] = 0.5
        _set(guarded, grads)
        with caplog.at_level("WARNING", logger="artnvg_core.finetune.finite_steps"):
            adam.step(step, torch.tensor(1.0, device=device), {})
        held = [2, 4] if step == 2 else [2] if step == 3 else []
        for name, grad in grads.items():  # the reference: Adam with those Gaussians' gradients and moments zeroed
            grad[held] = 0
            reference.state.get(plain[name], {}).get("exp_avg", torch.zeros(6, 1, device=device))[held] = 0
            reference.state.get(plain[name], {}).get("exp_avg_sq", torch.zeros(6, 1, device=device))[held] = 0
        _set(plain, grads)
        reference.step()
        if step == 1:
            after_first = {k: v.detach().clone() for k, v in guarded.items()}
    assert caplog.records == []  # nothing is logged before a report: a step never waits for the device
    keep = [0, 1, 3, 5]
    for name in ("sh", "opacity"):
        assert torch.isfinite(guarded[name]).all()
        torch.testing.assert_close(guarded[name][keep], plain[name][keep], rtol=2e-6, atol=1e-7)
        assert torch.equal(guarded[name][2], after_first[name][2]), name  # held back at steps 2 and 3
    torch.testing.assert_close(guarded["opacity"][4], plain["opacity"][4], rtol=2e-6, atol=1e-7)
    assert not torch.equal(guarded["opacity"][4], after_first["opacity"][4])  # stepped again at step 3
    with caplog.at_level("WARNING", logger="artnvg_core.finetune.finite_steps"):
        adam.report()
        adam.report()  # nothing new
    assert [r.message for r in caplog.records] == [
        "test: step 2: non-finite (or >= 1e+18) gradients in 2 Gaussians (2, 4), held at the last finite values "
        "this step"]


def test_a_non_finite_loss_or_a_skipped_step_changes_nothing(fused, caplog):
    device = DEVICES[fused]
    params = _params(device=device)
    adam = FiniteAdam(params, LRS, "test", fused=fused)

    def scalar(value):
        return torch.tensor(value, device=device)

    _set(params, _grads(1, device))
    adam.step(1, scalar(1.0), {"l1": scalar(1.0)})
    before = {k: v.detach().clone() for k, v in params.items()}
    moments = {k: (adam.exp_avg[k].clone(), adam.exp_avg_sq[k].clone()) for k in LRS}
    _set(params, {k: g * float("nan") for k, g in _grads(2, device).items()})  # a NaN loss gives NaN gradients
    adam.step(2, scalar(float("nan")), {"l1": scalar(float("nan")), "tv": scalar(0.5)})
    _set(params, _grads(3, device))
    adam.step(3, scalar(1.0), {"l1": scalar(1.0), "tv": scalar(0.5)}, skip=scalar(True))
    for name in LRS:
        assert torch.equal(params[name], before[name])
        assert torch.equal(adam.exp_avg[name], moments[name][0]) and torch.equal(adam.exp_avg_sq[name], moments[name][1])
    assert float(adam.taken) == 1
    with caplog.at_level("WARNING", logger="artnvg_core.finetune.finite_steps"):
        adam.summary()
    assert [r.message for r in caplog.records] == [
        "test: step 2: the loss is not finite (l1 nan, tv 0.5); the step is skipped",
        "test: 1 step skipped for a non-finite loss (first at step 2)"]


def test_the_warmups_are_the_launches_of_the_fused_step(monkeypatch):
    pytest.importorskip("triton")
    from artnvg_core.finetune.finite_steps_triton import warmups

    from triton_launches import record_launches, warmed

    device = DEVICES[True]
    launched = record_launches(monkeypatch)
    params = _params(device=device)
    adam = FiniteAdam(params, LRS, "test", fused=True)
    for step in (1, 2):
        _set(params, _grads(step, device))
        adam.step(step, torch.tensor(1.0, device=device), {})
    # the second parameter's step size is no 16-byte aligned entry of the rates: still the one compilation
    assert len(launched) == 2 and launched == warmed(warmups(device))
