"""Depth-warp consistency: exact geometry on an analytic plane, and the floor on a real scene."""

import math

import pytest
import torch

from artnvg_core.cameras import CameraSet, load_cameras, look_at
from artnvg_core.formats import load_scene
from artnvg_core.metrics.warp import reproject, warp_consistency
from artnvg_core.raster import render

PLANE_Z = 5.0
SIZE = 48


# --------------------------------------------------------------------------- analytic plane


def _plane_cameras() -> CameraSet:
    """Three cameras near the origin looking at the plane z = PLANE_Z from slightly different poses."""
    eyes = torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.2, 0.3], [-0.3, 0.25, -0.2]], dtype=torch.float64)
    targets = torch.tensor([[0.0, 0.0, PLANE_Z], [0.2, 0.1, PLANE_Z], [-0.1, 0.0, PLANE_Z]], dtype=torch.float64)
    up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    world_to_cam = torch.stack([look_at(e[None], t, up)[0] for e, t in zip(eyes, targets)])
    k = torch.tensor([[40.0, 0, SIZE / 2 + 0.7], [0, 42.0, SIZE / 2 - 0.4], [0, 0, 1]], dtype=torch.float64)
    return CameraSet(world_to_cam, k.expand(3, 3, 3).clone(), SIZE, SIZE, ["a", "b", "c"])


def _plane_hits(cameras: CameraSet, view: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [H, W, 3] where each pixel's ray meets the plane, and their camera z [H, W]."""
    w2c = cameras.world_to_cam[view].double()
    rot, center = w2c[:3, :3], cameras.centers[view].double()
    ys, xs = torch.meshgrid(torch.arange(SIZE) + 0.5, torch.arange(SIZE) + 0.5, indexing="ij")
    pixels = torch.stack([xs, ys, torch.ones_like(xs)], -1).double()
    directions = pixels @ torch.linalg.inv(cameras.intrinsics[view].double()).T @ rot  # world, camera z = 1
    s = (PLANE_Z - center[2]) / directions[..., 2]
    return center + s[..., None] * directions, s


def _texture(points: torch.Tensor) -> torch.Tensor:
    """A smooth colour field on the plane, [..., 3] in [0, 1]."""
    x, y = points[..., 0], points[..., 1]
    return torch.stack([0.5 + 0.4 * torch.sin(0.9 * x + 0.3), 0.5 + 0.4 * torch.cos(0.7 * y), 0.5 + 0.3 * torch.sin(0.5 * (x + y))], -1)


@pytest.fixture(scope="module")
def plane():
    cameras = _plane_cameras()
    hits = [_plane_hits(cameras, v) for v in range(len(cameras))]
    images = torch.stack([_texture(points) for points, _ in hits]).float()
    depth = torch.stack([z for _, z in hits])[..., None].float()
    return cameras, images, depth, torch.ones_like(depth)


def test_reprojection_lands_on_the_same_plane_point(plane):
    cameras, _, depth, _ = plane
    uv, z = reproject(depth[0, ..., 0].double(), cameras.world_to_cam[0], cameras.intrinsics[0],
                      cameras.world_to_cam[1], cameras.intrinsics[1])
    source_points, _ = _plane_hits(cameras, 0)
    # Independent route: cast view 1's ray through the reprojected pixel and intersect the plane.
    w2c = cameras.world_to_cam[1].double()
    pixels = torch.cat([uv, torch.ones_like(uv[..., :1])], -1)
    directions = pixels @ torch.linalg.inv(cameras.intrinsics[1].double()).T @ w2c[:3, :3]
    center = cameras.centers[1].double()
    s = (PLANE_Z - center[2]) / directions[..., 2]
    torch.testing.assert_close(center + s[..., None] * directions, source_points, atol=1e-4, rtol=0)
    torch.testing.assert_close(z, s, atol=1e-4, rtol=0)


def test_exact_depth_gives_only_interpolation_error(plane):
    cameras, images, depth, alpha = plane
    result = warp_consistency(images, depth, alpha, cameras)
    assert result.pairs == [(0, 1), (1, 2)]
    assert 0.3 < result.coverage < 1.0  # the views overlap only partly
    assert result.rmse < 2e-3 and result.mae <= result.rmse
    # One pixel of misregistration is far above that.
    shifted = warp_consistency(torch.roll(images, 1, dims=2), depth, alpha, cameras)
    assert shifted.rmse > 5 * result.rmse


def test_occluded_and_transparent_pixels_are_masked(plane):
    cameras, images, depth, alpha = plane
    base = warp_consistency(images, depth, alpha, cameras)
    occluded_images, occluded_depth = images.clone(), depth.clone()
    occluded_images[1, 10:30, 10:30] = 1.0  # something else in front in view 1 ...
    occluded_depth[1, 10:30, 10:30] *= 0.5  # ... at half the plane's depth
    masked = warp_consistency(occluded_images, occluded_depth, alpha, cameras, step=1)
    assert masked.coverage < base.coverage and masked.rmse < 2e-3
    unmasked = warp_consistency(occluded_images, occluded_depth, alpha, cameras, depth_tolerance=math.inf)
    assert unmasked.rmse > 0.05
    holes = alpha.clone()
    holes[:, :, : SIZE // 2] = 0
    half = warp_consistency(images, depth, holes, cameras)
    assert half.pixels < base.pixels and half.rmse < 2e-3


def test_long_range_step_and_input_checks(plane):
    cameras, images, depth, alpha = plane
    calls = []  # 0 first: evaluate's warp bars show from the start, as every other bar does
    result = warp_consistency(images, depth, alpha, cameras, step=2, progress=lambda *call: calls.append(call))
    assert result.pairs == [(0, 2)] and result.step == 2 and calls == [(0, 1, {}), (1, 1, {})]
    with pytest.raises(ValueError, match="step"):
        warp_consistency(images, depth, alpha, cameras, step=3)
    with pytest.raises(ValueError, match="depth"):
        warp_consistency(images, depth[:2], alpha, cameras)
    with pytest.raises(ValueError, match="cameras' size"):
        warp_consistency(images[:, :8], depth, alpha, cameras)
    for bad in (float("nan"), 1.0, 2.0, -0.1):
        with pytest.raises(ValueError, match="alpha_threshold"):
            warp_consistency(images, depth, alpha, cameras, alpha_threshold=bad)
    for bad in (float("nan"), 0.0, -1.0):
        with pytest.raises(ValueError, match="depth_tolerance"):
            warp_consistency(images, depth, alpha, cameras, depth_tolerance=bad)
    for bad, got in [((images * 255).to(torch.uint8), "a torch.uint8 tensor"), (images * 255, "values up to"),
                     (images * float("nan"), "NaN")]:  # an error of 94 on 8-bit values, NaN on NaN
        with pytest.raises(ValueError, match=rf"^warp_consistency: images: expected floats in \[0, 1\], got {got}"):
            warp_consistency(bad, depth, alpha, cameras)


# --------------------------------------------------------------------------- real scene


@pytest.fixture(scope="module")
def bear(shared_data):
    """Renders (colour, alpha, depth) of the bear's 10k most opaque and largest Gaussians at 128 px, views 0-2."""
    folder = shared_data / "scenes" / "bear"
    scene = load_scene(folder / "scene.ply")
    footprint = torch.sigmoid(scene.opacity_logits) * scene.log_scales.sort(dim=1).values[:, 1:].sum(1).exp()
    scene = scene.select(footprint.topk(10_000).indices)
    cameras = load_cameras(folder / "transforms.json").subset([0, 1, 2]).scaled(0.25)
    with torch.no_grad():
        out = render(scene, cameras, return_depth=True)
    return cameras, out.rgb.clamp(0, 1), out.depth, out.alpha


def _hue_rotation(degrees: float) -> torch.Tensor:
    """Rotation of RGB space about the grey axis (orthogonal, keeps greys)."""
    axis = torch.ones(3) / 3**0.5
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = math.radians(degrees)
    return torch.eye(3) * math.cos(angle) + math.sin(angle) * cross + (1 - math.cos(angle)) * torch.outer(axis, axis)


def test_real_scene_floor_noise_and_global_colour_change(bear):
    cameras, rgb, depth, alpha = bear
    floor = warp_consistency(rgb, depth, alpha, cameras)
    assert floor.coverage > 0.35
    assert floor.rmse < 0.05  # view-dependent colour, expected depth and interpolation only
    noisy = rgb + 0.1 * torch.randn(rgb.shape, generator=torch.Generator().manual_seed(0))
    assert warp_consistency(noisy, depth, alpha, cameras).rmse > floor.rmse + 0.05
    # The same colour change on every view: a rotation about the grey axis keeps each colour
    # difference's length, so RMSE is unchanged; a uniform scale scales it.
    rotated = warp_consistency(rgb @ _hue_rotation(50).T, depth, alpha, cameras)
    assert rotated.rmse == pytest.approx(floor.rmse, rel=1e-4)
    assert rotated.pixels == floor.pixels
    assert warp_consistency(rgb * 0.5, depth, alpha, cameras).rmse == pytest.approx(0.5 * floor.rmse, rel=1e-4)
    # Swapping the views' poses breaks the geometry and the error jumps.
    swapped = cameras.subset([1, 0, 2])
    assert warp_consistency(rgb, depth, alpha, swapped).rmse > 2 * floor.rmse
