"""Independent references, capture writers and test captures shared by the camera tests.

The references use no artnvg_core.cameras maths: quaternion rotation by Hamilton products,
projection by brute force in float64, nerfstudio transforms.json and COLMAP files written here
(COLMAP with ``struct`` following the COLMAP format docs). :func:`ring_of_cameras` builds its
views with the library's ``look_at``, which tests/test_cameras_geometry.py checks by projection.
"""

import json
import math
import struct
from pathlib import Path

import torch

from artnvg_core.cameras import CameraSet, look_at


def hamilton(a, b):
    """Quaternion product a * b of w x y z tensors [..., 4]."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def rotate(quat, points):
    """Rotate points [..., 3] by the unit quaternion quat [4] (w x y z): q p q*."""
    conj = quat * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=quat.dtype)
    pure = torch.cat([torch.zeros_like(points[..., :1]), points], -1)
    return hamilton(hamilton(quat.expand_as(pure), pure), conj.expand_as(pure))[..., 1:]


def rotation_of(quat):
    """3x3 matrix of a unit quaternion, built column by column from rotated basis vectors."""
    return rotate(quat, torch.eye(3, dtype=quat.dtype)).T


def project(cameras: CameraSet, points):
    """Pixel coordinates [C, P, 2] and depths [C, P] of world points [P, 3], float64 brute force."""
    w2c = cameras.world_to_cam.double()
    k = cameras.intrinsics.double()
    cam = torch.einsum("cij,pj->cpi", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]
    pix = torch.einsum("cij,cpj->cpi", k, cam)
    return pix[..., :2] / pix[..., 2:], cam[..., 2]


def random_quats(count, generator):
    quats = torch.randn(count, 4, dtype=torch.float64, generator=generator)
    return quats / quats.norm(dim=-1, keepdim=True)


def random_capture(count=5, seed=0):
    """(w2c quaternions [C, 4], w2c translations [C, 3]) of random OpenCV cameras."""
    generator = torch.Generator().manual_seed(seed)
    return random_quats(count, generator), torch.randn(count, 3, dtype=torch.float64, generator=generator) * 2


def assert_orthonormal(rotations, atol=1e-5):
    eye = torch.eye(3, dtype=torch.float64).expand_as(rotations)
    rotations = rotations.double()
    assert torch.allclose(rotations.transpose(-1, -2) @ rotations, eye, atol=atol)
    assert torch.allclose(torch.linalg.det(rotations), torch.ones(len(rotations), dtype=torch.float64), atol=atol)


def assert_same_cameras(a: CameraSet, b: CameraSet, atol=1e-5):
    assert (a.width, a.height, a.names) == (b.width, b.height, b.names)
    assert torch.allclose(a.world_to_cam, b.world_to_cam, atol=atol)
    assert torch.allclose(a.intrinsics, b.intrinsics, atol=atol)


# --------------------------------------------------------------------------- writers


def write_json(path: Path, data) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))
    return path


def opengl_cam_to_world(quat, translation):
    """nerfstudio's transform_matrix for an OpenCV world-to-camera pose (R(quat), t)."""
    rot = rotation_of(quat)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = rot.T @ torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    pose[:3, 3] = -rot.T @ translation
    return pose.tolist()


def write_transforms(path: Path, quats, translations, **meta) -> Path:
    frames = [
        {"file_path": f"images/view_{i:02d}.png", "transform_matrix": opengl_cam_to_world(q, t)}
        for i, (q, t) in enumerate(zip(quats, translations))
    ]
    intrinsics = {"w": 64, "h": 48, "fl_x": 50.0, "fl_y": 55.0, "cx": 30.5, "cy": 25.0}
    return write_json(path, {**intrinsics, **meta, "frames": frames})


COLMAP_MODEL_IDS = {
    "SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "OPENCV_FISHEYE": 5,
}


def write_colmap(folder: Path, cameras, images, binary: bool) -> Path:
    """Write a COLMAP sparse model. cameras: {id: (model, w, h, params)};
    images: [(image_id, quat wxyz, t, camera_id, name, points [(x, y, point3d_id)])]."""
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        data = struct.pack("<Q", len(cameras))
        for camera_id, (model, width, height, params) in cameras.items():
            data += struct.pack("<IiQQ", camera_id, COLMAP_MODEL_IDS[model], width, height)
            data += struct.pack(f"<{len(params)}d", *params)
        (folder / "cameras.bin").write_bytes(data)
        data = struct.pack("<Q", len(images))
        for image_id, quat, trans, camera_id, name, points in images:
            data += struct.pack("<I7dI", image_id, *map(float, quat), *map(float, trans), camera_id)
            data += name.encode() + b"\0" + struct.pack("<Q", len(points))
            data += b"".join(struct.pack("<ddq", *point) for point in points)
        (folder / "images.bin").write_bytes(data)
    else:
        lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
        lines += [f"{i} {m} {w} {h} " + " ".join(map(repr, p)) for i, (m, w, h, p) in cameras.items()]
        (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
        lines = ["# Image list with two lines of data per image:", f"# Number of images: {len(images)}"]
        for image_id, quat, trans, camera_id, name, points in images:
            numbers = " ".join(repr(float(v)) for v in (*quat, *trans))
            lines.append(f"{image_id} {numbers} {camera_id} {name}")
            lines.append(" ".join(f"{x!r} {y!r} {p}" for x, y, p in points))
        (folder / "images.txt").write_text("\n".join(lines) + "\n")
    return folder


def colmap_images(quats, translations, camera_ids=None):
    """COLMAP image records named view_XX.png, written in reverse name order."""
    records = []
    for i, (q, t) in enumerate(zip(quats, translations)):
        points = [(1.5, 2.5, 7), (10.25, 3.0, -1)] if i % 2 else []  # also images without 2D points
        records.append((i + 1, q.tolist(), t.tolist(), camera_ids[i] if camera_ids else 1, f"view_{i:02d}.png", points))
    return records[::-1]


# --------------------------------------------------------------------------- test captures


def ring_of_cameras(count=12, seed=12):
    """Cameras at irregular positions around (1, -2, 0.5), all looking at it, world up +z."""
    generator = torch.Generator().manual_seed(seed)
    target = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    angles = torch.rand(count, generator=generator, dtype=torch.float64) * 2 * math.pi
    dist = 3 + torch.rand(count, generator=generator, dtype=torch.float64)
    lift = 0.5 + torch.rand(count, generator=generator, dtype=torch.float64)
    eyes = target + torch.stack([dist * torch.cos(angles), dist * torch.sin(angles), lift], 1)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    k = torch.tensor([[60.0, 0, 40.0], [0, 60.0, 30.0], [0, 0, 1]]).repeat(count, 1, 1)
    return CameraSet(look_at(eyes, target, up).float(), k, 80, 60, [f"v{i}" for i in range(count)]), target, up
