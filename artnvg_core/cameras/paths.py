"""Novel-view camera paths through a capture: an orbit around it, a smooth path through chosen views.

Path views are roll-free and take the intrinsics and image size of one capture view; poses are
computed in float64 (rotations by quaternion slerp, centres by a Catmull-Rom spline).
"""

from __future__ import annotations

import math

import torch

from .camera_set import CameraSet, view_count, whole_number
from .geometry import camera_centers, look_at, quat_to_rotmat, rotmat_to_quat, slerp


class NoOrbit(ValueError):
    """:func:`orbit_path` found no orbit around the cameras; ``reason`` says why, in words that name none of its
    arguments (the message adds the one to pass), for callers that offer other choices."""

    def __init__(self, reason: str, argument: str):
        super().__init__(f"orbit_path: {reason}; pass {argument}=")
        self.reason = reason


def _path_camera_set(reference: CameraSet, world_to_cam: torch.Tensor) -> CameraSet:
    """Path views named ``path_0000``... with the single-view ``reference``'s intrinsics and size."""
    count = world_to_cam.shape[0]
    like = reference.world_to_cam
    return CameraSet(
        world_to_cam=world_to_cam.to(dtype=like.dtype, device=like.device),
        intrinsics=reference.intrinsics.expand(count, 3, 3).clone(),
        width=reference.width,
        height=reference.height,
        names=[f"path_{i:04d}" for i in range(count)],
    )


def _closest_point_to_axes(centers: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Least-squares point [3] nearest to the lines ``centers + s * directions`` ([C, 3], unit directions)."""
    projectors = torch.eye(3, dtype=centers.dtype) - directions[:, :, None] * directions[:, None, :]
    system = projectors.sum(0)
    eigenvalues = torch.linalg.eigvalsh(system)
    if eigenvalues[0] <= 1e-6 * eigenvalues[-1]:
        raise NoOrbit("the camera optical axes are (nearly) parallel, so have no centre", "center")
    return torch.linalg.solve(system, (projectors @ centers[..., None]).sum(0))[:, 0]


def _vector3(value, name: str) -> torch.Tensor:
    vector = torch.as_tensor(value, dtype=torch.float64).cpu()
    if tuple(vector.shape) != (3,) or not torch.isfinite(vector).all():
        raise ValueError(f"orbit_path: {name} must be 3 finite numbers, got {value!r}")
    return vector


def orbit_path(
    cameras: CameraSet, num_frames: int = 120, *, center=None, radius=None, height=None, up=None
) -> CameraSet:
    """``num_frames`` views on a horizontal circle around the scene, all looking at its centre.

    ``up`` (world vector) defaults to the mean of the cameras' up directions
    (their -y axes); ``center`` to the point nearest to all optical axes
    (least squares). The circle lies ``height`` above the centre along
    ``up`` with radius ``radius`` (world units), by default the cameras' mean
    elevation and mean horizontal distance. It starts at the first camera's
    azimuth and turns counter-clockwise about ``up``; frames are evenly spaced
    and do not repeat the start. Views are roll-free and use the first
    camera's intrinsics and image size. :class:`NoOrbit` when the cameras give no centre or no up direction
    (one camera, or all looking one way) and ``center`` or ``up`` is not given.
    """
    num_frames = view_count(num_frames, "orbit_path: num_frames")
    world_to_cam = cameras.world_to_cam.detach().cpu().to(torch.float64)
    rot = world_to_cam[:, :3, :3]
    centers = camera_centers(world_to_cam)
    up = -rot[:, 1, :].mean(0) if up is None else _vector3(up, "up")
    if up.norm() < 1e-9:
        raise NoOrbit("the up direction is zero (the cameras' up vectors cancel out)", "up")
    up = up / up.norm()
    center = _closest_point_to_axes(centers, rot[:, 2, :]) if center is None else _vector3(center, "center")

    offsets = centers - center
    elevations = offsets @ up
    horizontal = offsets - elevations[:, None] * up
    height = elevations.mean().item() if height is None else float(height)
    radius = horizontal.norm(dim=-1).mean().item() if radius is None else float(radius)
    if not (radius > 0 and math.isfinite(radius) and math.isfinite(height)):
        raise ValueError(f"orbit_path: radius must be positive and height finite, got radius={radius}, height={height}")

    start = horizontal[0]
    if start.norm() < 1e-9 * (1 + offsets[0].norm()):  # first camera straight above the centre
        start = torch.linalg.cross(up, torch.eye(3, dtype=torch.float64)[up.abs().argmin()])
    start = start / start.norm()
    side = torch.linalg.cross(up, start)
    angles = torch.arange(num_frames, dtype=torch.float64) * (2 * math.pi / num_frames)
    eyes = center + height * up + radius * (torch.cos(angles)[:, None] * start + torch.sin(angles)[:, None] * side)
    return _path_camera_set(cameras.subset([0]), look_at(eyes, center, up))


def _catmull_rom(points: torch.Tensor, steps: int, loop: bool) -> torch.Tensor:
    """Uniform Catmull-Rom spline through ``points`` [K, 3], ``steps`` samples per segment starting at each key."""
    count = points.shape[0]
    if loop:
        tangents = (points.roll(-1, 0) - points.roll(1, 0)) / 2
    else:
        padded = torch.cat([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
        tangents = (padded[2:] - padded[:-2]) / 2
    t = (torch.arange(steps, dtype=points.dtype) / steps)[:, None]
    h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
    segments = []
    for i in range(count if loop else count - 1):
        j = (i + 1) % count
        segments.append(h00 * points[i] + h10 * tangents[i] + h01 * points[j] + h11 * tangents[j])
    return torch.cat(segments)


def check_key_views(indices: list[int]) -> None:
    """ValueError unless ``indices`` name at least two views, the fewest a path through views passes through."""
    if len(indices) < 2:
        raise ValueError(f"a path through views needs at least 2 key views, got {len(indices)}: {indices}")


def interpolate_path(
    cameras: CameraSet, view_indices, frames_per_segment: int = 30, *, loop: bool = False
) -> CameraSet:
    """A smooth path through the capture views ``view_indices`` (at least two), in that order.

    Camera centres follow a uniform Catmull-Rom spline and rotations a
    quaternion slerp (constant angular speed within a segment). Frame
    ``k * frames_per_segment`` is exactly key view k. An open path ends on the
    last key view ((K-1) * frames_per_segment + 1 frames); with ``loop`` it
    returns towards the first (K * frames_per_segment frames, the first not
    repeated). Views use the first key view's intrinsics and image size.
    """
    indices = [whole_number(i, "interpolate_path: a view index") for i in view_indices]  # not int(): 0.5 was view 0
    check_key_views(indices)
    steps = view_count(frames_per_segment, "interpolate_path: frames_per_segment")
    view_count(steps * (len(indices) - (not loop)) + (not loop), "interpolate_path: the path's frames")
    keys = cameras.subset(indices)
    world_to_cam = keys.world_to_cam.detach().cpu().to(torch.float64)
    centers = camera_centers(world_to_cam)
    quats = rotmat_to_quat(world_to_cam[:, :3, :3])

    count = len(indices)
    t = torch.arange(steps, dtype=torch.float64) / steps
    segment_quats = [slerp(quats[i], quats[(i + 1) % count], t) for i in range(count if loop else count - 1)]
    path_quats = torch.cat(segment_quats)
    path_centers = _catmull_rom(centers, steps, loop)
    if not loop:  # close the open path on the last key view
        path_quats = torch.cat([path_quats, quats[-1:]])
        path_centers = torch.cat([path_centers, centers[-1:]])

    path_rot = quat_to_rotmat(path_quats)
    pose = torch.zeros(path_rot.shape[0], 4, 4, dtype=torch.float64)
    pose[:, :3, :3] = path_rot
    pose[:, :3, 3] = -(path_rot @ path_centers[..., None])[..., 0]
    pose[:, 3, 3] = 1
    return _path_camera_set(keys.subset([0]), pose)
