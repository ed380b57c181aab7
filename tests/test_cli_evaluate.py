"""The evaluate command end to end on a small real scene: floors, a perturbed scene, 2D stylized views."""

import argparse
import json
import re
from pathlib import Path

import pytest
import torch
from PIL import Image

from artnvg_core.cli.main import main
from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig
from artnvg_core.formats import load_scene, write_ply
from artnvg_core.images import load_image, save_png
from artnvg_core.metrics.csd import CSDConfig, CSDStyleEncoder
from artnvg_core.cli.evaluate import (
    add_evaluate_arguments,
    camera_path,
    format_table,
    load_view_images,
    render_views,
)
from artnvg_core.stylize import stylize_nnfm

VIEWS = "0,1,2"
SCALE = 0.125  # 64 x 64


@pytest.fixture(scope="module")
def inputs(shared_data, tmp_path_factory):
    """The bear's 3k most opaque and largest Gaussians, a few NNFM iterations of it, tiny random
    CLIP and CSD models, and the paths the command needs."""
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    folder = tmp_path_factory.mktemp("evaluate")
    bear, style = shared_data / "scenes" / "bear", shared_data / "styles" / "starry.jpg"
    scene = load_scene(bear / "scene.ply")
    footprint = torch.sigmoid(scene.opacity_logits) * scene.log_scales.sort(dim=1).values[:, 1:].sum(1).exp()
    scene = scene.select(footprint.topk(3_000).indices)
    write_ply(scene, folder / "original.ply")
    cameras = load_cameras(bear / "transforms.json").subset([0, 1, 2]).scaled(SCALE)
    config = FinetuneConfig(iterations=10, lr_sh_dc=0.05, nnfm_max_side=128)  # fast, visible colour change
    write_ply(stylize_nnfm(scene, cameras, load_image(style, max_side=128), config), folder / "nnfm.ply")

    torch.manual_seed(0)
    clip_config = CLIPVisionConfig(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=4,
                                   image_size=28, patch_size=7, projection_dim=8)
    CLIPVisionModelWithProjection(clip_config).save_pretrained(folder / "clip")
    torch.save(CSDStyleEncoder(CSDConfig(28, 7, 64, 1, 1, 8)).state_dict(), folder / "csd.pt")
    return {"folder": folder, "cameras": bear / "transforms.json", "style": style,
            "original": folder / "original.ply", "stylized": folder / "nnfm.ply"}


def _evaluate(inputs, out, *options) -> dict:
    parser = argparse.ArgumentParser()
    add_evaluate_arguments(parser)
    args = parser.parse_args([
        "--original", str(inputs["original"]), "--cameras", str(inputs["cameras"]), "--style", str(inputs["style"]),
        "--views", VIEWS, "--scale", str(SCALE), "--frames", "3", "--long-step", "2", "--device", "cpu",
        "--out", str(out), *options,
    ])
    return args.run(args)


@pytest.fixture
def no_cached_models(tmp_path, monkeypatch):
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty-hf-cache"))


def test_scene_against_itself_reports_the_floors(inputs, capsys):
    folder = inputs["folder"]
    report = _evaluate(inputs, folder / "self" / "report.json", "--stylized", str(inputs["original"]),
                       "--clip", str(folder / "clip"), "--csd", str(folder / "csd.pt"))
    metrics = report["metrics"]
    assert report["resolution"] == [64, 64] and report["view_indices"] == [0, 1, 2]
    assert report["views"] == load_cameras(inputs["cameras"]).subset([0, 1, 2]).names
    assert metrics["cfsd"]["per_view"] == [0.0, 0.0, 0.0] and metrics["cfsd"]["resolution"] == [64, 64]
    warp = metrics["warp"]
    assert warp["stylized"] == warp["floor"]
    assert warp["floor"]["short"]["step"] == 1 and warp["floor"]["long"]["step"] == 2
    assert warp["floor"]["short"]["rmse"] > 0 and warp["floor"]["short"]["coverage"] > 0.3
    assert warp["params"] == {"alpha_threshold": 0.5, "depth_tolerance": 0.05}
    assert metrics["csd"]["mean"] == pytest.approx(metrics["csd"]["original_mean"], abs=1e-6)
    assert metrics["clip_dc"]["mean"] == pytest.approx(1.0, abs=1e-4)
    assert metrics["clip_dc"]["sequence"] == "orbit path, 3 frames" and len(metrics["clip_dc"]["per_step"]) == 2

    out = folder / "self"
    assert json.loads((out / "report.json").read_text()) == json.loads(json.dumps(report))
    with Image.open(out / "report_strip.png") as strip:
        assert strip.height == 2 * 64 + 4 and strip.width > 3 * (64 + 4)
    with Image.open(out / "report_preview.gif") as gif:
        assert gif.n_frames == 3 and gif.size == (128, 64)
    printed = capsys.readouterr()
    table = printed.out
    assert "CFSD relu3_1 @ 64x64" in table and "original (floor)" in table and "CLIP-DC" in table
    assert "loaded 3,000 Gaussians" in table and "CSD of 3 stylized" in table and "CLIP-DC along orbit path" in table
    for stage in ("render original views", "render stylized views", "render original path", "render stylized path",
                  "CFSD", "warp step 1 (stylized)", "warp step 2 (floor)"):
        assert f"{stage}: 100%" in printed.err, stage  # a progress bar ran to its end


def test_stylized_scene_and_its_2d_views(inputs, no_cached_models, tmp_path):
    scene_report = _evaluate(inputs, tmp_path / "scene.json", "--stylized", str(inputs["stylized"]), "--path", "interp")
    metrics = scene_report["metrics"]
    assert metrics["cfsd"]["mean"] > 0
    assert metrics["warp"]["stylized"]["short"]["rmse"] != metrics["warp"]["floor"]["short"]["rmse"]
    assert metrics["csd"]["skipped"].startswith("no --csd given; CSD style descriptor weights (ViT-L/14) not found")
    assert "hf download openai/clip-vit-large-patch14" in metrics["clip_dc"]["skipped"]

    # The same stylized views as 2D images (as the diffusion stage writes them) score the same,
    # up to 8-bit quantisation.
    cameras = load_cameras(inputs["cameras"]).subset([0, 1, 2]).scaled(SCALE)
    views = render_views(load_scene(inputs["stylized"]), cameras).rgb
    images = tmp_path / "views"
    images.mkdir()
    for name, view in zip(cameras.names, views):
        save_png(view, images / f"{name}.png")
    image_report = _evaluate(inputs, tmp_path / "images.json", "--stylized-images", str(images))
    image_metrics = image_report["metrics"]
    assert image_metrics["cfsd"]["mean"] == pytest.approx(metrics["cfsd"]["mean"], rel=0.02)
    for label in ("short", "long"):
        assert image_metrics["warp"]["stylized"][label]["rmse"] == pytest.approx(
            metrics["warp"]["stylized"][label]["rmse"], abs=2e-3)
    assert image_metrics["warp"]["floor"] == metrics["warp"]["floor"]


def test_cli_reports_bad_input_with_exit_code_2(inputs, tmp_path, capsys):
    code = main(["evaluate", "--original", str(inputs["original"]), "--stylized-images", str(tmp_path / "none"),
                 "--cameras", str(inputs["cameras"]), "--style", str(tmp_path / "missing.png")])
    assert code == 2
    assert f"error: --style: {tmp_path / 'missing.png'}: image file not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["evaluate", "--original", "a.ply", "--stylized", "b.ply", "--stylized-images", "c",
              "--cameras", "t.json", "--style", "s.png"])


def test_view_images_and_model_files_are_named_before_the_scene_loads(inputs, tmp_path, capsys):
    """A folder of 2D views missing one, or a --vgg that is no VGG, was named only after every view and path
    rendered."""
    images, broken, wide = tmp_path / "views", tmp_path / "broken", tmp_path / "wide"
    for folder in (images, broken, wide):
        folder.mkdir()
    names = load_cameras(inputs["cameras"]).subset([int(v) for v in VIEWS.split(",")]).names
    for name in names:
        (broken / f"{name}.png").write_text("not an image")
        size = (64, 66) if name == names[-1] else (128, 128)  # the views: 512x512; 128x128 is resized
        save_png(torch.zeros(*size, 3), wide / f"{name}.png")
    for options, message in [(["--stylized-images", str(tmp_path / "none")], r"--stylized-images: .*none is not a folder"),
                             (["--stylized-images", str(images)], r"--stylized-images: .*views has no image for view "),
                             (["--stylized-images", str(broken)], r"--stylized-images: .*\.png: not a readable image"),
                             # it was stretched to the views' 512x512
                             (["--stylized-images", str(wide)], rf"--stylized-images: .*wide/{names[-1]}\.png: 66x64 "
                              r"pixels, not the aspect of the evaluated views' 512x512 \(it would be stretched\)"),
                             (["--stylized", str(inputs["original"]), "--vgg", str(inputs["style"])],
                              r"--vgg: weights .*: not a readable torch file")]:
        code = main(["evaluate", "--original", str(inputs["original"]), *options, "--cameras", str(inputs["cameras"]),
                     "--style", str(inputs["style"]), "--views", VIEWS, "--out", str(tmp_path / "r.json")])
        captured = capsys.readouterr()
        assert code == 2 and re.search(message, captured.err) and "loading" not in captured.out, captured


def test_the_views_built_around_the_scene_are_checked_before_anything_loads(inputs, tmp_path, capsys, monkeypatch):
    """Without --cameras, --views past the last view orbiting the scene, --path interp through one view and a folder
    of 2D views missing one or of another aspect were named only once the models and the scene had loaded; the views'
    names and size follow from --orbit-views, --orbit-size and --scale."""
    def reached(*args, **kwargs):
        raise ValueError("reached")

    monkeypatch.setattr("artnvg_core.cli.evaluate.load_vgg", reached)  # the first load after the checks
    images = tmp_path / "views"
    images.mkdir()
    save_png(torch.zeros(8, 8, 3), images / "orbit_0000.png")
    save_png(torch.zeros(8, 16, 3), images / "orbit_0001.png")
    stylized = ["--stylized", str(inputs["stylized"])]
    for options, message in [([*stylized, "--views", "0,4"], r"--views: view index 4 is out of range for 4 cameras "
                              r"\(0\.\.3\)"),
                             ([*stylized, "--views", "2", "--path", "interp"], "--path interp: needs at least 2 "
                              r"evaluated views \(see --views\)"),
                             (["--stylized-images", str(images), "--views", "0,2"], "--stylized-images: .*views has no "
                              "image for view orbit_0002 "),
                             (["--stylized-images", str(images), "--views", "1"], r"--stylized-images: .*orbit_0001\.png: "
                              "16x8 pixels, not the aspect of the evaluated views' 32x32"),
                             ([*stylized, "--views", "0,3", "--path", "interp"], "--vgg: reached"),
                             (["--stylized-images", str(images), "--views", "0"], "--vgg: reached")]:
        code = main(["evaluate", "--original", str(inputs["original"]), *options, "--orbit-views", "4",
                     "--orbit-size", "64", "--scale", "0.5", "--style", str(inputs["style"]),
                     "--out", str(tmp_path / "r.json")])
        captured = capsys.readouterr()
        assert code == 2 and re.match(f"error: {message}", captured.err), captured.err
        assert "loading" not in captured.out


def test_input_errors_name_the_problem(inputs, tmp_path):
    cameras = load_cameras(inputs["cameras"]).subset([0, 1])
    save_png(torch.zeros(8, 8, 3), tmp_path / f"{cameras.names[0]}.png")
    with pytest.raises(ValueError, match=f"has no image for view {cameras.names[1]}"):
        load_view_images(tmp_path, cameras)
    with pytest.raises(ValueError, match="is not a folder"):
        load_view_images(tmp_path / "nothing", cameras)
    assert load_view_images(tmp_path, cameras.subset([0]).scaled(0.05)).shape == (1, 26, 26, 3)  # resized
    save_png(torch.zeros(8, 12, 3), tmp_path / f"{cameras.names[0]}.png")  # it was stretched to 26x26
    with pytest.raises(ValueError, match=rf"--stylized-images: .*{cameras.names[0]}\.png: 12x8 pixels, not the aspect "
                                         r"of the evaluated views' 26x26 \(it would be stretched\)"):
        load_view_images(tmp_path, cameras.subset([0]).scaled(0.05))
    with pytest.raises(ValueError, match="--path interp: needs at least 2"):
        camera_path(cameras, [0], "interp", 10, 1.0)
    with pytest.raises(ValueError, match="--frames: need at least 2"):
        camera_path(cameras, [0, 1], "orbit", 1, 1.0)
    with pytest.raises(ValueError, match=r"--views: view 1 is given twice in '0,1,1'"):  # it would count twice
        _evaluate(inputs, tmp_path / "twice" / "report.json", "--stylized", str(inputs["original"]),
                  "--views", "0,1,1")


def test_orbit_error_names_only_cli_options(inputs):
    """Cameras that give no orbit (all at one point and looking one way, or one camera): the advice
    names --path interp, not orbit_path's own center= or up= arguments."""
    cameras = load_cameras(inputs["cameras"]).subset([0, 0, 0])
    for subset in (cameras, cameras.subset([0])):
        with pytest.raises(ValueError, match=r"--path orbit: no orbit around these cameras .*use --path interp") as error:
            camera_path(subset, [0, 1], "orbit", 10, 1.0)
        assert "=" not in str(error.value)


def test_a_path_the_cameras_give_none_of_is_refused_before_the_scenes_load(inputs, tmp_path, capsys):
    """One view: '--path orbit: no orbit' came after the first scene had loaded."""
    capture = json.loads(Path(inputs["cameras"]).read_text())
    (tmp_path / "one.json").write_text(json.dumps({**capture, "frames": capture["frames"][:1]}))
    code = main(["evaluate", "--original", str(inputs["original"]), "--stylized", str(inputs["original"]), "--cameras",
                 str(tmp_path / "one.json"), "--style", str(inputs["style"]), "--out", str(tmp_path / "r.json")])
    captured = capsys.readouterr()
    assert code == 2 and "error: --path orbit: no orbit around these cameras" in captured.err, captured
    assert "loading" not in captured.out


def _cli(inputs, *options):
    return main(["evaluate", "--original", str(inputs["original"]), "--stylized", str(inputs["original"]),
                 "--cameras", str(inputs["cameras"]), "--style", str(inputs["style"]), "--views", VIEWS,
                 "--scale", str(SCALE), "--device", "cpu", *options])


@pytest.mark.parametrize("option, value", [("--alpha-threshold", "nan"), ("--alpha-threshold", "2"),
                                           ("--alpha-threshold", "1"), ("--alpha-threshold", "-0.1"),
                                           ("--depth-tolerance", "-1"), ("--depth-tolerance", "0"),
                                           ("--depth-tolerance", "nan"), ("--scale", "inf"), ("--scale", "nan"),
                                           ("--scale", "0"), ("--scale", "x"), ("--frames", "1"),
                                           ("--long-step", "0")])
def test_bad_numbers_exit_2_naming_the_option(inputs, capsys, option, value):
    with pytest.raises(SystemExit) as exit_:
        _cli(inputs, option, value)
    assert exit_.value.code == 2 and f"error: argument {option}: expected" in capsys.readouterr().err


def test_outputs_checked_before_any_work(inputs, tmp_path, capsys):
    (tmp_path / "file").write_text("x")
    (tmp_path / "taken_strip.png").mkdir()
    for out, message in [("", "--out: the output path is empty"), (tmp_path, "is a folder"),
                         (tmp_path / "file" / "r.json", "file is a file, not a folder"),
                         (tmp_path / "taken.json", r"--out \(its strip taken_strip\.png\): .* is a folder"),
                         (tmp_path / "report.txt", r"--out: .*report\.txt: the report is JSON")]:
        assert _cli(inputs, "--out", str(out)) == 2
        err = capsys.readouterr().err
        assert "error: " in err and re.search(message, err) and "loading" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "taken_strip.png"]


def test_an_output_that_is_one_of_its_inputs_is_refused_before_any_work(inputs, tmp_path, capsys):
    """Found probing the writers: the strip written beside --out (NAME_strip.png) could be the style image,
    which evaluate wrote over at its end."""
    style = tmp_path / "out_strip.png"
    style.write_bytes(inputs["style"].read_bytes())
    assert _cli(inputs, "--style", str(style), "--out", str(tmp_path / "out.json")) == 2
    err = capsys.readouterr().err
    assert re.search(r"--out's strip: .*out_strip\.png is the same file as --style", err) and "loading" not in err, err
    assert style.read_bytes() == inputs["style"].read_bytes() and sorted(p.name for p in tmp_path.iterdir()) == [
        "out_strip.png"]


def test_a_failing_evaluate_writes_none_of_its_outputs(inputs, tmp_path, monkeypatch, capsys):
    from artnvg_core.cli import evaluate as report

    out = tmp_path / "eval" / "r.json"
    out.parent.mkdir()
    out.write_text("earlier report")

    def fail(report_dict, path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report, "_write_json", fail)
    assert _cli(inputs, "--out", str(out), "--views", "0,1", "--frames", "2", "--long-step", "1") == 2
    assert "No space left on device" in capsys.readouterr().err
    assert sorted(p.name for p in out.parent.iterdir()) == ["r.json"] and out.read_text() == "earlier report"


def test_the_table_keeps_a_skipped_metrics_reason_apart_from_its_value():
    """'warp step 7   skippedneeds more than 7 views' was printed for an evaluation of fewer views."""
    short = {"step": 1, "rmse": 0.067, "mae": 0.0479, "coverage": 0.5583}
    long = {"step": 7, "skipped": "needs more than 7 views"}
    warp = {key: {"short": short, "long": long} for key in ("stylized", "floor")}
    report = {"metrics": {"cfsd": {"resolution": [128, 128], "mean": 0.0411}, "warp": warp,
                          "csd": {"skipped": "no --csd given"}, "clip_dc": {"skipped": "no --clip given"}}}
    rows = format_table(report).splitlines()
    assert any(re.fullmatch("warp step 7 +skipped  needs more than 7 views", row) for row in rows), rows
    assert len({len(row) for row in rows[:5]}) == 1  # the other columns as aligned as before
