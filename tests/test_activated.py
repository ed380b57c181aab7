"""Activated (render-ready) Gaussians: formulas against float64 references, round trips, bad input."""

import pytest
import torch

from artnvg_core.activated import OPACITY_RANGE, ActivatedGaussians, activate, deactivate
from artnvg_core.scene import GaussianScene


def random_scene(n=2000, degree=3, seed=0) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    return GaussianScene(
        means=torch.randn(n, 3, generator=g) * 5,
        quats=torch.randn(n, 4, generator=g) * 3,
        log_scales=torch.randn(n, 3, generator=g) * 3 - 4,
        opacity_logits=torch.randn(n, generator=g) * 4,
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g),
    )


def ulps_apart(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """How many float32 steps separate a and b (same sign, finite)."""
    return (a.view(torch.int32).long() - b.view(torch.int32).long()).abs()


def test_activate_matches_float64_formulas():
    scene = random_scene()
    a = activate(scene)
    q = scene.quats.double()
    torch.testing.assert_close(a.scales, torch.exp(scene.log_scales.double()).float(), rtol=0, atol=0)
    torch.testing.assert_close(a.opacities, (1 / (1 + torch.exp(-scene.opacity_logits.double()))).float(),
                               rtol=1e-7, atol=0)
    torch.testing.assert_close(a.rotations, (q / q.norm(dim=1, keepdim=True)).float(), rtol=0, atol=0)
    assert torch.equal(a.positions, scene.means) and torch.equal(a.sh, scene.sh)
    assert a.opacities.shape == (len(scene),) and a.sh.shape == scene.sh.shape


def test_activated_round_trip_is_within_one_float32_step():
    """activated -> scene -> activated: positions and SH bit-identical, scales and rotations within 1 ulp."""
    a = activate(random_scene())
    a.opacities[::2] = torch.rand(len(a.opacities[::2]), generator=torch.Generator().manual_seed(1))  # any float32
    back = activate(deactivate(a, "test"))
    assert torch.equal(back.positions, a.positions) and torch.equal(back.sh, a.sh)
    for name in ("scales", "rotations"):
        steps = ulps_apart(getattr(back, name).abs(), getattr(a, name).abs())
        assert steps.max() <= 1, name
        assert (steps == 0).float().mean() > 0.85, name  # most values come back exactly
    assert torch.equal(back.rotations.sign(), a.rotations.sign())
    assert opacities_agree(back.opacities, a.opacities)


def opacities_agree(got: torch.Tensor, expected: torch.Tensor) -> bool:
    """Whether ``got`` is within the rounding of ``expected``'s float32 logit: relative (|logit| + 1) * 2^-24."""
    logit = torch.logit(expected.double())
    return bool(((got.double() - expected.double()).abs() <= (logit.abs() + 1) * 2.0**-24 * expected.double()).all())


def test_scene_round_trip_moves_raw_values_by_their_activated_rounding_only():
    scene = random_scene()
    back = deactivate(activate(scene), "test")
    assert torch.equal(back.means, scene.means) and torch.equal(back.sh, scene.sh)
    torch.testing.assert_close(back.quats, scene.quats / scene.quats.norm(dim=1, keepdim=True), rtol=0, atol=2e-7)
    # a float32 scale carries a relative error <= 2^-24, i.e. an absolute one on its log
    assert (back.log_scales - scene.log_scales).abs().max() <= 2 * 2.0**-24 + 2 * torch.finfo(torch.float32).eps
    # an opacity o carries an absolute error <= 2^-25 (o >= 0.5) or relative 2^-24: logit moves by that / (o (1 - o))
    o = torch.sigmoid(scene.opacity_logits.double())
    bound = (2.0**-24 / (1 - o)).float() + 4 * torch.finfo(torch.float32).eps * scene.opacity_logits.abs()
    assert ((back.opacity_logits - scene.opacity_logits).abs() <= bound).all()


def test_opacities_of_zero_and_one_get_finite_logits():
    a = activate(random_scene(n=2, degree=0))
    a.opacities = torch.tensor([0.0, 1.0])
    scene = deactivate(a, "test")
    assert torch.isfinite(scene.opacity_logits).all()
    torch.testing.assert_close(torch.sigmoid(scene.opacity_logits.double()).float(), torch.tensor(OPACITY_RANGE))


@pytest.mark.parametrize("field, value, message", [
    ("sh", torch.zeros(4, 25, 3), "sh: 25 coefficients"),
    ("sh", torch.zeros(4, 5, 3), "sh: 5 coefficients"),
    ("scales", torch.tensor([[1.0, 1, 1], [1, 0, 1], [1, 1, 1], [1, 1, 1]]), "scales: 1 of 4 Gaussians has a scale"),
    ("opacities", torch.tensor([0.5, 1.5, 0.5, -0.1]), "opacities: 2 of 4 Gaussians lie outside [0, 1]"),
    ("positions", torch.tensor([[0.0, 0, 0]] * 3 + [[float("nan"), 0, 0]]), "positions: 1 of 4 Gaussians has non-finite"),
    ("rotations", torch.zeros(4, 4), "rotations: 4 of 4 Gaussians have a zero quaternion"),
    ("opacities", torch.zeros(4, 1), "opacities: expected shape (4,)"),
])
def test_bad_activated_input_names_the_source_and_field(field, value, message):
    a = activate(random_scene(n=4, degree=0))
    setattr(a, field, value)
    with pytest.raises(ValueError, match=r"^splat\.ply: " + message.replace("(", r"\(").replace(")", r"\)")
                       .replace("[", r"\[").replace("]", r"\]")):
        deactivate(a, "splat.ply")


def test_map_applies_to_every_tensor():
    a = ActivatedGaussians(*(torch.ones(1) for _ in range(5)))
    assert all(t.item() == 2 for t in vars(a.map(lambda t: t * 2)).values())
