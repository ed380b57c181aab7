"""The node pack's contract with ComfyUI, checked without ComfyUI installed.

ComfyUI loads the pack folder as a package (its ``__init__.py`` with the folder as search
location) and reads NODE_CLASS_MAPPINGS / NODE_DISPLAY_NAME_MAPPINGS; each class declares
INPUT_TYPES, RETURN_TYPES, FUNCTION and CATEGORY. Saved workflows store widget values by
position, so input names and order are pinned here: changing them breaks users' workflows.
"""

import importlib.util
import inspect
import re
import sys
from pathlib import Path
from unittest import mock

import numpy
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
WIDGET_TYPES = {"INT", "FLOAT", "STRING", "BOOLEAN"}
CORE_TYPES = {"IMAGE", "MASK", "SPLAT", "GAUSSIAN", "MODEL", "CONTROL_NET", "CLIP_VISION", "CONDITIONING",
              "VAE"}  # ComfyUI's own link types the nodes take

PUBLIC_INPUTS = {
    "ArtNVGLoadGaussianScene": ["scene_file", "path", "drop_invalid", "spz_axes", "cameras"],
    "ArtNVGLoadCameras": ["camera_source", "path"],
    "ArtNVGCamerasAroundScene": ["scene", "count", "fov_deg", "width", "height", "up", "elevations", "distance_factor"],
    "ArtNVGRenderViews": ["scene", "cameras", "scale", "stride", "views", "key_views"],
    "ArtNVGRenderCameraPath": ["scene", "cameras", "path", "scale", "num_frames", "key_views", "frames_per_segment",
                               "loop"],
    "ArtNVGGroupNeighbouringViews": ["cameras", "group_size", "context"],
    "ArtNVGLoadCSGO": ["csgo_name"],
    "ArtNVGApplyCSGO": ["model", "control_net", "csgo", "clip_vision", "style_image", "style_scale", "content_scale",
                        "content_routing"],
    "ArtNVGNVAttentionPatch": ["model", "enabled", "levels", "nearest_views", "kv_downsample"],
    "ArtNVGSampleGroup": ["model", "positive", "negative", "vae", "control_net", "content_views", "groups",
                          "group_index", "seed", "steps", "cfg", "sampler_name", "scheduler", "denoise",
                          "control_scale", "resolution", "size_rule", "cfg_until"],
    "ArtNVGFinetuneGaussians": ["scene", "cameras", "style_image", "iterations", "optimize", "l1_weight",
                                "ssim_weight", "nnfm_weight", "content_weight", "tv_weight", "seed", "stylized_views",
                                "nnfm_max_side", "color_transfer", "preset", "views_per_step", "nnfm_search", "selection"],
    "ArtNVGSelectGaussians": ["scene", "mode", "bounds", "cameras", "mask", "views"],
    "ArtNVGBlendStylization": ["original", "stylized", "strength", "selection", "cameras", "view", "preview_strengths"],
    "ArtNVGSaveGaussianScene": ["scene", "filename_prefix", "format", "spz_version"],
    "ArtNVGSceneToSplat": ["scene"],
    "ArtNVGSplatToScene": ["splat"],
}
PUBLIC_OUTPUTS = {
    "ArtNVGLoadGaussianScene": ("ARTNVG_SCENE",),
    "ArtNVGLoadCameras": ("ARTNVG_CAMERAS",),
    "ArtNVGCamerasAroundScene": ("ARTNVG_CAMERAS",),
    "ArtNVGRenderViews": ("IMAGE", "ARTNVG_CAMERAS"),
    "ArtNVGRenderCameraPath": ("IMAGE", "ARTNVG_CAMERAS"),
    "ArtNVGGroupNeighbouringViews": ("ARTNVG_GROUPS",),
    "ArtNVGLoadCSGO": ("ARTNVG_CSGO",),
    "ArtNVGApplyCSGO": ("MODEL", "CONTROL_NET"),
    "ArtNVGNVAttentionPatch": ("MODEL",),
    "ArtNVGSampleGroup": ("IMAGE",),
    "ArtNVGFinetuneGaussians": ("ARTNVG_SCENE",),
    "ArtNVGSelectGaussians": ("ARTNVG_SELECTION",),
    "ArtNVGBlendStylization": ("ARTNVG_SCENE", "IMAGE"),
    "ArtNVGSaveGaussianScene": ("STRING", "LOAD3D_CAMERA"),  # + "FILE_3D_SPLAT_ANY" on a ComfyUI with 3D file types (tests/test_nodes_splat.py)
    "ArtNVGSceneToSplat": ("SPLAT",),  # the core's name: "GAUSSIAN" before its rename
    "ArtNVGSplatToScene": ("ARTNVG_SCENE",),
}


def _load_pack_like_comfyui(name: str = "artnvg_pack_under_test"):
    """Import the repository folder the way ComfyUI imports a custom node folder."""
    spec = importlib.util.spec_from_file_location(name, REPO / "__init__.py", submodule_search_locations=[str(REPO)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    finally:
        for key in [k for k in sys.modules if k == name or k.startswith(name + ".")]:
            del sys.modules[key]
    return module


def test_entry_file_imported_alone_loads_nothing():
    """pytest imports the folder's __init__.py as a plain module named ``__init__`` when the folder's
    name is not an identifier (custom_nodes/artnvg-comfyui): it must import cleanly, as no pack."""
    spec = importlib.util.spec_from_file_location("__init__", REPO / "__init__.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert not hasattr(module, "NODE_CLASS_MAPPINGS")


@pytest.fixture(scope="module")
def pack():
    return _load_pack_like_comfyui()


def _all_inputs(node) -> dict:
    types = node.INPUT_TYPES()
    assert set(types) <= {"required", "optional", "hidden"}
    return {**types.get("required", {}), **types.get("optional", {})}


def test_pack_exports_exactly_the_mappings(pack):
    assert set(pack.__all__) == {"NODE_CLASS_MAPPINGS", "NODE_DISPLAY_NAME_MAPPINGS"}
    assert set(pack.NODE_CLASS_MAPPINGS) == set(PUBLIC_INPUTS)
    assert set(pack.NODE_DISPLAY_NAME_MAPPINGS) == set(PUBLIC_INPUTS)
    names = list(pack.NODE_DISPLAY_NAME_MAPPINGS.values())
    assert len(set(names)) == len(names) and all(names)


def test_public_inputs_and_outputs_are_pinned(pack):
    for name, node in pack.NODE_CLASS_MAPPINGS.items():
        assert list(_all_inputs(node)) == PUBLIC_INPUTS[name], name
        assert tuple(node.RETURN_TYPES) == PUBLIC_OUTPUTS[name], name


def _check_widget(where: str, kind, options: dict) -> None:
    """A widget (a value typed or picked on the node) has a default within its range and a tooltip."""
    default = options.get("default")
    assert isinstance(options.get("tooltip"), str) and options["tooltip"].strip(), f"{where}: no tooltip"
    if kind == "COMBO":
        kind = options["options"]
    if isinstance(kind, (list, tuple)):
        assert all(isinstance(choice, str) for choice in kind), where
        assert default is None or default in kind, where
    elif kind == "INT":
        assert isinstance(default, int) and not isinstance(default, bool), where
        assert options.get("min", default) <= default <= options.get("max", default), where
    elif kind == "FLOAT":
        assert isinstance(default, float), where
        assert options.get("min", default) <= default <= options.get("max", default), where
    elif kind == "STRING":
        assert isinstance(default, str), where
    elif kind == "BOOLEAN":
        assert isinstance(default, bool), where


def test_every_node_contract_is_valid_and_consistent(pack):
    produced = set()
    consumed = set()
    for name, node in pack.NODE_CLASS_MAPPINGS.items():
        assert node.CATEGORY == "ArtNVG"
        assert isinstance(node.DESCRIPTION, str) and node.DESCRIPTION.strip()
        inputs = _all_inputs(node)
        required = list(node.INPUT_TYPES()["required"])
        for input_name, spec in inputs.items():
            assert isinstance(spec, tuple) and 1 <= len(spec) <= 2, (name, input_name)
            kind, options = spec[0], (spec[1] if len(spec) == 2 else {})
            if isinstance(kind, (list, tuple)) or kind in WIDGET_TYPES or kind == "COMBO":
                _check_widget(f"{name}.{input_name}", kind, options)
            else:
                assert kind in CORE_TYPES or kind.startswith("ARTNVG_"), (name, input_name, kind)
                consumed.add(kind)

        assert isinstance(node.RETURN_TYPES, tuple)
        assert len(getattr(node, "RETURN_NAMES", ())) == len(node.RETURN_TYPES), name
        produced.update(node.RETURN_TYPES)
        assert node.RETURN_TYPES or getattr(node, "OUTPUT_NODE", False), name  # a node without outputs saves

        parameters = inspect.signature(getattr(node, node.FUNCTION)).parameters
        hidden = list(node.INPUT_TYPES().get("hidden", {}))
        # every node answers ComfyUI's validation with the pack's checks of the prompt (nodes/prompt_checks.py),
        # through one input, which labels the message: its id, or the one input its messages name (a file list, a
        # COMBO, or text: ComfyUI checks neither); ComfyUI still holds every other input to its range and choices
        assert node.INPUT_TYPES()["hidden"] == {"node_id": "UNIQUE_ID"}, name
        assert list(inspect.signature(node.VALIDATE_INPUTS).parameters) == [node.REPORTED_INPUT], name
        assert node.REPORTED_INPUT == "node_id" or node.INPUT_TYPES()["required"][node.REPORTED_INPUT][0] in (
            "COMBO", "STRING"), name
        others = [spec[0] for key, spec in inputs.items() if key != node.REPORTED_INPUT]
        assert node.REPORTED_INPUT == "node_id" or all(  # no other input that a message could name: choices that
            isinstance(kind, list) or kind.startswith("ARTNVG_") for kind in others), name  # ComfyUI checks, links
        assert list(parameters)[1:] == list(inputs) + hidden, name  # self, then every input in order, then hidden
        for hidden_name in hidden:
            assert parameters[hidden_name].default is None, (name, hidden_name)
        for input_name in list(inputs)[len(required):]:
            assert parameters[input_name].default is not inspect.Parameter.empty, (name, input_name)
        for hook in ("VALIDATE_INPUTS", "IS_CHANGED"):
            if hasattr(node, hook):
                hook_parameters = inspect.signature(getattr(node, hook)).parameters
                assert set(hook_parameters) <= set(inputs) | set(hidden), (name, hook)
                assert all(p.default is not inspect.Parameter.empty
                           for key, p in hook_parameters.items() if key not in required), (name, hook)
    assert {kind for kind in consumed if kind.startswith("ARTNVG_")} <= produced


FILE_CHOICES = {"scene_file", "camera_source", "csgo_name"}


def test_only_file_choices_escape_comfyuis_list_check_and_their_loaders_check_them(pack):
    """ComfyUI compares a value with its choices only when they are a list (a tuple or a COMBO escapes): every
    choice input is a list but the file lists, COMBOs whose nodes check the files themselves (check_files, run
    on the whole prompt: nodes/prompt_checks.py)."""
    for name, node in pack.NODE_CLASS_MAPPINGS.items():
        assert not [input_name for input_name, spec in _all_inputs(node).items() if isinstance(spec[0], tuple)], name
        combos = {input_name for input_name, spec in _all_inputs(node).items() if spec[0] == "COMBO"}
        assert combos <= FILE_CHOICES, name
        if combos:
            checked = set(inspect.signature(node.check_files).parameters)
            assert combos <= checked and "_other_inputs" in checked, name


def _stand_in(kind, options: dict):
    """A value the run-time check lets through for an input of ``kind``: its default, a mock of its run type or a
    tensor of its rank (nodes/node_types.py RUN_TYPES), its first choice, a file name, else an object (a MODEL...)."""
    from nodes.node_types import RUN_TYPES

    expected = RUN_TYPES.get(kind) if isinstance(kind, str) else None
    if "default" in options:
        return options["default"]
    if expected is not None:
        return torch.zeros((1,) * expected.ranks[0]) if expected.ranks else mock.Mock(spec=expected.cls)
    return next(iter(kind), "") if isinstance(kind, list) else "" if kind == "COMBO" else object()


def test_every_node_refuses_an_input_not_of_its_declared_type_before_any_work():
    """Another pack's output declared as type * passes ComfyUI's link check: a node was given, say, a string for its
    scene and failed deep inside with an AttributeError. Each custom-typed input (and IMAGE, MASK) is checked when
    the node runs, by the base class, from the declared types."""
    from nodes import NODE_CLASS_MAPPINGS
    from nodes.node_errors import NodeInputError
    from nodes.node_types import RUN_TYPES

    checked = set()
    for node in NODE_CLASS_MAPPINGS.values():
        types = node.INPUT_TYPES()
        declared = {**types["required"], **types.get("optional", {})}
        fine = {name: _stand_in(*(*entry, {})[:2]) for name, entry in types["required"].items()}
        for name, (kind, *_) in declared.items():
            if not isinstance(kind, str) or kind not in RUN_TYPES:
                continue
            checked.add(kind)
            expected = RUN_TYPES[kind]
            wrong = [({"scene": 1}, "dict")] + ([(None, "NoneType")] if name in types["required"] else [])
            if expected.ranks:
                wrong.append((torch.zeros(2, 1, 1, 1, 1), "a tensor of shape [2, 1, 1, 1, 1]"))
            for value, got in wrong:
                start = re.escape(f"{node.DISPLAY_NAME}: input '{name}': expected {kind}, ")
                with pytest.raises(NodeInputError, match=f"^{start}.*{expected.cls.__name__}.*; got {re.escape(got)}$"):
                    getattr(node(), node.FUNCTION)(**{**fine, name: value})
    assert checked == set(RUN_TYPES)  # every run type is some node's input


def test_a_number_through_a_link_is_taken_as_comfyui_converts_a_prompts_but_never_loses_a_fraction():
    """Another pack's output of type * may give an INT input a float: ComfyUI passes it as it is, and the node's int()
    made 2.5 a silent 2. A whole float (3.0) is taken as ComfyUI takes a prompt's value (int(3.0)), a fraction or a
    bool is refused naming the node and input, when the node runs and, for a prompt's value (which ComfyUI itself
    would make 2), before anything runs."""
    from nodes.camera_nodes import CamerasAroundScene
    from nodes.node_errors import NodeInputError
    from tests.test_activated import random_scene

    def place(**changes):
        values = dict(count=3, fov_deg=40.0, width=16, height=16, up="+z", elevations="10", distance_factor=1.0)
        return CamerasAroundScene().place(random_scene(n=50, degree=0), **(values | changes))[0]

    cameras = place(count=3.0, width=numpy.float32(16), fov_deg=40, distance_factor=1)
    assert len(cameras) == 3 and (cameras.width, type(cameras.width)) == (16, int)
    assert torch.equal(cameras.world_to_cam, place().world_to_cam)
    for name, value, problem in [("count", 2.5, "expected a whole number, got 2.5"),
                                 ("width", float("nan"), "expected a whole number, got nan"),
                                 ("count", numpy.float64(2.5), "expected a whole number, got 2.5"),
                                 ("count", True, "expected a number, got True"),
                                 ("fov_deg", False, "expected a number, got False"),
                                 ("count", "3", "expected INT, int; got str")]:
        with pytest.raises(NodeInputError, match=f"^Cameras Around Scene: input '{name}': {problem}$"):
            place(**{name: value})
    assert CamerasAroundScene.check_values(count=3.0, width="16") is None  # ComfyUI makes them 3 and 16 itself
    refused = "Cameras Around Scene: input 'count': expected a whole number, got 2.5"
    assert CamerasAroundScene.check_values(count=2.5) == CamerasAroundScene.unreported_value(count=2.5) == refused
    assert CamerasAroundScene.unreported_value(count={"__value__": True}) == (
        "Cameras Around Scene: input 'count': expected a number, got True")


def test_numbers_reach_the_node_as_their_declared_types():
    """What the node's function is given: an INT's whole float (3.0, numpy's too) as the int 3, a FLOAT's int as a
    float, as ComfyUI converts a prompt's values; the node need not convert them itself."""
    from nodes.node_base import ArtNVGNode

    class Numbers(ArtNVGNode):
        """Returns its numbers."""

        DISPLAY_NAME = "Numbers"
        FUNCTION = "run"
        RETURN_TYPES = ()
        REQUIRED = {"count": ("INT", {"default": 1}), "scale": ("FLOAT", {"default": 1.0})}

        def run(self, count, scale, node_id=None):
            return count, scale

    for count, scale in [(3.0, 1), (numpy.float32(3), numpy.int64(1)), (3, 1.0)]:
        given = Numbers().run(count, scale=scale)
        assert given == (3, 1.0) and (type(given[0]), type(given[1])) == (int, float), (count, scale)
