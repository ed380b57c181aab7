"""Rotations and rigid poses: the one home of the quaternion and pose maths of the package.

Quaternions are w x y z; rotation matrices act on column vectors; poses are 4x4 rigid
transforms (rotation + translation). Cameras use the OpenCV convention of
:mod:`artnvg_core.cameras` (world-to-camera, x right, y down, z forward). Used by the
camera loaders, paths and framing, the views around a scene, the rasterizer, the scene file
formats and the activated Gaussians.
"""

from __future__ import annotations

import torch


def normalize_quats(quat: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] of ``quat`` [..., 4] of any finite norm (1e-40 to 3e38 in float32):
    each is divided by its largest absolute component before the norm is taken, so the squares
    neither underflow nor overflow. The zero quaternion stays zero (which :func:`quat_to_rotmat`
    maps to the identity)."""
    largest = quat.detach().abs().amax(-1, keepdim=True)
    scaled = quat / torch.where(largest > 0, largest, torch.ones_like(largest))
    return torch.nn.functional.normalize(scaled, dim=-1, eps=1e-12)


def quat_to_rotmat(quat: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] (w x y z, any finite norm, normalised
    with :func:`normalize_quats`; the zero quaternion gives the identity)."""
    w, x, y, z = normalize_quats(quat).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def rotmat_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] (w x y z, w >= 0) of rotation matrices [..., 3, 3].

    Every entry of 4 q q^T is linear in the matrix; the row with the largest
    diagonal entry is the best-conditioned multiple of q (Shepperd's method).
    """
    r = rot
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    ww, xx, yy, zz = 1 + trace, 1 + 2 * r[..., 0, 0] - trace, 1 + 2 * r[..., 1, 1] - trace, 1 + 2 * r[..., 2, 2] - trace
    wx, wy, wz = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    xy, xz, yz = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
    outer = torch.stack(  # 4 q q^T
        [
            torch.stack([ww, wx, wy, wz], -1),
            torch.stack([wx, xx, xy, xz], -1),
            torch.stack([wy, xy, yy, yz], -1),
            torch.stack([wz, xz, yz, zz], -1),
        ],
        -2,
    )
    best = torch.stack([ww, xx, yy, zz], -1).argmax(-1)
    row = torch.gather(outer, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    quat = row / row.norm(dim=-1, keepdim=True)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Shortest-arc spherical interpolation of unit quaternions q0, q1 [4] at t [T] -> [T, 4]."""
    if torch.dot(q0, q1) < 0:
        q1 = -q1
    cos = torch.dot(q0, q1).clamp(max=1.0)
    angle = torch.arccos(cos)
    t = t[:, None]
    if angle < 1e-8:
        mixed = (1 - t) * q0 + t * q1
    else:
        mixed = (torch.sin((1 - t) * angle) * q0 + torch.sin(t * angle) * q1) / torch.sin(angle)
    return mixed / mixed.norm(dim=-1, keepdim=True)


def check_rotation(rot: torch.Tensor, where) -> None:
    """ValueError unless ``rot`` [3, 3] (or each of [C, 3, 3]) is orthonormal with determinant +1 (to 1e-3).
    ``where`` names the matrix; for a batch, a function of the index naming the first bad one."""
    batch = rot.reshape(-1, 3, 3)
    errors = (batch.transpose(1, 2) @ batch - torch.eye(3, dtype=rot.dtype)).abs().amax((1, 2))
    dets = torch.linalg.det(batch)
    bad = (~((errors < 1e-3) & (dets > 0))).nonzero()
    if len(bad):
        index = int(bad[0, 0])
        raise ValueError(
            f"{where(index) if callable(where) else where}: the top-left 3x3 block must be a rotation (orthonormal, "
            f"determinant +1); got max|R^T R - I| = {errors[index]:.3g}, det = {dets[index]:.3g}"
        )


def rigid_inverse(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [..., 4, 4] (rotation + translation)."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    inverse = torch.zeros_like(pose)
    inverse[..., :3, :3] = rot_t
    inverse[..., :3, 3] = -(rot_t @ pose[..., :3, 3:])[..., 0]
    inverse[..., 3, 3] = 1
    return inverse


def camera_centers(world_to_cam: torch.Tensor) -> torch.Tensor:
    """Camera centres [C, 3] in world coordinates of world-to-camera poses [C, 4, 4]."""
    rot = world_to_cam[:, :3, :3]
    return -(rot.transpose(1, 2) @ world_to_cam[:, :3, 3:])[..., 0]


def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """OpenCV world-to-camera matrices [N, 4, 4] of cameras at ``eye`` [N, 3] looking at ``target`` [3].

    The camera's z axis points at the target and its y axis (down) is as
    close to ``-up`` as possible, so there is no roll about the view axis.
    """
    forward = target - eye
    right = torch.linalg.cross(forward, up.expand_as(forward))
    if (right.norm(dim=-1) <= 1e-9 * forward.norm(dim=-1) * up.norm()).any():
        raise ValueError("look_at: a view direction is zero or parallel to the up vector")
    forward = forward / forward.norm(dim=-1, keepdim=True)
    right = right / right.norm(dim=-1, keepdim=True)
    down = torch.linalg.cross(forward, right)
    pose = eye.new_zeros(eye.shape[0], 4, 4)
    pose[:, :3, :3] = torch.stack([right, down, forward], dim=1)
    pose[:, :3, 3] = -(pose[:, :3, :3] @ eye[..., None])[..., 0]
    pose[:, 3, 3] = 1
    return pose

