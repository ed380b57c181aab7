"""A loader's file inputs (nodes/input_files.py) and the base every node declares itself with (nodes/node_base.py).

Without ComfyUI the input folder is ``./input`` of the working directory.
"""

import os
from pathlib import Path

import pytest

from nodes.camera_nodes import CAMERA_SOURCE
from nodes.input_files import ANY_PATH_SETTING, InputFile, list_input_files
from nodes.node_base import ArtNVGNode
from nodes.node_errors import NodeInputError
from nodes.scene_nodes import SCENE_FILE


@pytest.fixture
def input_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "input"
    folder.mkdir()
    return folder


def _touch(path: Path, content: bytes, mtime_ns: int) -> None:
    path.write_bytes(content)
    os.utime(path, ns=(mtime_ns, mtime_ns))


def test_a_typed_path_wins_and_errors_name_the_input_that_chose(input_folder):
    scene_file = InputFile("scene_file", "scene file", lambda: [], tooltip="t", path_tooltip="p")
    (input_folder / "a.ply").write_bytes(b"")
    assert scene_file.resolve("a.ply", "  ") == (input_folder / "a.ply", "scene_file")
    assert scene_file.resolve("a.ply", "sub/b.ply") == (input_folder / "sub" / "b.ply", "path")
    for quoted in ('"sub/b.ply"', " 'sub/b.ply' "):  # as Windows' Copy as path gives it: was "not found: input/"sub...
        assert scene_file.resolve("a.ply", quoted) == (input_folder / "sub" / "b.ply", "path")
    assert scene_file.resolve("a.ply", '""') == (input_folder / "a.ply", "scene_file")
    assert scene_file.check("Load", "a.ply", "") is None
    missing = input_folder / "gone.ply"
    message = scene_file.check("Load", "gone.ply", "")
    assert message.startswith(f"Load: input 'scene_file': scene file not found: {missing}. ")
    assert f"input folder ({input_folder.resolve()})" in message and "its path into 'path'" in message
    assert scene_file.check("Load", "a.ply", "sub/b.ply").startswith(
        f"Load: input 'path': scene file not found: {input_folder / 'sub' / 'b.ply'}. ")
    (input_folder / "folder.ply").mkdir()
    assert "not found" in scene_file.check("Load", "folder.ply", "")  # no validate: a folder is not there to load
    assert scene_file.check("Load", "", " ").startswith("Load: input 'scene_file': no scene file chosen. Put it into")


def test_a_folder_chosen_as_the_scene_file_is_named_as_a_folder_with_the_formats_read(input_folder):
    """Load Gaussian Scene before the graph runs and as it runs: the library's words (was: 'scene file not found')."""
    from nodes.scene_nodes import LoadGaussianScene

    (input_folder / "capture.ply").mkdir()
    (input_folder / "capture").mkdir()
    for listed, path, name, folder in [("capture.ply", "", "scene_file", input_folder / "capture.ply"),
                                       ("x.ply", "capture", "path", input_folder / "capture")]:
        message = (f"Load Gaussian Scene: input '{name}': {folder}: scene file is a folder, not a regular file; "
                   "expected .ply (INRIA 3DGS or compressed PLY), .splat, .spz, .ksplat or .ckpt (nerfstudio "
                   "splatfacto checkpoint)")
        assert LoadGaussianScene.check_files(scene_file=listed, path=path) == message
        with pytest.raises(NodeInputError) as refused:
            LoadGaussianScene().load(listed, path)
        assert str(refused.value) == message


@pytest.fixture
def elsewhere(input_folder):
    """A folder beside ComfyUI's input and output folders, holding a scene file and a capture."""
    folder = input_folder.parent / "elsewhere"
    (folder / "capture").mkdir(parents=True)
    (folder / "secret.ply").write_bytes(b"ply\n")
    (folder / "capture" / "transforms.json").write_text("{}")
    return folder


def _refusal(source: InputFile, listed: str, path: str = "") -> str:
    message = source.check("Load", listed, path)
    assert isinstance(message, str)
    with pytest.raises(NodeInputError) as refused:
        source.readable("Load", listed, path)
    assert str(refused.value) == message and source.signature(listed, path) == ""
    return message


def test_paths_outside_comfyuis_folders_are_refused_alike_whether_or_not_they_exist(input_folder, elsewhere):
    existing, missing = str(elsewhere / "secret.ply"), str(elsewhere / "missing.ply")
    told = _refusal(SCENE_FILE, "", existing)
    assert told.startswith(f"Load: input 'path': {existing!r} is outside ComfyUI's input, output and model folders")
    assert ANY_PATH_SETTING in told
    assert _refusal(SCENE_FILE, "", missing) == told.replace(existing, missing)
    for listed in ("../elsewhere/secret.ply", "../elsewhere/missing.ply", "sub/../../elsewhere/secret.ply"):
        assert _refusal(SCENE_FILE, listed) == told.replace(f"'path': {existing!r}", f"'scene_file': {listed!r}")
    (input_folder / "link.ply").symlink_to(elsewhere / "secret.ply")  # a link out of the input folder
    assert "is outside ComfyUI's input" in _refusal(SCENE_FILE, "link.ply")
    assert "is outside ComfyUI's input" in _refusal(SCENE_FILE, "", "~/secret.ply")
    (input_folder / "capture").symlink_to(elsewhere / "capture", target_is_directory=True)
    assert "is outside ComfyUI's input" in _refusal(CAMERA_SOURCE, "capture")


def test_names_no_file_system_takes_are_refused_naming_the_input(input_folder):
    """A NUL character (no folder holds such a name: refused as outside them, before the graph runs and as the
    loader runs) and a name too long to look up: the loader's message, not the operating system's exception
    (which crashed the prompt check, so ComfyUI skipped it, and the node as it ran)."""
    assert _refusal(SCENE_FILE, "", "a\x00b.ply").startswith(
        "Load: input 'path': 'a\\x00b.ply' is outside ComfyUI's input, output and model folders")
    assert _refusal(CAMERA_SOURCE, "capture\x00").startswith("Load: input 'camera_source': 'capture\\x00' is outside")
    long = "x" * 300 + ".ply"
    assert SCENE_FILE.check("Load", "", long).startswith(f"Load: input 'path': cannot look for {input_folder / long}: ")


def test_files_inside_comfyuis_folders_are_read_and_the_setting_opens_every_path(input_folder, elsewhere, monkeypatch):
    output = input_folder.parent / "output"
    output.mkdir()
    (output / "saved.ply").write_bytes(b"ply\n")
    (input_folder / "saved.ply").symlink_to(output / "saved.ply")  # a link between ComfyUI's own folders
    assert SCENE_FILE.readable("Load", "saved.ply", "") == (input_folder / "saved.ply", "scene_file")
    assert SCENE_FILE.check("Load", "", "../output/saved.ply") is None
    capture = input_folder / "capture"
    capture.mkdir()
    (capture / "transforms.json").symlink_to(elsewhere / "capture" / "transforms.json")  # a file of the folder leads out
    assert "is outside ComfyUI's input" in _refusal(CAMERA_SOURCE, "capture")
    monkeypatch.setenv(ANY_PATH_SETTING, "1")
    assert SCENE_FILE.check("Load", "", str(elsewhere / "secret.ply")) is None
    assert CAMERA_SOURCE.check("Load", "capture", "") is None
    assert SCENE_FILE.check("Load", "", str(elsewhere / "missing.ply")).startswith("Load: input 'path': scene file not found")


def test_a_capture_folder_is_watched_through_its_transforms_json(input_folder):
    capture = input_folder / "capture"
    capture.mkdir()
    assert "capture: not a supported camera source" in CAMERA_SOURCE.check("Load Cameras", "capture", "")
    _touch(capture / "transforms.json", b"{}", 10**18)
    assert CAMERA_SOURCE.check("Load Cameras", "capture", "") is None  # a folder holding a capture counts
    first = CAMERA_SOURCE.signature("capture", "")
    _touch(capture / "image.png", b"more bytes", 2 * 10**18)  # the folder changes, the cameras do not
    assert CAMERA_SOURCE.signature("capture", "") == first
    _touch(capture / "transforms.json", b"{ }", 10**18)
    assert CAMERA_SOURCE.signature("capture", "") != first
    assert CAMERA_SOURCE.signature("missing", "") == ""


def test_inputs_are_data_and_choices_are_listed_when_asked(input_folder):
    class Loader(ArtNVGNode):
        """Loads things."""

        REQUIRED = {"file": lambda: (list_input_files(suffixes=(".ply",)), {}), "count": ("INT", {"default": 1})}

    class Described(ArtNVGNode):
        """Docstring."""

        DESCRIPTION = "Own words."
        OPTIONAL = {"flag": ("BOOLEAN", {"default": False})}

    hidden = {"node_id": "UNIQUE_ID"}  # every node's: its id, for its VALIDATE_INPUTS (nodes/prompt_checks.py)
    assert Loader.INPUT_TYPES() == {"required": {"file": ([], {}), "count": ("INT", {"default": 1})}, "hidden": hidden}
    (input_folder / "new.ply").write_bytes(b"")
    assert Loader.INPUT_TYPES()["required"]["file"] == (["new.ply"], {})
    assert (Loader.CATEGORY, Loader.DESCRIPTION) == ("ArtNVG", "Loads things.")
    assert Described.DESCRIPTION == "Own words."
    assert Described.INPUT_TYPES() == {"required": {}, "optional": {"flag": ("BOOLEAN", {"default": False})},
                                       "hidden": hidden}


def test_descriptions_are_plain_text_paragraphs():
    from nodes import NODE_CLASS_MAPPINGS
    from nodes.node_base import plain_text

    assert plain_text("""Reads ``*.ply`` files,
        one per line.

        Second ``paragraph``.""") == "Reads *.ply files, one per line.\n\nSecond paragraph."
    for name, node in NODE_CLASS_MAPPINGS.items():
        assert "``" not in node.DESCRIPTION and "\n\n\n" not in node.DESCRIPTION, name
        assert all(paragraph == " ".join(paragraph.split()) for paragraph in node.DESCRIPTION.split("\n\n")), name
