"""The command line's regions (--region, --region-mask) for stylize and blend."""

import dataclasses
import re

import pytest
import torch

from artnvg_core.cameras import load_cameras
from artnvg_core.cli.main import main
from artnvg_core.formats import load_scene, write_ply
from artnvg_core.images import save_png
from artnvg_core.stylize import DemoInputs


def _scenes(tmp_path):
    """1,000 Gaussians of the demo bear and a recoloured copy, written as PLY."""
    original = load_scene(DemoInputs().scene).select(slice(0, None, 40))
    stylized = dataclasses.replace(original, sh=original.sh.flip(-1))
    write_ply(original, tmp_path / "original.ply")
    write_ply(stylized, tmp_path / "stylized.ply")
    return original, stylized


def _mask(tmp_path):
    mask = torch.zeros(64, 64, 3)
    mask[:, :32] = 1  # the left half of a view painted, at 1/8 of its size
    save_png(mask, tmp_path / "mask.png")
    return tmp_path / "mask.png"


def test_blend_with_a_mask_changes_what_the_painted_pixels_see(tmp_path, capsys):
    original, _ = _scenes(tmp_path)
    name = load_cameras(DemoInputs().cameras).names[0]
    out = tmp_path / "blend.ply"
    assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "1",
                 "--cameras", str(DemoInputs().cameras), "--region-mask", f"{name}:{_mask(tmp_path)}",
                 "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "Gaussians selected" in captured.out
    assert re.search(r"region masks: 100%\|.*\| 1/1 \[.*\]", captured.err), captured.err  # seconds a view
    changed = (load_scene(out).sh != original.sh).flatten(1).any(1)
    assert 0 < changed.sum() < len(original)


def test_stylize_a_region_changes_only_its_gaussians(tmp_path, capsys):
    original, _ = _scenes(tmp_path)
    out = tmp_path / "stylized.ply"
    assert main(["stylize", str(tmp_path / "original.ply"), "--cameras", str(DemoInputs().cameras), "--style",
                 str(DemoInputs().style), "--stylizer", "nnfm", "--iters", "2", "--scale", "0.125", "--device", "cpu",
                 "--region", "box:-1,-1,-1,1,1,1", "--out", str(out)]) == 0
    inside = (original.means.abs() <= 1).all(1)
    assert f"region: {int(inside.sum()):,} of 1,000 Gaussians selected" in capsys.readouterr().out
    result = load_scene(out)
    assert torch.equal(result.sh[~inside], original.sh[~inside]) and not torch.equal(result.sh[inside], original.sh[inside])


def test_a_mask_on_an_unknown_view_is_refused(tmp_path, capsys):
    _scenes(tmp_path)
    assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "1",
                 "--cameras", str(DemoInputs().cameras), "--region-mask", f"frame_9:{_mask(tmp_path)}",
                 "--out", str(tmp_path / "o.ply")]) == 2
    assert "'frame_9' is neither a view index below 24 nor a view name" in capsys.readouterr().err


def test_a_mask_on_a_view_built_around_the_scene_is_checked_before_anything_loads(tmp_path, capsys, monkeypatch):
    """Without --cameras, stylize's masks on views past those orbiting the scene, or of another aspect, were named only
    once the scene (and the diffusion models) had loaded; the views' names and size follow from --orbit-views,
    --orbit-size and --scale."""
    def reached(*args, **kwargs):
        raise ValueError("reached")

    monkeypatch.setattr("artnvg_core.cli.stylize.load_scene_verbose", reached)
    _scenes(tmp_path)
    square, wide = _mask(tmp_path), tmp_path / "wide.png"
    save_png(torch.ones(32, 64, 3), wide)
    for mask, message in [(f"4:{square}", f"--region-mask 4:{square}: '4' is neither a view index below 4 nor a view "
                           "name of the cameras (e.g. 'orbit_0000')"),
                          (f"orbit_0004:{square}", f"--region-mask orbit_0004:{square}: 'orbit_0004' is neither"),
                          (f"orbit_0003:{wide}", f"--region-mask orbit_0003:{wide}: 64x32 pixels, not the aspect of its "
                           "view's 32x32"),
                          (f"orbit_0003:{square}", "reached"), (f"3:{square}", "reached")]:
        assert main(["stylize", str(tmp_path / "original.ply"), "--style", str(DemoInputs().style), "--stylizer",
                     "nnfm", "--orbit-views", "4", "--orbit-size", "64", "--scale", "0.5", "--region-mask", mask,
                     "--out", str(tmp_path / "out.ply")]) == 2
        captured = capsys.readouterr()
        assert captured.err.startswith(f"error: {message}"), captured.err


@pytest.mark.parametrize("command", ["stylize", "blend"])
def test_a_mask_of_another_aspect_than_its_view_is_refused_before_any_scene_loads(tmp_path, capsys, command):
    """It was stretched to the view (within 2% silently; else refused after the scene loaded)."""
    _scenes(tmp_path)
    save_png(torch.ones(32, 64, 3), tmp_path / "wide.png")
    inputs = ([str(tmp_path / "original.ply"), "--style", str(DemoInputs().style), "--scale", "0.5"]
              if command == "stylize" else [str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "1"])
    assert main([command, *inputs, "--cameras", str(DemoInputs().cameras), "--region-mask",
                 f"3:{tmp_path / 'wide.png'}", "--out", str(tmp_path / "out.ply")]) == 2
    captured = capsys.readouterr()
    view = "256x256" if command == "stylize" else "512x512"
    assert captured.err == (f"error: --region-mask 3:{tmp_path / 'wide.png'}: 64x32 pixels, not the aspect of its "
                            f"view's {view} (it would be stretched); paint the mask on a render of the view, at any "
                            "scale\n")
    assert "loading" not in captured.out


def test_a_missing_mask_is_named_before_any_scene_loads(tmp_path, capsys):
    _scenes(tmp_path)
    missing = tmp_path / "mask_40.png"
    assert main(["blend", str(tmp_path / "original.ply"), str(tmp_path / "stylized.ply"), "--strength", "1",
                 "--cameras", str(DemoInputs().cameras), "--region-mask", f"0:{missing}",
                 "--out", str(tmp_path / "o.ply")]) == 2
    captured = capsys.readouterr()
    assert captured.err == f"error: {missing}: --region-mask image not found\n" and "loading" not in captured.out
