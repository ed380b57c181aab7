"""nerfstudio transforms.json: OpenGL -> OpenCV, intrinsics, dataparser transforms, errors naming file and key."""

import json
import re

import pytest
import torch

from artnvg_core.cameras import load_nerfstudio
from camera_references import (
    assert_orthonormal,
    project,
    random_capture,
    random_quats,
    rotation_of,
    write_json,
    write_transforms,
)


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
        (  # found by fuzzing: torch.tensor read an empty string as an empty list, giving matrices [C, 4, 4, 0]
            lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(0, ""),
            r"frame 0: 'transform_matrix': expected a 3x4 or 4x4 matrix of numbers, got something else",
        ),
        (lambda d: d["frames"][0].update(file_path=None), r"frame 0: 'file_path'"),
        (lambda d: d.update(fl_y="55"), r"frame 0: 'fl_y': expected a number, got a string"),
        (lambda d: d.update(camera_model="OPENCV_FISHEYE"), r"'camera_model'.*OPENCV_FISHEYE"),
        (lambda d: d.update(frames=[]), r"'frames': expected a non-empty list, got a list of 0 items"),
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
    bad.write_text('{"fl_x": 50, "frames": [{"file_path": "a.png", "file_path": "b.png"}]}')
    with pytest.raises(ValueError, match=r"broken\.json: key 'file_path' is given twice in one object"):
        load_nerfstudio(bad)  # a dict would keep b.png silently
    quats, trans = random_capture(2)
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    dp_path = write_json(tmp_path / "dp.json", {"transform": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], "scale": 1.0})
    with pytest.raises(ValueError, match=r"dp\.json: 'transform'.*rotation"):
        load_nerfstudio(path, dataparser_transforms=dp_path)
    write_json(dp_path, {"transform": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]})
    with pytest.raises(ValueError, match=r"dp\.json: missing key 'scale'"):
        load_nerfstudio(path, dataparser_transforms=dp_path)


def test_a_dataparser_translation_putting_cameras_beyond_range_is_named(tmp_path):
    """Found by fuzzing: a dataparser_transforms.json translation beyond float32 was blamed on the
    transforms.json's frame ('pose: values beyond float32's range'), not on the file that held it."""
    path = write_transforms(tmp_path / "transforms.json", *random_capture(2))
    dp_path = write_json(tmp_path / "dp.json", {"transform": [[1, 0, 0, 1e308], [0, 1, 0, 0], [0, 0, 1, 0]],
                                                "scale": 1.0})
    with pytest.raises(ValueError, match=r"dp\.json: 'transform' and 'scale' put frame 0 of .*transforms\.json at "
                                         r"x: expected a finite number within \+-1e\+09"):
        load_nerfstudio(path, dataparser_transforms=dp_path)


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
    with pytest.raises(ValueError, match=r"transforms\.json: not UTF-8 text \(at byte offset \d+\)"):
        load_nerfstudio(path)


def test_hostile_json_is_refused_by_name_before_or_while_reading(tmp_path, monkeypatch):
    from artnvg_core.cameras import common

    path = tmp_path / "transforms.json"
    path.write_text("[" * 100_000 + "]" * 100_000)  # nesting no parser recursion can follow
    with pytest.raises(ValueError, match=r"transforms\.json: not valid JSON \(it nests too deeply\)"):
        load_nerfstudio(path)
    quats, trans = random_capture(2)
    write_transforms(path, quats, trans)
    monkeypatch.setattr(common, "MAX_CAMERA_TEXT_BYTES", path.stat().st_size - 1)
    with pytest.raises(ValueError, match=r"transforms\.json: [\d,]+ bytes, more than the [\d,]+ a camera file may "
                       r"have .*; not read"):
        load_nerfstudio(path)


@pytest.mark.parametrize("second", ["images/view_00.png", "./images/view_00.png", "images//view_00.png",
                                    "images/../images/view_00.png", "{folder}/images/view_00.png"])
def test_two_frames_of_one_image_are_refused_naming_both_fields_and_the_image(tmp_path, second):
    """Two poses for one image contradict each other: refused, with the paths compared as the loader joins them
    to the file's folder (nothing is read from the disk: the images do not exist)."""
    quats, trans = random_capture(4)
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    data = json.loads(path.read_text())
    data["frames"][3]["file_path"] = second.format(folder=tmp_path)
    write_json(path, data)
    image = tmp_path / "images" / "view_00.png"
    with pytest.raises(ValueError, match=rf"transforms\.json: frames\[0\]\.file_path and frames\[3\]\.file_path both "
                                         rf"name the image {re.escape(str(image))}; "):
        load_nerfstudio(path)
    data["frames"][3]["file_path"] = "other/view_00.png"  # another folder: another image
    write_json(path, data)
    assert load_nerfstudio(path).image_paths[3] == tmp_path / "other" / "view_00.png"


@pytest.mark.parametrize("edit, message", [
    (lambda text: text.replace('"fl_x": 50.0', '"fl_x": 1' + "0" * 400), r"frame 0: 'fl_x': expected a finite number "
     r"within float range, got inf"),
    (lambda text: text.replace('"cy": 25.0', '"cy": -1e400'), r"frame 0: 'cy': expected a finite number within "
     r"float range, got -inf"),
    (lambda text: text.replace('"fl_x": 50.0', '"fl_x": 1e300'), r"frame 0: 'fl_x': expected a finite number "
     r"within \+-1e\+09, got 1e\+300"),
    # found by fuzzing: an image size beyond float range met int() before the range check
    (lambda text: text.replace('"w": 64', '"w": 1e400'), r"frame 0: 'w': expected a finite number within float "
     r"range, got inf"),
])
def test_numbers_beyond_range_are_refused_naming_file_frame_and_field(tmp_path, edit, message):
    path = write_transforms(tmp_path / "transforms.json", *random_capture(2))
    path.write_text(edit(path.read_text()))
    with pytest.raises(ValueError, match=r"transforms\.json: " + message):
        load_nerfstudio(path)


def test_camera_positions_beyond_range_are_refused_at_load_naming_the_frame(tmp_path):
    quats, trans = random_capture(3)
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    data = json.loads(path.read_text())
    data["frames"][2]["transform_matrix"][1][3] = 1e300
    write_json(path, data)
    with pytest.raises(ValueError, match=r"transforms\.json: frame 2: 'transform_matrix': the camera position's y: "
                       r"expected a finite number within \+-1e\+09, got 1e\+300"):
        load_nerfstudio(path)
    data["frames"][2]["transform_matrix"][1][3] = 2.0
    write_json(path, data)
    with pytest.raises(ValueError, match=r"dataparser_transforms\.json: 'transform' and 'scale' put frame 0 of "
                       r".*transforms\.json at x: expected a finite number within \+-1e\+09, got 3\.\d+e\+299"):
        load_nerfstudio(path, dataparser_transforms=write_json(
            tmp_path / "dataparser_transforms.json", {"transform": torch.eye(4)[:3].tolist(), "scale": 1e300}))


def test_distortion_that_moves_a_corner_a_pixel_is_told_once_per_load_and_less_not_at_all(tmp_path, caplog):
    """k1..k4, p1, p2 were ignored silently: the views render as pinhole cameras. A frame's own coefficient overrides
    the top level's; under a pixel at the corners nothing is told. 100x100 views, f 100 at the centre: k1 0.1 moves each corner (x, y = +-0.5, r² 0.5) by
    0.05 * 0.5 * 100 = 2.5 px along each axis, 3.5 px in all; p2 0.1 by 100 * 0.1 * (r² + 2x²) = 10 px along x and
    100 * 2 * 0.1 * |x y| = 5 px along y: 11.2 px."""
    def frame(index: int, **coefficients) -> dict:
        return {"file_path": f"{index}.png", "transform_matrix": [[1, 0, 0, index], [0, 1, 0, 0], [0, 0, 1, 0],
                                                                  [0, 0, 0, 1]], **coefficients}

    intrinsics = {"w": 100, "h": 100, "fl_x": 100.0, "fl_y": 100.0, "cx": 50.0, "cy": 50.0}
    mixed = write_json(tmp_path / "mixed.json", {**intrinsics, "k1": 0.1, "frames": [frame(0), frame(1, k1=0),
                                                                                      frame(2, k1=0, p2=0.1)]})
    radial = write_json(tmp_path / "radial.json", {**intrinsics, "k1": 0.1, "frames": [frame(0), frame(1)]})
    zero = write_json(tmp_path / "zero.json", {**intrinsics, "k1": 0, "k2": 0.0, "p1": 0, "p2": 0,
                                               "frames": [frame(0), frame(1, k3=0.0)]})
    slight = write_json(tmp_path / "slight.json", {**intrinsics, "k1": 0.02, "frames": [frame(0)]})  # 0.7 px
    told = {}
    with caplog.at_level("WARNING"):
        for path in (mixed, radial, zero, slight):
            told[path.stem] = []
            load_nerfstudio(path, notes=told[path.stem].append)
    assert told == {"mixed": [
        "lens distortion ignored (k1, p2 non-zero in 2 of 3 views): the views are rendered as pinhole cameras, as "
        "undistorted images; photos taken through the lens differ from them by up to 11.2 px towards the image corners"],
        "radial": ["lens distortion ignored (k1 non-zero in 2 of 2 views): the views are rendered as pinhole cameras, "
                   "as undistorted images; photos taken through the lens differ from them by up to 3.5 px towards the "
                   "image corners"], "zero": [], "slight": []}
    assert not caplog.records  # told, not logged
    load_nerfstudio(radial)  # without notes: logged after the file
    assert [r.getMessage() for r in caplog.records] == [f"{radial}: {told['radial'][0]}"]
