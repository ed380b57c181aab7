"""The pack's bridge to ComfyUI: folders, model lists, progress bar, interrupt and inference mode.

ComfyUI's modules are replaced by small fakes with the same names and call signatures
(``folder_paths``, ``comfy.utils.ProgressBar``, ``comfy.model_management``,
``server.PromptServer.instance.send_progress_text``, ``comfy_execution.utils.get_executing_context``);
the real server is exercised by tests/integration/.
"""

import re
import sys
import types

import pytest
import torch

from artnvg_core.cameras import CameraSet
from artnvg_core.progress import Cancelled
from artnvg_core.scene import GaussianScene
from nodes import comfy_bridge
from nodes.blend_nodes import BlendStylization
from nodes.model_patch_nodes import CSGO_FOLDER, LoadCSGO
from nodes.finetune_nodes import FinetuneGaussians
from nodes.render_nodes import RenderViews
from nodes.scene_nodes import LoadGaussianScene, SaveGaussianScene
from nodes.selection_nodes import SelectGaussians


class InterruptProcessingException(Exception):
    pass


class FakeComfy:
    """Just enough of ComfyUI's module surface, recording what the pack does with it."""

    def __init__(self, root):
        self.root = root
        self.interrupted = False
        self.bars = []  # one list of (value, total) per ProgressBar
        self.emptied = 0
        models_dir = root / "models"
        folder_paths = types.ModuleType("folder_paths")
        folder_paths.models_dir = str(models_dir)
        folder_paths.folder_names_and_paths = {
            name: ([str(models_dir / name)], {".safetensors", ".bin"})
            for name in ("checkpoints", "controlnet", "clip_vision")
        }
        folder_paths.get_input_directory = lambda: str(root / "input")
        folder_paths.get_output_directory = lambda: str(root / "output")
        folder_paths.get_folder_paths = lambda name: list(folder_paths.folder_names_and_paths[name][0])

        def listed(name):
            folders, extensions = folder_paths.folder_names_and_paths[name]
            return sorted(p.name for f in folders if (root / f).is_dir() for p in (root / f).iterdir()
                          if p.suffix in extensions)

        def full_path(name, filename):
            if name not in folder_paths.folder_names_and_paths:
                return None
            for folder in folder_paths.folder_names_and_paths[name][0]:
                candidate = root / folder / filename
                if candidate.is_file():
                    return str(candidate)
            return None

        folder_paths.get_filename_list = listed
        folder_paths.get_full_path = full_path

        fake = self

        class ProgressBar:
            def __init__(self, total, node_id=None):
                self.updates = []
                fake.bars.append(self.updates)

            def update_absolute(self, value, total=None, preview=None):
                self.updates.append((value, total))

        utils = types.ModuleType("comfy.utils")
        utils.ProgressBar = ProgressBar
        management = types.ModuleType("comfy.model_management")
        management.InterruptProcessingException = InterruptProcessingException
        management.processing_interrupted = lambda: fake.interrupted
        management.get_torch_device = lambda: torch.device("cpu")

        def throw_if_interrupted():
            if fake.interrupted:
                fake.interrupted = False
                raise InterruptProcessingException()

        def soft_empty_cache():
            fake.emptied += 1

        management.throw_exception_if_processing_interrupted = throw_if_interrupted
        management.soft_empty_cache = soft_empty_cache
        comfy = types.ModuleType("comfy")
        comfy.utils, comfy.model_management = utils, management
        self.texts = []  # (text, node id) sent under a node
        server = types.ModuleType("server")
        server.PromptServer = types.SimpleNamespace(instance=types.SimpleNamespace(
            send_progress_text=lambda text, node_id, sid=None: fake.texts.append((text, node_id))))
        execution = types.ModuleType("comfy_execution.utils")
        execution.get_executing_context = lambda: types.SimpleNamespace(prompt_id="p", node_id="7", list_index=None)
        self.modules = {"folder_paths": folder_paths, "comfy": comfy, "comfy.utils": utils,
                        "comfy.model_management": management, "server": server,
                        "comfy_execution": types.ModuleType("comfy_execution"), "comfy_execution.utils": execution}


@pytest.fixture
def comfy(tmp_path, monkeypatch):
    fake = FakeComfy(tmp_path)
    for name, module in fake.modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    return fake


def _tiny_scene(count: int = 40, seed: int = 0) -> GaussianScene:
    """Gaussians in front of the camera of :func:`_tiny_cameras` (z about 3)."""
    generator = torch.Generator().manual_seed(seed)
    means = torch.randn(count, 3, generator=generator) * 0.4 + torch.tensor([0.0, 0.0, 3.0])
    return GaussianScene(
        means=means,
        quats=torch.randn(count, 4, generator=generator),
        log_scales=torch.full((count, 3), -2.0),
        opacity_logits=torch.full((count,), 1.0),
        sh=torch.randn(count, 4, 3, generator=generator) * 0.5,
    )


def _tiny_cameras(count: int = 2) -> CameraSet:
    pose = torch.eye(4).repeat(count, 1, 1)
    pose[:, 0, 3] = torch.linspace(-0.2, 0.2, count)
    intrinsics = torch.tensor([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]).repeat(count, 1, 1)
    return CameraSet(pose, intrinsics, 16, 16, [f"view{i}" for i in range(count)])


def test_fallbacks_without_comfyui(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert "folder_paths" not in sys.modules
    assert comfy_bridge.input_directory() == tmp_path / "input"
    assert comfy_bridge.output_directory() == tmp_path / "output"
    assert comfy_bridge.model_files("checkpoints") == []
    assert comfy_bridge.model_file_path("checkpoints", "x.safetensors") is None
    assert comfy_bridge.progress_bar() is None
    assert comfy_bridge.interrupt_requested() is False
    comfy_bridge.register_model_folder("csgo", {".bin"})  # a no-op without ComfyUI

    @comfy_bridge.cancellable
    def stopped():
        raise Cancelled("stopped by request")

    with pytest.raises(Cancelled):
        stopped()


def test_folders_and_model_lists_come_from_comfyui(comfy):
    root = comfy.root
    assert comfy_bridge.input_directory() == root / "input"
    assert comfy_bridge.output_directory() == root / "output"
    (root / "models" / "checkpoints").mkdir(parents=True)
    (root / "models" / "checkpoints" / "sdxl.safetensors").write_bytes(b"")
    assert comfy_bridge.model_files("checkpoints") == ["sdxl.safetensors"]
    assert comfy_bridge.model_file_path("checkpoints", "sdxl.safetensors") == root / "models/checkpoints/sdxl.safetensors"
    assert comfy_bridge.model_file_path("checkpoints", "other.safetensors") is None
    comfy_bridge.register_model_folder(CSGO_FOLDER, {".bin"})
    assert (root / "models" / CSGO_FOLDER).is_dir()  # registering creates it
    (root / "models" / CSGO_FOLDER / "csgo_4_32.bin").write_bytes(b"")
    assert LoadCSGO.INPUT_TYPES()["required"]["csgo_name"][1]["options"] == ["csgo_4_32.bin"]


def test_register_model_folder_keeps_user_paths(comfy):
    registry = comfy.modules["folder_paths"].folder_names_and_paths
    assert not (comfy.root / "models" / "csgo").exists()
    comfy_bridge.register_model_folder("csgo", {".bin", ".safetensors"})
    assert registry["csgo"] == ([str(comfy.root / "models" / "csgo")], {".bin", ".safetensors"})
    assert (comfy.root / "models" / "csgo").is_dir()  # created, for the file a missing-file message asks for
    registry["csgo"] = (["/elsewhere/csgo"], {".pt"})  # e.g. from extra_model_paths.yaml
    comfy_bridge.register_model_folder("csgo", {".bin"})
    comfy_bridge.register_model_folder("csgo", {".bin"})
    assert registry["csgo"] == (["/elsewhere/csgo", str(comfy.root / "models" / "csgo")], {".pt", ".bin"})


def test_a_models_folder_that_cannot_be_written_is_logged_and_registered(comfy, caplog):
    (comfy.root / "models").mkdir()
    (comfy.root / "models" / "csgo").write_text("a file where the folder belongs")
    with caplog.at_level("WARNING", logger="artnvg"):
        comfy_bridge.register_model_folder("csgo", {".bin"})
    assert [r.message.split(" (")[0] for r in caplog.records] == [
        f"ArtNVG: could not create the model folder {comfy.root / 'models' / 'csgo'}"]
    assert "csgo" in comfy.modules["folder_paths"].folder_names_and_paths


def test_cancelled_becomes_comfyui_interrupt(comfy):
    @comfy_bridge.cancellable
    def stopped():
        raise Cancelled("stopped by request")

    comfy.interrupted = True
    with pytest.raises(InterruptProcessingException):
        stopped()
    assert comfy.interrupted is False  # the request is consumed, as ComfyUI's own check does


def test_render_views_reports_progress_and_stops(comfy):
    scene, cameras = _tiny_scene(), _tiny_cameras(3)
    with torch.inference_mode():
        images, _ = RenderViews().render(scene, cameras, 1.0, 1, "")
    assert images.shape == (3, 16, 16, 3)
    assert comfy.bars == [[(0, 3), (1, 3), (2, 3), (3, 3)]]  # the bar shows as the first view starts
    comfy.interrupted = True
    with pytest.raises(InterruptProcessingException), torch.inference_mode():
        RenderViews().render(scene, cameras, 1.0, 1, "")


def test_blend_previews_report_progress_and_stop(comfy):
    """One render a preview strength (seconds each at a capture's size on a CPU, every time the dial moves)."""
    scene, cameras = _tiny_scene(), _tiny_cameras(2)
    with torch.inference_mode():
        BlendStylization().blend(scene, scene, 0.5, cameras=cameras, preview_strengths="0, 0.5, 1")
    assert comfy.bars == [[(0, 3), (1, 3), (2, 3), (3, 3)]]
    comfy.interrupted = True
    with pytest.raises(InterruptProcessingException), torch.inference_mode():
        BlendStylization().blend(scene, scene, 0.5, cameras=cameras, preview_strengths="0, 0.5, 1")


def test_select_gaussians_by_masks_reports_progress_and_stops(comfy):
    """Each masked view is a render with its gradient (seconds per view at a capture's size on a CPU): the bar
    moves per view and Cancel stops it."""
    scene, cameras = _tiny_scene(), _tiny_cameras(3)
    masks = torch.ones(3, 16, 16)
    with torch.inference_mode():
        (selection,) = SelectGaussians().select(scene, "mask", "", cameras=cameras, mask=masks, views="0, 1, 2")
    assert selection.any()
    assert comfy.bars == [[(0, 3), (1, 3), (2, 3), (3, 3)]]
    assert comfy.texts == [(f"selected {int(selection.sum())} of 40 Gaussians", "7")]  # the title above names it
    comfy.interrupted = True
    with pytest.raises(InterruptProcessingException), torch.inference_mode():
        SelectGaussians().select(scene, "mask", "", cameras=cameras, mask=masks, views="0, 1, 2")


@pytest.mark.parametrize("format", ["ply", "spz"])
def test_scene_files_load_and_save_with_progress_and_stop_leaving_no_file(comfy, monkeypatch, format):
    """Millions of Gaussians take seconds to read or write: the bar moves a chunk at a time, Cancel stops it."""
    from artnvg_core.formats import common, save_scene

    from artnvg_core import scene as scenes

    monkeypatch.setattr(common, "CHUNK_GAUSSIANS", 16)
    monkeypatch.setattr(scenes, "CHECKED_ROWS", 16)
    scene = _tiny_scene()
    (comfy.root / "input").mkdir()
    save_scene(scene, comfy.root / "input" / f"scene.{format}")
    size = (comfy.root / "input" / f"scene.{format}").stat().st_size
    with torch.inference_mode():
        LoadGaussianScene().load(f"scene.{format}")
        (bar,) = comfy.bars  # one bar over the file's bytes, filled once: a PLY's rows read, decoded, checked
        assert {total for _, total in bar} == {size} and bar[0] == (0, size) and bar[-1] == (size, size), bar
        assert [value for value, _ in bar] == sorted(value for value, _ in bar) and len(bar) >= 7, bar
        comfy.bars.clear()
        SaveGaussianScene().save(scene, "artnvg/saved", format)
        # the scene's 40 Gaussians (an SPZ writes its 6 attribute arrays in turn, each a sixth of the bar)
        assert comfy.bars[0][0] == (0, 40) and comfy.bars[0][-1] == (40, 40)
    assert [p.name for p in (comfy.root / "output" / "artnvg").iterdir()] == [f"saved_00001.{format}"]
    for run in (lambda: LoadGaussianScene().load(f"scene.{format}"),
                lambda: SaveGaussianScene().save(scene, "artnvg/saved", format)):
        comfy.interrupted = True
        with pytest.raises(InterruptProcessingException), torch.inference_mode():
            run()
    assert [p.name for p in (comfy.root / "output" / "artnvg").iterdir()] == [f"saved_00001.{format}"]


def test_finetune_runs_under_inference_mode_with_progress_and_stops(comfy, caplog):
    """ComfyUI runs nodes under torch.inference_mode(); the finetune must still get gradients."""
    with torch.inference_mode():  # inputs made by other nodes are inference tensors
        scene, cameras = _tiny_scene(), _tiny_cameras(2)
        style = torch.rand(1, 24, 24, 3)
        node = FinetuneGaussians()
        with caplog.at_level("WARNING", logger="artnvg"):
            (result,) = node.finetune(scene, cameras, style, 2, "appearance", 0.8, 0.2, 1.0, 0.5, 0.0, 0)
    assert not torch.equal(result.sh, scene.sh)
    assert torch.equal(result.means, scene.means)  # appearance only
    # one bar, four stages, each named under the node as it starts (0): the 2 views rendered before (colour
    # transfer, one render call), their content features, the 2 steps, the 2 views after
    assert comfy.bars == [[(0, 2), (2, 2), (0, 2), (1, 2), (2, 2), (0, 2), (1, 2), (2, 2), (0, 2), (2, 2)]]
    # under the node's title, without it (one line where the node is as wide as the shipped workflows have it);
    # the console's log names the node
    texts = ["rendering the 2 views before finetuning", "computing the VGG features of the 2 views for the content "
             "term", "finetuning: 2 steps", "rendering the 2 finetuned views for the colour match"]
    assert [text for text, _ in comfy.texts[:-1]] == texts
    # the last stage's name does not stay under the node once it has finished
    assert re.fullmatch(r"finished 2 steps in \d+\.\d s", comfy.texts[-1][0]), comfy.texts[-1]
    assert [r.message for r in caplog.records] == [f"Finetune Gaussians: {text}" for text, _ in comfy.texts]

    def interrupt_after_first_step(step, total, info):
        comfy.interrupted = True

    comfy.modules["comfy.utils"].ProgressBar.update_absolute = lambda self, value, total=None, preview=None: (
        interrupt_after_first_step(value, total, None))
    with pytest.raises(InterruptProcessingException), torch.inference_mode():
        node.finetune(scene, cameras, style, 50, "appearance", 0.8, 0.2, 1.0, 0.5, 0.0, 0)


def test_gsplat_kernel_build_is_announced_under_the_running_node(comfy, monkeypatch, caplog):
    from artnvg_core import raster
    from artnvg_core.raster import gsplat_backend

    monkeypatch.setattr(raster, "choose_backend", lambda backend, device, dtype=None: "gsplat")
    monkeypatch.setattr(gsplat_backend, "_loaded", False)
    monkeypatch.setattr(gsplat_backend, "build_pending", lambda: True)
    monkeypatch.setattr(gsplat_backend, "_import_kernels", lambda: object())
    with caplog.at_level("WARNING", logger="artnvg"):
        comfy_bridge.prepare_rasterizer(torch.device("cuda"))
        comfy_bridge.prepare_rasterizer(torch.device("cuda"))
    assert [text for text, _ in comfy.texts][0] == gsplat_backend.BUILD_NOTICE
    assert len(comfy.texts) == 2 and {node for _, node in comfy.texts} == {"7"}
    assert comfy.texts[1][0].startswith("gsplat: CUDA kernels built in ")
    assert [r.message for r in caplog.records] == [text for text, _ in comfy.texts]


def test_render_and_finetune_nodes_prepare_the_rasterizer_first(comfy, monkeypatch):
    prepared = []
    monkeypatch.setattr(comfy_bridge, "prepare_rasterizer", prepared.append)
    with torch.inference_mode():
        RenderViews().render(_tiny_scene(), _tiny_cameras(1), 1.0, 1, "")
        FinetuneGaussians().finetune(_tiny_scene(), _tiny_cameras(1), torch.rand(1, 8, 8, 3), 1, "appearance",
                                     0.8, 0.2, 1.0, 0.5, 0.0, 0)
    assert prepared == [torch.device("cpu"), torch.device("cpu")]


def test_loader_change_signature_follows_the_file(comfy):
    folder = comfy.root / "input"
    folder.mkdir()
    scene_file = folder / "scene.ply"
    scene_file.write_bytes(b"one")
    first = LoadGaussianScene.IS_CHANGED("scene.ply")
    scene_file.write_bytes(b"longer")
    assert LoadGaussianScene.IS_CHANGED("scene.ply") != first
    assert LoadGaussianScene.IS_CHANGED("missing.ply") == ""


def test_finetune_of_a_selection_names_its_coverage_pass_under_the_node(comfy):
    """The selection's coverage, one render a view before the others, moves the bar and is named."""
    with torch.inference_mode():
        scene, cameras = _tiny_scene(), _tiny_cameras(2)
        selection = torch.ones(len(scene), dtype=torch.bool)
        FinetuneGaussians().finetune(scene, cameras, torch.rand(1, 24, 24, 3), 1, "appearance", 0.8, 0.2, 1.0, 0.5,
                                     0.0, 0, selection=selection)
    assert comfy.bars == [[(0, 2), (1, 2), (2, 2), (0, 2), (2, 2), (0, 2), (1, 2), (2, 2), (0, 1), (1, 1), (0, 2),
                           (2, 2)]]
    assert comfy.texts[0] == ("measuring what the selection covers in the 2 views", "7")
    assert ("finetuning: 1 step", "7") in comfy.texts  # was "1 steps"
