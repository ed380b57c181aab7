"""The strength dial: exact ends in renders, a float64 mix in between, selections, and refusals."""

import dataclasses

import pytest
import torch

from artnvg_core.blend import blend, check_corresponding, render_strengths
from artnvg_core.finetune.color_transfer import match_colors, recolor_scene
from artnvg_core.metrics.color import mean_cov_distance
from artnvg_core.progress import Cancelled
from artnvg_core.raster import render
from artnvg_core.scene import GaussianScene

from raster_scenes import hard_scene, make_cameras


def _pair(seed: int = 0, moved: bool = True) -> tuple[GaussianScene, GaussianScene]:
    """A float32 scene and a "finetune" of it: every SH band and opacity changed, and (``moved``) the
    geometry nudged, some quaternions stored with the opposite sign."""
    original = hard_scene(seed, n=80, degree=3, dtype=torch.float32)
    g = torch.Generator().manual_seed(seed + 1)
    n = len(original)

    def noise(t, scale):
        return t + scale * torch.randn(t.shape, generator=g, dtype=t.dtype)

    # opacities of another scale than the original's: a + (b - a) is not b there, as a naive mix would give
    stylized = dataclasses.replace(original, sh=noise(original.sh, 0.3), opacity_logits=noise(original.opacity_logits * 0, 0.02))
    if moved:
        flip = torch.where(torch.arange(n) % 3 == 0, -1.0, 1.0)[:, None]
        stylized = dataclasses.replace(stylized, means=noise(original.means, 0.01),
                                       log_scales=noise(original.log_scales, 0.05),
                                       quats=noise(original.quats, 0.05) * flip)
    return original, stylized


def _cameras():
    return make_cameras([[0.0, 0.3, -4.0], [3.0, -0.5, -2.5]], width=48, height=40)


def _render(scene):
    with torch.no_grad():
        return render(scene, _cameras(), backend="torch")


def test_ends_render_the_two_scenes_bit_for_bit():
    original, stylized = _pair()
    for strength, expected in ((0.0, original), (1.0, stylized), (0, original), (1, stylized)):
        got, want = _render(blend(original, stylized, strength)), _render(expected)
        assert torch.equal(got.rgb, want.rgb) and torch.equal(got.alpha, want.alpha), strength
        mixed = blend(original, stylized, strength)
        assert all(torch.equal(mixed.tensors()[k], v) for k, v in expected.tensors().items() if k != "quats")
    assert not torch.equal(_render(original).rgb, _render(stylized).rgb)  # the two ends differ


def test_mix_matches_a_float64_reference_on_every_field():
    original, stylized = _pair()
    strength = 0.3
    mixed = blend(original, stylized, strength)
    for name in ("sh", "opacity_logits", "means", "log_scales"):
        a, b = getattr(original, name).double(), getattr(stylized, name).double()
        torch.testing.assert_close(getattr(mixed, name).double(), (1 - strength) * a + strength * b,
                                   rtol=0, atol=1e-6)
    # quaternions: q and -q are one rotation; the mix goes the short way, toward the stylized one's rotation
    a, b = original.quats.double(), stylized.quats.double()
    aligned = torch.where((a * b).sum(1, keepdim=True) < 0, -b, b)
    torch.testing.assert_close(mixed.quats.double(), (1 - strength) * a + strength * aligned, rtol=0, atol=1e-6)
    assert (mixed.quats.double() * a).sum(1).min() > 0


def test_selection_mixes_only_its_gaussians():
    original, stylized = _pair()
    selection = torch.arange(len(original)) % 4 == 1
    mixed = blend(original, stylized, 0.6, selection)
    for name, value in mixed.tensors().items():
        before, after = getattr(original, name), getattr(stylized, name)
        assert torch.equal(value[~selection], before[~selection]), name
        reference = blend(original.select(selection), stylized.select(selection), 0.6)
        torch.testing.assert_close(value[selection], getattr(reference, name), rtol=0, atol=0)
        assert not torch.equal(value[selection], before[selection]) and not torch.equal(value[selection], after[selection])


def test_unmoved_geometry_is_kept_as_it_is():
    original, stylized = _pair(moved=False)
    mixed = blend(original, stylized, 0.5)
    assert mixed.means is original.means and mixed.quats is original.quats and mixed.log_scales is original.log_scales


def test_colour_distance_to_the_style_falls_monotonically_with_strength():
    original, _ = _pair(moved=False)
    style = torch.stack(torch.meshgrid(torch.linspace(0.5, 0.9, 30), torch.linspace(0.1, 0.3, 30), indexing="ij")
                        + (torch.full((30, 30), 0.6),), -1)
    stylized = recolor_scene(original, match_colors(_render(original).rgb.clamp(0, 1), style))
    distances = [mean_cov_distance(_render(blend(original, stylized, s)).rgb, style) for s in torch.linspace(0, 1, 6).tolist()]
    assert all(later < earlier for earlier, later in zip(distances, distances[1:])), distances
    assert distances[-1] < 0.5 * distances[0]


def test_scenes_that_do_not_correspond_are_refused():
    original, stylized = _pair()
    with pytest.raises(ValueError, match=r"cannot blend a.ply and b.ply: a.ply has 90 Gaussians, b.ply 89"):
        blend(original, stylized.select(slice(1, None)), 0.5, names=("a.ply", "b.ply"))
    lower = dataclasses.replace(stylized, sh=stylized.sh[:, :9])
    with pytest.raises(ValueError, match="SH degree 3 in original, 2 in stylized"):
        blend(original, lower, 0.5)
    with pytest.raises(ValueError, match="render settings"):
        blend(original, dataclasses.replace(stylized, antialiased=True), 0.5)
    reordered = stylized.select(torch.randperm(len(stylized), generator=torch.Generator().manual_seed(0)))
    with pytest.raises(ValueError, match="not one scene before and after a finetune"):
        blend(original, reordered, 0.5)
    other = hard_scene(7, n=80, degree=3)
    with pytest.raises(ValueError, match="not one scene before and after a finetune"):
        check_corresponding(original, other)
    check_corresponding(original, stylized)  # a finetune's small moves are accepted


def test_scenes_of_no_size_are_blended():
    """One Gaussian (or all at one point) has no size to measure a move by: a finetune that moved it stopped with a
    ZeroDivisionError while the refusal was being worded."""
    original, stylized = (scene.select([0]) for scene in _pair())
    mixed = blend(original, stylized, 0.25)
    torch.testing.assert_close(mixed.means, torch.lerp(original.means, stylized.means, 0.25), rtol=0, atol=0)


@pytest.mark.parametrize("strength", [-0.1, 1.5, float("nan"), "0.5"])
def test_strength_outside_zero_to_one_is_refused(strength):
    original, stylized = _pair()
    with pytest.raises(ValueError, match="strength must be a number from 0 to 1"):
        blend(original, stylized, strength)


def test_selection_of_another_scene_is_refused():
    original, stylized = _pair()
    with pytest.raises(ValueError, match="boolean mask of the scene's 90 Gaussians"):
        blend(original, stylized, 0.5, torch.ones(89, dtype=torch.bool))


def test_the_strength_previews_report_each_render_and_stop_when_asked():
    """A capture's view takes seconds to render on a CPU, one per strength: the bar shows from the start and moves
    per render, and a stop request ends the previews."""
    original, stylized = _pair()
    reports = []
    previews = render_strengths(original, stylized, _cameras(), [0, 0.5, 1], backend="torch",
                                progress=lambda done, total, info: reports.append((done, total)))
    assert reports == [(0, 3), (1, 3), (2, 3), (3, 3)]
    torch.testing.assert_close(previews[2:], _render(stylized).rgb[:1].clamp(0, 1))
    with pytest.raises(Cancelled):
        render_strengths(original, stylized, _cameras(), [0, 1], backend="torch", should_stop=lambda: bool(reports))
