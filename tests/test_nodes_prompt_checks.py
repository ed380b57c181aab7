"""The whole-prompt file checks (nodes/prompt_checks.py): a failing loader blocks every output it feeds."""

import sys
import types

import pytest

from nodes import prompt_checks
from nodes.prompt_checks import check_prompt, check_result, failed_checks


class Loader:
    @classmethod
    def check_files(cls, name="", **_other_inputs):
        return None if name == "there" else f"Loader: '{name}' is missing"


class Step:
    pass


class Output:
    OUTPUT_NODE = True


CLASSES = {"Loader": Loader, "Step": Step, "Output": Output}


def _prompt(first: str, second: str) -> dict:
    """Loader 1 -> Step 2 -> Output 3; Loader 4 -> Output 5; Output 6 on its own."""
    return {"1": {"class_type": "Loader", "inputs": {"name": first, "count": 2}},
            "2": {"class_type": "Step", "inputs": {"x": ["1", 0]}},
            "3": {"class_type": "Output", "inputs": {"images": ["2", 0]}},
            "4": {"class_type": "Loader", "inputs": {"name": second}},
            "5": {"class_type": "Output", "inputs": {"images": ["4", 0]}},
            "6": {"class_type": "Output", "inputs": {}}}


def test_a_good_prompt_passes_unchanged():
    request = {"prompt": _prompt("there", "there"), "client_id": "c"}
    assert check_prompt(dict(request), CLASSES) == request


def test_only_the_outputs_fed_by_a_failing_loader_remain_so_validation_fails_as_a_whole():
    request = check_prompt({"prompt": _prompt("gone", "there")}, CLASSES)
    assert request["partial_execution_targets"] == ["3"]
    assert failed_checks(request["prompt"], CLASSES) == {"1": "Loader: 'gone' is missing"}
    both = check_prompt({"prompt": _prompt("gone", "lost")}, CLASSES)
    assert both["partial_execution_targets"] == ["3", "5"] and both["prompt_id"] != request["prompt_id"]


def test_chosen_targets_are_kept_when_none_of_them_is_blocked():
    request = check_prompt({"prompt": _prompt("gone", "there"), "partial_execution_targets": ["5", "6"]}, CLASSES)
    assert request["partial_execution_targets"] == ["5", "6"]
    request = check_prompt({"prompt": _prompt("gone", "there"), "partial_execution_targets": ["3", "6"]}, CLASSES)
    assert request["partial_execution_targets"] == ["3"]


@pytest.fixture
def executing(monkeypatch):
    """A stand-in for ComfyUI's comfy_execution.utils whose executing context names ``context["prompt"]``."""
    context = {"prompt": None}
    module = types.ModuleType("comfy_execution.utils")
    module.get_executing_context = lambda: (None if context["prompt"] is None
                                            else types.SimpleNamespace(prompt_id=context["prompt"], node_id="?"))
    monkeypatch.setitem(sys.modules, "comfy_execution", types.ModuleType("comfy_execution"))
    monkeypatch.setitem(sys.modules, "comfy_execution.utils", module)
    return context


def test_validation_reads_the_message_of_its_own_prompt_and_node(executing):
    first = check_prompt({"prompt": _prompt("gone", "there"), "prompt_id": "p1"}, CLASSES)
    check_prompt({"prompt": _prompt("there", "lost"), "prompt_id": "p2"}, CLASSES)
    assert first["prompt_id"] == "p1"
    assert check_result("1") is True  # outside validation
    executing["prompt"] = "p1"
    assert check_result("1") == "Loader: 'gone' is missing" and check_result("4") is True
    executing["prompt"] = "p2"
    assert check_result("1") is True and check_result("4") == "Loader: 'lost' is missing"


def test_only_the_latest_prompts_are_remembered(executing):
    for number in range(prompt_checks._KEPT_PROMPTS + 5):
        check_prompt({"prompt": _prompt("gone", "there"), "prompt_id": f"q{number}"}, CLASSES)
    assert len(prompt_checks._results) == prompt_checks._KEPT_PROMPTS
    executing["prompt"] = "q0"
    assert check_result("1") is True


def test_values_outside_a_nodes_declared_ranges_block_every_output_it_feeds():
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    finetune = {"class_type": "ArtNVGFinetuneGaussians", "inputs": {"iterations": -1, "scene": ["9", 0]}}
    prompt = {"1": finetune, "2": {"class_type": "Output", "inputs": {"scene": ["1", 0]}},
              "3": {"class_type": "ArtNVGSaveGaussianScene", "inputs": {"format": "obj", "filename_prefix": "a"}},
              "4": {"class_type": "Output", "inputs": {"x": ["3", 0]}}, "5": {"class_type": "Output", "inputs": {}}}
    request = check_prompt({"prompt": prompt}, classes)
    assert failed_checks(prompt, classes) == {
        "1": "Finetune Gaussians: input 'iterations': -1 is outside 0 to 100000",
        "3": "Save Gaussian Scene: input 'format': expected one of ['ply', 'spz', 'splat', 'ksplat'], got 'obj'"}
    assert request["partial_execution_targets"] == ["2", "3", "4"]  # the others (5) do not run either
    finetune["inputs"]["iterations"], prompt["3"]["inputs"]["format"] = 10, "spz"
    assert failed_checks(prompt, classes) == {}
    finetune["inputs"]["iterations"] = float("nan")
    assert failed_checks(prompt, classes)["1"] == "Finetune Gaussians: input 'iterations': expected a finite number, got nan"
    finetune["inputs"]["iterations"], finetune["inputs"]["optimize"] = 10, "everything"  # choices declared as a tuple
    assert failed_checks(prompt, classes)["1"] == (
        "Finetune Gaussians: input 'optimize': expected one of ['appearance', 'all'], got 'everything'")


def test_validation_repeats_no_problem_comfyui_reports_itself(executing):
    """A value out of its range or choices: ComfyUI's own message alone (the node's VALIDATE_INPUTS answers True;
    its outputs are blocked all the same). A FLOAT NaN, which ComfyUI's comparisons let through: the pack's."""
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    finetune = {"class_type": "ArtNVGFinetuneGaussians", "inputs": {"iterations": -1}}
    prompt = {"1": finetune, "2": {"class_type": "Output", "inputs": {"scene": ["1", 0]}},
              "3": {"class_type": "Output", "inputs": {}}}
    for values, shown in [({"iterations": -1}, True), ({"optimize": "everything"}, True),
                          ({"iterations": float("nan")}, True),  # ComfyUI's int() refuses it
                          ({"l1_weight": float("inf")}, True),  # over its max
                          ({"l1_weight": float("nan")}, "Finetune Gaussians: input 'l1_weight': expected a finite "
                                                        "number, got nan")]:
        finetune["inputs"] = values
        request = check_prompt({"prompt": prompt}, classes)
        executing["prompt"] = request["prompt_id"]
        assert request["partial_execution_targets"] == ["2"] and check_result("1") == shown, values


def test_a_model_loader_whose_file_is_not_in_its_folder_blocks_its_outputs(monkeypatch):
    """ComfyUI's own loaders (and Load CSGO) are checked by folder: ComfyUI names the file itself."""
    monkeypatch.setattr(prompt_checks, "model_file_path",
                        lambda folder, name: f"/models/{folder}/{name}" if name == "sdxl.safetensors" else None)
    prompt = {"1": {"class_type": "CheckpointLoaderSimple", "inputs": {"ckpt_name": "sdxl.safetensors"}},
              "2": {"class_type": "ArtNVGLoadCSGO", "inputs": {"csgo_name": "csgo_4_32.bin"}},
              "3": {"class_type": "Output", "inputs": {"model": ["1", 0], "csgo": ["2", 0]}},
              "4": {"class_type": "Output", "inputs": {}}}
    assert failed_checks(prompt, CLASSES) == {"2": "'csgo_4_32.bin' is not in the 'csgo' model folder"}
    request = check_prompt({"prompt": prompt}, CLASSES)
    assert request["partial_execution_targets"] == ["3"]


def test_a_style_image_a_load_image_feeds_in_is_checked_before_the_graph_runs(tmp_path, monkeypatch):
    """The rule Apply CSGO and Finetune Gaussians apply when they run (artnvg_core.style_image), applied to the
    file of a stock Load Image linked straight to their style_image: the graph is refused before any work."""
    from PIL import Image

    from nodes import NODE_CLASS_MAPPINGS

    monkeypatch.chdir(tmp_path)
    (tmp_path / "input").mkdir()
    (tmp_path / "elsewhere").mkdir()
    for folder in ("input", "elsewhere"):
        Image.new("RGB", (20000, 2)).save(tmp_path / folder / "line.png")
    Image.new("RGB", (64, 48)).save(tmp_path / "input" / "fine.png")
    classes = {**NODE_CLASS_MAPPINGS, "LoadImage": Step, "Output": Output}
    prompt = {"1": {"class_type": "LoadImage", "inputs": {"image": "line.png"}},
              "2": {"class_type": "ArtNVGFinetuneGaussians", "inputs": {"style_image": ["1", 0], "iterations": 5}},
              "3": {"class_type": "ArtNVGApplyCSGO", "inputs": {"style_image": ["1", 0]}},
              "4": {"class_type": "Output", "inputs": {"scene": ["2", 0]}}, "5": {"class_type": "Output", "inputs": {}}}
    rule = "image size: 20000x2 pixels; a style image may be at most 32 times as long as it is wide"
    failures = failed_checks(prompt, classes)
    assert sorted(failures) == ["2", "3"] and failures["2"].startswith(f"Finetune Gaussians: input 'style_image': {rule}")
    assert failures["3"].startswith(f"Apply CSGO: input 'style_image': {rule}")
    assert check_prompt({"prompt": prompt}, classes)["partial_execution_targets"] == ["4"]
    for image in ("fine.png", "missing.png", "../elsewhere/line.png"):  # the last two: Load Image's to refuse
        prompt["1"]["inputs"]["image"] = image
        assert failed_checks(prompt, classes) == {}, image
    prompt["1"] = {"class_type": "Step", "inputs": {"image": "line.png"}}  # another node's IMAGE: checked as it runs
    assert failed_checks(prompt, classes) == {}
