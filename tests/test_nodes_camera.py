"""Load Cameras, Cameras Around Scene and Group Neighbouring Views, called as ComfyUI calls them: cameras from the
input folder or a path, the core's orbit_cameras and its text inputs, the core's view groups."""

import pytest
import torch

from artnvg_core.grouping import group_views
from artnvg_core.orbit import orbit_cameras
from node_calls import bear, call, comfy_dirs  # noqa: F401  (fixtures)
from nodes.camera_nodes import CamerasAroundScene, GroupNeighbouringViews, LoadCameras
from nodes.node_errors import NodeInputError
from tests.test_activated import random_scene

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


@pytest.mark.parametrize("inputs, message", [
    ({"up": "1, 2"}, r"up: expected 3 finite numbers"),
    ({"up": "1, x, 2"}, r"input 'up': expected auto, an axis such as -y, or three numbers"),
    ({"up": "sideways"}, r"up: expected 'auto', one of"),
    ({"elevations": "10, high"}, r"input 'elevations': expected comma-separated angles"),
    ({"elevations": "95"}, r"elevations_deg must be angles in \(-90, 90\)"),
])
def test_bad_text_inputs_name_the_input(inputs, message):
    with pytest.raises(NodeInputError, match=r"^Cameras Around Scene: .*" + message):
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


def test_group_neighbouring_views_matches_the_core(bear):
    (groups,) = call(GroupNeighbouringViews, cameras=bear["cameras"], group_size=15, context=2)
    expected = group_views(bear["cameras"], 15, context=2)
    assert groups == expected and len(groups) == 7
