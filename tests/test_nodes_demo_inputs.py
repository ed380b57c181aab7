"""The demo inputs the pack puts into ComfyUI's input folder (nodes/demo_inputs.py)."""

import logging
import os

from nodes.demo_inputs import DEMO_CAMERAS, DEMO_SCENE, DEMO_STYLE, demo_files, install_demo_inputs
from nodes.input_files import list_input_files

from artnvg_core.stylize import DemoInputs


def test_missing_files_are_copied_once_and_never_overwritten(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="artnvg"):
        copied = install_demo_inputs(tmp_path)
    assert set(copied) == set(demo_files()) and {DEMO_SCENE, DEMO_CAMERAS, DEMO_STYLE} <= set(copied)
    assert (tmp_path / DEMO_SCENE).read_bytes() == DemoInputs().scene.read_bytes()
    assert (tmp_path / DEMO_STYLE).read_bytes() == DemoInputs().style.read_bytes()
    assert DEMO_STYLE in caplog.text and str(tmp_path) in caplog.text
    assert not [p for p in tmp_path.rglob(".*")]  # no temporary file left
    umask = os.umask(0)
    os.umask(umask)
    assert {oct(p.stat().st_mode & 0o777) for p in tmp_path.rglob("*") if p.is_file()} == {oct(0o666 & ~umask)}  # as a user's files

    (tmp_path / DEMO_CAMERAS).write_text("edited by the user")
    (tmp_path / DEMO_STYLE).unlink()
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="artnvg"):
        assert install_demo_inputs(tmp_path) == [DEMO_STYLE]
    assert (tmp_path / DEMO_CAMERAS).read_text() == "edited by the user"
    caplog.clear()
    assert install_demo_inputs(tmp_path) == [] and caplog.text == ""  # silent when all are there


def test_the_loaders_list_what_was_installed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    install_demo_inputs(tmp_path / "input")
    assert DEMO_SCENE in list_input_files(suffixes=(".ply",))
    assert DEMO_CAMERAS in list_input_files(names=("transforms.json",))
    assert "/" not in DEMO_STYLE  # Load Image lists only the top of the input folder


def test_an_unwritable_input_folder_is_logged_not_raised(tmp_path, caplog):
    blocker = tmp_path / "input"
    blocker.write_text("a file where the folder should be")
    with caplog.at_level(logging.WARNING, logger="artnvg"):
        assert install_demo_inputs(blocker) == []
    assert "could not put the demo inputs" in caplog.text
