"""The command line's own output: progress while loading and rendering (evaluate: tests/test_cli_evaluate.py)."""

import re
import sys

import pytest

from artnvg_core.cli.main import main
from artnvg_core.formats import load_scene, save_scene, write_ply
from artnvg_core.images import load_image
from artnvg_core.stylize import DemoInputs
from child_process import child_env


def test_render_reports_loading_and_each_view(tmp_path, capsys):
    demo = DemoInputs()
    scene = tmp_path / "scene.ply"
    write_ply(load_scene(demo.scene).select(slice(0, None, 40)), scene)  # 1,000 Gaussians: quick renders
    assert main(["render", str(scene), "--cameras", str(demo.cameras), "--out", str(tmp_path / "out"),
                 "--views", "0,5,9", "--scale", "0.1", "--device", "cpu"]) == 0
    lines = capsys.readouterr().out.splitlines()  # no note on the demo's lens: it moves a corner by 0.6 px
    assert re.fullmatch(rf"loading {re.escape(str(scene))} \(0\.1 MiB\)", lines[0])
    assert lines[1].startswith("loaded 1,000 Gaussians (SH degree 1) in ")
    assert lines[2].startswith("rendering 3 views at ")
    views = [line for line in lines if line.startswith("[")]
    assert [line.split("]")[0] + "]" for line in views] == ["[1/3]", "[2/3]", "[3/3]"]
    assert len(list((tmp_path / "out").glob("*.png"))) == 3
    assert main(["render", str(scene), "--cameras", str(demo.cameras), "--out", str(tmp_path / "one"), "--views", "0",
                 "--scale", "0.1", "--device", "cpu"]) == 0
    assert capsys.readouterr().out.splitlines()[2].startswith("rendering 1 view at ")  # was "1 views"


def _small_scene(tmp_path):
    scene = tmp_path / "scene.ply"
    write_ply(load_scene(DemoInputs().scene).select(slice(0, None, 40)), scene)
    return scene


@pytest.mark.parametrize("command", ["render", "stylize"])
@pytest.mark.parametrize("value", ["inf", "nan", "0", "-1", "x"])
def test_bad_scale_exits_2_naming_it(tmp_path, capsys, command, value):
    with pytest.raises(SystemExit) as exit_:
        main([command, "scene.ply", "--cameras", "t.json", "--style", "s.png", "--out", str(tmp_path), "--scale", value])
    assert exit_.value.code == 2 and "error: argument --scale: expected" in capsys.readouterr().err


def test_absurd_size_refused_before_rendering(tmp_path, capsys):
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    out = tmp_path / "renders"
    assert main(["render", str(scene), "--cameras", str(demo.cameras), "--out", str(out), "--scale", "1e6"]) == 2
    captured = capsys.readouterr()
    assert "error: CameraSet.scaled: factor 1000000.0 makes" in captured.err and "rendering" not in captured.out
    assert not out.exists()


def test_tiny_scale_renders_one_pixel_views(tmp_path):
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    assert main(["render", str(scene), "--cameras", str(demo.cameras), "--out", str(tmp_path / "r"), "--views", "0",
                 "--scale", "1e-6", "--device", "cpu"]) == 0
    assert load_image(next((tmp_path / "r").glob("*.png"))).shape == (1, 1, 3)


@pytest.mark.parametrize("cameras", [True, False])
def test_render_names_a_view_given_twice_before_loading(tmp_path, capsys, cameras):
    scene = _small_scene(tmp_path)
    given = ["--cameras", str(DemoInputs().cameras)] if cameras else ["--orbit-views", "4"]
    assert main(["render", str(scene), *given, "--out", str(tmp_path / "r"), "--views", "1,0,1"]) == 2
    captured = capsys.readouterr()
    assert "error: --views: view 1 is given twice in '1,0,1'; give each view once" in captured.err, captured.err
    assert "loading" not in captured.out and not (tmp_path / "r").exists()


@pytest.mark.parametrize("command", ["render", "stylize", "evaluate", "blend"])
def test_a_folder_given_as_a_scene_is_named_as_one_before_any_loading(tmp_path, capsys, command):
    demo, folder = DemoInputs(), tmp_path / "capture"
    folder.mkdir()
    inputs = {"render": [str(folder), "--device", "cpu"], "stylize": [str(folder), "--style", str(demo.style)],
              "evaluate": ["--original", str(demo.scene), "--stylized", str(folder), "--style", str(demo.style)],
              "blend": [str(demo.scene), str(folder), "--strength", "0.5"]}
    out = tmp_path / "out" / ("report.json" if command == "evaluate" else "s.ply")
    assert main([command, *inputs[command], "--cameras", str(demo.cameras), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err == (f"error: {folder}: scene file is a folder, not a regular file; expected .ply (INRIA 3DGS or "
                            "compressed PLY), .splat, .spz, .ksplat or .ckpt (nerfstudio splatfacto checkpoint)\n")
    assert "loading" not in captured.out and not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["render", "stylize"])
def test_outputs_checked_before_loading(tmp_path, capsys, command):
    demo = DemoInputs()
    (tmp_path / "file").write_text("x")
    (tmp_path / "taken.contact.png").mkdir()
    cases = [("", "the output (path|folder) is empty"), (tmp_path / "file" / "x.ply", "file is a file, not a folder")]
    cases += [(tmp_path / "file", "exists and is not a folder")] if command == "render" else [
        (tmp_path, "a scene file name is wanted"), (tmp_path / "taken.ply", r"\(its contact sheet\): .* is a folder")]
    style = ["--style", str(demo.style)] if command == "stylize" else []
    for out, message in cases:
        code = main([command, str(demo.scene), "--cameras", str(demo.cameras), *style, "--out", str(out), "--device", "cpu"])
        captured = capsys.readouterr()
        assert code == 2 and re.search("error: --out.*" + message, captured.err) and "loading" not in captured.out, captured
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "taken.contact.png"]


@pytest.mark.parametrize("command", ["stylize", "blend"])
def test_a_folder_given_as_out_is_told_a_scene_file_name_is_wanted(tmp_path, capsys, command):
    """'--out o2/' once said "cannot write scene file type ''"."""
    demo = DemoInputs()
    inputs = ["--style", str(demo.style)] if command == "stylize" else [str(demo.scene), "--strength", "1"]
    assert main([command, str(demo.scene), *inputs, "--out", f"{tmp_path / 'o2'}/"]) == 2
    captured = capsys.readouterr()
    assert captured.err == (f"error: --out: {tmp_path / 'o2'}/: a scene file name is wanted, ending in one of .ply, "
                            f".spz, .splat, .ksplat (e.g. {tmp_path / 'o2.ply'}, or {tmp_path / 'o2' / 'NAME.ply'} in "
                            f"folder {tmp_path / 'o2'})\n")
    assert "loading" not in captured.out and list(tmp_path.iterdir()) == []


def test_a_scene_type_that_cannot_be_written_is_refused_before_any_work(tmp_path, capsys):
    demo = DemoInputs()
    out = tmp_path / "result.txt"
    assert main(["stylize", str(demo.scene), "--cameras", str(demo.cameras), "--style", str(demo.style),
                 "--out", str(out), "--stylizer", "nnfm", "--iters", "1", "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert captured.err == (f"error: --out: {out}: cannot write scene file type '.txt'; "
                            "expected one of .ply, .spz, .splat, .ksplat\n")
    assert captured.out == "" and list(tmp_path.iterdir()) == []


def test_a_scene_refused_by_its_writer_is_named_by_the_users_path(tmp_path, capsys, monkeypatch):
    """The writer sees a temporary file (both outputs appear together); its message names --out."""
    import artnvg_core.stylize

    monkeypatch.setattr(artnvg_core.stylize, "stylize_nnfm", lambda scene, *args, **kwargs: scene.select(slice(0, 0)))
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    out = tmp_path / "s" / "stylized.ply"
    assert main(["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out", str(out),
                 "--stylizer", "nnfm", "--scale", "0.05", "--device", "cpu"]) == 2
    err = capsys.readouterr().err  # after the contact sheet's bars
    assert err.endswith(f"]\nerror: {out}: not written: the scene contains no Gaussians\n"), err
    assert list(out.parent.iterdir()) == []


@pytest.mark.parametrize("option, expected", [([], "tf32"), (["--nnfm-search", "bf16"], "bf16")])
def test_nnfm_search_reaches_the_finetune(tmp_path, monkeypatch, option, expected):
    """--nnfm-search (default tf32, the choice BENCHMARKS.md prices) is the finetune's search arithmetic."""
    import artnvg_core.stylize

    seen = []
    monkeypatch.setattr(artnvg_core.stylize, "stylize_nnfm",
                        lambda scene, cameras, style, config, **kwargs: seen.append(config.nnfm_search) or scene)
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    assert main(["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out",
                 str(tmp_path / "o.ply"), "--stylizer", "nnfm", "--scale", "0.05", "--device", "cpu", *option]) == 0
    assert seen == [expected]


def test_a_failing_stylize_writes_neither_output(tmp_path, capsys, monkeypatch):
    import artnvg_core.stylize

    def full_disk(image, path):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(artnvg_core.stylize, "save_png", full_disk)
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    out = tmp_path / "s" / "stylized.ply"
    out.parent.mkdir()
    out.write_text("an earlier result")
    assert main(["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out", str(out),
                 "--stylizer", "nnfm", "--iters", "1", "--scale", "0.05", "--device", "cpu"]) == 2
    assert capsys.readouterr().err.endswith(f"error: [Errno 28] No space left on device: '{out}, "
                                            f"{out.parent / 'stylized.contact.png'}'\n")
    assert [p.name for p in out.parent.iterdir()] == ["stylized.ply"] and out.read_text() == "an earlier result"


@pytest.mark.parametrize("failure", [MemoryError(), RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried")])
def test_out_of_memory_is_an_error_with_advice(tmp_path, capsys, monkeypatch, failure):
    import artnvg_core.cameras

    def exhausted(path, notes):
        raise failure

    monkeypatch.setattr(artnvg_core.cameras, "load_cameras", exhausted)
    command = ["render", str(_small_scene(tmp_path)), "--cameras", "t.json", "--out", str(tmp_path / "r")]
    assert main(command) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: out of memory (") and "try a smaller --scale" in err
    monkeypatch.setattr(artnvg_core.cameras, "load_cameras", lambda path, notes: 1 / 0)
    with pytest.raises(ZeroDivisionError):  # other failures are not disguised
        main(command)


def test_gsplat_kernel_build_is_announced_on_stdout_before_it_starts(monkeypatch, capsys):
    """The commands load the rasterizer before their first render; gsplat's build (stood in for
    here) is announced on stdout, before it starts and with its time after, once."""
    import torch

    from artnvg_core import raster
    from artnvg_core.cli import common
    from artnvg_core.raster import gsplat_backend

    monkeypatch.setattr(raster, "choose_backend", lambda backend, device, dtype=None: "gsplat")
    monkeypatch.setattr(gsplat_backend, "_loaded", False)
    monkeypatch.setattr(gsplat_backend, "build_pending", lambda: True)
    monkeypatch.setattr(gsplat_backend, "_import_kernels", lambda: print("(building)") or object())
    common.prepare_rasterizer(torch.device("cuda"))
    common.prepare_rasterizer(torch.device("cuda"))
    lines = capsys.readouterr().out.splitlines()
    assert lines[:2] == [gsplat_backend.BUILD_NOTICE, "(building)"] and len(lines) == 3
    assert lines[2].startswith("gsplat: CUDA kernels built in ")


def _stylize(scene, style, out, *extra):
    demo = DemoInputs()
    return main(["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(style), "--out", str(out),
                 "--stylizer", "nnfm", "--iters", "1", "--scale", "0.05", "--device", "cpu", *extra])


def test_stylize_never_writes_over_its_inputs(tmp_path, capsys):
    """The scene, the style image (as the contact sheet: S.contact.png for --out S.ply) and a hard link to
    the scene are refused as outputs before anything is loaded; every input is left as it was."""
    import os

    scene = _small_scene(tmp_path)
    style = tmp_path / "S.contact.png"
    style.write_bytes(DemoInputs().style.read_bytes())
    os.link(scene, tmp_path / "linked.ply")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    cases = [(scene, DemoInputs().style, r"--out: .*scene\.ply is the same file as SCENE"),
             (tmp_path / "S.ply", style, r"--out's contact sheet: .*S\.contact\.png is the same file as --style"),
             (tmp_path / "linked.ply", DemoInputs().style, r"--out: .*linked\.ply is the same file as SCENE")]
    for out, style_image, message in cases:
        assert _stylize(scene, style_image, out) == 2
        captured = capsys.readouterr()
        assert re.search(r"^error: " + message + r".*would write over its own input", captured.err), captured.err
        assert "loading" not in captured.out
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_bad_lora_is_refused_naming_it_before_any_work(tmp_path, capsys):
    """A strength that is not a number (by the parser) and a missing file: each an error naming the option or
    file, before the scene is loaded (a LoRA given to a stylizer without SDXL: the test below)."""
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    common = ["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out",
              str(tmp_path / "out.ply"), "--device", "cpu"]
    with pytest.raises(SystemExit) as exit_:
        main([*common, "--lora", "style.safetensors:strong"])
    assert exit_.value.code == 2
    assert ("error: argument --lora: 'style.safetensors:strong': strength 'strong' is not a number"
            in capsys.readouterr().err)
    missing = tmp_path / "missing.safetensors"
    for stylizer in ("auto", "nnfm"):
        assert main([*common, "--lora", f"{missing}:0.5", "--stylizer", stylizer]) == 2
        captured = capsys.readouterr()
        assert f"error: LoRA '{missing}': no such file" in captured.err and "loading" not in captured.out, captured
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


def test_render_never_writes_over_the_captures_photos(tmp_path, capsys):
    import json

    demo = DemoInputs()
    transforms = json.loads(demo.cameras.read_text())
    for frame in transforms["frames"]:
        frame["file_path"] = frame["file_path"].replace(".jpg", ".png")
    (tmp_path / "images").mkdir()
    for frame in transforms["frames"][:3]:
        (tmp_path / frame["file_path"]).write_bytes(b"a photo")
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    scene = _small_scene(tmp_path)
    assert main(["render", str(scene), "--cameras", str(tmp_path / "transforms.json"), "--out",
                 str(tmp_path / "images"), "--views", "0,1", "--device", "cpu", "--overwrite"]) == 2
    captured = capsys.readouterr()
    assert re.search(r"error: --out: .*frame_\d+\.png is the same file as the capture's image .*frame_\d+\.png",
                     captured.err) and "loading" not in captured.out
    assert all(p.read_bytes() == b"a photo" for p in (tmp_path / "images").iterdir())


@pytest.mark.parametrize("suffix, field, value, message", [
    (".splat", "log_scales", 95.0, r"log_scales: 2 of 1,?000 Gaussians lie outside \[-87\.0, 88\.0\]"),
    (".ksplat", "log_scales", -95.0, r"log_scales: 2 of 1,?000 Gaussians lie outside"),
    (".spz", "means", 1e30, r"means: 2 Gaussians of 1,000 with a \|coordinate\| of 2\^23 or more \(up to 1e\+30\)"),
])
def test_a_scene_the_output_format_cannot_hold_is_refused_before_the_finetune(tmp_path, capsys, monkeypatch,
                                                                              suffix, field, value, message):
    """The finetune keeps positions and scales: a log-scale of 95 (.splat, .ksplat) or a coordinate of
    1e30 (.spz, on two Gaussians of 1,000: it would move one onto its range) is refused right after loading,
    not at the save after the whole finetune."""
    import artnvg_core.stylize

    def no_finetune(*args, **kwargs):
        raise AssertionError("the finetune ran")

    monkeypatch.setattr(artnvg_core.stylize, "stylize_nnfm", no_finetune)
    scene = load_scene(DemoInputs().scene).select(slice(0, None, 40))
    getattr(scene, field)[3:5, 1] = value
    write_ply(scene, tmp_path / "scene.ply")
    out = tmp_path / f"out{suffix}"
    assert _stylize(tmp_path / "scene.ply", DemoInputs().style, out) == 2
    err = capsys.readouterr().err
    assert re.search(rf"^error: --out: .*out\{suffix}: not written: {message}.*choose \.ply", err, re.M), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


def test_invalid_gaussians_are_refused_in_the_clis_words_and_dropped_with_drop_invalid(tmp_path, capsys, caplog):
    import struct

    path = _small_scene(tmp_path)
    data = path.read_bytes()
    body = data.index(b"end_header\n") + len(b"end_header\n")
    record = (len(data) - body) // 1000
    path.write_bytes(data[: body + 5 * record] + struct.pack("<f", float("nan")) + data[body + 5 * record + 4 :])  # x of 5
    (tmp_path / "nan.ply").write_bytes(path.read_bytes())
    demo, out = DemoInputs(), tmp_path / "r"
    command = ["render", str(tmp_path / "nan.ply"), "--cameras", str(demo.cameras), "--out", str(out), "--views", "0",
               "--scale", "0.05", "--device", "cpu"]
    assert main(command) == 2
    err = capsys.readouterr().err
    assert err.rstrip().endswith("give --drop-invalid to drop them") and "drop_invalid=True" not in err
    with caplog.at_level("INFO"):
        assert main(command + ["--drop-invalid"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[1] == "note: dropped 1 invalid Gaussian of 1,000 (means: 1 with non-finite values)"
    assert lines[0].startswith("loading ") and lines[2].startswith("loaded 999 Gaussians (SH degree 1) in ")
    assert captured.out.count("dropped") == 1 and "dropped" not in captured.err
    assert not [record for record in caplog.records if "dropped" in record.getMessage()]


def test_the_axes_a_spz_is_read_in_are_printed_once_between_its_loading_lines(tmp_path, capsys, caplog):
    """Without --cameras nothing chooses the axes of a .spz that names none: the PLY's are taken, as said."""
    scene = tmp_path / "scene.spz"
    save_scene(load_scene(DemoInputs().scene).select(slice(0, None, 40)), scene)
    with caplog.at_level("INFO"):
        assert main(["render", str(scene), "--out", str(tmp_path / "out"), "--views", "0", "--orbit-views", "2",
                     "--scale", "0.05", "--device", "cpu"]) == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[0].startswith(f"loading {scene} ") and lines[2].startswith("loaded 1,000 Gaussians")
    assert lines[1] == ("note: the file names no axes: read in the PLY's axes (x right, y down, z forward), as "
                        "splat-transform, spz-js and Niantic's ply-to-spz write; if it is upside down, read it with "
                        "spz axes 'rub' (--spz-axes rub, the Load Gaussian Scene node's spz_axes)")
    assert captured.out.count("names no axes") == 1 and "names no axes" not in captured.err
    assert not [record for record in caplog.records if "names no axes" in record.getMessage()]


def test_out_of_memory_while_loading_does_not_advise_a_smaller_scale(tmp_path, capsys, monkeypatch):
    import artnvg_core.formats

    def exhausted(path, **options):
        raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 9 GB")

    monkeypatch.setattr(artnvg_core.formats, "load_scene", exhausted)
    assert main(["render", str(_small_scene(tmp_path)), "--out", str(tmp_path / "r"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: out of memory (") and "scene.ply needs more memory to load than is free on cpu" in err
    assert "--scale" not in err


@pytest.mark.parametrize("option, value", [("--seed", "-1"), ("--seed", str(2**64)), ("--iters", "-5")])
def test_seed_and_iters_are_checked_by_the_parser_naming_the_option(capsys, option, value):
    with pytest.raises(SystemExit) as exit_:
        main(["stylize", "scene.ply", "--style", "s.png", option, value])
    assert exit_.value.code == 2 and f"error: argument {option}: expected an integer >= 0" in capsys.readouterr().err


def test_help_names_every_scene_format(capsys):
    for command in ("render", "stylize"):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert ".ksplat" in text and ".spz" in text and ".ckpt" in text, command


def test_stylize_refuses_a_bad_out_before_importing_the_diffusion_libraries(tmp_path):
    """The refusal must come within the command's start-up (it once took 5-9 s importing diffusers)."""
    import subprocess
    import sys

    code = ("import sys; from artnvg_core.cli.main import main; "
            f"status = main(['stylize', {str(_small_scene(tmp_path))!r}, '--style', {str(DemoInputs().style)!r}, "
            f"'--out', {str(tmp_path / 'out.txt')!r}]); "
            "print(status, sorted(m for m in ('diffusers', 'transformers') if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            env=child_env(), cwd=str(DemoInputs().scene.parents[2]))
    assert result.stdout.split("\n")[0] == "2 []" and "cannot write scene file type '.txt'" in result.stderr


def test_stylize_keeps_peft_out_of_a_process_without_a_lora(tmp_path):
    """diffusers imports PEFT when it can find it: a stylize process (``python -m artnvg_core``) given no
    --lora hides it first, one given a LoRA keeps it, and main() called inside another process (a test's,
    a batch worker's) leaves it alone."""
    import subprocess
    import sys

    stylize = (f"['stylize', {str(_small_scene(tmp_path))!r}, '--style', {str(DemoInputs().style)!r}, "
               f"'--out', {str(tmp_path / 'out.txt')!r}")  # refused at once: '.txt'
    code = ("import importlib.util, sys; from artnvg_core.cli.main import main; "
            f"main({stylize}, '--lora', 'style.safetensors'], whole_process=True); "
            f"main({stylize}]); print(importlib.util.find_spec('peft') is not None); "
            f"main({stylize}], whole_process=True); import diffusers.utils.import_utils as u; "
            "print(u.is_peft_available(), importlib.util.find_spec('peft'))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                            env=child_env(), cwd=str(DemoInputs().scene.parents[2]))
    assert result.stdout.split("\n")[:2] == ["True", "False None"]


def test_the_process_ends_with_its_exit_handlers_run_and_streams_flushed(tmp_path):
    """python -m artnvg_core ends through exit_without_teardown: the status is kept, atexit handlers run and
    what was printed but not yet flushed comes out."""
    import subprocess
    import sys

    code = ("import atexit, pathlib, sys; from artnvg_core.cli.main import exit_without_teardown; "
            f"atexit.register(lambda: pathlib.Path({str(tmp_path / 'ran')!r}).write_text('yes')); "
            "sys.stdout.write('no newline, not flushed'); sys.stderr.write('err'); exit_without_teardown(3)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            env=child_env(), cwd=str(DemoInputs().scene.parents[2]))
    assert result.returncode == 3 and result.stdout == "no newline, not flushed" and result.stderr == "err"
    assert (tmp_path / "ran").read_text() == "yes"


def test_spz_axes_default_reads_a_spz_in_front_of_the_cameras_and_writes_the_plys_axes(tmp_path, capsys):
    """render of a .spz holding RUB with no record renders as the scene itself by default (its --cameras
    decide), upside down with --spz-axes ply; stylize writes its .spz in the PLY's axes by default (here as
    --spz-version 2 asks)."""
    import gzip

    from artnvg_core.formats import save_scene

    demo, scene = DemoInputs(), _small_scene(tmp_path)
    save_scene(load_scene(scene), tmp_path / "rub.spz", spz_axes="rub")
    renders = {}
    for name, source, extra in [("auto", "rub.spz", []), ("ply_axes", "rub.spz", ["--spz-axes", "ply"]),
                                ("ply", "scene.ply", [])]:
        assert main(["render", str(tmp_path / source), "--cameras", str(demo.cameras), "--out", str(tmp_path / name),
                     "--views", "0", "--scale", "0.1", "--device", "cpu", *extra]) == 0
        renders[name] = load_image(next((tmp_path / name).glob("*.png")))
    assert (renders["auto"] - renders["ply"]).abs().mean() < 0.01
    assert (renders["ply_axes"] - renders["ply"]).abs().mean() > 0.05
    assert _stylize(scene, demo.style, tmp_path / "out.spz", "--spz-version", "2") == 0
    assert gzip.decompress((tmp_path / "out.spz").read_bytes())[4] == 2  # the header's version
    kept = load_scene(tmp_path / "out.spz", spz_axes="ply").means
    assert (kept - load_scene(scene).means).abs().max() <= 2.0**-12


@pytest.mark.parametrize("command", [["stylize", "scene.ply", "--style", "s.png"],
                                     ["blend", "a.ply", "b.ply", "--strength", "1"]])
def test_an_spz_version_other_than_2_or_3_is_refused_by_name(tmp_path, capsys, command):
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--out", str(tmp_path / "o.spz"), "--spz-version", "4"])
    assert exit_.value.code == 2
    assert "argument --spz-version: invalid choice: 4 (choose from 2, 3)" in capsys.readouterr().err


@pytest.mark.slow
def test_a_diffusion_free_preview_imports_no_diffusion_library(tmp_path):
    """A whole ``stylize --preset preview`` run in a fresh process (the demo at 1/8 size, 2 steps) never
    imports diffusers, transformers or peft: seconds of start-up the preview does not need. (torch._dynamo
    is not asserted: on the CPU the reference rasterizer's activation checkpointing imports it.)"""
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "preview.ply"
    code = ("import sys\nfrom artnvg_core.cli.main import main\n"
            f"assert main(['stylize', '--preset', 'preview', '--iters', '2', '--scale', '0.125', '--device', 'cpu', "
            f"'--out', {str(out)!r}]) == 0\n"
            "print(sorted(m for m in ('diffusers', 'transformers', 'peft') if m in sys.modules))")
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert any(line.startswith("stylizer: nnfm (preset preview: ") for line in lines), done.stdout
    assert lines[-1] == "[]" and out.is_file()


def test_render_into_a_folder_that_is_not_empty_needs_overwrite(tmp_path, capsys):
    scene, out = _small_scene(tmp_path), tmp_path / "out"
    out.mkdir()
    (out / "kept.png").write_bytes(b"an earlier render")
    command = ["render", str(scene), "--cameras", str(DemoInputs().cameras), "--out", str(out), "--views", "0",
               "--scale", "0.1", "--device", "cpu"]
    assert main(command) == 2
    captured = capsys.readouterr()
    assert f"error: --out: {out} is not empty; give an empty or new folder, or --overwrite" in captured.err
    assert "loading" not in captured.out and sorted(p.name for p in out.iterdir()) == ["kept.png"]
    assert main([*command, "--overwrite"]) == 0
    assert (out / "kept.png").read_bytes() == b"an earlier render" and len(list(out.glob("*.png"))) == 2


def test_render_refuses_long_view_names_and_huge_plans_before_loading(tmp_path, capsys, monkeypatch):
    import json

    import artnvg_core.raster as raster

    transforms = json.loads(DemoInputs().cameras.read_text())
    transforms["frames"][0]["file_path"] = "images/" + "v" * 250 + ".jpg"
    (tmp_path / "transforms.json").write_text(json.dumps(transforms))
    scene = _small_scene(tmp_path)
    assert main(["render", str(scene), "--cameras", str(tmp_path / "transforms.json"), "--out", str(tmp_path / "out"),
                 "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert "error: --out (the PNG of view 0): the file name vvvv" in captured.err and "loading" not in captured.out
    monkeypatch.setattr(raster, "available_memory", lambda: 2**30)
    assert main(["render", str(scene), "--orbit-size", "8192", "--out", str(tmp_path / "out"), "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert ("error: --orbit-size and --scale: 60 views of 8192x8192 pixels, 1 of their images held at once, need "
            "11.1 GiB, more than half the 1.0 GiB of memory available now") in captured.err
    assert "loading" not in captured.out and not (tmp_path / "out").exists()


def test_ctrl_c_while_saving_stops_without_a_traceback(tmp_path, capsys, monkeypatch):
    import artnvg_core.images as images

    def interrupted(image, path):
        raise KeyboardInterrupt

    monkeypatch.setattr(images, "save_png", interrupted)
    assert main(["render", str(_small_scene(tmp_path)), "--cameras", str(DemoInputs().cameras), "--out",
                 str(tmp_path / "out"), "--views", "0", "--scale", "0.1", "--device", "cpu"]) == 130
    captured = capsys.readouterr()  # the scene's load took milliseconds: no bar above the message
    assert captured.err == "interrupted: stopped; no file was left half-written\n"
    assert list((tmp_path / "out").iterdir()) == []


@pytest.mark.parametrize("command", ["render", "stylize", "evaluate"])
@pytest.mark.parametrize("option, value, expected", [
    ("--orbit-views", "0", "expected an integer >= 1, got '0'"),
    ("--fov", "180", "expected degrees between 0 and 180 (both excluded), got '180'"),
    ("--fov", "nan", "expected degrees between 0 and 180 (both excluded), got 'nan'"),
    ("--orbit-size", "100000", "expected WIDTHxHEIGHT or N, each 1 to 16384 pixels, e.g. 512x384, got '100000'"),
    ("--orbit-size", "0x3", "expected WIDTHxHEIGHT or N, each 1 to 16384 pixels, e.g. 512x384, got '0x3'"),
    ("--up", "side", "expected 'auto', one of +x, -x, +y, -y, +z, -z or 3 comma-separated numbers such as 0, -1, 0, "
     "got 'side'"),  # parse_up, which reads the node's up input too
    ("--up", "0,0", "expected 3 finite numbers, not all zero, got '0,0'"),
])
def test_orbit_options_are_checked_by_the_parser_naming_the_option(capsys, command, option, value, expected):
    """The views built around a scene without cameras: bad values are refused by name before the scene loads
    (not by orbit_cameras or CameraSet, naming their own arguments, after it)."""
    with pytest.raises(SystemExit) as exit_:
        main([command, "scene.ply", option, value])
    assert exit_.value.code == 2 and f"error: argument {option}: {expected}" in capsys.readouterr().err


def test_ctrl_c_during_a_progress_bar_prints_its_line_below_the_bar(tmp_path, capsys, monkeypatch):
    """The bar is closed first: the message once followed the bar on its line, and the bar was drawn again
    below it when the process ended."""
    import artnvg_core.stylize

    def interrupted(scene, cameras, style, config, progress, **kwargs):
        progress(1, 10, {})
        raise KeyboardInterrupt

    monkeypatch.setattr(artnvg_core.stylize, "stylize_nnfm", interrupted)
    assert _stylize(_small_scene(tmp_path), DemoInputs().style, tmp_path / "out.ply") == 130
    err = capsys.readouterr().err
    assert re.search(r"finetune: +10%.*\| 1/10 \[.*\]\ninterrupted: stopped; no file was left half-written\n$", err), err


@pytest.mark.parametrize("stylizer", ["nnfm", "auto"])
def test_a_devices_typo_is_refused_before_any_work_whichever_stylizer_runs(tmp_path, capsys, stylizer):
    """'--devices cuda0' once went unread when the NNFM stylizer ran (and was read after the scene and the
    models loaded when diffusion did)."""
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    assert main(["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out",
                 str(tmp_path / "out.ply"), "--stylizer", stylizer, "--devices", "cuda0", "--iters", "1",
                 "--scale", "0.05", "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert captured.err == "error: --devices: 'cuda0' is not a device (expected e.g. cuda:0,cuda:1)\n"
    assert "loading" not in captured.out and sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]


@pytest.mark.parametrize("stylizer", ["nnfm", "auto"])
def test_options_only_the_diffusion_stylizer_reads_are_refused_before_any_work_when_nnfm_would_run(tmp_path, capsys, stylizer,
                                                                                                    monkeypatch):
    """docs/scale_out.md's 'stylize ... --devices cuda:0,cuda:1', run where the model files are missing (auto:
    NNFM), once ran NNFM's 1,000 iterations on the CPU (two hours at 512x512), the devices unread; --ray-address
    and (with auto) --lora went unread the same way. Each is refused before the scene loads, saying why NNFM runs."""
    import torch
    from huggingface_hub import constants
    from safetensors.torch import save_file

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty-hf-cache"))  # no model file anywhere
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    save_file({"unet.down.lora_A.weight": torch.zeros(2, 2)}, tmp_path / "style.safetensors")
    reason = "requested" if stylizer == "nnfm" else "auto: diffusion models not found (SDXL 1.0 base"
    for option, value, what in [("--devices", "cuda:0,cuda:1", "the devices share the diffusion stage's groups"),
                                ("--ray-address", "auto", "the Ray cluster shares the diffusion stage's groups"),
                                ("--lora", str(tmp_path / "style.safetensors"), "a LoRA changes SDXL"),
                                # these ran NNFM as if not given
                                ("--steps", "5", "the denoising steps are the diffusion stage's"),
                                ("--scheduler", "unipc", "the sampler is the diffusion stage's"),
                                ("--cfg-until", "0.5", "classifier-free guidance is the diffusion stage's"),
                                ("--key-views", "4", "the key views are those the diffusion stage stylizes"),
                                ("--content-routing", "paper", "the content routing is CSGO's"),
                                ("--compile", None, "the compiled blocks are SDXL's and the ControlNet's"),
                                ("--group-multiple", "2", "the groups are the diffusion stage's")]:
        assert main(["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out",
                     str(tmp_path / "out.ply"), "--stylizer", stylizer, option, *[value] * (value is not None),
                     "--iters", "1", "--scale", "0.05", "--device", "cpu"]) == 2
        captured = capsys.readouterr()
        assert captured.err.startswith(f"error: {option}: {what}, which only the diffusion stylizer runs; the NNFM "
                                       f"stylizer would run here ({reason}"), captured.err
        assert "loading" not in captured.out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply", "style.safetensors"]


@pytest.mark.parametrize("preset", ["fast", "paper"])
def test_a_diffusion_preset_given_by_name_without_the_model_files_is_refused_before_any_work(tmp_path, capsys, preset):
    """'stylize ... --preset balanced' where the model files are missing ran NNFM's 1,000 iterations instead (two
    hours at 512x512 on a CPU), the preset unread: a diffusion preset named is refused, naming the missing file and
    what runs without diffusion. Without --preset (the demo, a first try) auto still falls back to NNFM."""
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    common = ["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out",
              str(tmp_path / "out.ply"), "--sdxl", str(tmp_path / "no_sdxl"), "--iters", "1", "--scale", "0.05",
              "--device", "cpu"]
    assert main([*common, "--preset", preset]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"error: --preset {preset}: a diffusion preset, and diffusion models not found "
                                   "(SDXL 1.0 base"), captured.err
    assert "--preset preview for a first look without diffusion, or --stylizer nnfm" in captured.err
    assert "loading" not in captured.out and sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"]
    assert main([*common, "--preset", preset, "--stylizer", "nnfm"]) == 0  # NNFM asked for: it runs


def test_a_model_file_named_and_missing_is_refused_before_any_work_and_without_it_auto_falls_back(tmp_path, capsys,
                                                                                                 monkeypatch):
    """'stylize ... --sdxl TYPO' ran NNFM's 1,000 iterations instead (two hours at 512x512 on a CPU), the path's typo
    told only in passing; as with a diffusion preset named, a model file named asks for diffusion."""
    from huggingface_hub import constants

    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "empty-hf-cache"))  # no model file anywhere
    demo, scene = DemoInputs(), _small_scene(tmp_path)
    common = ["stylize", str(scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--out",
              str(tmp_path / "out.ply"), "--iters", "1", "--scale", "0.05", "--device", "cpu"]
    for option in ("--sdxl", "--controlnet", "--image-encoder", "--csgo"):
        assert main([*common, option, str(tmp_path / "typo")]) == 2
        captured = capsys.readouterr()
        assert captured.err.startswith(f"error: {option}: a diffusion model file named, and diffusion models not "
                                       "found ("), captured.err
        assert "loading" not in captured.out and not (tmp_path / "out.ply").exists()
    assert main(common) == 0  # none named: auto falls back, saying why
    assert "stylizer: nnfm (auto: diffusion models not found (SDXL 1.0 base" in capsys.readouterr().out


def test_a_bar_first_told_of_its_work_at_the_end_shows_no_rate(capsys):
    """A render of one chunk once drew its bar only when done, at 170,000 it/s: 8 views over no time."""
    from artnvg_core.cli.common import ProgressBar

    ProgressBar("render views")(8, 8, {})
    err = capsys.readouterr().err
    assert re.search(r"render views: 100%\|.*\| 8/8 \[00:00<\?, \?it/s\]", err), err


def test_a_bar_with_a_delay_shows_only_for_work_that_lasts_it(capsys):
    """A scene file's load or save (a delay of SCENE_FILE_BAR_DELAY): thousands of Gaussians, read in milliseconds,
    leave nothing on screen; work that outlasts the delay draws its bar, and its last state stays."""
    import time

    from artnvg_core.cli.common import ProgressBar
    from tests.test_stylize import _terminal

    quick = ProgressBar("loading", "B", delay=0.2)
    for step in range(0, 11):
        quick(step, 10, {})
    assert capsys.readouterr().err == ""
    slow = ProgressBar("loading", "B", delay=0.2)
    for step in range(0, 11):
        slow(step, 10, {})
        time.sleep(0.05)  # 0.5 s in all
    screen = _terminal(capsys.readouterr().err)
    assert re.fullmatch(r"loading: 100%\|█+\| 10\.0/10\.0 \[[^\]]+B/s\]", screen[0]) and screen[1:] == [""], screen


def test_a_bar_reporting_after_the_bars_were_closed_draws_nothing(capsys):
    """close_progress_bars runs before a command's error or interrupt message is printed; a background
    thread's bar (the diffusion models' load) reporting after it once drew its bar below the message."""
    from artnvg_core.cli.common import ProgressBar, close_progress_bars

    views, models = ProgressBar("views"), ProgressBar("models", "B")
    views(1, 4, {})
    close_progress_bars()
    print("error: the message", file=sys.stderr)
    models(0, 2**20, {"loading": "SDXL"})
    views(2, 4, {"stage": "content"})
    err = capsys.readouterr().err
    assert re.search(r"views: +25%.*\| 1/4 \[.*\]\nerror: the message\n$", err), err


def test_a_line_printed_while_a_bar_is_drawn_gets_a_line_of_its_own(tmp_path, monkeypatch):
    """stdout and stderr share the terminal: a status line printed while a bar is drawn (the scene loading
    beside the diffusion models' load in a background thread) was glued to the end of the bar's line."""
    import io

    import artnvg_core.stylize
    from tests.test_stylize import _terminal

    def finetune_that_prints(scene, cameras, style, config, progress, **kwargs):
        progress(1, 10, {})
        print("a status line")
        progress(10, 10, {})
        return scene

    monkeypatch.setattr(artnvg_core.stylize, "stylize_nnfm", finetune_that_prints)
    monkeypatch.setattr(artnvg_core.stylize, "save_result", lambda *args, **kwargs: tmp_path / "sheet.png")
    terminal = io.StringIO()
    monkeypatch.setattr(sys, "stdout", terminal)
    monkeypatch.setattr(sys, "stderr", terminal)
    assert _stylize(_small_scene(tmp_path), DemoInputs().style, tmp_path / "out.ply") == 0
    screen = _terminal(terminal.getvalue())
    at = screen.index("a status line")
    assert re.fullmatch(r"finetune: 100%\|#+\| 10/10 \[[^\]]+\]", screen[at + 1]), screen  # ASCII: no Unicode in a StringIO


def test_render_names_an_sh_degree_above_the_scenes_before_writing(tmp_path, capsys):
    """'--sh-degree 5' on a degree-1 scene said 'render: sh_degree must be in 0..1 for this scene' after making --out."""
    scene, out = _small_scene(tmp_path), tmp_path / "r"
    assert main(["render", str(scene), "--cameras", str(DemoInputs().cameras), "--out", str(out), "--views", "0",
                 "--sh-degree", "2", "--device", "cpu"]) == 2
    captured = capsys.readouterr()
    assert captured.err == f"error: --sh-degree: 2 is above the SH degree of {scene}, 1; give 0 to 1\n"
    assert "rendering" not in captured.out and not out.exists()
    with pytest.raises(SystemExit):
        main(["render", str(scene), "--out", str(out), "--sh-degree", "-1"])
    assert "argument --sh-degree: expected an integer >= 0, got '-1'" in capsys.readouterr().err


def test_every_option_says_what_it_does_and_its_default():
    """'--stylizer {auto,nnfm,diffusion}' and render's '--backend' had no help line, and --preset, --device and
    evaluate's --out and --path kept their defaults to themselves."""
    import argparse

    from artnvg_core.cli.main import build_parser

    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    for name, command in commands.items():
        for option in command._actions:
            if not option.option_strings or option.dest == "help":
                continue
            assert option.help, (name, option.option_strings)
            if option.default not in (None, False, []):
                assert "default" in option.help, (name, option.option_strings, option.default)


@pytest.mark.parametrize("command", ["render", "stylize", "evaluate", "blend"])
def test_a_camera_file_refused_is_named_by_its_option(tmp_path, capsys, command):
    """'error: scene.ply: not a supported camera source' named the file, not the option that gave it, as --style's
    errors do."""
    demo = DemoInputs()
    inputs = {"render": [str(demo.scene), "--device", "cpu"], "stylize": [str(demo.scene), "--style", str(demo.style)],
              "evaluate": ["--original", str(demo.scene), "--stylized", str(demo.scene), "--style", str(demo.style)],
              "blend": [str(demo.scene), str(demo.scene), "--strength", "0.5"]}
    out = tmp_path / "out" / ("report.json" if command == "evaluate" else "s.ply")
    assert main([command, *inputs[command], "--cameras", str(demo.scene), "--out", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"error: --cameras: {demo.scene}: not a supported camera source; expected a "
                                   "nerfstudio .json file"), captured.err
    assert "loading" not in captured.out and not (tmp_path / "out").exists()


@pytest.mark.parametrize("command", ["render", "stylize", "evaluate"])
def test_an_orbit_option_given_with_cameras_is_refused_before_any_work(tmp_path, capsys, command):
    """'render scene.ply --cameras t.json --orbit-size 1024' rendered the cameras' views, the size unread."""
    demo = DemoInputs()
    quick = ["--scale", "0.05", "--device", "cpu"]  # were the option not refused
    inputs = {"render": [str(demo.scene), "--views", "0", *quick],
              "stylize": [str(demo.scene), "--style", str(demo.style), "--iters", "0", *quick],
              "evaluate": ["--original", str(demo.scene), "--stylized", str(demo.scene), "--style", str(demo.style),
                           "--views", "0,1", "--frames", "2", *quick]}
    out = tmp_path / "out" / ("report.json" if command == "evaluate" else "s.ply")
    for option in ("--orbit-views=4", "--fov=40", "--up=-y", "--orbit-size=64", "--orbit-around=full"):
        assert main([command, *inputs[command], "--cameras", str(demo.cameras), option, "--out", str(out)]) == 2
        captured = capsys.readouterr()
        assert captured.err == (f"error: {option.split('=')[0]}: the views orbiting the scene are built only without "
                                "--cameras, whose views are used here; give one or the other\n"), captured.err
        assert "loading" not in captured.out and not (tmp_path / "out").exists()


def test_an_orbit_option_given_to_the_demo_names_the_demo_not_cameras_it_was_not_given(tmp_path, capsys):
    """'stylize --orbit-views 4' (no inputs: the demo, whose cameras the demo brings) said the option was given
    with --cameras, which the user never typed."""
    assert main(["stylize", "--orbit-views=4", "--out", str(tmp_path / "out" / "s.ply")]) == 2
    captured = capsys.readouterr()
    assert captured.err == ("error: --orbit-views: the bundled demo renders its own cameras' views; give SCENE and "
                            "--style, without --cameras, for views orbiting a scene\n"), captured.err
    assert "demo" not in captured.out and not (tmp_path / "out").exists()


@pytest.mark.parametrize("size, scale", [("64", 0.5), ("50x30", 0.3), ("7x5", 0.01)])
def test_the_views_built_around_a_scene_are_known_by_name_and_size_before_it_loads(size, scale):
    """What the options naming those views (--views, --region-mask, --stylized-images) are checked against before the
    scene loads is what orbit_from_args builds once it has, at --scale."""
    from artnvg_core.cli.main import build_parser
    from artnvg_core.cli.options import orbit_from_args, orbit_views_ahead

    args = build_parser().parse_args(["render", "s.ply", "--out", "o", "--orbit-views", "3", "--orbit-size", size])
    built = orbit_from_args(args, load_scene(DemoInputs().scene).select(slice(0, None, 40))).scaled(scale)
    assert orbit_views_ahead(args, scale) == (built.names, built.width, built.height)
