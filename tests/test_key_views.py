"""Key views: farthest-point traversal over camera poses, checked against brute force and on real captures."""

import itertools
import math

import numpy as np
import pytest
import torch

from artnvg_core.cameras import CameraSet, load_cameras
from artnvg_core.key_views import covering_radius, select_key_views, view_distances
from artnvg_core.formats import read_ply


def _random_cameras(count: int, seed: int) -> CameraSet:
    """Cameras at random centres with random orientations (float64 rotations from QR)."""
    generator = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(count, 3, 3, generator=generator, dtype=torch.float64))
    rotations = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2))[:, None, :]
    rotations[torch.det(rotations) < 0] *= -1
    centers = 3 * torch.randn(count, 3, generator=generator, dtype=torch.float64)
    world_to_cam = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    world_to_cam[:, :3, :3] = rotations
    world_to_cam[:, :3, 3] = -(rotations @ centers[:, :, None])[..., 0]
    intrinsics = torch.tensor([[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]).repeat(count, 1, 1)
    return CameraSet(world_to_cam.float(), intrinsics, 64, 64, [f"v{i}" for i in range(count)])


def _pose_distances(cameras: CameraSet) -> np.ndarray:
    """The documented distance, written out pair by pair: centres over their RMS spread, forward axes."""
    w2c = cameras.world_to_cam.double()
    centers = [-(w2c[i, :3, :3].T @ w2c[i, :3, 3]) for i in range(len(cameras))]
    mean = sum(centers) / len(centers)
    spread = math.sqrt(sum(float((c - mean).dot(c - mean)) for c in centers) / len(centers))
    forward = [w2c[i, :3, :3].T @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) for i in range(len(cameras))]
    count = len(cameras)
    out = np.zeros((count, count))
    for i, j in itertools.product(range(count), repeat=2):
        out[i, j] = math.sqrt(float((centers[i] - centers[j]).square().sum()) / spread**2
                              + float((forward[i] - forward[j]).square().sum()))
    return out


def test_distance_is_the_documented_pose_distance():
    cameras = _random_cameras(7, seed=1)
    np.testing.assert_allclose(view_distances(cameras), _pose_distances(cameras), atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_traversal_adds_the_farthest_view_and_meets_the_maximin_and_covering_bounds(seed):
    """Against brute force over every subset of 9 views: each new key view is the farthest from the
    previous ones, the smallest pairwise distance is at least half the best possible (maximin design),
    and the covering radius at most twice the best possible (K-centre)."""
    cameras = _random_cameras(9, seed)
    distances = _pose_distances(cameras)
    previous = select_key_views(cameras, 1)
    for count in range(2, 7):
        chosen = select_key_views(cameras, count)
        (added,) = set(chosen) - set(previous)
        assert set(previous) < set(chosen)
        gaps = {v: min(distances[v, c] for c in previous) for v in range(9) if v not in previous}
        assert gaps[added] == pytest.approx(max(gaps.values()), abs=1e-9)
        subsets = list(itertools.combinations(range(9), count))
        best_maximin = max(min(distances[a, b] for a, b in itertools.combinations(s, 2)) for s in subsets)
        best_radius = min(max(min(distances[v, c] for c in s) for v in range(9)) for s in subsets)
        ours = min(distances[a, b] for a, b in itertools.combinations(chosen, 2))
        assert ours >= best_maximin / 2 - 1e-9
        assert covering_radius(cameras, chosen) <= 2 * best_radius + 1e-6
        previous = chosen


def test_all_views_deterministic_and_independent_of_view_order():
    cameras = _random_cameras(12, seed=3)
    assert select_key_views(cameras, 0) == select_key_views(cameras, 12) == select_key_views(cameras, 40) == \
        list(range(12))
    chosen = select_key_views(cameras, 5)
    assert len(chosen) == 5 and chosen == sorted(chosen) and select_key_views(cameras, 5) == chosen
    order = torch.randperm(12, generator=torch.Generator().manual_seed(4)).tolist()
    shuffled = cameras.subset(order)
    assert sorted(order[i] for i in select_key_views(shuffled, 5)) == chosen
    for bad in (-1, 2.5, True):
        with pytest.raises(ValueError, match="select_key_views: count must be an integer >= 0"):
            select_key_views(cameras, bad)


def _angular_gaps(points: torch.Tensor, cameras: CameraSet, chosen: list[int]) -> torch.Tensor:
    """For every (view, point it sees): the angle in degrees between the view's line of sight to the point
    and the nearest such line of a chosen view that sees the point (180 when none sees it); frustum
    visibility, no occlusion. Independent of the pose distance the selection uses."""
    w2c, intrinsics = cameras.world_to_cam.double(), cameras.intrinsics.double()
    local = torch.einsum("cij,nj->cni", w2c[:, :3, :3], points.double()) + w2c[:, None, :3, 3]
    pixels = torch.einsum("cij,cnj->cni", intrinsics, local)
    u, v = pixels[..., 0] / local[..., 2], pixels[..., 1] / local[..., 2]
    visible = (local[..., 2] > 1e-3) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
    rays = cameras.centers.double()[:, None] - points.double()[None]
    rays = rays / rays.norm(dim=-1, keepdim=True)
    cosines = torch.einsum("cnk,dnk->cdn", rays, rays[chosen])
    cosines = torch.where(visible[chosen][None], cosines, torch.tensor(-2.0, dtype=torch.float64))
    best = cosines.max(1).values
    angles = torch.where(best < -1.5, torch.tensor(180.0, dtype=torch.float64),
                         torch.rad2deg(torch.arccos(best.clamp(-1, 1))))
    return angles[visible]


@pytest.mark.parametrize("scene", ["garden", "face"])
def test_covers_real_captures_better_than_every_nth_view(shared_data, scene):
    """On real captures the key views leave a smaller pose covering radius and smaller worst lines of sight
    (95th percentile over what each view sees) than evenly spaced view indices."""
    folder = shared_data / "scenes" / scene
    cameras = load_cameras(folder / "transforms.json")
    points = read_ply(folder / "scene.ply").means[::50]
    for count in (12, 24):
        keys = select_key_views(cameras, count)
        spaced = [round(i * len(cameras) / count) for i in range(count)]
        assert covering_radius(cameras, keys) < covering_radius(cameras, spaced), count
        ours, theirs = (_angular_gaps(points, cameras, c).quantile(0.95).item() for c in (keys, spaced))
        assert ours < theirs, (count, ours, theirs)
