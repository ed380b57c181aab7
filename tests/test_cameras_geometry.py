"""Rotations and poses: quaternion <-> matrix against Hamilton products, look_at against projection."""

import pytest
import torch

from artnvg_core.cameras import look_at, quat_to_rotmat, rotmat_to_quat
from camera_references import project, random_quats, ring_of_cameras, rotation_of


def test_quaternion_round_trip_including_half_turns():
    generator = torch.Generator().manual_seed(10)
    half_turns = torch.cat([torch.zeros(3, 1), torch.eye(3)], 1).double()  # w = 0: 180 degree rotations
    quats = torch.cat([random_quats(200, generator), half_turns, torch.tensor([[1.0, 0, 0, 0]]).double()])
    rotations = quat_to_rotmat(quats)
    for q, r in zip(quats, rotations):
        assert torch.allclose(r, rotation_of(q), atol=1e-12)
    back = rotmat_to_quat(rotations)
    sign = torch.where((back * quats).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    assert torch.allclose(back * sign, quats, atol=1e-12)


def test_look_at_points_the_camera_at_the_target():
    cameras, target, up = ring_of_cameras()
    pixels, depth = project(cameras, target[None])
    assert torch.allclose(pixels[:, 0], torch.tensor([40.0, 30.0], dtype=torch.float64), atol=1e-4)
    assert (depth > 0).all()
    with pytest.raises(ValueError, match="parallel to the up vector"):
        look_at(torch.zeros(1, 3), torch.tensor([0.0, 0.0, 5.0]), torch.tensor([0.0, 0.0, 1.0]))
