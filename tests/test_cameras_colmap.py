"""COLMAP sparse models: binary and text agree, every supported model, errors naming file and field."""

import re

import pytest
import torch

from artnvg_core.cameras import load_cameras, load_colmap, load_nerfstudio
from camera_references import assert_same_cameras, colmap_images, random_capture, rotate, write_colmap, write_transforms


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
    for source in (tmp_path, tmp_path / "sparse", tmp_path / "sparse" / "0"):  # sparse: COLMAP's folder of models
        cameras = load_colmap(source)
        assert cameras.image_paths == [None, tmp_path / "images" / "view_01.png", None]
        assert_same_cameras(load_cameras(source), cameras, atol=0)


@pytest.mark.parametrize("binary", [False, True])
def test_an_image_name_too_long_for_the_file_system_is_a_view_without_its_image(tmp_path, binary):
    """Found by fuzzing: looking for an image of a name over the file system's limit raised OSError
    (ENAMETOOLONG) from Path.is_file; such an image is not there."""
    quats, trans = random_capture(2, seed=7)
    images = colmap_images(quats, trans)
    images[0] = (*images[0][:4], "x" * 300 + ".png", images[0][5])
    write_colmap(tmp_path / "sparse" / "0", {1: ("PINHOLE", 64, 48, MODEL_PARAMS["PINHOLE"])}, images, binary)
    (tmp_path / "images").mkdir()
    assert load_colmap(tmp_path).image_paths == [None, None]


def test_colmap_errors_name_file_and_field(tmp_path):
    quats, trans = random_capture(3, seed=8)
    images = colmap_images(quats, trans, camera_ids=[1, 2, 1])

    pinhole = ("PINHOLE", 64, 48, [50.0] * 4)
    folder = write_colmap(tmp_path / "fisheye", {1: pinhole, 2: ("OPENCV_FISHEYE", 64, 48, [1.0] * 8)}, images, True)
    with pytest.raises(ValueError, match=r"cameras\.bin: camera 2: camera model OPENCV_FISHEYE is not supported"):
        load_colmap(folder)

    folder = write_colmap(tmp_path / "sizes", {1: pinhole, 2: ("PINHOLE", 32, 48, [50.0] * 4)}, images, False)
    with pytest.raises(ValueError, match=r"images\.txt: image record 1: camera 2 is 32x48 .* 64x48"):
        load_colmap(folder)

    folder = write_colmap(tmp_path / "missing", {1: pinhole}, images, True)
    with pytest.raises(ValueError, match=r"images\.bin: image record 1: camera id 2 is not in .*cameras\.bin"):
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
    with pytest.raises(ValueError, match=r"images\.txt: line 4: expected the 2D points .* of the image line before, got a line of 2 fields"):
        load_colmap(folder)


@pytest.mark.parametrize("file", ["cameras.bin", "images.bin"])
def test_colmap_binary_counts_must_cover_every_record(tmp_path, file):
    quats, trans = random_capture(3, seed=2)
    folder = write_colmap(tmp_path / "model", {1: ("PINHOLE", 64, 48, [50.0] * 4), 2: ("PINHOLE", 64, 48, [50.0] * 4)},
                          colmap_images(quats, trans), True)
    data = bytearray((folder / file).read_bytes())
    data[:8] = (int.from_bytes(data[:8], "little") - 1).to_bytes(8, "little")  # one record fewer than written
    (folder / file).write_bytes(bytes(data))
    counted = {"cameras.bin": "1 camera", "images.bin": "2 images"}[file]  # 'the header says 1 cameras' once
    with pytest.raises(ValueError, match=rf"{file}: the header says {counted}, but the file has \d+ bytes more after "
                       "the last of them"):
        load_colmap(folder)


def test_colmap_text_errors_never_quote_the_file(tmp_path):
    quats, trans = random_capture(2, seed=3)
    folder = write_colmap(tmp_path / "model", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, colmap_images(quats, trans), False)
    secret = "root:x:0:0:root:/root:/bin/bash"
    for file, line in (("cameras.txt", secret), ("cameras.txt", f"1 {secret} 64 48"), ("images.txt", secret)):
        original = (folder / file).read_text()
        (folder / file).write_text(original + line + "\n")
        with pytest.raises(ValueError, match=rf"{file}: line \d+: ") as refused:
            load_colmap(folder)
        assert "root" not in str(refused.value).replace(str(tmp_path), "")
        (folder / file).write_text(original)


def test_colmap_binary_counts_beyond_the_file_are_refused_before_any_record(tmp_path):
    quats, trans = random_capture(2, seed=4)
    folder = write_colmap(tmp_path / "model", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, colmap_images(quats, trans), True)
    data = (folder / "images.bin").read_bytes()
    (folder / "images.bin").write_bytes((2**40).to_bytes(8, "little") + data[8:])
    with pytest.raises(ValueError, match=r"images\.bin: the header says 1,099,511,627,776 images; the file has \d+ bytes "
                       r"left, room for at most \d, and a model may have 1,000,000"):
        load_colmap(folder)


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("second", ["view_02.png", "./view_02.png", "sub/../view_02.png"])
def test_colmap_one_image_named_twice_is_refused_naming_both_records_and_the_image(tmp_path, binary, second):
    """Two records (their own ids) of one image, compared as paths with . and .. folded: two poses for one
    image contradict each other."""
    quats, trans = random_capture(3, seed=5)
    images = colmap_images(quats, trans)  # view_02.png, view_01.png, view_00.png
    images[2] = (*images[2][:4], second, images[2][5])
    folder = write_colmap(tmp_path / "model", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, images, binary)
    with pytest.raises(ValueError, match=rf"images\.{'bin' if binary else 'txt'}: image record 0's NAME and image "
                                         r"record 2's NAME both name the image view_02\.png; "):
        load_colmap(folder)


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_an_id_given_twice_is_refused_naming_both_places(tmp_path, binary):
    """A model that gives one image id (or camera id) twice is refused, not read with both images (or the last
    camera)."""
    quats, trans = random_capture(3, seed=5)
    images = colmap_images(quats, trans)  # ids 3, 2, 1: image lines 3, 5, 7 of images.txt
    images[2] = (images[0][0], *images[2][1:])
    pinhole = ("PINHOLE", 64, 48, [50.0] * 4)
    folder = write_colmap(tmp_path / "images", {1: pinhole}, images, binary)
    places = ("image record 0", "image record 2") if binary else ("line 3", "line 7")
    with pytest.raises(ValueError, match=rf"images\.{'bin' if binary else 'txt'}: image id 3 is given twice, at "
                                         rf"{places[0]} and at {places[1]}; give each its own id$"):
        load_colmap(folder)

    folder = write_colmap(tmp_path / "cameras", {1: pinhole, 2: pinhole}, colmap_images(quats, trans), binary)
    if binary:  # the second record (after the count and the first record's 56 bytes) given id 1
        data = bytearray((folder / "cameras.bin").read_bytes())
        data[64:68] = (1).to_bytes(4, "little")
        (folder / "cameras.bin").write_bytes(bytes(data))
    else:
        (folder / "cameras.txt").write_text((folder / "cameras.txt").read_text().replace("\n2 PINHOLE", "\n1 PINHOLE"))
    places = ("camera record 0", "camera record 1") if binary else ("line 3", "line 4")
    with pytest.raises(ValueError, match=rf"cameras\.{'bin' if binary else 'txt'}: camera id 1 is given twice, at "
                                         rf"{places[0]} and at {places[1]}; give each its own id$"):
        load_colmap(folder)


@pytest.mark.parametrize("binary", [False, True])
def test_distortion_that_moves_a_corner_a_pixel_is_told_once_per_load_and_less_not_at_all(tmp_path, binary, caplog):
    """It was ignored silently: the views render as pinhole cameras. The note names the coefficients (as k1..k4, p1,
    p2), the views that have them, and the most an image corner moves (64x48 views, f 50: SIMPLE_RADIAL's k moves the
    farthest corner, (64, 0) at x = 0.67, y = -0.5 from the centre (r² 0.6989), by k * 0.6989 * 50 * sqrt(0.67² +
    0.5²) px: 0.29 px for MODEL_PARAMS' 0.01, too little to tell, 2.9 px for 0.1)."""
    quats, trans = random_capture(4, seed=6)

    def told(cameras: dict) -> list[str]:
        notes = []
        load_colmap(write_colmap(tmp_path / str(len(list(tmp_path.iterdir()))), cameras, colmap_images(quats, trans),
                                 binary), notes=notes.append)
        return notes

    for model, params in [*MODEL_PARAMS.items(), ("OPENCV", [50.0, 50.0, 30.5, 25.0, 0, 0, 0, 0])]:
        assert told({1: (model, 64, 48, params)}) == [], model  # zero, or under a pixel
    assert told({1: ("SIMPLE_RADIAL", 64, 48, [50.0, 30.5, 25.0, 0.1])}) == [
        "lens distortion ignored (k1 non-zero in 4 of 4 views): the views are rendered as pinhole cameras, as "
        "undistorted images; photos taken through the lens differ from them by up to 2.9 px towards the image corners"]
    (note,) = told({1: ("RADIAL", 64, 48, [50.0, 30.5, 25.0, 0.1, -0.02])})
    assert note.startswith("lens distortion ignored (k1, k2 non-zero in 4 of 4 views)")
    (note,) = told({1: ("OPENCV", 64, 48, [50.0, 50.0, 30.5, 25.0, 0.1, -0.02, 0.01, 0.005])})
    assert note.startswith("lens distortion ignored (k1, k2, p1, p2 non-zero in 4 of 4 views)")
    two = {1: ("PINHOLE", 64, 48, MODEL_PARAMS["PINHOLE"]), 2: ("OPENCV", 64, 48, [*MODEL_PARAMS["PINHOLE"], 0, 0, 0, 0.3])}
    with caplog.at_level("WARNING"):  # without notes, logged after the file
        load_colmap(write_colmap(tmp_path / "two", two, colmap_images(quats, trans, [1, 2, 2, 1]), binary))
    (record,) = [r.getMessage() for r in caplog.records if "lens distortion" in r.getMessage()]
    assert re.match(r".*cameras\.(txt|bin): lens distortion ignored \(p2 non-zero in 2 of 4 views\)", record)
