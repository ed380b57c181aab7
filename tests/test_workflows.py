"""The shareable workflows (UI and API format) and the queueing script, without ComfyUI.

Checks that example_workflows/ (the folder ComfyUI's template browser reads) holds only UI workflows,
each with its thumbnail and a Note describing it, laid out without overlapping nodes; that every
workflow references only existing node types, that links connect matching types, that widget
values fit the inputs, and that each API file (workflows_api/) describes the same graph as its UI file. The stock ComfyUI nodes used are described in STOCK_NODES;
tests/integration/ compares that description with a real server's /object_info.
"""

import http.server
import importlib.util
import json
import re
import threading
from pathlib import Path
from typing import ClassVar

import pytest
from PIL import Image

from nodes import NODE_CLASS_MAPPINGS
from nodes.demo_inputs import DEMO_STYLE, demo_files

REPO = Path(__file__).resolve().parents[1]
# the folders ComfyUI (0.3.64) serves a pack's templates from; it logs a request to rename any other to
# example_workflows, the one ComfyUI's and the Comfy Registry's docs name
TEMPLATE_FOLDERS = ("example_workflows", "example", "examples", "workflow", "workflows")
WORKFLOWS = REPO / "example_workflows"
API_WORKFLOWS = REPO / "workflows_api"
FRONTEND_ONLY = {"Note", "MarkdownNote"}  # editor-side nodes: not in the API prompt
TITLE_HEIGHT = 30  # the editor draws a node's title bar above its pos
WIDGET_TYPES = {"INT", "FLOAT", "STRING", "BOOLEAN"}
FILE_LISTS = {"scene_file", "camera_source", "image", "ckpt_name", "lora_name", "control_net_name", "clip_name",
              "csgo_name"}
BYPASSED = 4  # a UI node's mode when bypassed: the queued prompt leaves it out and passes its inputs through
SEED_CONTROL = ("fixed", "increment", "decrement", "randomize")
ANY = "*"  # the input type that takes any link

# Stock ComfyUI nodes the workflows use: INPUT_TYPES (file lists as []), RETURN_TYPES, display name.
STOCK_NODES = {
    "LoadImage": ({"required": {"image": ([], {"image_upload": True})}}, ("IMAGE", "MASK"), "Load Image"),
    "PreviewImage": ({"required": {"images": ("IMAGE",)}}, (), "Preview Image"),
    "SaveImage": ({"required": {"images": ("IMAGE",), "filename_prefix": ("STRING", {"default": "ComfyUI"})}}, (),
                  "Save Image"),
    "CheckpointLoaderSimple": ({"required": {"ckpt_name": ([],)}}, ("MODEL", "CLIP", "VAE"), "Load Checkpoint"),
    "LoraLoader": ({"required": {"model": ("MODEL",), "clip": ("CLIP",), "lora_name": ([],),
                                 "strength_model": ("FLOAT", {"default": 1.0, "min": -100.0, "max": 100.0}),
                                 "strength_clip": ("FLOAT", {"default": 1.0, "min": -100.0, "max": 100.0})}},
                   ("MODEL", "CLIP"), "Load LoRA"),
    "ControlNetLoader": ({"required": {"control_net_name": ([],)}}, ("CONTROL_NET",), "Load ControlNet Model"),
    "CLIPVisionLoader": ({"required": {"clip_name": ([],)}}, ("CLIP_VISION",), "Load CLIP Vision"),
    "CLIPTextEncode": ({"required": {"text": ("STRING", {"multiline": True}), "clip": ("CLIP",)}}, ("CONDITIONING",),
                       "CLIP Text Encode (Prompt)"),
    "PreviewAny": ({"required": {"source": (ANY, {})}}, (), "Preview Any"),
    "Preview3D": ({"required": {"model_file": ("STRING", {"default": "", "multiline": False})},
                   "optional": {"camera_info": ("LOAD3D_CAMERA", {})}}, (), "Preview 3D"),
}
UPLOAD_WIDGET_VALUE = "image"  # LoadImage's upload button, stored after the file name
EDITOR_WIDGETS = {"Preview3D": [""]}  # values of widgets the editor adds after the node's own (its 3D view)


def load_queue_script():
    spec = importlib.util.spec_from_file_location("queue_workflow", API_WORKFLOWS / "queue_workflow.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def node_description(class_type: str) -> tuple[dict, tuple, str]:
    """(INPUT_TYPES, RETURN_TYPES, display name) of a node type."""
    if class_type in STOCK_NODES:
        return STOCK_NODES[class_type]
    node = NODE_CLASS_MAPPINGS[class_type]
    return node.INPUT_TYPES(), tuple(node.RETURN_TYPES), node.DISPLAY_NAME


def node_spec(class_type: str) -> tuple[dict, tuple]:
    """(inputs by name in order, output types) of a node type."""
    types, outputs, _ = node_description(class_type)
    return {**types.get("required", {}), **types.get("optional", {})}, outputs


def required_inputs(class_type: str) -> set[str]:
    return set(node_description(class_type)[0]["required"])


def is_widget(spec) -> bool:
    return isinstance(spec[0], (list, tuple)) or spec[0] in WIDGET_TYPES or spec[0] == "COMBO"


def widget_problem(name: str, spec, value) -> str | None:
    """Why ``value`` does not fit widget input ``name`` with ``spec``, or None."""
    kind, options = spec[0], (spec[1] if len(spec) > 1 else {})
    if kind == "COMBO":
        kind = options["options"]
    if isinstance(kind, (list, tuple)):
        if name in FILE_LISTS:
            return None if isinstance(value, str) and value else f"{name}: expected a file name, got {value!r}"
        return None if value in kind else f"{name}: {value!r} not in {list(kind)}"
    expected = {"INT": int, "FLOAT": (int, float), "STRING": str, "BOOLEAN": bool}[kind]
    if not isinstance(value, expected) or (kind != "BOOLEAN" and isinstance(value, bool)):
        return f"{name}: expected {kind}, got {value!r}"
    if kind in ("INT", "FLOAT") and not options.get("min", value) <= value <= options.get("max", value):
        return f"{name}: {value} outside [{options.get('min')}, {options.get('max')}]"
    return None


def widget_values_by_name(class_type: str, values: list) -> dict:
    """Map a UI node's ``widgets_values`` onto input names, as the graph editor does.

    INT inputs named seed get a second widget (what to do after each run); LoadImage's
    file list is followed by its upload button's value.
    """
    inputs, _ = node_spec(class_type)
    added = EDITOR_WIDGETS.get(class_type, [])
    assert values[len(values) - len(added):] == added, f"{class_type}: the editor's own widget values"
    named, remaining = {}, list(values[:len(values) - len(added)])
    for name, spec in inputs.items():
        if not is_widget(spec):
            continue
        assert remaining, f"{class_type}: no widget value left for {name}"
        named[name] = remaining.pop(0)
        if spec[0] == "INT" and name in ("seed", "noise_seed"):
            assert remaining and remaining.pop(0) in SEED_CONTROL, f"{class_type}: {name} needs its control value"
        if len(spec) > 1 and spec[1].get("image_upload"):
            assert remaining and remaining.pop(0) == UPLOAD_WIDGET_VALUE, f"{class_type}: upload widget value"
    assert not remaining, f"{class_type}: {len(remaining)} widget values too many: {remaining}"
    return named


def ui_to_api(ui: dict) -> dict:
    """The API-format prompt the graph editor queues for a UI-format workflow."""
    links = {link[0]: link for link in ui["links"]}
    nodes = {node["id"]: node for node in ui["nodes"]}

    def source(link_id: int) -> list:
        """[origin id, slot] of a link, through bypassed nodes (to their input of the link's type)."""
        _, origin, origin_slot, _, _, kind = links[link_id]
        if nodes[origin].get("mode") == BYPASSED:
            return source(next(s["link"] for s in nodes[origin]["inputs"] if s["type"] == kind))
        return [str(origin), origin_slot]

    api = {}
    for node in ui["nodes"]:
        if node["type"] in FRONTEND_ONLY or node.get("mode") == BYPASSED:
            continue
        inputs = dict(widget_values_by_name(node["type"], node.get("widgets_values", [])))
        for socket in node.get("inputs", []):
            if socket.get("link") is not None:
                inputs[socket["name"]] = source(socket["link"])
        title = node.get("title") or node_description(node["type"])[2]
        api[str(node["id"])] = {"inputs": inputs, "class_type": node["type"], "_meta": {"title": title}}
    return api


UI_FILES = sorted(WORKFLOWS.glob("*.json"))
API_FILES = sorted(API_WORKFLOWS.glob("*_api.json"))
NNFM_API = API_WORKFLOWS / "ArtNVG_1_quick_start_NNFM_no_model_downloads_api.json"
CAMERA_FREE_API = API_WORKFLOWS / "ArtNVG_2_scene_without_cameras_NNFM_api.json"
FULL_API = API_WORKFLOWS / "ArtNVG_3_full_method_CSGO_SDXL_needs_4_model_files_api.json"
REGION_API = API_WORKFLOWS / "ArtNVG_4_strength_dial_and_region_NNFM_api.json"


def api_twin(ui_path: Path) -> Path:
    return API_WORKFLOWS / f"{ui_path.stem}_api.json"


def test_each_workflow_comes_in_both_formats_and_the_template_folder_holds_ui_workflows_only():
    assert [p.stem for p in UI_FILES] == ["ArtNVG_1_quick_start_NNFM_no_model_downloads",
                                          "ArtNVG_2_scene_without_cameras_NNFM",
                                          "ArtNVG_3_full_method_CSGO_SDXL_needs_4_model_files",
                                          "ArtNVG_4_strength_dial_and_region_NNFM"]
    assert API_FILES == [api_twin(p) for p in UI_FILES]
    assert all("nodes" in json.loads(p.read_text()) for p in UI_FILES)  # the browser opens only UI workflows
    assert sorted(p.name for p in WORKFLOWS.iterdir()) == sorted(
        name for p in UI_FILES for name in (p.name, f"{p.stem}.jpg"))


def test_the_templates_are_in_example_workflows_alone():
    assert [name for name in TEMPLATE_FOLDERS if (REPO / name).exists()] == ["example_workflows"]


@pytest.mark.parametrize("path", UI_FILES, ids=lambda p: p.stem)
def test_each_template_has_a_small_thumbnail_and_a_note(path):
    """The browser shows ``<name>.jpg`` as the card and the name (``_`` as spaces) as its description."""
    image = Image.open(path.with_suffix(".jpg"))
    assert image.format == "JPEG" and 128 <= min(image.size) and max(image.size) <= 512
    assert path.with_suffix(".jpg").stat().st_size < 60_000
    notes = [n for n in json.loads(path.read_text())["nodes"] if n["type"] == "Note"]
    assert len(notes) == 1 and len(notes[0]["widgets_values"][0]) > 200


def node_rectangles(ui: dict) -> dict[int, tuple[float, float, float, float]]:
    """Node id -> (left, top, right, bottom) as the editor draws it: the title bar above ``pos``."""
    return {n["id"]: (n["pos"][0], n["pos"][1] - TITLE_HEIGHT, n["pos"][0] + n["size"][0], n["pos"][1] + n["size"][1])
            for n in ui["nodes"]}


def overlapping(rectangles: dict) -> list[tuple[int, int]]:
    """Pairs of ids whose rectangles share some area (touching edges do not count)."""
    items = sorted(rectangles.items())
    return [(a, b) for i, (a, (l1, t1, r1, b1)) in enumerate(items) for b, (l2, t2, r2, b2) in items[i + 1:]
            if min(r1, r2) > max(l1, l2) and min(b1, b2) > max(t1, t2)]


def test_overlap_check_sees_a_covered_corner_and_not_neighbours():
    ui = {"nodes": [{"id": 1, "pos": [0, 0], "size": [100, 100]}, {"id": 2, "pos": [100, 0], "size": [50, 50]},
                    {"id": 3, "pos": [90, 125], "size": [20, 20]}, {"id": 4, "pos": [0, 230], "size": [10, 10]}]}
    assert overlapping(node_rectangles(ui)) == [(1, 3)]  # 3's title bar reaches into 1; 4's stops at 200


@pytest.mark.parametrize("path", UI_FILES, ids=lambda p: p.stem)
def test_no_nodes_overlap_at_the_sizes_the_editor_needs(path):
    """Every node is at least as tall as the editor makes it (MIN_HEIGHTS, measured in ComfyUI 0.3.64's
    editor; tests/integration checks the live editor), and no two nodes overlap."""
    ui = json.loads(path.read_text())
    for node in ui["nodes"]:
        assert node["size"][1] >= MIN_HEIGHTS.get(node["type"], 0), (path.stem, node["type"])
    assert overlapping(node_rectangles(ui)) == []


# heights the 0.3.64 editor gives each node (its computeSize); Finetune and Save with room for the text they show
MIN_HEIGHTS = {"ArtNVGLoadGaussianScene": 106, "ArtNVGLoadCameras": 82, "LoadImage": 326, "ArtNVGRenderViews": 150,
               "ArtNVGFinetuneGaussians": 420, "ArtNVGSaveGaussianScene": 150, "ArtNVGRenderCameraPath": 198,
               "ArtNVGCamerasAroundScene": 202, "ArtNVGGroupNeighbouringViews": 82, "ArtNVGNVAttentionPatch": 130,
               "ArtNVGSampleGroup": 406}


@pytest.mark.parametrize("path", UI_FILES, ids=lambda p: p.name)
def test_ui_workflow_links_and_widgets(path):
    ui = json.loads(path.read_text())
    nodes = {node["id"]: node for node in ui["nodes"]}
    assert len(nodes) == len(ui["nodes"]) and ui["last_node_id"] >= max(nodes)
    assert ui["last_link_id"] >= max(link[0] for link in ui["links"])
    for link_id, origin, origin_slot, target, target_slot, kind in ui["links"]:
        origin_outputs = node_spec(nodes[origin]["type"])[1]
        assert origin_outputs[origin_slot] == kind, (path.name, link_id)
        assert link_id in nodes[origin]["outputs"][origin_slot]["links"]
        socket = nodes[target]["inputs"][target_slot]
        assert socket["link"] == link_id and socket["type"] in (kind, ANY)
        assert node_spec(nodes[target]["type"])[0][socket["name"]][0] in (kind, ANY), (path.name, link_id)
    for node in ui["nodes"]:
        if node["type"] in FRONTEND_ONLY:
            continue
        inputs, outputs = node_spec(node["type"])
        assert [o["type"] for o in node.get("outputs", [])] == list(outputs), node["type"]
        connected = {s["name"] for s in node.get("inputs", []) if s.get("link") is not None}
        sockets = {name for name in required_inputs(node["type"]) if not is_widget(inputs[name])}
        assert sockets <= connected, f"{path.name}: {node['type']} has unconnected inputs {sockets - connected}"
        for name, value in widget_values_by_name(node["type"], node.get("widgets_values", [])).items():
            assert widget_problem(name, inputs[name], value) is None, (path.name, node["type"])


@pytest.mark.parametrize("path", API_FILES, ids=lambda p: p.name)
def test_api_workflow_links_and_widgets(path):
    api = json.loads(path.read_text())
    for node_id, node in api.items():
        inputs, _ = node_spec(node["class_type"])
        assert set(node["inputs"]) <= set(inputs), node_id
        for name, value in node["inputs"].items():
            if is_widget(inputs[name]) and not isinstance(value, list):  # a widget may take a link instead
                assert widget_problem(name, inputs[name], value) is None, (path.name, node_id)
            else:
                origin, slot = value
                assert inputs[name][0] in (node_spec(api[origin]["class_type"])[1][slot], ANY), (path.name, node_id, name)
        assert required_inputs(node["class_type"]) <= set(node["inputs"]), (path.name, node_id)


@pytest.mark.parametrize("path", UI_FILES, ids=lambda p: p.name)
def test_api_and_ui_files_describe_the_same_graph(path):
    ui = json.loads(path.read_text())
    api = json.loads(api_twin(path).read_text())
    assert ui_to_api(ui) == api


@pytest.mark.parametrize("path", API_FILES, ids=lambda p: p.name)
def test_input_files_are_the_demo_files_the_pack_installs(path, tmp_path):
    """Every input file a workflow names is one the pack puts into the input folder at load, from the demo."""
    installed = demo_files()
    for node in json.loads(path.read_text()).values():
        for name in ("scene_file", "camera_source", "image"):
            if name in node["inputs"]:
                assert node["inputs"][name] in installed, (path.name, node["inputs"][name])
    assert [n["inputs"]["image"] for n in json.loads(path.read_text()).values()
            if n["class_type"] == "LoadImage"] == [DEMO_STYLE]  # top level: Load Image's list shows it


def test_nnfm_only_workflow_needs_no_diffusion_weights():
    api = json.loads((NNFM_API).read_text())
    used = {node["class_type"] for node in api.values()}
    assert {"ArtNVGFinetuneGaussians", "ArtNVGSaveGaussianScene"} <= used
    assert not used & {"ArtNVGLoadCSGO", "ArtNVGApplyCSGO", "ArtNVGNVAttentionPatch", "ArtNVGSampleGroup"}


def test_camera_free_workflow_needs_only_a_scene_file_and_a_style_image():
    api = json.loads((CAMERA_FREE_API).read_text())
    used = {node["class_type"] for node in api.values()}
    assert "ArtNVGLoadCameras" not in used and {"ArtNVGCamerasAroundScene", "ArtNVGFinetuneGaussians"} <= used
    assert not used & {"ArtNVGLoadCSGO", "ArtNVGSampleGroup"}  # the NNFM stylizer
    rig = next(node_id for node_id, node in api.items() if node["class_type"] == "ArtNVGCamerasAroundScene")
    views = next(node for node in api.values() if node["class_type"] == "ArtNVGRenderViews")
    assert views["inputs"]["cameras"] == [rig, 0]


def test_region_workflow_finetunes_and_blends_one_selection_without_diffusion():
    api = json.loads(REGION_API.read_text())
    used = {node["class_type"] for node in api.values()}
    assert not used & {"ArtNVGLoadModels", "ArtNVGSampleGroup"}  # the NNFM stylizer
    (select,) = [i for i, node in api.items() if node["class_type"] == "ArtNVGSelectGaussians"]
    (finetune,) = [i for i, node in api.items() if node["class_type"] == "ArtNVGFinetuneGaussians"]
    (blend,) = [node for node in api.values() if node["class_type"] == "ArtNVGBlendStylization"]
    assert api[finetune]["inputs"]["selection"] == blend["inputs"]["selection"] == [select, 0]
    assert blend["inputs"]["stylized"] == [finetune, 0]
    assert blend["inputs"]["original"] == api[finetune]["inputs"]["scene"] == api[select]["inputs"]["scene"]


def test_full_workflow_feeds_stylized_views_to_the_finetune():
    api = json.loads((FULL_API).read_text())
    finetune = next(node for node in api.values() if node["class_type"] == "ArtNVGFinetuneGaussians")
    source, _ = finetune["inputs"]["stylized_views"]
    assert api[source]["class_type"] == "ArtNVGSampleGroup"
    sampler = api[source]["inputs"]
    patched = api[sampler["model"][0]]
    assert patched["class_type"] == "ArtNVGNVAttentionPatch"
    csgo = api[patched["inputs"]["model"][0]]
    assert csgo["class_type"] == "ArtNVGApplyCSGO" and sampler["control_net"] == [patched["inputs"]["model"][0], 1]
    assert api[csgo["inputs"]["model"][0]]["class_type"] == "CheckpointLoaderSimple"  # the LoRA loader is bypassed
    assert sampler["content_views"][0] == finetune["inputs"]["cameras"][0]  # same Render Views node


def test_full_workflow_declares_its_four_model_files_for_the_missing_models_dialog():
    """The top-level ``models`` list (name, url, directory) names exactly the files the loaders pick."""
    ui = json.loads(next(WORKFLOWS.glob("ArtNVG_3_*.json")).read_text())
    picked = {node["widgets_values"][0]: node["type"] for node in ui["nodes"]
              if node["type"] in ("CheckpointLoaderSimple", "ControlNetLoader", "CLIPVisionLoader", "ArtNVGLoadCSGO")}
    folders = {"CheckpointLoaderSimple": "checkpoints", "ControlNetLoader": "controlnet",
               "CLIPVisionLoader": "clip_vision", "ArtNVGLoadCSGO": "csgo"}
    assert {m["name"]: m["directory"] for m in ui["models"]} == {name: folders[kind] for name, kind in picked.items()}
    assert all(m["url"].startswith("https://huggingface.co/") and m["url"].endswith(m["url"].rsplit("/", 1)[-1])
               for m in ui["models"])


def test_full_workflow_note_says_how_to_get_each_file_the_editor_does_not_download():
    """The missing models dialog of ComfyUI 0.3.64's frontend (1.27.10) downloads only .safetensors and .sft
    files; for any other (CSGO's .bin) it shows "Only allowed suffixes are ..." instead: the note gives the
    command that fetches it into its folder."""
    ui = json.loads(next(WORKFLOWS.glob("ArtNVG_3_*.json")).read_text())
    (note,) = [n["widgets_values"][0] for n in ui["nodes"] if n["type"] == "Note"]
    by_hand = [m for m in ui["models"] if not m["name"].endswith((".safetensors", ".sft"))]
    assert by_hand
    for model in by_hand:
        repository = model["url"].removeprefix("https://huggingface.co/").split("/resolve/")[0]
        assert f"hf download {repository} {model['name']} --local-dir ComfyUI/models/{model['directory']}" in note


@pytest.mark.parametrize("path", API_FILES, ids=lambda p: p.stem)
def test_workflows_read_spz_files_by_the_loaders_default_axes(path):
    """Templates are for the user's own scenes: Load Gaussian Scene's spz_axes stays at its default (auto: the axes
    that put a .spz in front of its cameras), not one convention that turns another tool's .spz upside down."""
    default = NODE_CLASS_MAPPINGS["ArtNVGLoadGaussianScene"].INPUT_TYPES()["optional"]["spz_axes"][1]["default"]
    loaders = [n for n in json.loads(path.read_text()).values() if n["class_type"] == "ArtNVGLoadGaussianScene"]
    assert loaders and all(n["inputs"]["spz_axes"] == default for n in loaders)


# --------------------------------------------------------------------------- queue script


@pytest.fixture(scope="module")
def queue():
    return load_queue_script()


def test_overrides_by_id_or_title(queue):
    workflow = queue.load_api_workflow(NNFM_API)
    queue.apply_override(workflow, "Load Gaussian Scene.path=/data/my scene.ply")
    queue.apply_override(workflow, "6.iterations=25")
    queue.apply_override(workflow, "Render Views.views=0,5")
    queue.apply_override(workflow, "1.drop_invalid=true")
    assert workflow["1"]["inputs"]["path"] == "/data/my scene.ply"
    assert workflow["6"]["inputs"]["iterations"] == 25
    assert workflow["4"]["inputs"]["views"] == "0,5"
    assert workflow["1"]["inputs"]["drop_invalid"] is True
    for bad, problem in (("nothing", "NODE.INPUT=VALUE"), ("Nobody.x=1", "matches no node"),
                         ("Preview Image.images=1", "matches no node"), ("6.scene=1", "is a link")):
        with pytest.raises(queue.WorkflowError, match=problem):
            queue.apply_override(workflow, bad)


def test_unknown_inputs_are_refused_with_the_inputs_the_node_has(queue):
    workflow = queue.load_api_workflow(NNFM_API)
    with pytest.raises(queue.WorkflowError) as refused:
        queue.apply_override(workflow, "4.iterations=200")  # node 4 is Render Views, which has no iterations
    assert str(refused.value) == ("--set: node 4 (Render Views) has no input 'iterations'; its inputs that take a "
                                  "value: scale, stride, views, key_views")
    with pytest.raises(queue.WorkflowError, match="node 6 \\(Finetune Gaussians\\) has no input 'iteratons'; .*iterations"):
        queue.apply_override(workflow, "Finetune Gaussians.iteratons=5")
    with pytest.raises(queue.WorkflowError) as unknown:
        queue.apply_override(workflow, "Finetune.iterations=5")
    assert "1 (Load Gaussian Scene), 2 (Load Cameras), 3 (Style image), 4 (Render Views)" in str(unknown.value)
    assert "iterations" in workflow["6"]["inputs"] and "iteratons" not in workflow["6"]["inputs"]


def test_a_name_of_two_nodes_is_refused_as_ambiguous(queue):
    workflow = queue.load_api_workflow(NNFM_API)
    workflow["9"]["_meta"]["title"] = "Content views"  # two nodes titled alike
    workflow["8"]["_meta"]["title"] = "4"  # node 8's title is node 4's id
    for key, named in (("Content views", "5 (Content views), 9 (Content views)"), ("4", "4 (Render Views), 8 (4)")):
        with pytest.raises(queue.WorkflowError, match=f"node '{key}' is ambiguous: it names {re.escape(named)}"):
            queue.apply_override(workflow, f"{key}.scale=1")


def test_ui_format_is_refused_with_advice(queue):
    with pytest.raises(queue.WorkflowError, match="UI-format workflow; queue the API-format file"):
        queue.load_api_workflow(UI_FILES[0])


def _history_entry(status: str, messages: list, outputs: dict) -> dict:
    return {"status": {"status_str": status, "completed": status == "success", "messages": messages},
            "outputs": outputs}


def test_summary_of_success_error_and_interrupt(queue):
    done = _history_entry("success", [["execution_success", {}]],
                          {"7": {"scenes": [{"filename": "nnfm_00001.ply", "subfolder": "artnvg", "type": "output"}]}})
    assert queue.run_summary(done) == {"status": "success", "error": None, "outputs": [
        {"node": "7", "title": None, "kind": "scenes", "file": "artnvg/nnfm_00001.ply", "type": "output"}]}
    # the nodes' titles, from the prompt ComfyUI's history keeps (number, id, prompt, extra data, outputs)
    titled = {**done, "prompt": [0, "abc", {"7": {"class_type": "ArtNVGSaveGaussianScene", "inputs": {},
                                                  "_meta": {"title": "Save Gaussian Scene"}}}, {}, ["7"]]}
    assert queue.summary_text(queue.run_summary(titled)).splitlines()[1] == \
        "  node 7 (Save Gaussian Scene) scenes: artnvg/nnfm_00001.ply [output]"
    failed = _history_entry("error", [["execution_error", {"node_id": "1", "node_type": "ArtNVGLoadGaussianScene",
                                                          # as ComfyUI names a pack's class: its folder's path
                                                          "exception_type": "/c/custom_nodes/artnvg-comfyui.nodes."
                                                                            "node_errors.NodeInputError",
                                                          "exception_message": "scene file not found: x.ply"}]], {})
    assert queue.run_summary(failed)["error"] == \
        "node 1 (ArtNVGLoadGaussianScene): NodeInputError: scene file not found: x.ply"
    stopped = _history_entry("error", [["execution_interrupted", {"node_id": "6",
                                                                  "node_type": "ArtNVGFinetuneGaussians"}]], {})
    assert queue.run_summary(stopped)["status"] == "interrupted"
    assert queue.summary_text(queue.run_summary(stopped)) == "interrupted: in node 6 (ArtNVGFinetuneGaussians)"
    stopped["prompt"] = [0, "abc", {"6": {"class_type": "ArtNVGFinetuneGaussians", "_meta": {"title": "Finetune"}}}]
    assert queue.run_summary(stopped)["error"] == "in node 6 (Finetune)"


def test_text_summary_is_one_line_per_node_and_kind(queue):
    frames = [{"node": "9", "kind": "images", "file": f"ComfyUI_temp_{i:05d}_.png", "type": "temp"} for i in range(12)]
    scene = [{"node": "7", "kind": "scenes", "file": "artnvg/nnfm_00001.ply", "type": "output"}]
    text = queue.summary_text({"status": "success", "error": None, "outputs": scene + frames})
    assert text.splitlines() == ["success", "  node 7 scenes: artnvg/nnfm_00001.ply [output]",
                                 "  node 9 images: ComfyUI_temp_00000_.png (+11 more) [temp]"]


class _FakeServer(http.server.BaseHTTPRequestHandler):
    """Answers /prompt and /history like ComfyUI; ``reject`` makes /prompt fail validation."""

    reject = False
    partial = False  # /prompt queues the workflow but reports node_errors, as ComfyUI does when some outputs validate
    posted: ClassVar[list] = []
    running: ClassVar[list] = []  # prompt ids /queue lists as running and pending; abc in either has not ended
    pending: ClassVar[list] = []

    def _answer(self, code: int, payload: dict) -> None:
        body = json.dumps(payload).encode()
        self.send_response(code)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_POST(self):
        self.posted.append((self.path, json.loads(self.rfile.read(int(self.headers["Content-Length"])))))
        if self.path != "/prompt":
            self._answer(200, {})
        elif self.partial:
            self._answer(200, {"prompt_id": "abc", "number": 0, "node_errors": {"6": {
                "class_type": "ArtNVGFinetuneGaussians", "dependent_outputs": ["7"], "errors": [
                    {"type": "value_smaller_than_min", "message": "Value smaller than min",
                     "details": "iterations -1 < 1", "extra_info": {"input_name": "iterations"}}]}}})
        elif self.reject:
            self._answer(400, {"error": {"message": "Prompt outputs failed validation", "details": ""},
                               "node_errors": {"1": {"class_type": "ArtNVGLoadGaussianScene", "errors": [
                                   {"type": "custom_validation_failed", "message": "Custom validation failed for node",
                                    "details": "node_id - Load Gaussian Scene: input 'scene_file': scene file not "
                                               "found: /in/x.ply", "extra_info": {"input_name": "node_id"}},
                                   {"type": "custom_validation_failed", "message": "Custom validation failed for node",
                                    "details": "path - no such path", "extra_info": {"input_name": "path"}}]}}})
        else:
            self._answer(200, {"prompt_id": "abc", "number": 0, "node_errors": {}})

    def do_GET(self):
        if self.path == "/queue":
            listed = {name: [[number, prompt_id, {}, {}, []] for number, prompt_id in enumerate(ids)]
                      for name, ids in (("queue_running", self.running), ("queue_pending", self.pending))}
            self._answer(200, listed)
            return
        assert self.path == "/history/abc"
        if "abc" in self.running + self.pending:
            self._answer(200, {})
            return
        self._answer(200, {"abc": _history_entry("success", [], {"7": {"scenes": [
            {"filename": "nnfm_00001.ply", "subfolder": "artnvg", "type": "output"}]}})})

    def log_message(self, *args):
        pass


@pytest.fixture
def fake_server():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _FakeServer)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    _FakeServer.posted.clear()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    _FakeServer.reject = _FakeServer.partial = False
    _FakeServer.running, _FakeServer.pending = [], []


def test_main_queues_waits_and_reports(queue, fake_server, capsys):
    status = queue.main([str(NNFM_API), "--server", fake_server,
                         "--set", "6.iterations=3", "--json"])
    assert status == 0
    assert _FakeServer.posted[0][1]["prompt"]["6"]["inputs"]["iterations"] == 3
    report = json.loads(capsys.readouterr().out)
    assert report["status"] == "success" and report["outputs"][0]["file"] == "artnvg/nnfm_00001.ply"


def test_main_reports_rejections_and_unreachable_servers(queue, fake_server, capsys):
    _FakeServer.reject = True
    assert queue.main([str(NNFM_API), "--server", fake_server]) == 2
    # the node's own message: not ComfyUI's 'Custom validation failed for node: node_id - ', which names the
    # argument of the pack's check (a hidden input) as if it were an input
    assert capsys.readouterr().err.splitlines()[-2:] == [
        "node 1 (Load Gaussian Scene): Load Gaussian Scene: input 'scene_file': scene file not found: /in/x.ply",
        "node 1 (Load Gaussian Scene), input 'path': no such path"]
    closed = http.server.HTTPServer(("127.0.0.1", 0), _FakeServer)
    address = f"http://127.0.0.1:{closed.server_address[1]}"
    closed.server_close()
    assert queue.main([str(NNFM_API), "--server", address]) == 3
    assert "cannot reach the server" in capsys.readouterr().err


def test_node_errors_in_an_accepted_prompt_are_a_failure_and_the_prompt_is_withdrawn(queue, fake_server, capsys):
    _FakeServer.partial, _FakeServer.running = True, ["abc"]  # it started at once
    assert queue.main([str(NNFM_API), "--server", fake_server, "--set", "Finetune Gaussians.iterations=-1"]) == 2
    assert ("node 6 (Finetune Gaussians), input 'iterations': Value smaller than min: iterations -1 < 1"
            in capsys.readouterr().err)
    assert [path for path, _ in _FakeServer.posted] == ["/prompt", "/queue", "/interrupt"]
    assert _FakeServer.posted[1][1] == {"delete": ["abc"]} and _FakeServer.posted[2][1] == {"prompt_id": "abc"}


@pytest.mark.parametrize("running, pending, posted, done", [
    (["abc"], ["xyz"], [("/queue", {"delete": ["abc"]}), ("/interrupt", {"prompt_id": "abc"})], "interrupted it"),
    (["xyz"], ["abc"], [("/queue", {"delete": ["abc"]})], "deleted it from the queue before it started"),
])
def test_a_run_past_its_timeout_is_taken_off_the_server(queue, fake_server, capsys, running, pending, posted, done):
    """It went on running on the server after the script had given up on it. Our prompt is interrupted only when it
    is the one running, never another client's (xyz); a pending one is deleted from the queue."""
    _FakeServer.running, _FakeServer.pending = running, pending
    assert queue.main([str(NNFM_API), "--server", fake_server, "--timeout", "0"]) == 3
    assert capsys.readouterr().err.splitlines()[-1] == f"error: prompt abc did not finish within 0 s; {done}"
    assert _FakeServer.posted[1:] == posted
