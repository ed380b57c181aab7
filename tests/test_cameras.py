"""The package face: load_cameras chooses the loader by layout; view names; the shared bear capture."""

import json

import pytest
import torch

from artnvg_core.cameras import load_cameras, load_colmap, load_nerfstudio
from camera_references import (
    assert_orthonormal,
    assert_same_cameras,
    colmap_images,
    project,
    random_capture,
    write_colmap,
    write_json,
    write_transforms,
)


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
    with pytest.raises(ValueError, match=r"^\S*ns/transfroms\.json: camera file or folder not found$"):  # a typo
        load_cameras(tmp_path / "ns" / "transfroms.json")


def test_views_sharing_an_image_stem_get_distinct_names(tmp_path):
    quats, trans = random_capture(3, seed=5)
    records = colmap_images(quats, trans)
    names = ["cam0/0001.png", "cam1/0001.png", "cam1/0002.jpg"]
    records = [(*r[:4], name, r[5]) for r, name in zip(records, names)]
    cameras = load_colmap(write_colmap(tmp_path / "rig", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, records, True))
    assert cameras.names == ["cam0_0001", "cam1_0001", "0002"]
    records = [(*r[:4], name, r[5]) for r, name in zip(records, ["a.png", "a.jpg", "b.png"])]
    with pytest.raises(ValueError, match=r"images\.txt: views 0, 1 \(in load order\) have image files that give them one name"):
        load_colmap(write_colmap(tmp_path / "clash", {1: ("PINHOLE", 64, 48, [50.0] * 4)}, records, False))
    path = write_transforms(tmp_path / "transforms.json", quats, trans)
    data = json.loads(path.read_text())
    data["frames"][1]["file_path"] = "images_2/view_00.png"
    assert load_nerfstudio(write_json(path, data)).names == ["images_view_00", "images_2_view_00", "view_02"]


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
