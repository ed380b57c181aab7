"""Camera paths: an orbit around the capture, a smooth path through chosen views."""

import math

import pytest
import torch

from artnvg_core.cameras import CameraSet, interpolate_path, orbit_path
from camera_references import assert_orthonormal, project, ring_of_cameras


def test_orbit_finds_the_centre_and_keeps_distance_and_level():
    cameras, target, up = ring_of_cameras()
    orbit = orbit_path(cameras, 36)
    assert len(orbit) == 36 and orbit.names[0] == "path_0000" and orbit.names[-1] == "path_0035"
    assert (orbit.width, orbit.height) == (80, 60)
    assert torch.equal(orbit.intrinsics, cameras.intrinsics[:1].expand(36, 3, 3))
    pixels, depth = project(orbit, target[None])
    assert torch.allclose(pixels[:, 0], torch.tensor([40.0, 30.0], dtype=torch.float64), atol=1e-3)
    rotations = orbit.world_to_cam[:, :3, :3].double()
    assert_orthonormal(rotations)
    offsets = orbit.centers.double() - target
    assert torch.allclose(offsets.norm(dim=-1), depth[:, 0], atol=1e-4)
    assert torch.allclose(offsets.norm(dim=-1), offsets.norm(dim=-1).mean().expand(36), atol=1e-4)
    # The orbit's up is the estimated one (mean camera up): close to +z, normal to the circle.
    normal = torch.linalg.cross(offsets[9] - offsets[0], offsets[18] - offsets[0])
    normal = normal / normal.norm()
    assert normal @ up > math.cos(math.radians(10))
    assert torch.allclose(rotations[:, 0] @ normal, torch.zeros(36, dtype=torch.float64), atol=1e-5)  # no roll
    assert (rotations[:, 1] @ normal < 0).all()  # image y points down
    mean_elevation = ((cameras.centers.double() - target) @ normal).mean()
    assert torch.allclose(offsets @ normal, mean_elevation.expand(36), atol=1e-4)


def test_orbit_explicit_parameters_and_errors():
    cameras, target, up = ring_of_cameras()
    orbit = orbit_path(cameras, 8, center=[0.0, 0.0, 0.0], radius=2.0, height=-1.0, up=[0.0, 0.0, 2.0])
    centers = orbit.centers.double()
    assert torch.allclose(centers[:, 2], torch.full((8,), -1.0, dtype=torch.float64), atol=1e-5)
    assert torch.allclose(centers[:, :2].norm(dim=-1), torch.full((8,), 2.0, dtype=torch.float64), atol=1e-5)
    step = (centers[1] - centers[0]).norm()
    assert torch.allclose(step, torch.tensor(2 * 2.0 * math.sin(math.pi / 8), dtype=torch.float64), atol=1e-5)
    parallel = CameraSet(torch.eye(4).repeat(3, 1, 1), cameras.intrinsics[:3], 80, 60, ["a", "b", "c"])
    parallel.world_to_cam[:, 0, 3] = torch.tensor([0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="parallel.*center="):
        orbit_path(parallel)
    with pytest.raises(ValueError, match="radius must be positive"):
        orbit_path(cameras, radius=0.0)
    for frames, got in [(0, "0"), (10**9, "1,000,000,000"), (2.5, "2.5")]:  # 10^9 frames were killed for memory
        with pytest.raises(ValueError, match=f"^orbit_path: num_frames: expected (an int|1 to 1,000,000), got {got}$"):
            orbit_path(cameras, frames)


def rotation_angles(a, b):
    """Angles (radians) between rotation matrices a and b [N, 3, 3]."""
    cos = ((a.transpose(-1, -2) @ b).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    return torch.arccos(cos.clamp(-1, 1))


@pytest.mark.parametrize("loop", [False, True])
def test_interpolate_passes_through_keys_smoothly(loop):
    cameras, _, _ = ring_of_cameras(count=12, seed=13)
    keys, steps = [3, 7, 0, 10], 20
    path = interpolate_path(cameras, keys, steps, loop=loop)
    assert len(path) == (len(keys) * steps if loop else (len(keys) - 1) * steps + 1)
    assert torch.allclose(path.world_to_cam[::steps], cameras.world_to_cam[keys], atol=1e-5)
    rotations = path.world_to_cam[:, :3, :3].double()
    assert_orthonormal(rotations)
    key_rot = cameras.world_to_cam[keys, :3, :3].double()
    key_pairs = [(i, (i + 1) % len(keys)) for i in range(len(keys) if loop else len(keys) - 1)]
    max_key_angle = max(rotation_angles(key_rot[[i]], key_rot[[j]]).item() for i, j in key_pairs)
    max_key_dist = max((cameras.centers[keys[i]] - cameras.centers[keys[j]]).norm().item() for i, j in key_pairs)
    order = list(range(len(path))) + ([0] if loop else [])
    angle_steps = rotation_angles(rotations[order[:-1]], rotations[order[1:]])
    center_steps = (path.centers[order[1:]] - path.centers[order[:-1]]).norm(dim=-1)
    assert angle_steps.max() <= max_key_angle / steps + 1e-3  # slerp: constant angular speed
    assert center_steps.max() <= 2 * max_key_dist / steps
    assert path.names[:2] == ["path_0000", "path_0001"]
    assert torch.equal(path.intrinsics, cameras.intrinsics[3:4].expand(len(path), 3, 3))


def test_interpolate_errors():
    cameras, _, _ = ring_of_cameras(count=4)
    with pytest.raises(ValueError, match="at least 2"):
        interpolate_path(cameras, [1])
    with pytest.raises(ValueError, match="index 9 out of range"):
        interpolate_path(cameras, [0, 9])
    with pytest.raises(ValueError, match="frames_per_segment"):
        interpolate_path(cameras, [0, 1], 0)
    with pytest.raises(ValueError, match="^interpolate_path: frames_per_segment: expected 1 to 1,000,000, got 1,000,001$"):
        interpolate_path(cameras, [0, 1], 10**6 + 1)  # 10^9 was killed for memory
    with pytest.raises(ValueError, match="^interpolate_path: the path's frames: expected 1 to 1,000,000, got 1,500,001$"):
        interpolate_path(cameras, [0, 1, 2, 3], 500_000)
    with pytest.raises(ValueError, match="^interpolate_path: a view index: expected an int, got 0.5$"):
        interpolate_path(cameras, [0.5, 2])  # was view 0
