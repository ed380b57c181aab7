"""CameraSet: scaled and subset views, absurd image sizes refused."""

import re

import numpy as np
import pytest
import torch

from artnvg_core.cameras import CameraSet, load_nerfstudio
from camera_references import random_capture, rotation_of, write_transforms


def test_scaled_and_subset():
    quats, trans = random_capture(4, seed=11)
    w2c = torch.eye(4).repeat(4, 1, 1)
    w2c[:, :3, :3] = torch.stack([rotation_of(q) for q in quats]).float()
    w2c[:, :3, 3] = trans.float()
    k = torch.tensor([[100.0, 0, 64.0], [0, 90.0, 48.0], [0, 0, 1]]).repeat(4, 1, 1)
    cameras = CameraSet(w2c, k, 128, 96, ["a", "b", "c", "d"])
    half = cameras.scaled(0.5)
    assert (half.width, half.height) == (64, 48)
    assert torch.equal(half.intrinsics[0], torch.tensor([[50.0, 0, 32.0], [0, 45.0, 24.0], [0, 0, 1]]))
    assert torch.equal(half.world_to_cam, cameras.world_to_cam)
    picked = cameras.subset([3, 0, 2])
    assert picked.names == ["d", "a", "c"]
    assert torch.equal(picked.world_to_cam, w2c[[3, 0, 2]])
    assert cameras.subset(torch.tensor([3, -1])).names == cameras.subset(np.array([3, 3])).names == ["d", "d"]
    for index in (0.5, True, "1"):  # 0.5 was view 0, True view 1
        with pytest.raises(ValueError, match=f"CameraSet.subset: a view index: expected an int, got {index!r}"):
            cameras.subset([index])
    for factor in (True, "2", None):  # True was 1, "2" a TypeError
        with pytest.raises(ValueError, match="CameraSet.scaled: factor must be a finite number > 0"):
            cameras.scaled(factor)


def test_in_view_is_in_front_and_inside_the_image():
    """Points placed by pixel and depth through each camera's own inverse: inside iff depth > 0 and the pixel
    lies in [0, width) x [0, height)."""
    quats, trans = random_capture(3, seed=5)
    w2c = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    w2c[:, :3, :3] = torch.stack([rotation_of(q) for q in quats])
    w2c[:, :3, 3] = trans
    k = torch.tensor([[100.0, 0, 64.0], [0, 90.0, 48.0], [0, 0, 1]]).repeat(3, 1, 1)
    cameras = CameraSet(w2c.float(), k, 128, 96, ["a", "b", "c"])
    pixels = torch.tensor([[1.0, 1], [127.9, 95.9], [-0.1, 50], [64, 96.1], [128.1, 10], [60, 40], [60, 40]])
    depths = torch.tensor([2.0, 3, 2, 2, 2, 5, -5])
    expected = torch.tensor([True, True, False, False, False, True, False])
    for c in range(3):
        in_camera = torch.cat([(pixels - k[c, :2, 2]) / k[c, [0, 1], [0, 1]] * depths[:, None], depths[:, None]], 1)
        world = (in_camera.double() - w2c[c, :3, 3]) @ w2c[c, :3, :3]
        assert torch.equal(cameras.in_view(world)[c], expected), c


@pytest.mark.parametrize("size", [1e20, 10**6, 16385])
def test_absurd_image_sizes_refused_early(tmp_path, size):
    quats, trans = random_capture(2, seed=6)
    with pytest.raises(ValueError, match=r"transforms\.json: frame 0: 'w': expected a whole number of pixels from 1 to 16384"):
        load_nerfstudio(write_transforms(tmp_path / "transforms.json", quats, trans, w=size))
    cameras = load_nerfstudio(write_transforms(tmp_path / "ok.json", quats, trans))
    for factor in (size, float("inf"), float("nan"), 0.0, -1.0):
        with pytest.raises(ValueError, match="CameraSet.scaled: factor"):
            cameras.scaled(factor)
    assert cameras.scaled(1e-6).width == 1 and cameras.scaled(256).width == 16384


@pytest.mark.parametrize("width", [16.0, 16.5, "16", True, None])
def test_image_sides_that_are_not_whole_numbers_refused(width):
    """A float width of 16.0 stopped deep inside render with bincount's "argument 'minlength' must be int", 16.5 and
    True were taken, "16" raised a TypeError."""
    w2c, k = torch.eye(4)[None], torch.tensor([[10.0, 0, 8], [0, 10, 6], [0, 0, 1]])[None]
    with pytest.raises(ValueError, match=f"CameraSet.width: expected an int, got {width!r}"):
        CameraSet(w2c, k, width, 12, ["a"])
    cameras = CameraSet(w2c, k, np.int64(16), torch.tensor(12), ["a"])
    assert (type(cameras.width), type(cameras.height), cameras.width, cameras.height) == (int, int, 16, 12)


@pytest.mark.parametrize("field, value, expected", [
    ("world_to_cam", lambda t: t.long(), "expected a floating-point torch.Tensor, got torch.int64"),
    ("world_to_cam", lambda t: t.numpy(), "expected a floating-point torch.Tensor, got ndarray"),
    ("intrinsics", lambda t: t.to("meta"), "expected world_to_cam's device (cpu), got meta"),
])
def test_poses_and_intrinsics_of_another_kind_or_device_are_refused(field, value, expected):
    """Integer poses rendered with their rotations truncated to integers; numpy arrays and a device apart from the
    poses' stopped later, inside render."""
    tensors = {"world_to_cam": torch.eye(4)[None], "intrinsics": torch.tensor([[10.0, 0, 8], [0, 10, 6], [0, 0, 1]])[None]}
    tensors[field] = value(tensors[field])
    with pytest.raises(ValueError, match=re.escape(f"CameraSet.{field}: {expected}")):
        CameraSet(**tensors, width=16, height=12, names=["a"])
