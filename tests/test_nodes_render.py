"""Render Views and Render Camera Path on the shared bear scene, called as ComfyUI calls them, against the
core's render of the same cameras; bad view lists and plans beyond the memory budget refused first."""

import pytest
import torch

from artnvg_core.cameras import interpolate_path, orbit_path
from artnvg_core.key_views import select_key_views
from artnvg_core.raster import render
from node_calls import SCALE, bear, call, small_bear  # noqa: F401  (fixtures)
from nodes.node_errors import NodeInputError
from nodes.render_nodes import RenderCameraPath, RenderViews

def test_render_views_matches_the_core_renderer(small_bear, bear):
    cameras = bear["cameras"]
    images, used = call(RenderViews, scene=small_bear, cameras=cameras, scale=SCALE, stride=1, views="0, 60")
    expected_cameras = cameras.subset([0, 60]).scaled(SCALE)
    expected = render(small_bear, expected_cameras).rgb.clamp(0, 1)
    assert images.shape == (2, 64, 64, 3) and images.dtype == torch.float32
    assert torch.equal(images, expected)
    assert torch.equal(used.intrinsics, expected_cameras.intrinsics) and used.names == expected_cameras.names
    images_by_stride, used_by_stride = call(RenderViews, scene=small_bear, cameras=cameras, scale=SCALE, stride=60,
                                            views="")
    assert used_by_stride.names == used.names and torch.equal(images_by_stride, images)
    key_images, keys = call(RenderViews, scene=small_bear, cameras=cameras, scale=SCALE, stride=2, views="",
                            key_views=3)
    expected_cameras = cameras.subset(range(0, len(cameras), 2))
    expected_cameras = expected_cameras.subset(select_key_views(expected_cameras, 3)).scaled(SCALE)
    assert keys.names == expected_cameras.names and len(set(keys.names)) == 3
    assert torch.equal(key_images, render(small_bear, expected_cameras).rgb.clamp(0, 1))


def test_render_views_rejects_bad_view_lists(small_bear, bear):
    for views, problem in (("0, 96", "out of range"), ("0, x", "'x'"), ("5, 0, 5", "view 5 is given twice")):
        with pytest.raises(NodeInputError, match=f"Render Views: input 'views': .*{problem}"):
            call(RenderViews, scene=small_bear, cameras=bear["cameras"], scale=SCALE, stride=1, views=views)


def test_render_camera_path_orbit_and_interpolation(small_bear, bear):
    cameras = bear["cameras"]
    frames, path = call(RenderCameraPath, scene=small_bear, cameras=cameras, path="orbit", scale=SCALE,
                        num_frames=2, key_views="", frames_per_segment=30, loop=False)
    expected_path = orbit_path(cameras, 2).scaled(SCALE)
    assert torch.allclose(path.world_to_cam, expected_path.world_to_cam)
    assert torch.equal(frames, render(small_bear, expected_path).rgb.clamp(0, 1))

    frames, path = call(RenderCameraPath, scene=small_bear, cameras=cameras, path="interpolate", scale=SCALE,
                        num_frames=60, key_views="0,30", frames_per_segment=2, loop=False)
    expected_path = interpolate_path(cameras, [0, 30], 2).scaled(SCALE)
    assert frames.shape == (3, 64, 64, 3) and torch.allclose(path.world_to_cam, expected_path.world_to_cam)
    # blank key_views: through every view (the view-list grammar), here both views of a two-view set
    blank_frames, blank_path = call(RenderCameraPath, scene=small_bear, cameras=cameras.subset([0, 30]),
                                    path="interpolate", scale=SCALE, num_frames=60, key_views="",
                                    frames_per_segment=2, loop=False)
    assert torch.equal(blank_frames, frames) and torch.equal(blank_path.world_to_cam, path.world_to_cam)
    with pytest.raises(NodeInputError, match=r"^Render Camera Path: input 'cameras': no orbit around these cameras "
                       r"\(.*\); set 'path' to interpolate, through two views or more$"):  # said "pass center="
        call(RenderCameraPath, scene=small_bear, cameras=cameras.subset([5]), path="orbit", scale=SCALE,
             num_frames=60, key_views="", frames_per_segment=2, loop=False)
    with pytest.raises(NodeInputError, match="Render Camera Path: input 'key_views': .*at least 2"):
        call(RenderCameraPath, scene=small_bear, cameras=cameras.subset([5]), path="interpolate", scale=SCALE,
             num_frames=60, key_views="", frames_per_segment=2, loop=False)
    # a key view twice (through a link, as the node runs): a zero-length segment; loop returns to the first
    with pytest.raises(NodeInputError, match="^Render Camera Path: input 'key_views': view 30 is given twice"):
        call(RenderCameraPath, scene=small_bear, cameras=cameras, path="interpolate", scale=SCALE, num_frames=60,
             key_views="0, 30, 30", frames_per_segment=2, loop=False)


def test_render_camera_paths_key_views_are_checked_against_the_cameras_in_mode_interpolate_alone(small_bear, bear,
                                                                                                monkeypatch):
    """Through a link the count is known only as the node starts: refused then, before any render, naming the mode
    (as at validation, check_views); orbit reads no key view, so none is refused."""
    import nodes.render_nodes as render_nodes

    cameras = bear["cameras"]
    inputs = dict(scene=small_bear, cameras=cameras, scale=SCALE, num_frames=2, key_views="0, 96",
                  frames_per_segment=2, loop=False)
    with monkeypatch.context() as patched:
        patched.setattr(render_nodes, "render_views", lambda *args, **kwargs: pytest.fail("rendered"))
        with pytest.raises(NodeInputError, match=r"^Render Camera Path: input 'key_views': path interpolate: view index "
                                                 r"96 is out of range for 96 cameras \(0\.\.95\)$"):
            call(RenderCameraPath, path="interpolate", **inputs)
    frames, path = call(RenderCameraPath, path="orbit", **inputs)
    assert torch.equal(path.world_to_cam, orbit_path(cameras, 2).scaled(SCALE).world_to_cam) and len(frames) == 2


def test_a_render_plan_beyond_the_memory_budget_is_refused_before_the_first_view(small_bear, bear, monkeypatch):
    import artnvg_core.raster as raster
    import artnvg_core.raster.views as views

    monkeypatch.setattr(raster, "available_memory", lambda: 2**30)
    monkeypatch.setattr(views, "render", lambda *args, **kwargs: pytest.fail("rendered"))
    with pytest.raises(NodeInputError, match=r"^Render Camera Path: input 'scale': 60 views of 2048x2048 "
                       r"pixels, all their images held at once, need 3\.5 GiB, more than half the 1\.0 GiB"):
        call(RenderCameraPath, scene=small_bear, cameras=bear["cameras"], path="orbit", scale=4.0, num_frames=60,
             key_views="", frames_per_segment=30, loop=False)
