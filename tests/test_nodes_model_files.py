"""A loader's model file (nodes/model_files.py): Load CSGO's message when its file is not in the csgo folder names
the file, the folders looked in and what they hold, where to get it and where to save it; at validation, through
the whole-prompt check, labelled with the input itself."""

import sys

import pytest
from test_nodes_comfy_bridge import FakeComfy

from nodes import comfy_bridge, prompt_checks
from nodes.model_patch_nodes import CSGO_EXTENSIONS, CSGO_FOLDER, LoadCSGO
from nodes.node_errors import NodeInputError
from nodes.prompt_checks import check_prompt

WHERE_TO_GET = ("Get the CSGO content/style weights (4 content / 32 style tokens) from https://huggingface.co/InstantX/"
                "CSGO/blob/main/csgo_4_32.bin")


def where_to_get(folder) -> str:
    """The end of the message: the command saving the file straight into ``folder``, and the path it saves."""
    return (f"{WHERE_TO_GET}: `hf download InstantX/CSGO csgo_4_32.bin --local-dir {folder}` saves it as "
            f"{folder}/csgo_4_32.bin")


@pytest.fixture
def csgo_folder(tmp_path, monkeypatch):
    """ComfyUI's csgo model folder (registered by the pack, as it loads), empty; validation in prompt "p", node "7"."""
    for name, module in FakeComfy(tmp_path).modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    comfy_bridge.register_model_folder(CSGO_FOLDER, CSGO_EXTENSIONS)
    return tmp_path / "models" / CSGO_FOLDER


def test_a_missing_file_names_the_folder_looked_in_where_to_get_it_and_where_to_save_it(csgo_folder):
    assert LoadCSGO.INPUT_TYPES()["required"]["csgo_name"][1]["options"] == []
    expected = (f"Load CSGO: input 'csgo_name': 'csgo_4_32.bin' is not in the 'csgo' model folder (looked in "
                f"{csgo_folder}; found nothing). {where_to_get(csgo_folder)}")
    assert LoadCSGO.check_files(csgo_name="csgo_4_32.bin") == expected
    with pytest.raises(NodeInputError) as missing:
        LoadCSGO().load("csgo_4_32.bin")
    assert str(missing.value) == expected
    # a name of the user's own: saved under it, the node finds it (the command would save the source's name)
    assert LoadCSGO.check_files(csgo_name="mine.bin").endswith(
        f"{WHERE_TO_GET} (`hf download InstantX/CSGO csgo_4_32.bin`) and save it as {csgo_folder / 'mine.bin'}")
    assert LoadCSGO.check_files(csgo_name="").startswith(
        f"Load CSGO: input 'csgo_name': no file chosen from the 'csgo' model folder (looked in {csgo_folder}; found ")
    assert LoadCSGO.check_files(csgo_name=" ").endswith(where_to_get(csgo_folder))


def test_the_files_the_folders_hold_are_named_and_every_folder_looked_in(csgo_folder, tmp_path):
    extra = tmp_path / "shared" / "csgo"  # a second folder, as extra_model_paths.yaml adds one
    extra.mkdir(parents=True)
    sys.modules["folder_paths"].folder_names_and_paths[CSGO_FOLDER][0].insert(0, str(extra))
    for index in range(7):
        (csgo_folder / f"csgo_{index}.bin").write_bytes(b"")
    message = LoadCSGO.check_files(csgo_name="csgo_4_32.bin")
    assert (f"(looked in {extra}, {csgo_folder}; found 'csgo_0.bin', 'csgo_1.bin', 'csgo_2.bin', 'csgo_3.bin', "
            f"'csgo_4.bin' and 2 more). ") in message
    assert message.endswith(where_to_get(extra))
    assert LoadCSGO.check_files(csgo_name="csgo_6.bin") is None


def test_a_file_deleted_after_it_was_listed_is_missing(csgo_folder):
    (csgo_folder / "csgo_4_32.bin").write_bytes(b"")
    assert LoadCSGO.INPUT_TYPES()["required"]["csgo_name"][1]["options"] == ["csgo_4_32.bin"]
    assert LoadCSGO.check_files(csgo_name="csgo_4_32.bin") is None
    (csgo_folder / "csgo_4_32.bin").unlink()
    assert "'csgo_4_32.bin' is not in the 'csgo' model folder" in LoadCSGO.check_files(csgo_name="csgo_4_32.bin")


def test_without_comfyui_the_message_names_comfyuis_models_folder():
    assert "folder_paths" not in sys.modules
    assert LoadCSGO.check_files(csgo_name="csgo_4_32.bin") == (
        "Load CSGO: input 'csgo_name': 'csgo_4_32.bin' is not in the 'csgo' model folder (looked in ComfyUI's "
        f"models/csgo; found nothing). {where_to_get('models/csgo')}")


def test_validation_refuses_the_prompt_with_the_message_labelled_by_the_file_input(csgo_folder):
    """ComfyUI labels a VALIDATE_INPUTS message with each input that function takes ("csgo_name - ..."), and does not
    compare a COMBO's value with its options (its "Value not in list" named no folder); the pack's check alone,
    once. Every output Load CSGO feeds is blocked."""
    import inspect

    from nodes import NODE_CLASS_MAPPINGS

    class Output:
        OUTPUT_NODE = True

    classes = {**NODE_CLASS_MAPPINGS, "Output": Output}
    prompt = {"7": {"class_type": "ArtNVGLoadCSGO", "inputs": {"csgo_name": {"__value__": "csgo_4_32.bin"}}},
              "8": {"class_type": "Output", "inputs": {"csgo": ["7", 0]}}, "9": {"class_type": "Output", "inputs": {}}}
    assert inspect.getfullargspec(LoadCSGO.VALIDATE_INPUTS).args == ["cls", "csgo_name"]  # as ComfyUI reads it
    assert LoadCSGO.INPUT_TYPES()["required"]["csgo_name"][0] == "COMBO"
    request = check_prompt({"prompt": prompt, "prompt_id": "p"}, classes)
    assert request["partial_execution_targets"] == ["8"]
    shown = LoadCSGO.VALIDATE_INPUTS(csgo_name="csgo_4_32.bin")  # node 7 of prompt p (the fixture's context)
    assert shown == LoadCSGO.check_files(csgo_name="csgo_4_32.bin") and shown.startswith("Load CSGO: input 'csgo_name'")
    (csgo_folder / "csgo_4_32.bin").write_bytes(b"")
    assert "partial_execution_targets" not in check_prompt({"prompt": prompt, "prompt_id": "p"}, classes)
    assert LoadCSGO.VALIDATE_INPUTS(csgo_name="csgo_4_32.bin") is True
    assert "p" not in prompt_checks._results


def test_each_file_the_shipped_workflows_give_a_stock_loader_is_told_its_exact_source():
    """ComfyUI's own loaders (STOCK_LOADERS): the name a shipped workflow picks gets the source the full workflow's
    missing-models list downloads (one file: its repository and path); another name, the kind of model wanted with
    that source as an example."""
    import json

    from test_workflows import API_FILES, FULL_API, WORKFLOWS

    from nodes.model_files import STOCK_LOADERS

    picked = {(loader, node["inputs"][loader.name]) for path in API_FILES for node in json.loads(path.read_text()).values()
              for loader in STOCK_LOADERS.get(node["class_type"], ())}
    assert {loader.folder for loader, _ in picked} == {"checkpoints", "controlnet", "clip_vision"}
    listed = {model["name"]: model["url"] for model in
              json.loads(next(WORKFLOWS.glob(f"{FULL_API.stem.removesuffix('_api')}.json")).read_text())["models"]}
    for loader, name in picked:
        source = loader.source
        assert loader.usual_name == name
        file = source.download_file or source.repo_path
        assert listed[name] == f"https://huggingface.co/{source.repo}/resolve/main/{file}"
        where = f"{source.description} from {source.url} (`{source.download_command}`)"
        direct = f"hf download {source.repo} {name} --local-dir models/{loader.folder}"  # the file at the repo's top
        assert loader.where_to_get(name) == (
            f"Get the {source.description} from {source.url}: `{direct}` saves it as models/{loader.folder}/{name}"
            if source.download_as(f"models/{loader.folder}/{name}") else
            f"Get the {where} and save it as models/{loader.folder}/{name}")
        assert loader.where_to_get("mine.safetensors") == (
            f"Save {loader.kind} as models/{loader.folder}/mine.safetensors, e.g. the {where}")


def test_apply_csgo_names_the_image_encoders_source_from_the_same_entry():
    from artnvg_core.diffusion.model_files import IMAGE_ENCODER_FILE
    from nodes.model_patch_nodes import ApplyCSGO

    tooltip = ApplyCSGO.INPUT_TYPES()["required"]["clip_vision"][1]["tooltip"]
    assert (f"from {IMAGE_ENCODER_FILE.url} (`hf download h94/IP-Adapter sdxl_models/image_encoder/model.safetensors`) "
            "and save it as models/clip_vision/CLIP-ViT-bigG-14-laion2B-39B-b160k.safetensors") in tooltip
