"""Load Cameras, Cameras Around Scene and Group Neighbouring Views, called as ComfyUI calls them: cameras from the
input folder or a path, the core's orbit_cameras and its text inputs, the core's view groups."""

import json
import re

import pytest
import torch

from artnvg_core.grouping import group_views
from artnvg_core.orbit import orbit_cameras
from node_calls import bear, call, comfy_dirs  # noqa: F401  (fixtures)
from nodes.camera_nodes import CamerasAroundScene, GroupNeighbouringViews, LoadCameras
from nodes.node_errors import NodeInputError
from tests.test_activated import random_scene
from tests.test_orbit import standing_blob

SETTINGS = dict(count=7, fov_deg=40.0, width=64, height=48, distance_factor=1.5)


def place(scene, up="auto", elevations="10, 30", **changes):
    return CamerasAroundScene().place(scene, **(SETTINGS | changes), up=up, elevations=elevations)[0]


@pytest.mark.parametrize("up, core_up", [("auto", None), ("-y", "-y"), (" 0.2, -1, 0 ", [0.2, -1.0, 0.0])])
def test_node_places_the_cores_orbit(up, core_up):
    scene = random_scene(n=300, degree=0)
    cameras = place(scene, up=up, elevations="-5, 20,45")
    expected = orbit_cameras(scene, 7, fov_deg=40.0, width=64, height=48, up=core_up,
                             elevations_deg=(-5.0, 20.0, 45.0), distance_factor=1.5)
    assert torch.equal(cameras.world_to_cam, expected.world_to_cam)
    assert torch.equal(cameras.intrinsics, expected.intrinsics)
    assert (cameras.width, cameras.height, len(cameras)) == (64, 48, 7)



def test_node_shows_a_guessed_up_under_itself_in_its_own_terms(caplog):
    """A scene with no ground: the guessed up is noted under the node (and once on the console), naming its up input."""
    standing = standing_blob()
    with caplog.at_level("WARNING"):
        place(standing)
    (message,) = [record.getMessage() for record in caplog.records]
    assert message.startswith("Cameras Around Scene: note: the up direction is a guess")
    assert message.endswith("set this node's up input to -y or another axis") and "--up" not in message
    caplog.clear()
    with caplog.at_level("WARNING"):
        place(standing, up="+z")
    assert not caplog.records

BAD_TEXT = [  # (inputs, the message after "Cameras Around Scene: input '<name>': ")
    ({"up": "1, 2"}, "expected 3 finite numbers, not all zero, got '1, 2'"),
    ({"up": "1, x, 2"}, "expected 'auto', one of +x, -x, +y, -y, +z, -z or 3 comma-separated numbers"),
    ({"up": "sideways"}, "expected 'auto', one of +x, -x, +y, -y, +z, -z or 3 comma-separated numbers"),
    ({"elevations": "10, high"}, "expected comma-separated angles in degrees such as 10, 30, got ' high'"),
    ({"elevations": "10, 95"}, "95 degrees is not an elevation in (-90, 90)"),
    ({"elevations": " , "}, "expected at least one angle in degrees"),
]


@pytest.mark.parametrize("inputs, message", BAD_TEXT)
def test_bad_text_is_refused_at_validation_naming_node_and_input(inputs, message):
    """ComfyUI's validation (the pack's prompt check) refuses it before anything runs; it used to pass, and
    orbit_cameras refused it only as the node ran, under its own name."""
    (name,) = inputs
    values = {"count": 60, "up": "auto", "elevations": "10, 30"} | inputs
    assert CamerasAroundScene.check_values(**values).startswith(f"Cameras Around Scene: input '{name}': {message}")


@pytest.mark.parametrize("inputs, message", BAD_TEXT)
def test_bad_text_through_a_link_is_refused_as_the_node_runs_naming_node_and_input(inputs, message):
    (name,) = inputs
    with pytest.raises(NodeInputError, match="^" + re.escape(f"Cameras Around Scene: input '{name}': {message}")):
        place(random_scene(n=50, degree=0), **inputs)


def test_load_cameras_from_input_folder_or_path(comfy_dirs, bear):
    listed = LoadCameras.INPUT_TYPES()["required"]["camera_source"]
    assert listed[1]["options"] == ["bear/transforms.json"]
    (from_list,) = call(LoadCameras, camera_source="bear/transforms.json")
    (from_folder,) = call(LoadCameras, camera_source="", path=str(comfy_dirs / "input" / "bear"))
    for cameras in (from_list, from_folder):
        assert torch.equal(cameras.world_to_cam, bear["cameras"].world_to_cam)
        assert cameras.names == bear["cameras"].names
    assert "camera_source" in LoadCameras.check_files(camera_source="bear/missing.json")
    assert LoadCameras.check_files(camera_source="", path=str(comfy_dirs / "input" / "bear")) is None
    assert "is outside ComfyUI's input" in LoadCameras.check_files(camera_source="", path=str(bear["folder"]))
    scene = comfy_dirs / "input" / "bear" / "scene.ply"  # refused only as the node ran, after the scene loaded
    assert LoadCameras.check_files(camera_source="", path="bear/scene.ply") == (
        f"Load Cameras: input 'path': {scene}: not a supported camera source; expected a nerfstudio .json file (e.g. "
        "transforms.json), a folder containing transforms.json, or a COLMAP model folder (cameras.bin + images.bin "
        "or cameras.txt + images.txt, directly or in sparse/0 or 0)")


def test_load_cameras_tells_the_lens_distortion_it_ignores_once_as_it_runs(comfy_dirs, caplog):
    """The bear's transforms.json has OPENCV's k1, k2, p1, p2, moving a corner by 0.6 px: nothing told. With ten
    times its k1 (ignored silently before): shown under the node and logged once on the console as the node runs;
    counting its cameras before the graph runs tells nothing."""
    bear = comfy_dirs / "input" / "bear" / "transforms.json"
    wide = json.loads(bear.read_text())
    (comfy_dirs / "input" / "wide").mkdir()
    (comfy_dirs / "input" / "wide" / "transforms.json").write_text(json.dumps({**wide, "k1": 10 * wide["k1"]}))
    with caplog.at_level("WARNING"):
        call(LoadCameras, camera_source="bear/transforms.json")
        assert LoadCameras.camera_count(camera_source="wide/transforms.json", path="") == 96
        assert not caplog.records
        call(LoadCameras, camera_source="wide/transforms.json")
    (message,) = [record.getMessage() for record in caplog.records]
    assert message.startswith("Load Cameras: note: lens distortion ignored (k1, k2, p1, p2 non-zero in 96 of 96 "
                              "views): the views are rendered as pinhole cameras")


def test_group_neighbouring_views_matches_the_core(bear):
    (groups,) = call(GroupNeighbouringViews, cameras=bear["cameras"], group_size=15, context=2)
    expected = group_views(bear["cameras"], 15, context=2)
    assert groups == expected and len(groups) == 7
