"""Camera loaders (nerfstudio, COLMAP), conventions and novel-view camera paths.

References are computed independently of artnvg_core.cameras: quaternion
rotation by Hamilton products, projection by brute force in float64, and
COLMAP files written here with ``struct`` following the COLMAP format docs.
"""

import json
import math
import struct
from pathlib import Path

import pytest
import torch

from artnvg_core.cameras import (
    CameraSet,
    interpolate_path,
    load_cameras,
    load_colmap,
    load_nerfstudio,
    look_at,
    orbit_path,
    quat_to_rotmat,
    rotmat_to_quat,
)

# --------------------------------------------------------------------------- independent references


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


# --------------------------------------------------------------------------- nerfstudio


def test_opengl_to_opencv_on_a_hand_made_frame(tmp_path):
    # Camera at +3 x looking at the origin, world z up: OpenGL axes right=+y, up=+z, back=+x.
    c2w = [[0, 0, 1, 3], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]
    path = write_json(
        tmp_path / "transforms.json",
        {"w": 640, "h": 480, "fl_x": 500.0, "fl_y": 510.0, "cx": 321.0, "cy": 242.0,
         "frames": [{"file_path": "a.png", "transform_matrix": c2w}]},
    )
    cameras = load_nerfstudio(path)
    points = torch.tensor([[0, 0, 0], [0, 0.6, 0], [0, 0, 0.3]], dtype=torch.float64)
    pixels, depth = project(cameras, points)
    assert torch.allclose(depth[0], torch.full((3,), 3.0, dtype=torch.float64), atol=1e-6)
    expected = torch.tensor(
        [[321.0, 242.0], [321.0 + 500 * 0.6 / 3, 242.0], [321.0, 242.0 - 510 * 0.3 / 3]], dtype=torch.float64
    )
    assert torch.allclose(pixels[0], expected, atol=1e-4)  # right -> u > cx, up -> v < cy
    assert torch.allclose(cameras.centers[0], torch.tensor([3.0, 0.0, 0.0]), atol=1e-6)
    assert_orthonormal(cameras.world_to_cam[:, :3, :3])


def test_global_and_per_frame_intrinsics(tmp_path):
    quats, trans = random_capture(3)
    path = write_transforms(tmp_path / "scene" / "transforms.json", quats, trans)
    data = json.loads(path.read_text())
    del data["cx"], data["cy"]
    data["frames"][1].update({"fl_x": 80.0, "cx": 10.0, "cy": 20.0})
    data["frames"][2].update({"fl_y": 70.0, "w": 64})
    write_json(path, data)
    cameras = load_nerfstudio(path)
    expected = torch.tensor(
        [
            [[50, 0, 32], [0, 55, 24], [0, 0, 1]],  # global; cx, cy default to w/2, h/2
            [[80, 0, 10], [0, 55, 20], [0, 0, 1]],
            [[50, 0, 32], [0, 70, 24], [0, 0, 1]],
        ],
        dtype=torch.float32,
    )
    assert torch.equal(cameras.intrinsics, expected)
    assert (cameras.width, cameras.height) == (64, 48)
    assert cameras.names == ["view_00", "view_01", "view_02"]
    assert cameras.image_paths == [tmp_path / "scene" / "images" / f"view_{i:02d}.png" for i in range(3)]


@pytest.mark.parametrize("applied_transform", ["none", "recorded", "legacy colmap layout"])
def test_dataparser_transform_maps_points_consistently(tmp_path, applied_transform):
    quats, trans = random_capture(4, seed=1)
    generator = torch.Generator().manual_seed(2)
    dp_quat = random_quats(1, generator)[0]
    dp_rot, dp_shift, dp_scale = rotation_of(dp_quat), torch.tensor([0.3, -1.2, 0.7], dtype=torch.float64), 0.37
    transform = torch.cat([dp_rot, dp_shift[:, None]], 1)  # json frame -> dataparser frame, before scaling
    meta, saved_scale = {}, dp_scale
    if applied_transform != "none":
        # nerfstudio saves the transform relative to the original (pre-applied_transform) frame
        # and the scale multiplied by applied_scale.
        if applied_transform == "recorded":
            applied = torch.tensor([[0, 1, 0, 0.5], [1, 0, 0, 0], [0, 0, -1, 2.0]], dtype=torch.float64)
            meta = {"applied_transform": applied.tolist(), "applied_scale": 2.0}
            saved_scale = dp_scale * 2.0
        else:  # old ns-process-data output: not recorded, implied by a colmap/sparse/0 folder
            applied = torch.tensor([[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]], dtype=torch.float64)
            (tmp_path / "colmap" / "sparse" / "0").mkdir(parents=True)
        transform = transform @ torch.cat([applied, torch.tensor([[0, 0, 0, 1.0]], dtype=torch.float64)])
    path = write_transforms(tmp_path / "transforms.json", quats, trans, **meta)
    dp_path = write_json(
        tmp_path / "out" / "dataparser_transforms.json", {"transform": transform.tolist(), "scale": saved_scale}
    )

    plain = load_nerfstudio(path)
    mapped = load_nerfstudio(path, dataparser_transforms=dp_path)
    points = torch.randn(20, 3, dtype=torch.float64, generator=generator)
    mapped_points = dp_scale * (points @ dp_rot.T + dp_shift)
    pixels, depth = project(plain, points)
    mapped_pixels, mapped_depth = project(mapped, mapped_points)
    assert torch.allclose(mapped_pixels, pixels, atol=1e-3)
    assert torch.allclose(mapped_depth, dp_scale * depth, atol=1e-5)
    assert_orthonormal(mapped.world_to_cam[:, :3, :3])


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["frames"][1].pop("transform_matrix"), r"frame 1: missing key 'transform_matrix'"),
        (lambda d: d.pop("fl_x"), r"frame 0: missing key 'fl_x'"),
        (lambda d: d["frames"][2].update(w=100), r"frame 2: image size 100x48 differs"),
        (
            lambda d: d["frames"][0].update(transform_matrix=[[0.0] * 4] * 3 + [[0, 0, 0, 1]]),
            r"frame 0: 'transform_matrix'.*rotation",
        ),
        (
            lambda d: d["frames"][0].update(transform_matrix=[[1, 0, 0], [0, 1, 0]]),
            r"frame 0: 'transform_matrix'.*3x4 or 4x4",
        ),
        (
            lambda d: d["frames"][0]["transform_matrix"][3].__setitem__(0, 1.0),
            r"frame 0: 'transform_matrix'.*bottom row",
        ),
        (lambda d: d["frames"][0].update(file_path=None), r"frame 0: 'file_path'"),
        (lambda d: d.update(fl_y="55"), r"frame 0: 'fl_y': expected a finite number"),
        (lambda d: d.update(camera_model="OPENCV_FISHEYE"), r"'camera_model'.*OPENCV_FISHEYE"),
        (lambda d: d.update(frames=[]), r"non-empty list under 'frames'"),
    ],
)
def test_nerfstudio_errors_name_file_frame_and_key(tmp_path, edit, message):
    quats, trans = random_capture(3)
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    data = json.loads(path.read_text())
    edit(data)
    write_json(path, data)
    with pytest.raises(ValueError, match=r"transforms\.json: .*" + message):
        load_nerfstudio(path)


def test_nerfstudio_rejects_invalid_json_and_bad_dataparser_file(tmp_path):
    bad = tmp_path / "broken.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"broken\.json: not valid JSON"):
        load_nerfstudio(bad)
    quats, trans = random_capture(2)
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    dp_path = write_json(tmp_path / "dp.json", {"transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1.0})
    with pytest.raises(ValueError, match=r"dp\.json: 'transform'.*rotation"):
        load_nerfstudio(path, dataparser_transforms=dp_path)
    write_json(dp_path, {"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]})
    with pytest.raises(ValueError, match=r"dp\.json: missing key 'scale'"):
        load_nerfstudio(path, dataparser_transforms=dp_path)


# --------------------------------------------------------------------------- COLMAP

MODEL_PARAMS = {  # each gives fx = fy = 50, cx = 30.5, cy = 25 once distortion is ignored
    "SIMPLE_PINHOLE": [50.0, 30.5, 25.0],
    "PINHOLE": [50.0, 50.0, 30.5, 25.0],
    "SIMPLE_RADIAL": [50.0, 30.5, 25.0, 0.01],
    "RADIAL": [50.0, 30.5, 25.0, 0.01, -0.002],
    "OPENCV": [50.0, 50.0, 30.5, 25.0, 0.01, -0.002, 0.001, 0.0005],
}


@pytest.mark.parametrize("model", MODEL_PARAMS)
def test_colmap_text_and_binary_agree_for_each_model(tmp_path, model):
    quats, trans = random_capture(5, seed=3)
    cameras = {1: (model, 64, 48, MODEL_PARAMS[model])}
    loaded = {
        binary: load_colmap(write_colmap(tmp_path / str(binary), cameras, colmap_images(quats, trans), binary))
        for binary in (False, True)
    }
    assert_same_cameras(loaded[False], loaded[True], atol=0)
    cams = loaded[True]
    assert cams.names == [f"view_{i:02d}" for i in range(5)]  # sorted by image name
    assert (cams.width, cams.height) == (64, 48)
    k = torch.tensor([[50, 0, 30.5], [0, 50, 25], [0, 0, 1]])
    assert torch.equal(cams.intrinsics, k.expand(5, 3, 3))
    points = torch.randn(7, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    for i in range(5):  # COLMAP: x_cam = R(q) X + t, checked with Hamilton products
        expected = rotate(quats[i], points) + trans[i]
        got = points @ cams.world_to_cam[i, :3, :3].double().T + cams.world_to_cam[i, :3, 3].double()
        assert torch.allclose(got, expected, atol=1e-5)


def test_colmap_models_give_identical_camera_sets(tmp_path):
    quats, trans = random_capture(4, seed=5)
    sets = [
        load_colmap(write_colmap(tmp_path / model, {1: (model, 64, 48, params)}, colmap_images(quats, trans), True))
        for model, params in MODEL_PARAMS.items()
    ]
    for other in sets[1:]:
        assert_same_cameras(sets[0], other, atol=0)


def test_colmap_matches_equivalent_transforms_json(tmp_path):
    quats, trans = random_capture(6, seed=6)
    from_json = load_nerfstudio(write_transforms(tmp_path / "ns" / "transforms.json", quats, trans))
    model = {1: ("PINHOLE", 64, 48, [50.0, 55.0, 30.5, 25.0])}
    from_colmap = load_colmap(write_colmap(tmp_path / "colmap", model, colmap_images(quats, trans), binary=False))
    assert_same_cameras(from_json, from_colmap)
    assert torch.allclose(from_json.centers, from_colmap.centers, atol=1e-5)


def test_colmap_finds_sparse_0_and_images(tmp_path):
    quats, trans = random_capture(3, seed=7)
    model = {1: ("PINHOLE", 64, 48, MODEL_PARAMS["PINHOLE"])}
    write_colmap(tmp_path / "sparse" / "0", model, colmap_images(quats, trans), binary=True)
    (tmp_path / "images").mkdir()
    (tmp_path / "images" / "view_01.png").write_bytes(b"")
    for source in (tmp_path, tmp_path / "sparse" / "0"):
        cameras = load_colmap(source)
        assert cameras.image_paths == [None, tmp_path / "images" / "view_01.png", None]
    assert_same_cameras(load_cameras(tmp_path), load_colmap(tmp_path / "sparse" / "0"), atol=0)


def test_colmap_errors_name_file_and_field(tmp_path):
    quats, trans = random_capture(3, seed=8)
    images = colmap_images(quats, trans, camera_ids=[1, 2, 1])

    pinhole = ("PINHOLE", 64, 48, [50.0] * 4)
    folder = write_colmap(tmp_path / "fisheye", {1: pinhole, 2: ("OPENCV_FISHEYE", 64, 48, [1.0] * 8)}, images, True)
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 2: camera model OPENCV_FISHEYE is not supported"):
        load_colmap(folder)

    folder = write_colmap(tmp_path / "sizes", {1: pinhole, 2: ("PINHOLE", 32, 48, [50.0] * 4)}, images, False)
    with pytest.raises(ValueError, match=r"images\.txt: image 'view_01\.png': camera 2 is 32x48 .* 64x48"):
        load_colmap(folder)

    folder = write_colmap(tmp_path / "missing", {1: pinhole}, images, True)
    with pytest.raises(ValueError, match=r"images\.bin: image 'view_01\.png': camera id 2 is not in .*cameras\.bin"):
        load_colmap(folder)

    data = (folder / "images.bin").read_bytes()
    (folder / "images.bin").write_bytes(data[:-10])
    with pytest.raises(ValueError, match=r"images\.bin: file ends inside .* \(truncated\?\)"):
        load_colmap(folder)

    folder = write_colmap(tmp_path / "badline", {1: pinhole}, images, False)
    (folder / "cameras.txt").write_text("1 PINHOLE 64 48 50 50 30\n")
    with pytest.raises(ValueError, match=r"cameras\.txt: line 1: expected .* 4 PINHOLE parameters"):
        load_colmap(folder)

    with pytest.raises(ValueError, match=r"no COLMAP model found"):
        load_colmap(tmp_path / "nothing")


# --------------------------------------------------------------------------- dispatch, real data


def test_load_cameras_dispatch(tmp_path):
    quats, trans = random_capture(3, seed=9)
    path = write_transforms(tmp_path / "ns" / "transforms.json", quats, trans)
    assert_same_cameras(load_cameras(path), load_nerfstudio(path), atol=0)
    assert_same_cameras(load_cameras(tmp_path / "ns"), load_nerfstudio(path), atol=0)
    model = write_colmap(tmp_path / "cm", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, colmap_images(quats, trans), False)
    assert_same_cameras(load_cameras(model), load_colmap(model), atol=0)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"empty: not a supported camera source.*transforms\.json.*cameras\.bin"):
        load_cameras(tmp_path / "empty")


def test_bear_transforms(shared_data):
    folder = shared_data / "scenes" / "bear"
    cameras = load_cameras(folder)
    assert len(cameras) == 96
    assert cameras.names[0] == "frame_00096"
    assert (cameras.width, cameras.height) == (512, 512)
    assert cameras.image_paths[0] == folder / "images" / "frame_00096.jpg"
    assert_orthonormal(cameras.world_to_cam[:, :3, :3])
    # The SfM points (same frame) lie in front of the cameras and mostly inside the images;
    # a wrong axis convention puts most of them behind.
    ply_lines = (folder / "sparse_pc.ply").read_text().splitlines()
    body = ply_lines[ply_lines.index("end_header") + 1 :: 50]
    points = torch.tensor([[float(v) for v in line.split()[:3]] for line in body], dtype=torch.float64)
    pixels, depth = project(cameras, points)
    inside = (depth > 0) & (pixels >= 0).all(-1) & (pixels <= 512).all(-1)
    assert (depth > 0).double().mean() > 0.85
    assert inside.double().mean() > 0.5


# --------------------------------------------------------------------------- rotations, CameraSet helpers


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


# --------------------------------------------------------------------------- camera paths


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


def test_look_at_points_the_camera_at_the_target():
    cameras, target, up = ring_of_cameras()
    pixels, depth = project(cameras, target[None])
    assert torch.allclose(pixels[:, 0], torch.tensor([40.0, 30.0], dtype=torch.float64), atol=1e-4)
    assert (depth > 0).all()
    with pytest.raises(ValueError, match="parallel to the up vector"):
        look_at(torch.zeros(1, 3), torch.tensor([0.0, 0.0, 5.0]), torch.tensor([0.0, 0.0, 1.0]))


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
    with pytest.raises(ValueError, match="num_frames"):
        orbit_path(cameras, 0)


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


# --------------------------------------------------------------------------- bad input (issue 14)


def test_missing_or_unreadable_files_are_value_errors_naming_them(tmp_path):
    quats, trans = random_capture(2)
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    with pytest.raises(ValueError, match=r"absent\.json: cannot read the file"):
        load_nerfstudio(tmp_path / "absent.json")
    with pytest.raises(ValueError, match=r"dataparser_transforms\.json: cannot read the file"):
        load_nerfstudio(path, dataparser_transforms=tmp_path / "dataparser_transforms.json")
    with pytest.raises(ValueError, match=r"folder: cannot read the file"):
        load_nerfstudio((tmp_path / "folder").mkdir() or tmp_path / "folder")
    path.write_bytes(path.read_bytes().replace(b"view_00", b"vi\xe9w_00"))  # Latin-1, not UTF-8
    with pytest.raises(ValueError, match=r"transforms\.json: not UTF-8 text .*b'\\xe9'"):
        load_nerfstudio(path)


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_non_utf8_text_and_names(tmp_path, binary):
    quats, trans = random_capture(2, seed=1)
    images = [(*record[:4], record[4].replace("view", "vi\xe9w"), record[5]) for record in colmap_images(quats, trans)]
    folder = tmp_path / "model"
    write_colmap(folder, {1: ("PINHOLE", 64, 48, [50.0] * 4)}, images, binary)
    file = folder / f"images.{'bin' if binary else 'txt'}"
    file.write_bytes(file.read_bytes().replace("\xe9".encode(), b"\xe9"))
    with pytest.raises(ValueError, match=rf"images\.{'bin' if binary else 'txt'}: .*not UTF-8"):
        load_colmap(folder)


BAD_INTRINSICS = [  # (model, width, height, params), each with one thing wrong
    ("PINHOLE", 64, 48, [float("nan"), 50.0, 30.0, 20.0]),
    ("PINHOLE", 64, 48, [50.0, float("inf"), 30.0, 20.0]),
    ("PINHOLE", 64, 48, [50.0, 0.0, 30.0, 20.0]),
    ("SIMPLE_PINHOLE", 64, 48, [-50.0, 30.0, 20.0]),
    ("SIMPLE_RADIAL", 64, 48, [50.0, float("nan"), 20.0, 0.0]),
    ("PINHOLE", 0, 0, [50.0, 50.0, 30.0, 20.0]),
    ("PINHOLE", 64, 0, [50.0, 50.0, 30.0, 20.0]),
    ("PINHOLE", 10**6, 48, [50.0, 50.0, 30.0, 20.0]),
]


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("camera", BAD_INTRINSICS)
def test_colmap_bad_intrinsics_rejected_naming_file_and_camera(tmp_path, binary, camera):
    quats, trans = random_capture(2, seed=2)
    folder = write_colmap(tmp_path / "m", {7: camera}, colmap_images(quats, trans, camera_ids=[7, 7]), binary)
    with pytest.raises(ValueError, match=rf"cameras\.{'bin' if binary else 'txt'}: camera 7: (focal|image size)"):
        load_colmap(folder)


def test_colmap_images_txt_is_read_by_structure(tmp_path):
    """COLMAP writes two lines per image; files without the 2D-points lines hold every image too."""
    quats, trans = random_capture(5, seed=4)
    model = {1: ("PINHOLE", 64, 48, [50.0] * 4)}
    full = load_colmap(write_colmap(tmp_path / "full", model, colmap_images(quats, trans), binary=False))
    folder = write_colmap(tmp_path / "bare", model, colmap_images(quats, trans), binary=False)
    lines = (folder / "images.txt").read_text().splitlines()
    image_lines = [line for line in lines if line.startswith("#") or len(line.split()) == 10]
    for kept in (image_lines, image_lines[:3] + lines[4:]):  # no points lines; some missing
        (folder / "images.txt").write_text("\n".join(kept) + "\n")
        assert_same_cameras(load_colmap(folder), full, atol=0)
        assert load_colmap(folder).names == full.names
    (folder / "images.txt").write_text("\n".join(image_lines[:3] + ["1.5 2.5"] + image_lines[3:]) + "\n")
    with pytest.raises(ValueError, match=r"images\.txt: line 4: expected the 2D points .* of image 'view_04\.png'"):
        load_colmap(folder)


def test_views_sharing_an_image_stem_get_distinct_names(tmp_path):
    quats, trans = random_capture(3, seed=5)
    records = colmap_images(quats, trans)
    names = ["cam0/0001.png", "cam1/0001.png", "cam1/0002.jpg"]
    records = [(*r[:4], name, r[5]) for r, name in zip(records, names)]
    cameras = load_colmap(write_colmap(tmp_path / "rig", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, records, True))
    assert cameras.names == ["cam0_0001", "cam1_0001", "0002"]
    records = [(*r[:4], name, r[5]) for r, name in zip(records, ["a.png", "a.jpg", "b.png"])]
    with pytest.raises(ValueError, match=r"images\.txt: image files \['a\.jpg', 'a\.png'\] give views one name"):
        load_colmap(write_colmap(tmp_path / "clash", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, records, False))
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    data = json.loads(path.read_text())
    data["frames"][1]["file_path"] = "images_2/view_00.png"
    assert load_nerfstudio(write_json(path, data)).names == ["images_view_00", "images_2_view_00", "view_02"]


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
