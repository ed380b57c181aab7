"""stylize's checks of its style image, made before the scene loads (its runs: tests/test_cli_main.py)."""

import re

import pytest

from artnvg_core.stylize import DemoInputs
from tests.test_cli_main import _small_scene, _stylize


@pytest.mark.parametrize("name, message", [
    ("line.png", r"image size: 80000x1 pixels; a style image may be at most 32 times as long as it is wide \(its "
     r"features are matched at the renders' size\); crop it"),
    ("cut.jpg", r"not a readable image \(image file is truncated \(\d+ bytes not processed\)\)")])
def test_a_style_image_too_long_for_its_width_or_truncated_is_refused_before_loading(tmp_path, capsys, name, message):
    """80000x1 pixels (318 bytes) once passed every check and asked 10.8 GB for the contact sheet after the work; a
    truncated JPEG, whose header reads, was found only after the scene loaded."""
    from PIL import Image

    if name == "line.png":
        Image.new("RGB", (80000, 1), (200, 30, 30)).save(tmp_path / name)
    else:
        (tmp_path / name).write_bytes(DemoInputs().style.read_bytes()[:5000])
    assert _stylize(_small_scene(tmp_path), tmp_path / name, tmp_path / "out.ply") == 2
    captured = capsys.readouterr()
    assert re.fullmatch(re.escape(f"error: --style: {tmp_path / name}: ") + message + "\n", captured.err), captured
    assert "loading" not in captured.out


def test_the_nnfm_stylizers_work_on_every_view_and_the_contact_sheet_show_progress(tmp_path, capsys):
    """Its colour transfer renders every view before the steps and after them: at full size, minutes (185
    views of the garden on a CPU) that once passed with nothing on screen; so did the content term's VGG
    features of every view and the contact sheet's renders (seconds each)."""
    assert _stylize(_small_scene(tmp_path), DemoInputs().style, tmp_path / "out.ply") == 0
    err = capsys.readouterr().err
    for bar in ("views (setup)", "views (features)", "views (final)"):
        assert re.search(rf"{re.escape(bar)}: 100%\|.*\| 24/24 \[.*it/s\]", err), err
    for bar in ("contact sheet (original)", "contact sheet (stylized)"):
        assert re.search(rf"{re.escape(bar)}: 100%\|.*\| 4/4 \[.*it/s\]", err), err


def test_what_the_output_format_drops_is_printed_once(tmp_path, capsys, caplog):
    """The demo scene is of SH degree 1, a .splat of degree 0."""
    with caplog.at_level("INFO"):
        assert _stylize(_small_scene(tmp_path), DemoInputs().style, tmp_path / "out.splat") == 0
    printed = capsys.readouterr().out.splitlines()
    assert [line for line in printed if "view-dependent" in line] == [
        "note: .splat holds SH up to degree 0; the degree 1 view-dependent terms are dropped"]
    assert not [record for record in caplog.records if "view-dependent" in record.getMessage()]
