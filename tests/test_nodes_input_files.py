"""A loader's file inputs (nodes/input_files.py) and the base every node declares itself with (nodes/node_base.py).

Without ComfyUI the input folder is ``./input`` of the working directory.
"""

import os
from pathlib import Path

import pytest

from nodes.camera_nodes import CAMERA_SOURCE
from nodes.input_files import InputFile, list_input_files
from nodes.node_base import ArtNVGNode


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
    assert scene_file.check("Load", "a.ply", "") is True
    missing = input_folder / "gone.ply"
    message = scene_file.check("Load", "gone.ply", "")
    assert message.startswith(f"Load: input 'scene_file': scene file not found: {missing}. ")
    assert f"input folder ({input_folder.resolve()})" in message and "full path into 'path'" in message
    assert scene_file.check("Load", "a.ply", "/no/b.ply").startswith("Load: input 'path': scene file not found: /no/b.ply. ")
    (input_folder / "folder.ply").mkdir()
    assert "not found" in scene_file.check("Load", "folder.ply", "")  # a folder is no scene file


def test_a_capture_folder_is_watched_through_its_transforms_json(input_folder):
    capture = input_folder / "capture"
    capture.mkdir()
    assert CAMERA_SOURCE.check("Load Cameras", "capture", "") is True  # folders count for cameras
    _touch(capture / "transforms.json", b"{}", 10**18)
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

    assert Loader.INPUT_TYPES() == {"required": {"file": ([], {}), "count": ("INT", {"default": 1})}}
    (input_folder / "new.ply").write_bytes(b"")
    assert Loader.INPUT_TYPES()["required"]["file"] == (["new.ply"], {})
    assert (Loader.CATEGORY, Loader.DESCRIPTION) == ("ArtNVG", "Loads things.")
    assert Described.DESCRIPTION == "Own words."
    assert Described.INPUT_TYPES() == {"required": {}, "optional": {"flag": ("BOOLEAN", {"default": False})}}


def test_descriptions_are_plain_text_paragraphs():
    from nodes import NODE_CLASS_MAPPINGS
    from nodes.node_base import plain_text

    assert plain_text("""Reads ``*.ply`` files,
        one per line.

        Second ``paragraph``.""") == "Reads *.ply files, one per line.\n\nSecond paragraph."
    for name, node in NODE_CLASS_MAPPINGS.items():
        assert "``" not in node.DESCRIPTION and "\n\n\n" not in node.DESCRIPTION, name
        assert all(paragraph == " ".join(paragraph.split()) for paragraph in node.DESCRIPTION.split("\n\n")), name
