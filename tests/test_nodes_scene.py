"""Scene, camera, render, grouping, finetune and save nodes on the shared bear scene, small settings.

Each node is called the way ComfyUI calls it (under ``torch.inference_mode()``) and its
output is compared with the direct ``artnvg_core`` call it adapts. Without ComfyUI the
input and output folders are ``./input`` and ``./output`` of the working directory.
"""

import gzip
import shutil
import struct
from unittest import mock

import pytest
import torch

from artnvg_core.cameras import CameraSet, interpolate_path, load_cameras, orbit_path
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.grouping import group_views
from artnvg_core.key_views import select_key_views
from artnvg_core.raster import render
from artnvg_core.formats import load_scene, read_ply, save_scene
from artnvg_core.scene import GaussianScene
from artnvg_core.stylize import DemoInputs
from nodes.camera_nodes import GroupNeighbouringViews, LoadCameras
from nodes.finetune_nodes import FinetuneGaussians
from nodes.node_errors import NodeInputError
from nodes.render_nodes import RenderCameraPath, RenderViews
from nodes.scene_nodes import LoadGaussianScene, SaveGaussianScene

SCALE = 0.125  # 512 x 512 views -> 64 x 64


def call(node_class, **inputs):
    """Run a node's function as ComfyUI does."""
    with torch.inference_mode():
        return getattr(node_class(), node_class.FUNCTION)(**inputs)


def _same_scene(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.tensors().values(), b.tensors().values()))


@pytest.fixture(scope="module")
def bear(shared_data):
    folder = shared_data / "scenes" / "bear"
    return {"folder": folder, "scene": load_scene(folder / "scene.ply"), "cameras": load_cameras(folder)}


@pytest.fixture(scope="module")
def small_bear(bear):
    """Every 25th Gaussian of the bear (4,000): renders stay fast on a CPU."""
    scene = bear["scene"]
    return scene.select(torch.arange(0, len(scene), 25))


@pytest.fixture
def comfy_dirs(tmp_path, monkeypatch, bear):
    """A working directory whose input folder holds the bear capture (as ComfyUI users lay it out; copies, since
    a link that leads out of ComfyUI's folders is not read)."""
    monkeypatch.chdir(tmp_path)
    capture = tmp_path / "input" / "bear"
    capture.mkdir(parents=True)
    for name in ("scene.ply", "transforms.json"):
        shutil.copyfile(bear["folder"] / name, capture / name)
    return tmp_path


def test_load_scene_from_input_folder_or_path(comfy_dirs, bear, monkeypatch):
    listed = LoadGaussianScene.INPUT_TYPES()["required"]["scene_file"]
    assert listed[0] == "COMBO" and listed[1]["options"] == ["bear/scene.ply"]
    assert LoadGaussianScene.check_files(scene_file="bear/scene.ply", drop_invalid=True) is None
    (from_list,) = call(LoadGaussianScene, scene_file="bear/scene.ply")
    (from_path,) = call(LoadGaussianScene, scene_file="", path=str(comfy_dirs / "input" / "bear" / "scene.ply"))
    assert _same_scene(from_list, bear["scene"]) and _same_scene(from_path, bear["scene"])
    outside = str(bear["folder"] / "scene.ply")
    assert "is outside ComfyUI's input" in LoadGaussianScene.check_files(scene_file="", path=outside)
    monkeypatch.setenv("ARTNVG_READ_ANY_PATH", "1")  # the setting that opens every path
    assert _same_scene(call(LoadGaussianScene, scene_file="", path=outside)[0], bear["scene"])


def test_missing_scene_names_the_input_and_the_file(comfy_dirs):
    message = LoadGaussianScene.check_files(scene_file="bear/nothing.ply")
    assert "scene_file" in message and "bear/nothing.ply" in message
    message = LoadGaussianScene.check_files(scene_file="bear/scene.ply", path="/no/such/scene.ply")
    assert "'path'" in message and "/no/such/scene.ply" in message
    with pytest.raises(NodeInputError, match=r"Load Gaussian Scene: input 'path': .*/no/such/scene\.ply"):
        call(LoadGaussianScene, scene_file="bear/scene.ply", path="/no/such/scene.ply")
    (comfy_dirs / "input" / "broken.ply").write_text("not a ply")
    with pytest.raises(NodeInputError, match=r"input 'scene_file': .*broken\.ply"):
        call(LoadGaussianScene, scene_file="broken.ply")


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
    with pytest.raises(NodeInputError, match="Render Camera Path: input 'key_views': .*at least 2"):
        call(RenderCameraPath, scene=small_bear, cameras=cameras.subset([5]), path="interpolate", scale=SCALE,
             num_frames=60, key_views="", frames_per_segment=2, loop=False)
    # a key view twice (through a link, as the node runs): a zero-length segment; loop returns to the first
    with pytest.raises(NodeInputError, match="^Render Camera Path: input 'key_views': view 30 is given twice"):
        call(RenderCameraPath, scene=small_bear, cameras=cameras, path="interpolate", scale=SCALE, num_frames=60,
             key_views="0, 30, 30", frames_per_segment=2, loop=False)


def test_group_neighbouring_views_matches_the_core(bear):
    (groups,) = call(GroupNeighbouringViews, cameras=bear["cameras"], group_size=15, context=2)
    expected = group_views(bear["cameras"], 15, context=2)
    assert groups == expected and len(groups) == 7


def test_finetune_node_matches_the_core_and_checks_stylized_views(small_bear, bear):
    cameras = bear["cameras"].subset([0, 48]).scaled(SCALE)
    style = torch.rand(1, 32, 40, 3, generator=torch.Generator().manual_seed(0))
    stylized = torch.rand(2, 64, 64, 3, generator=torch.Generator().manual_seed(1))
    weights = {"l1_weight": 0.8, "ssim_weight": 0.2, "nnfm_weight": 1.0, "content_weight": 0.5, "tv_weight": 0.1}
    (result,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=2,
                     optimize="appearance", seed=3, stylized_views=stylized, **weights)
    expected = finetune(small_bear, cameras, style[0], stylized=stylized,
                        config=FinetuneConfig(iterations=2, optimize="appearance", seed=3, **weights))
    assert _same_scene(result, expected)
    assert not torch.equal(result.sh, small_bear.sh)
    (full,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=2,
                   optimize="appearance", seed=3, stylized_views=stylized, nnfm_max_side=0, **weights)
    expected = finetune(small_bear, cameras, style[0], stylized=stylized,
                        config=FinetuneConfig(iterations=2, optimize="appearance", seed=3, nnfm_max_side=None, **weights))
    assert _same_scene(full, expected)
    (plain,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=1,
                    optimize="appearance", seed=3, color_transfer=False, **weights)
    expected = finetune(small_bear, cameras, style[0],
                        config=FinetuneConfig(iterations=1, optimize="appearance", seed=3, color_transfer=False, **weights))
    assert _same_scene(plain, expected)


def test_finetune_node_names_stylized_views_of_other_cameras_before_any_work():
    """Stylized views made from other cameras than those connected (say Load Cameras' every view, where Sample
    Group was given a Render Views of some of them) are refused naming the input and the two counts; no scene
    is given (a mock): none is touched."""
    scene = mock.Mock(spec=GaussianScene)
    with pytest.raises(NodeInputError, match=r"^Finetune Gaussians: input 'stylized_views': got \(1, 64, 64, 3\) "
                                             r"for 2 cameras; expected \[2, H, W, 3\], one view per camera"):
        call(FinetuneGaussians, scene=scene, cameras=load_cameras(DemoInputs().cameras).subset([0, 12]),
             style_image=torch.rand(1, 8, 8, 3),
             iterations=1, optimize="appearance", l1_weight=0.8, ssim_weight=0.2, nnfm_weight=1.0,
             content_weight=0.5, tv_weight=0.1, seed=0, stylized_views=torch.rand(1, 64, 64, 3))
    assert not scene.mock_calls


def test_finetune_node_refuses_a_style_image_the_command_line_refuses_before_any_work():
    """The rule of artnvg_core.style_image, as stylize --style applies it; no scene is given (mocks): none is touched."""
    with pytest.raises(NodeInputError, match=r"^Finetune Gaussians: input 'style_image': image size: 2x20000 pixels; "
                                             "a style image may be at most 32 times as long as it is wide"):
        call(FinetuneGaussians, scene=mock.Mock(spec=GaussianScene), cameras=mock.Mock(spec=CameraSet), style_image=torch.rand(1, 20000, 2, 3), iterations=1,
             optimize="appearance", l1_weight=0.8, ssim_weight=0.2, nnfm_weight=1.0, content_weight=0.5,
             tv_weight=0.1, seed=0)


def test_finetune_node_preview_preset_is_the_cores_preview(small_bear, bear, monkeypatch):
    """preset "preview" replaces iterations, views per step and the cameras' size by the preview preset's
    (PRESETS["preview"], shortened here): the same scene as the core's finetune with those settings."""
    import dataclasses

    from artnvg_core.presets import PRESETS

    preview = dataclasses.replace(PRESETS["preview"], finetune_iterations=3)
    monkeypatch.setitem(PRESETS, "preview", preview)
    cameras = bear["cameras"].subset([0, 24, 48, 72]).scaled(SCALE)
    style = torch.rand(1, 32, 40, 3, generator=torch.Generator().manual_seed(0))
    weights = {"l1_weight": 0.8, "ssim_weight": 0.2, "nnfm_weight": 1.0, "content_weight": 0.5, "tv_weight": 0.1}
    (result,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=1,
                     optimize="appearance", seed=3, preset="preview", nnfm_search="fp32", **weights)
    config = FinetuneConfig(iterations=preview.finetune_iterations, views_per_step=preview.views_per_step,
                            optimize="appearance", seed=3, nnfm_search="fp32", **weights)
    expected = finetune(small_bear, cameras.scaled(preview.scale), style[0], config=config)
    assert _same_scene(result, expected)


def test_save_scene_writes_numbered_plys_into_the_output_folder(comfy_dirs, small_bear):
    saved = [call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/stylized") for _ in range(2)]
    assert [s["ui"]["scenes"][0]["filename"] for s in saved] == ["stylized_00001.ply", "stylized_00002.ply"]
    assert saved[0]["ui"]["scenes"][0]["subfolder"] == "artnvg" and saved[0]["ui"]["scenes"][0]["type"] == "output"
    folder = comfy_dirs / "output" / "artnvg"
    assert sorted(p.name for p in folder.iterdir()) == ["stylized_00001.ply", "stylized_00002.ply"]
    assert _same_scene(read_ply(folder / "stylized_00002.ply"), small_bear)
    size = (folder / "stylized_00002.ply").stat().st_size
    assert saved[1]["ui"]["text"] == [f"wrote output/artnvg/stylized_00002.ply ({size / 1e6:.1f} MB, "
                                      f"{len(small_bear):,} Gaussians)"]
    assert saved[1]["result"][0] == "artnvg/stylized_00002.ply"  # the path Preview Any shows and Preview 3D loads
    (folder / "stylized_00007.ply").write_bytes(b"")
    (folder / "stylized_extra_00009.ply").write_bytes(b"")  # another prefix: not counted
    call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/stylized")
    assert (folder / "stylized_00008.ply").is_file()
    for prefix in ("../escape", ""):
        with pytest.raises(NodeInputError, match="Save Gaussian Scene: input 'filename_prefix'"):
            call(SaveGaussianScene, scene=small_bear, filename_prefix=prefix)


def test_load_scene_reads_a_spz_naming_no_axes_in_front_of_connected_cameras(comfy_dirs, bear, small_bear):
    """A .spz in RUB with no record: read upright with the capture's cameras connected (spz_axes auto), in
    the PLY's axes without them; a .spz Save Gaussian Scene writes reads back upright either way."""
    save_scene(small_bear, comfy_dirs / "input" / "rub.spz", spz_axes="rub")
    (with_cameras,) = call(LoadGaussianScene, scene_file="rub.spz", cameras=bear["cameras"])
    (alone,) = call(LoadGaussianScene, scene_file="rub.spz")
    assert (with_cameras.means - small_bear.means).abs().max() < 1e-3
    assert torch.equal(alone.means, with_cameras.means * torch.tensor([1.0, -1, -1]))
    saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="ours", format="spz")
    name = saved["ui"]["scenes"][0]["filename"]
    for cameras in (None, bear["cameras"]):
        (ours,) = call(LoadGaussianScene, scene_file="", path=str(comfy_dirs / "output" / name), cameras=cameras)
        assert (ours.means - small_bear.means).abs().max() < 1e-3


def test_save_scene_format_picks_spz_splat_or_ksplat_and_load_reads_them(comfy_dirs, small_bear):
    for fmt in ("spz", "splat", "ksplat"):
        saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/small", format=fmt)
        name = saved["ui"]["scenes"][0]["filename"]
        assert name == f"small_00001.{fmt}"
        (loaded,) = call(LoadGaussianScene, scene_file="", path=str(comfy_dirs / "output" / "artnvg" / name))
        degree = {"spz": small_bear.sh_degree, "splat": 0, "ksplat": min(small_bear.sh_degree, 2)}[fmt]
        assert len(loaded) == len(small_bear) and loaded.sh_degree == degree
    with pytest.raises(NodeInputError, match="Save Gaussian Scene: input 'format': expected one of"):
        call(SaveGaussianScene, scene=small_bear, filename_prefix="artnvg/small", format="obj")


def test_save_scene_spz_version_reaches_the_writer(comfy_dirs, small_bear):
    """spz_version 2 (for spz-js) writes a version 2 header; 3 is the default; others are refused by name."""
    for version in ("2", "3", None):
        saved = call(SaveGaussianScene, scene=small_bear, filename_prefix="v", format="spz",
                     **({} if version is None else {"spz_version": version}))
        header = gzip.decompress((comfy_dirs / "output" / saved["ui"]["scenes"][0]["filename"]).read_bytes())
        assert header[:8] == struct.pack("<II", 0x5053474E, int(version or 3)), version
    with pytest.raises(NodeInputError, match=r"Save Gaussian Scene: input 'spz_version': expected one of \['3', '2'\]"):
        call(SaveGaussianScene, scene=small_bear, filename_prefix="v", format="spz", spz_version="4")


def test_save_scene_refuses_a_prefix_too_long_for_its_files_before_the_graph_runs(comfy_dirs):
    fits = "artnvg/" + "s" * 200  # 200 + "_00001.ply" and the temporary's 29 bytes: 239 of 255
    assert SaveGaussianScene.check_files(filename_prefix=fits) is None
    message = SaveGaussianScene.check_files(filename_prefix="artnvg/" + "s" * 225, format="ply")
    assert message.startswith("Save Gaussian Scene: input 'filename_prefix': the file name: the file name ssss")
    assert "is 235 bytes long; it may have at most 226 here" in message
    assert SaveGaussianScene.check_files(filename_prefix="../escape").startswith(
        "Save Gaussian Scene: input 'filename_prefix': '../escape' must name a file inside the output folder")
    assert not (comfy_dirs / "output" / "artnvg").exists()  # nothing made by a check


def test_a_render_plan_beyond_the_memory_budget_is_refused_before_the_first_view(small_bear, bear, monkeypatch):
    import artnvg_core.raster.views as views

    monkeypatch.setattr(views, "available_memory", lambda: 2**30)
    monkeypatch.setattr(views, "render", lambda *args, **kwargs: pytest.fail("rendered"))
    with pytest.raises(NodeInputError, match=r"Render Camera Path: input 'scale': 60 views at scale 4\.0: 60 views of "
                       r"2048x2048 pixels, all their images held at once, need 3\.5 GiB, more than half the 1\.0 GiB"):
        call(RenderCameraPath, scene=small_bear, cameras=bear["cameras"], path="orbit", scale=4.0, num_frames=60,
             key_views="", frames_per_segment=30, loop=False)


def test_save_scene_refuses_a_prefix_whose_folder_is_a_file_before_the_graph_runs(comfy_dirs, small_bear):
    """A prefix's folder that is a file in the output folder is refused by name before the run, and by the
    node itself, rather than failing in mkdir with a bare FileExistsError; the file is left as it was."""
    taken = comfy_dirs / "output" / "taken"
    taken.parent.mkdir()
    taken.write_bytes(b"a user's file")
    expected = f"Save Gaussian Scene: input 'filename_prefix': its folder: {taken.resolve()} exists and is not a folder"
    assert SaveGaussianScene.check_files(filename_prefix="taken/stylized") == expected
    with pytest.raises(NodeInputError) as refused:
        call(SaveGaussianScene, scene=small_bear, filename_prefix="taken/stylized")
    assert str(refused.value) == expected
    assert taken.read_bytes() == b"a user's file" and sorted(taken.parent.iterdir()) == [taken]
