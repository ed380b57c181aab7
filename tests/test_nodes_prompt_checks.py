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
    """A stand-in for ComfyUI's comfy_execution.utils whose executing context names ``context["prompt"]`` and
    ``context["node"]`` (the node ComfyUI validates)."""
    context = {"prompt": None, "node": "1"}
    module = types.ModuleType("comfy_execution.utils")
    module.get_executing_context = lambda: (None if context["prompt"] is None else types.SimpleNamespace(
        prompt_id=context["prompt"], node_id=context["node"], list_index=None))
    monkeypatch.setitem(sys.modules, "comfy_execution", types.ModuleType("comfy_execution"))
    monkeypatch.setitem(sys.modules, "comfy_execution.utils", module)
    return context


def test_validation_reads_the_message_of_its_own_prompt_and_node(executing):
    first = check_prompt({"prompt": _prompt("gone", "there"), "prompt_id": "p1"}, CLASSES)
    check_prompt({"prompt": _prompt("there", "lost"), "prompt_id": "p2"}, CLASSES)
    assert first["prompt_id"] == "p1"
    assert check_result() is True  # outside validation
    executing["prompt"] = "p1"
    assert check_result() == "Loader: 'gone' is missing"
    executing["node"] = "4"
    assert check_result() is True
    executing["prompt"] = "p2"
    assert check_result() == "Loader: 'lost' is missing"
    executing["node"] = "1"
    assert check_result() is True


def test_only_the_latest_prompts_are_remembered(executing):
    for number in range(prompt_checks._KEPT_PROMPTS + 5):
        check_prompt({"prompt": _prompt("gone", "there"), "prompt_id": f"q{number}"}, CLASSES)
    assert len(prompt_checks._results) == prompt_checks._KEPT_PROMPTS
    executing["prompt"] = "q0"
    assert check_result() is True


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
    assert failed_checks(prompt, classes)["1"] == (
        "Finetune Gaussians: input 'iterations': expected a value of type INT, got nan")  # ComfyUI's int() refuses it
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
        assert request["partial_execution_targets"] == ["2"] and check_result() == shown, values


@pytest.fixture
def model_folders(tmp_path, monkeypatch):
    """ComfyUI's model folders that the stock loaders read (checkpoints, loras, vae...) under tmp_path/models, empty."""
    from test_nodes_comfy_bridge import FakeComfy

    from nodes.model_files import STOCK_LOADERS

    for name, module in FakeComfy(tmp_path).modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    folder_paths = sys.modules["folder_paths"]
    folder_paths.get_annotated_filepath = lambda name: str(tmp_path / "input" / name)  # Load Image's file
    for folder in {model_file.folder for model_files in STOCK_LOADERS.values() for model_file in model_files}:
        folder_paths.folder_names_and_paths[folder] = ([str(tmp_path / "models" / folder)], {".safetensors", ".yaml"})
        (tmp_path / "models" / folder).mkdir(parents=True)
    return tmp_path / "models"


def test_a_model_loader_whose_file_is_not_in_its_folder_blocks_its_outputs(model_folders):
    """ComfyUI's own loaders are checked by folder: ComfyUI names the file itself ("Value not in list"), so
    their VALIDATE_INPUTS (none) has nothing to add; Load CSGO's file is its check_files' (test_nodes_model_files)."""
    from nodes import NODE_CLASS_MAPPINGS

    (model_folders / "checkpoints" / "sdxl.safetensors").write_bytes(b"")
    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"1": {"class_type": "CheckpointLoaderSimple", "inputs": {"ckpt_name": "sdxl.safetensors"}},
              "2": {"class_type": "ControlNetLoader", "inputs": {"control_net_name": "tile.safetensors"}},
              "3": {"class_type": "Output", "inputs": {"model": ["1", 0], "control_net": ["2", 0]}},
              "4": {"class_type": "Output", "inputs": {}}}
    missing = ("ControlNetLoader (node #2, ControlNetLoader): input 'control_net_name': 'tile.safetensors' is not in "
               "the 'controlnet' model folder")
    assert list(failed_checks(prompt, classes)) == ["2"] and failed_checks(prompt, classes)["2"].startswith(missing)
    request = check_prompt({"prompt": prompt}, classes)
    assert request["partial_execution_targets"] == ["3"]
    assert prompt_checks._results[request["prompt_id"]] == {}  # ComfyUI's message alone
    # a name as the editor wraps a list value, which ComfyUI unwraps: the check read the wrapper
    prompt["1"]["inputs"]["ckpt_name"] = {"__value__": "sdxl.safetensors"}
    prompt["2"]["inputs"]["control_net_name"] = {"__value__": "tile.safetensors"}
    assert list(failed_checks(prompt, classes)) == ["2"] and failed_checks(prompt, classes)["2"].startswith(missing)
    prompt["2"]["inputs"]["control_net_name"] = ["4", 0]  # a name another node gives: known as the graph runs
    assert failed_checks(prompt, classes) == {}


def _full_workflow() -> dict:
    """The shipped full-method API workflow (ArtNVG_3)."""
    import json

    from test_workflows import FULL_API

    return json.loads(FULL_API.read_text())


def _model_file_messages(prompt: dict) -> dict[str, str]:
    """Node id -> message of the prompt's nodes that failed for a model file: the stock loaders, the pack's nodes they
    feed (the scene and camera loaders, whose demo files are not in this input folder, left out)."""
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "PreviewImage": Output, "SaveImage": Output}
    return {node_id: message for node_id, message in failed_checks(prompt, classes).items()
            if prompt[node_id]["class_type"] not in ("ArtNVGLoadGaussianScene", "ArtNVGLoadCameras")}


def test_a_pack_node_fed_by_a_stock_loader_whose_file_is_missing_names_its_input_the_loader_and_the_file(
        model_folders, executing):
    """The shipped full workflow, its SDXL checkpoint missing: ComfyUI's "Value not in list: ckpt_name:
    'sd_xl_base_1.0.safetensors' not in []" on Load Checkpoint was all it said. Apply CSGO (its model) and Sample
    Group (its vae), which Load Checkpoint feeds straight, fail too, each once, naming their input, the loader, the
    file, the folder looked in and where to get it; nodes fed through a node of the pack (NV-Attention Patch) do
    not repeat it."""
    from nodes import NODE_CLASS_MAPPINGS

    from artnvg_core.diffusion.model_files import SDXL_BASE

    for folder, name in (("controlnet", "TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors"),
                         ("clip_vision", "CLIP-ViT-bigG-14-laion2B-39B-b160k.safetensors")):
        (model_folders / folder / name).write_bytes(b"")
    sys.modules["folder_paths"].folder_names_and_paths["csgo"] = ([str(model_folders / "csgo")], {".bin"})
    (model_folders / "csgo").mkdir()
    (model_folders / "csgo" / "csgo_4_32.bin").write_bytes(b"")
    prompt = _full_workflow()
    folder = model_folders / "checkpoints"
    loader = ("Load Checkpoint (node #4, CheckpointLoaderSimple): input 'ckpt_name': 'sd_xl_base_1.0.safetensors' is "
              f"not in the 'checkpoints' model folder (looked in {folder}; found nothing). Get the SDXL 1.0 base "
              f"checkpoint from {SDXL_BASE.url}: `hf download {SDXL_BASE.repo} sd_xl_base_1.0.safetensors "
              f"--local-dir {folder}` saves it as {folder / 'sd_xl_base_1.0.safetensors'}")
    assert _model_file_messages(prompt) == {"4": loader, "9": f"Apply CSGO: input 'model' comes from {loader}",
                                            "10": f"Sample Group: input 'vae' comes from {loader}"}
    request = check_prompt({"prompt": prompt}, {**NODE_CLASS_MAPPINGS, "PreviewImage": Output, "SaveImage": Output})
    executing["prompt"], executing["node"] = request["prompt_id"], "9"
    assert NODE_CLASS_MAPPINGS["ArtNVGApplyCSGO"].VALIDATE_INPUTS() == f"Apply CSGO: input 'model' comes from {loader}"
    executing["node"] = "4"  # ComfyUI's own node: its "Value not in list" alone
    assert check_result() is True
    (folder / "sd_xl_base_1.0.safetensors").write_bytes(b"")  # the file there: nothing changes
    assert _model_file_messages(prompt) == {}


def test_a_loader_feeding_through_lora_loaders_is_named_once_per_node_with_each_input_it_feeds(model_folders):
    """Load Checkpoint -> Load LoRA -> Load LoRA -> a node of the pack, another input of it straight from Load
    Checkpoint: a line per missing file, each naming the node's inputs it reaches; a title left out names the type."""
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"1": {"class_type": "CheckpointLoaderSimple", "inputs": {"ckpt_name": "mine.safetensors"}},
              "2": {"class_type": "LoraLoader", "inputs": {"lora_name": "ink.safetensors", "model": ["1", 0],
                                                            "clip": ["1", 1]}, "_meta": {"title": "Ink LoRA"}},
              "3": {"class_type": "LoraLoader", "inputs": {"lora_name": "there.safetensors", "model": ["2", 0],
                                                            "clip": ["2", 1]}},
              "4": {"class_type": "ArtNVGSampleGroup", "inputs": {"model": ["3", 0], "vae": ["1", 2]}},
              "5": {"class_type": "Output", "inputs": {"images": ["4", 0]}}}
    (model_folders / "loras" / "there.safetensors").write_bytes(b"")
    lines = failed_checks(prompt, classes)["4"].split("\n")
    assert len(lines) == 2
    assert lines[0].startswith("Sample Group: input 'model' comes from Ink LoRA (node #2, LoraLoader): input "
                               "'lora_name': 'ink.safetensors' is not in the 'loras' model folder")
    assert lines[0].endswith(f"Save a LoRA trained on SDXL 1.0 as {model_folders / 'loras' / 'ink.safetensors'}, e.g. "
                             "the Pixel Art XL style LoRA from https://huggingface.co/nerijs/pixel-art-xl/blob/main/"
                             "pixel-art-xl.safetensors (`hf download nerijs/pixel-art-xl pixel-art-xl.safetensors`)")
    assert lines[1].startswith("Sample Group: inputs 'model', 'vae' come from CheckpointLoaderSimple (node #1, "
                               "CheckpointLoaderSimple): input 'ckpt_name': 'mine.safetensors' is not in ")
    assert "Save an SDXL 1.0 checkpoint (the base or a fine-tune of it" in lines[1]
    assert sorted(failed_checks(prompt, classes)) == ["1", "2", "4"]


def test_every_comfyui_loader_that_feeds_a_node_of_the_pack_is_followed_through_the_loaders_links(model_folders):
    """Load Diffusion Model -> LoraLoaderModelOnly -> Apply CSGO's model, the same UNet -> Load ControlNet Model (diff)
    -> its control_net, Load VAE -> Sample Group's vae: these loaders were not followed, so Apply CSGO and Sample
    Group said nothing (ComfyUI's "Value not in list" on each loader alone) and the outputs they did not feed ran."""
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"1": {"class_type": "UNETLoader", "inputs": {"unet_name": "sdxl_unet.safetensors", "weight_dtype":
                                                            "default"}, "_meta": {"title": "SDXL UNet"}},
              "2": {"class_type": "LoraLoaderModelOnly", "inputs": {"lora_name": "ink.safetensors", "model": ["1", 0],
                                                                    "strength_model": 1.0}},
              "3": {"class_type": "DiffControlNetLoader", "inputs": {"control_net_name": "tile.safetensors",
                                                                     "model": ["1", 0]}},
              "4": {"class_type": "VAELoader", "inputs": {"vae_name": "sdxl_vae.safetensors"}},
              "5": {"class_type": "ArtNVGApplyCSGO", "inputs": {"model": ["2", 0], "control_net": ["3", 0]}},
              "6": {"class_type": "ArtNVGSampleGroup", "inputs": {"model": ["5", 0], "control_net": ["5", 1],
                                                                  "vae": ["4", 0]}},
              "7": {"class_type": "Output", "inputs": {"images": ["6", 0]}},
              "8": {"class_type": "Output", "inputs": {}}}
    (model_folders / "controlnet" / "tile.safetensors").write_bytes(b"")
    failed = failed_checks(prompt, classes)
    assert sorted(failed) == ["1", "2", "4", "5", "6"]
    unets, vaes = model_folders / "diffusion_models", model_folders / "vae"
    unet = (f"SDXL UNet (node #1, UNETLoader): input 'unet_name': 'sdxl_unet.safetensors' is not in the "
            f"'diffusion_models' model folder (looked in {unets}; found nothing). Save an SDXL 1.0 UNet alone (the "
            f"base's or a fine-tune's, in ComfyUI's or diffusers' layout) as {unets / 'sdxl_unet.safetensors'}, e.g. "
            "the SDXL 1.0 base's UNet (diffusers layout, fp16) from https://huggingface.co/stabilityai/stable-diffusion-"
            "xl-base-1.0/blob/main/unet/diffusion_pytorch_model.fp16.safetensors (`hf download stabilityai/stable-"
            "diffusion-xl-base-1.0 unet/diffusion_pytorch_model.fp16.safetensors`)")
    lora = failed["2"]
    assert lora.startswith("LoraLoaderModelOnly (node #2, LoraLoaderModelOnly): input 'lora_name': 'ink.safetensors' "
                           "is not in the 'loras' model folder") and "Save a LoRA trained on SDXL 1.0 as" in lora
    assert failed["5"].split("\n") == [f"Apply CSGO: input 'model' comes from {lora}",
                                       f"Apply CSGO: inputs 'model', 'control_net' come from {unet}"]
    assert failed["6"] == (
        "Sample Group: input 'vae' comes from VAELoader (node #4, VAELoader): input 'vae_name': 'sdxl_vae.safetensors' "
        f"is not in the 'vae' model folder (looked in {vaes}; found nothing). Get the SDXL VAE, fp16-safe from "
        "https://huggingface.co/madebyollin/sdxl-vae-fp16-fix/blob/main/sdxl_vae.safetensors: `hf download "
        f"madebyollin/sdxl-vae-fp16-fix sdxl_vae.safetensors --local-dir {vaes}` saves it as "
        f"{vaes / 'sdxl_vae.safetensors'}")
    assert check_prompt({"prompt": prompt}, classes)["partial_execution_targets"] == ["7"]


def test_a_loader_with_two_files_is_named_once_per_missing_file(model_folders):
    """Load Checkpoint With Config (CheckpointLoader): its config and its checkpoint, each a line."""
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"1": {"class_type": "CheckpointLoader", "inputs": {"config_name": "v1-inference.yaml",
                                                                 "ckpt_name": "sdxl.safetensors"}},
              "2": {"class_type": "ArtNVGNVAttentionPatch", "inputs": {"model": ["1", 0]}},
              "3": {"class_type": "Output", "inputs": {"model": ["2", 0]}}}
    configs = model_folders / "configs"
    loader = "CheckpointLoader (node #1, CheckpointLoader)"
    config = (f"{loader}: input 'config_name': 'v1-inference.yaml' is not in the 'configs' model folder (looked in "
              f"{configs}; found nothing). Get the Stable Diffusion inference config from https://huggingface.co/"
              "stable-diffusion-v1-5/stable-diffusion-v1-5/blob/main/v1-inference.yaml: `hf download stable-diffusion-"
              f"v1-5/stable-diffusion-v1-5 v1-inference.yaml --local-dir {configs}` saves it as "
              f"{configs / 'v1-inference.yaml'}")
    checkpoint = f"{loader}: input 'ckpt_name': 'sdxl.safetensors' is not in the 'checkpoints' model folder"
    lines = failed_checks(prompt, classes)["2"].split("\n")
    assert lines[0] == f"NV-Attention Patch Model: input 'model' comes from {config}" and len(lines) == 2
    assert lines[1].startswith(f"NV-Attention Patch Model: input 'model' comes from {checkpoint}")
    assert failed_checks(prompt, classes)["1"].split("\n")[0] == config
    (configs / "v1-inference.yaml").write_bytes(b"")
    assert failed_checks(prompt, classes)["2"].startswith(f"NV-Attention Patch Model: input 'model' comes from {checkpoint}")
    (model_folders / "checkpoints" / "sdxl.safetensors").write_bytes(b"")
    assert failed_checks(prompt, classes) == {}


def test_a_name_the_loader_lists_that_is_no_file_is_not_missing(model_folders):
    """Load VAE lists 'pixel_space' (and its TAESD decoders, when in models/vae_approx), which are no file of
    models/vae: ComfyUI accepts them; a name it does not list is missing."""
    from nodes import NODE_CLASS_MAPPINGS

    class VAELoader:  # ComfyUI's, listing models/vae (empty) and the names that are no file
        @classmethod
        def INPUT_TYPES(cls):
            return {"required": {"vae_name": (["taesdxl", "pixel_space"],)}}

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output, "VAELoader": VAELoader}
    prompt = {"1": {"class_type": "VAELoader", "inputs": {"vae_name": "pixel_space"}},
              "2": {"class_type": "ArtNVGSampleGroup", "inputs": {"vae": ["1", 0]}},
              "3": {"class_type": "Output", "inputs": {"images": ["2", 0]}}}
    assert failed_checks(prompt, classes) == {}
    prompt["1"]["inputs"]["vae_name"] = {"__value__": "taesdxl"}
    assert failed_checks(prompt, classes) == {}
    prompt["1"]["inputs"]["vae_name"] = "taesd"
    assert failed_checks(prompt, classes)["2"].startswith(
        "Sample Group: input 'vae' comes from VAELoader (node #1, VAELoader): input 'vae_name': 'taesd' is not in the "
        "'vae' model folder")


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


def test_view_indices_past_the_cameras_a_loader_gives_are_refused_before_the_graph_runs(tmp_path, monkeypatch):
    """Render Views' views and Blend Stylization's view were checked against the cameras only as the nodes ran, after
    the nodes before them (the scene's load, a finetune); the count is known as soon as Load Cameras' file is, or
    Cameras Around Scene's count: each names the node, the input, the index and the range."""
    import shutil

    from artnvg_core.stylize import DemoInputs
    from nodes import NODE_CLASS_MAPPINGS

    monkeypatch.chdir(tmp_path)
    (tmp_path / "input").mkdir()
    shutil.copyfile(DemoInputs().cameras, tmp_path / "input" / "transforms.json")  # 24 cameras
    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"1": {"class_type": "ArtNVGLoadCameras", "inputs": {"camera_source": "transforms.json", "path": ""}},
              "2": {"class_type": "ArtNVGRenderViews", "inputs": {"cameras": ["1", 0], "views": "0, 24", "stride": 1}},
              "3": {"class_type": "ArtNVGBlendStylization", "inputs": {"cameras": ["1", 0], "view": 30, "strength": 1}},
              "4": {"class_type": "ArtNVGCamerasAroundScene", "inputs": {"count": 3, "scene": ["9", 0]}},
              "5": {"class_type": "ArtNVGRenderViews", "inputs": {"cameras": ["4", 0], "views": "3", "stride": 1}},
              "6": {"class_type": "Output", "inputs": {"a": ["2", 0], "b": ["3", 0]}},
              "7": {"class_type": "Output", "inputs": {"a": ["5", 0]}}, "8": {"class_type": "Output", "inputs": {}}}
    assert failed_checks(prompt, classes) == {
        "2": "Render Views: input 'views': view index 24 is out of range for 24 cameras (0..23)",
        "3": "Blend Stylization: input 'view': view index 30 is out of range for 24 cameras (0..23)",
        "5": "Render Views: input 'views': view index 3 is out of range for 3 cameras (0..2)"}
    assert check_prompt({"prompt": prompt}, classes)["partial_execution_targets"] == ["6", "7"]
    prompt["2"]["inputs"]["views"], prompt["3"]["inputs"]["view"], prompt["5"]["inputs"]["views"] = "0, 23", 23, "2"
    assert failed_checks(prompt, classes) == {}
    prompt["2"]["inputs"]["views"], prompt["3"]["inputs"]["view"] = "", 0  # every view, the first: read no file
    monkeypatch.setattr("nodes.camera_nodes.load_cameras", lambda *args, **kwargs: pytest.fail("read for nothing"))
    assert failed_checks(prompt, classes) == {}
    monkeypatch.undo()
    monkeypatch.chdir(tmp_path)
    prompt["2"]["inputs"]["views"], prompt["5"]["inputs"]["views"] = "99", "99"
    for unknown in ({"camera_source": "missing.json", "path": ""},  # Load Cameras names it
                    {"camera_source": "transforms.json", "path": ["10", 0]}):  # a path through a link: known as it runs
        prompt["1"]["inputs"], prompt["4"]["inputs"]["count"] = unknown, ["11", 0]
        assert set(failed_checks(prompt, classes)) <= {"1"}


def test_view_indices_a_mode_reads_are_refused_before_the_graph_runs_in_that_mode_alone(tmp_path, monkeypatch):
    """Render Camera Path's key_views (read by path interpolate) and Select Gaussians' views (read by mode mask) were
    checked against the cameras only as the nodes ran; in the mode that reads them the count Load Cameras gives refuses
    them before, naming the mode. An input its mode ignores, or whose mode comes through a link, is never refused."""
    import shutil

    from artnvg_core.stylize import DemoInputs
    from nodes import NODE_CLASS_MAPPINGS

    monkeypatch.chdir(tmp_path)
    (tmp_path / "input").mkdir()
    shutil.copyfile(DemoInputs().cameras, tmp_path / "input" / "transforms.json")  # 24 cameras
    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    path = {"cameras": ["1", 0], "path": "interpolate", "key_views": "0, 30", "scale": 0.5, "num_frames": 2,
            "frames_per_segment": 2, "loop": False}
    select = {"scene": ["9", 0], "cameras": ["1", 0], "mask": ["10", 0], "mode": "mask", "bounds": "", "views": "5, 24"}
    prompt = {"1": {"class_type": "ArtNVGLoadCameras", "inputs": {"camera_source": "transforms.json", "path": ""}},
              "2": {"class_type": "ArtNVGRenderCameraPath", "inputs": path},
              "3": {"class_type": "ArtNVGSelectGaussians", "inputs": select},
              "4": {"class_type": "Output", "inputs": {"a": ["2", 0], "b": ["3", 0]}}}
    assert failed_checks(prompt, classes) == {
        "2": "Render Camera Path: input 'key_views': path interpolate: view index 30 is out of range for 24 cameras "
             "(0..23)",
        "3": "Select Gaussians: input 'views': mode mask: view index 24 is out of range for 24 cameras (0..23)"}
    path["key_views"], select["views"] = "0, 23", "5, 23"
    assert failed_checks(prompt, classes) == {}
    path["key_views"], select["views"] = "0, 30", "5, 24"
    for orbit, box in (("orbit", "box"), ("orbit", "sphere"), (["11", 0], ["12", 0])):  # ignored, or the mode unknown
        path["path"], select["mode"], select["bounds"] = orbit, box, "0, 0, 0, 1, 1, 1" if box == "box" else "0, 0, 0, 1"
        assert failed_checks(prompt, classes) == {}


def _inputs_of_type(kind: str) -> list[tuple[str, type, str, dict]]:
    """(node type, class, input name, options) of every input of type ``kind`` of every node of the pack."""
    from nodes import NODE_CLASS_MAPPINGS

    found = []
    for node_type, cls in NODE_CLASS_MAPPINGS.items():
        types = cls.INPUT_TYPES()
        for name, entry in {**types["required"], **types.get("optional", {})}.items():
            if entry[0] == kind:
                found.append((node_type, cls, name, (*entry, {})[1]))
    return found


def _validated(node_type: str, inputs: dict, executing) -> tuple:
    """Node 1 of ``node_type`` with ``inputs`` feeding output 2, beside output 3, posted: (what node 1's
    VALIDATE_INPUTS answers, its message in failed_checks, the targets left to run)."""
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"1": {"class_type": node_type, "inputs": inputs}, "2": {"class_type": "Output", "inputs": {"x": ["1", 0]}},
              "3": {"class_type": "Output", "inputs": {}}}
    request = check_prompt({"prompt": prompt}, classes)
    executing["prompt"] = request.get("prompt_id")
    return (classes[node_type].VALIDATE_INPUTS(), failed_checks(prompt, classes).get("1"),
            request.get("partial_execution_targets"))


@pytest.mark.parametrize("nan", [float("nan"), "nan", "-NaN", {"__value__": float("nan")}])  # all NaN to ComfyUI
def test_every_float_input_of_every_node_refuses_nan_at_validation_naming_node_and_input(executing, nan):
    """ComfyUI's min/max comparisons let a NaN through; Blend Stylization refused it only as it ran, Sample Group's
    cfg not at all."""
    floats = _inputs_of_type("FLOAT")
    assert {("ArtNVGBlendStylization", "strength"), ("ArtNVGSampleGroup", "cfg")} <= {(t, n) for t, _, n, _ in floats}
    for node_type, cls, name, _ in floats:
        shown, message, targets = _validated(node_type, {name: nan}, executing)
        assert shown == message == f"{cls.DISPLAY_NAME}: input '{name}': expected a finite number, got nan", name
        assert targets == ["2"], name  # output 3 does not run either


@pytest.mark.parametrize("kind, value", [
    ("FLOAT", float("inf")), ("FLOAT", "-Infinity"), ("FLOAT", "1e999"), ("FLOAT", {"__value__": float("-inf")}),
    ("INT", 2**64), ("INT", -(2**63)), ("INT", "18446744073709551616"), ("INT", "-99999"),  # text ComfyUI reads
    ("INT", float("inf")), ("INT", "nan"), ("INT", "ten"), ("INT", None),  # values ComfyUI cannot make an INT of
])
def test_every_number_input_refuses_what_comfyui_reports_itself_once_and_blocks_every_output(executing, kind, value):
    """Out of the declared range (every number input declares min and max, so ComfyUI compares), or not a number:
    ComfyUI's own message alone (VALIDATE_INPUTS answers True), every output still blocked. Text such as "-99999"
    escaped the pack's checks: the outputs it did not feed ran."""
    for node_type, cls, name, options in _inputs_of_type(kind):
        assert {"min", "max"} <= set(options), name
        shown, message, targets = _validated(node_type, {name: value}, executing)
        assert shown is True and message.startswith(f"{cls.DISPLAY_NAME}: input '{name}': "), name
        assert targets == ["2"], name


def test_values_in_every_spelling_comfyui_reads_pass_unchanged_when_valid():
    """Every declared default, as given, as text and wrapped as the editor wraps a list value: no problem found."""
    from nodes import NODE_CLASS_MAPPINGS

    for cls in NODE_CLASS_MAPPINGS.values():
        types = cls.INPUT_TYPES()
        for name, entry in {**types["required"], **types.get("optional", {})}.items():
            default = (*entry, {})[1].get("default")
            spellings = [default, {"__value__": default}] + ([str(default)] if entry[0] in ("INT", "FLOAT") else [])
            for value in spellings if default is not None else []:
                assert cls.check_values(**{name: value}) is None, (cls.DISPLAY_NAME, name, value)
                assert cls.passed_values({name: value})[name] == default


def test_a_file_list_given_no_text_or_a_path_in_any_spelling_is_the_loaders_to_refuse(executing, tmp_path, monkeypatch):
    """A COMBO (a loader's file list), which ComfyUI neither converts nor compares, given a number: the pack's
    message (it crashed the prompt check, which ComfyUI then skipped, and the node as it ran). A path as ComfyUI
    passes it: {"__value__": ...} unwrapped, a number made text (the check crashed on both)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "input").mkdir()
    for node_type, cls, name, _ in _inputs_of_type("COMBO"):
        for value in (5, None, {"a": 1}):
            shown, message, targets = _validated(node_type, {name: value}, executing)
            assert shown == message == f"{cls.DISPLAY_NAME}: input '{name}': expected a file name, got {value!r}"
            assert targets == ["2"]
    shown, _, _ = _validated("ArtNVGLoadGaussianScene", {"scene_file": "", "path": {"__value__": "/etc/passwd"}},
                             executing)
    assert shown.startswith("Load Gaussian Scene: input 'path': '/etc/passwd' is outside ComfyUI's input, output")
    shown, _, _ = _validated("ArtNVGLoadGaussianScene", {"scene_file": "", "path": 7}, executing)
    assert shown.startswith(f"Load Gaussian Scene: input 'path': scene file not found: {tmp_path / 'input' / '7'}. ")


@pytest.mark.parametrize("text", ["false", {"__value__": "False"}, "true", ""])
def test_every_boolean_input_refuses_text_which_comfyui_reads_as_its_truth(executing, text):
    """ComfyUI makes a BOOLEAN with bool(): "false" was True. JSON's true and false (and 0, 1) pass."""
    booleans = _inputs_of_type("BOOLEAN")
    assert ("ArtNVGRenderCameraPath", "loop") in {(t, n) for t, _, n, _ in booleans}
    for node_type, cls, name, _ in booleans:
        shown, message, targets = _validated(node_type, {name: text}, executing)
        assert shown == message == f"{cls.DISPLAY_NAME}: input '{name}': expected true or false, got {text!r}", name
        assert targets == ["2"], name
        assert all(cls.check_values(**{name: value}) is None for value in (True, False, 0, 1, {"__value__": True}))


def test_malformed_nodes_leave_the_checks_of_the_others_whole(executing):
    """ComfyUI refuses a node whose inputs are not an object itself; the pack's handler, which crashed on one (and
    ComfyUI then let every value through unchecked), still blocks the outputs of a NaN elsewhere."""
    from nodes import NODE_CLASS_MAPPINGS

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"1": {"class_type": "ArtNVGBlendStylization", "inputs": {"strength": float("nan")}},
              "2": {"class_type": "Output", "inputs": {"x": ["1", 0]}}, "3": {"class_type": "Output", "inputs": None},
              "4": {"class_type": "ArtNVGRenderViews", "inputs": ["x"]}, "5": "not a node",
              "6": {"class_type": "Output", "inputs": {"x": ["5", 0], "y": ["4", 0]}}}
    request = check_prompt({"prompt": prompt}, classes)
    assert request["partial_execution_targets"] == ["2"] and list(failed_checks(prompt, classes)) == ["1"]


def test_a_prompt_id_posted_again_is_validated_by_its_latest_values(executing):
    """A client that sets its own prompt id and posts again after mending a value: the message kept from the
    first post refused the mended prompt."""
    check_prompt({"prompt": _prompt("gone", "there"), "prompt_id": "again"}, CLASSES)
    check_prompt({"prompt": _prompt("there", "there"), "prompt_id": "again"}, CLASSES)
    executing["prompt"] = "again"
    assert check_result() is True


def test_an_optional_input_a_value_needs_connected_is_named_at_validation(executing):
    """Select Gaussians in mask mode with no mask connected was refused only as it ran."""
    scene, cameras, mask = ["9", 0], ["8", 0], ["7", 0]
    shown, failed, targets = _validated("ArtNVGSelectGaussians", {"scene": scene, "mode": "mask", "cameras": cameras},
                                        executing)
    assert shown == failed == "Select Gaussians: input 'mask': mode mask needs cameras and mask connected"
    assert targets == ["2"]
    linked = {"scene": scene, "mode": "mask", "cameras": cameras, "mask": mask}
    assert _validated("ArtNVGSelectGaussians", linked, executing)[1:] == (None, None)


@pytest.mark.parametrize("node_type, inputs, message", [
    ("ArtNVGRenderViews", {"views": "3, 0,3"}, "Render Views: input 'views': view 3 is given twice in '3, 0,3'; give "
                                                "each view once"),  # as render --views and evaluate --views
    ("ArtNVGRenderViews", {"views": "-2"}, "Render Views: input 'views': view index -2 is out of range: views count "
                                           "from 0"),
    ("ArtNVGBlendStylization", {"preview_strengths": "0, 2"}, "Blend Stylization: input 'preview_strengths': expected "
                                                             "comma-separated numbers from 0 to 1"),

    # a key view twice: a zero-length segment of the path (loop returns to the first); as evaluate --views
    ("ArtNVGRenderCameraPath", {"key_views": "0, 5, 5"}, "Render Camera Path: input 'key_views': view 5 is given "
                                                         "twice in '0, 5, 5'; give each view once"),
    # one key view: no path through it (the node ran until interpolate_path refused it, naming that function)
    ("ArtNVGRenderCameraPath", {"path": "interpolate", "key_views": " 4,"}, "Render Camera Path: input 'key_views': a "
                                                                            "path through views needs at least 2 key "
                                                                            "views, got 1: [4]"),
    ("ArtNVGCamerasAroundScene", {"elevations": "10, 95"}, "Cameras Around Scene: input 'elevations': 95 degrees is "
                                                           "not an elevation in (-90, 90)"),  # once only as it ran
    ("ArtNVGCamerasAroundScene", {"up": "0, 0, 0"}, "Cameras Around Scene: input 'up': expected 3 finite numbers, "
                                                    "not all zero"),
    # within the declared 0 to 16384, which ComfyUI checks; refused as 'FinetuneConfig.nnfm_max_side' once it ran
    ("ArtNVGFinetuneGaussians", {"nnfm_max_side": 7}, "Finetune Gaussians: input 'nnfm_max_side': expected 0 (full "
                                                      "resolution) or at least 16 px, got 7"),
])
def test_values_a_node_would_refuse_when_it_runs_are_refused_at_validation(executing, node_type, inputs, message):
    """A node's VALUE_CHECKS: the parser it reads the text (or number) with, run before the graph runs (the camera
    count is not known here: an index past the last view is refused where Load Cameras gives the count)."""
    shown, failed, targets = _validated(node_type, inputs, executing)
    assert shown == failed and shown.startswith(message) and targets == ["2"]
    assert _validated("ArtNVGRenderViews", {"views": "0, 2; 1"}, executing)[1] is None
    for path, key_views in (("orbit", "4"), ("interpolate", ""), ("interpolate", "4, 0")):  # orbit reads none
        assert _validated("ArtNVGRenderCameraPath", {"path": path, "key_views": key_views}, executing)[1] is None
