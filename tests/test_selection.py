"""Selections: regions against brute-force point tests, masks and coverage against per-Gaussian weights
from the float64 brute-force renderer (tests/raster_reference.py)."""

import dataclasses

import numpy as np
import pytest
import torch

from artnvg_core.scene import SH_C0, GaussianScene
from artnvg_core.selection import Box, Sphere, check_mask_size, check_selection, coverage, gaussian_weights, parse_region, select_by_masks, select_region

from raster_reference import brute_force_render
from raster_scenes import make_cameras

WIDTH, HEIGHT = 24, 20


def _scene(n: int = 24, seed: int = 0) -> GaussianScene:
    """float64 Gaussians in front of the cameras, overlapping one another."""
    g = torch.Generator().manual_seed(seed)
    return GaussianScene(
        means=torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5,
        quats=torch.randn(n, 4, generator=g, dtype=torch.float64),
        log_scales=torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.3 - 1.8,
        opacity_logits=torch.randn(n, generator=g, dtype=torch.float64) + 1,
        sh=torch.randn(n, 1, 3, generator=g, dtype=torch.float64),
    )


def _cameras():
    return make_cameras([[0.0, 0.2, -3.0], [2.5, -0.5, -1.5]], width=WIDTH, height=HEIGHT, dtype=torch.float64,
                        focal=22.0)


def _reference_weights(scene: GaussianScene, cameras) -> np.ndarray:
    """[N, C, H, W] float64: each Gaussian's compositing weight at every pixel, from brute-force renders in
    which it alone is white in one colour channel (colour 1) and every other Gaussian black there (three
    Gaussians a render, one per channel)."""
    weights = np.zeros((len(scene), len(cameras), HEIGHT, WIDTH))
    for first in range(0, len(scene), 3):
        sh = np.full((len(scene), 1, 3), -0.5 / SH_C0)
        for channel, g in enumerate(range(first, min(first + 3, len(scene)))):
            sh[g, 0, channel] = 0.5 / SH_C0
        for c in range(len(cameras)):
            rgb, _, _ = brute_force_render(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, sh,
                                           cameras.world_to_cam[c], cameras.intrinsics[c], WIDTH, HEIGHT)
            channels = min(3, len(scene) - first)
            weights[first:first + channels, c] = np.moveaxis(rgb[..., :channels], -1, 0)
    return weights


@pytest.fixture(scope="module")
def weights():
    return _reference_weights(_scene(), _cameras())


def _painted() -> torch.Tensor:
    """[2, H, W]: a painted rectangle in the first view, a soft stroke in the second."""
    masks = torch.zeros(2, HEIGHT, WIDTH, dtype=torch.float64)
    masks[0, 4:14, 3:12] = 1
    masks[1, :, 13:] = 0.7
    return masks


def test_gaussian_weights_match_the_brute_force_renderer(weights):
    scene, cameras, masks = _scene(), _cameras(), _painted()
    weighted, total = gaussian_weights(scene, cameras, masks, backend="torch")
    np.testing.assert_allclose(total.numpy(), weights.sum(axis=(1, 2, 3)), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(weighted.numpy(), (weights * masks.numpy()[None]).sum(axis=(1, 2, 3)), rtol=1e-9,
                               atol=1e-12)
    assert (total > 0.1).sum() > len(scene) // 2  # most are seen


def test_masks_select_the_gaussians_mostly_on_painted_pixels(weights):
    scene, cameras, masks = _scene(), _cameras(), _painted()
    inside, total = (weights * masks.numpy()[None]).sum(axis=(1, 2, 3)), weights.sum(axis=(1, 2, 3))
    expected = (total > 0) & (inside >= 0.5 * total)
    got = select_by_masks(scene, cameras, masks, backend="torch")
    assert 0 < expected.sum() < len(scene)
    np.testing.assert_array_equal(got.numpy(), expected)


def test_a_mask_selects_the_front_gaussian_not_the_one_it_hides():
    """An opaque Gaussian hides part of one behind it: painting the front one's footprint, which covers
    some of the other's visible pixels too, selects the front one only."""
    scene = GaussianScene(means=torch.tensor([[0.0, 0.0, -1.0], [0.8, 0.0, 1.0]], dtype=torch.float64),
                          quats=torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64),
                          log_scales=torch.tensor([[-1.2, -1.2, -1.2], [-1.0, -1.0, -1.0]], dtype=torch.float64),
                          opacity_logits=torch.tensor([8.0, 8.0], dtype=torch.float64),
                          sh=torch.zeros(2, 1, 3, dtype=torch.float64))
    cameras = make_cameras([[0.0, 0.0, -4.0]], width=WIDTH, height=HEIGHT, dtype=torch.float64, focal=22.0)
    weights = _reference_weights(scene, cameras)[:, 0]
    painted = torch.from_numpy(weights[0] > 0.3)[None].double()  # the front Gaussian's footprint
    assert 0.1 < (weights[1] * painted[0].numpy()).sum() / weights[1].sum() < 0.5  # seen through its edge too
    assert select_by_masks(scene, cameras, painted, backend="torch").tolist() == [True, False]


def test_coverage_is_the_selected_gaussians_summed_weight(weights):
    scene, cameras = _scene(), _cameras()
    selection = torch.arange(len(scene)) % 3 == 0
    expected = weights[selection.numpy()].sum(axis=0)
    np.testing.assert_allclose(coverage(scene, selection, cameras, backend="torch").numpy(), expected, rtol=0,
                               atol=1e-9)
    everything = coverage(scene, torch.ones(len(scene), dtype=torch.bool), cameras, backend="torch")
    np.testing.assert_allclose(everything.numpy(), weights.sum(axis=0), rtol=0, atol=1e-9)  # the render's alpha


def test_regions_match_brute_force_point_tests():
    scene = _scene(n=400, seed=1)
    box = parse_region("box:-0.3,-0.5,-0.2,0.4,0.1,0.6")
    sphere = parse_region(" sphere:0.1,-0.2,0.3,0.5")
    assert box == Box((-0.3, -0.5, -0.2), (0.4, 0.1, 0.6)) and sphere == Sphere((0.1, -0.2, 0.3), 0.5)
    points = scene.means.tolist()
    in_box = [all(lo <= v <= hi for v, lo, hi in zip(p, box.low, box.high)) for p in points]
    in_sphere = [sum((v - c) ** 2 for v, c in zip(p, sphere.center)) <= 0.25 for p in points]
    assert select_region(scene, box).tolist() == in_box and 0 < sum(in_box) < len(points)
    assert select_region(scene, sphere).tolist() == in_sphere and 0 < sum(in_sphere) < len(points)


def test_region_boundaries_are_inside():
    scene = dataclasses.replace(_scene(n=2), means=torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 2.0]], dtype=torch.float64))
    assert select_region(scene, Box((1.0, 2.0, 3.0), (1.0, 2.0, 3.0))).tolist() == [True, False]
    assert select_region(scene, Sphere((0.0, 0.0, 0.0), 2.0)).tolist() == [False, True]


@pytest.mark.parametrize("text, message", [
    ("cube:0,0,0,1,1,1", "expected box:XMIN"),
    ("box:0,0,0,1,1", "a box takes 6 finite numbers, XMIN, YMIN, ZMIN, XMAX, YMAX, ZMAX, .*got '0,0,0,1,1'"),
    ("sphere:0,0,0,x", "a sphere takes 4 finite numbers, X, Y, Z, R, .*got '0,0,0,x'"),
    ("box:0,0,0,1,nan,1", "a box takes 6 finite numbers"),
    ("box:0,2,0,1,1,1", "minimum corner"),
    ("sphere:0,0,0,0", "radius must be > 0"),
])
def test_bad_regions_are_refused_naming_the_option(text, message):
    with pytest.raises(ValueError, match=f"--region: .*{message}"):
        parse_region(text)


@pytest.mark.parametrize("make, message", [
    (lambda: Box((0.0, float("nan"), 0.0), (1.0, 1.0, 1.0)), r"a box's corners must be 3 finite numbers each"),
    (lambda: Box((0.0, 0.0), (1.0, 1.0, 1.0)), r"a box's corners must be 3 finite numbers each"),
    (lambda: Box((0.0, 2.0, 0.0), (1.0, 1.0, 1.0)), r"the box's minimum corner \(0.0, 2.0, 0.0\) must not exceed"),
    (lambda: Sphere((0.0, 0.0, float("inf")), 1.0), r"the sphere's centre must be 3 finite numbers"),
    (lambda: Sphere((0.0, 0.0, 0.0), -1.0), r"the sphere's radius must be > 0, got -1.0"),
    (lambda: Sphere((0.0, 0.0, 0.0), float("nan")), r"the sphere's radius must be > 0, got nan"),
])
def test_regions_made_in_python_are_checked_as_parsed_ones(make, message):
    """A box with a NaN corner or reversed corners, and a sphere of negative radius, selected nothing, silently."""
    with pytest.raises(ValueError, match="^" + message):
        make()


def test_bad_masks_and_selections_are_refused():
    scene, cameras = _scene(), _cameras()
    with pytest.raises(ValueError, match=r"one mask \[H, W\] per view \(2\)"):
        select_by_masks(scene, cameras, torch.ones(1, HEIGHT, WIDTH))
    ones = torch.ones(2, HEIGHT, WIDTH)
    for masks, got in [(ones * float("nan"), "NaN or infinite values"), (ones * 255, "values up to 255"),
                       (ones.to(torch.uint8), "a torch.uint8 tensor")]:  # NaN selected nothing, silently
        with pytest.raises(ValueError, match=rf"^select_by_masks: masks: expected floats in \[0, 1\], got {got}"):
            select_by_masks(scene, cameras, masks)
    assert torch.equal(select_by_masks(scene, cameras, ones.bool()), select_by_masks(scene, cameras, ones))
    with pytest.raises(ValueError, match="boolean mask of the scene's 24 Gaussians"):
        coverage(scene, torch.ones(3, dtype=torch.bool), cameras)


def test_a_mask_is_resized_to_its_view_only_at_its_aspect_within_a_pixels_rounding():
    """A mask of another aspect was once stretched to its view without a word."""
    generator = np.random.default_rng(0)
    for aspect, mask_height, view_height in generator.uniform((0.2, 1, 1), (5, 3000, 3000), (20000, 3)):
        if min(aspect * mask_height, aspect * view_height) >= 1:  # any two renders of one aspect at any scales pass
            check_mask_size(round(aspect * mask_height), round(mask_height), round(aspect * view_height),
                            round(view_height), "mask")
    check_mask_size(1297, 840, 648, 420, "mask")  # a capture's photo, for its views at half size
    for mask, view in [((1000, 510), (1000, 500)), ((640, 480), (1920, 1080)), ((2000, 1004), (1000, 500))]:
        with pytest.raises(ValueError, match=rf"^mask.png: {mask[0]}x{mask[1]} pixels, not the aspect of its view's "
                                             rf"{view[0]}x{view[1]} \(it would be stretched\)"):
            check_mask_size(*mask, *view, "mask.png")
    with pytest.raises(ValueError, match=rf"^select_by_masks: masks: {WIDTH}x{HEIGHT // 2} pixels, not the aspect"):
        select_by_masks(_scene(), _cameras(), torch.ones(2, HEIGHT // 2, WIDTH))


@pytest.mark.parametrize("selection", [torch.ones(24), torch.ones(23, dtype=torch.bool), torch.ones(24, 1, dtype=torch.bool)])
def test_a_selection_that_is_not_one_boolean_per_gaussian_is_refused_naming_its_caller(selection):
    check_selection(torch.ones(24, dtype=torch.bool), 24, "blend")
    with pytest.raises(ValueError, match=r"^finetune: selection must be a boolean mask of the scene's 24 Gaussians, got"):
        check_selection(selection, 24, "finetune")
