"""The command line's own output: progress while loading and rendering (evaluate: tests/test_cli_evaluate.py)."""

import re

import pytest

from artnvg_core.cli.main import main
from artnvg_core.fileio import load_image
from artnvg_core.formats import load_scene, write_ply
from artnvg_core.stylize import DemoInputs


def test_render_reports_loading_and_each_view(tmp_path, capsys):
    demo = DemoInputs()
    scene = tmp_path / "scene.ply"
    write_ply(load_scene(demo.scene).select(slice(0, None, 40)), scene)  # 1,000 Gaussians: quick renders
    assert main(["render", str(scene), "--cameras", str(demo.cameras), "--out", str(tmp_path),
                 "--views", "0,5,9", "--scale", "0.1", "--device", "cpu"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert re.fullmatch(rf"loading {re.escape(str(scene))} \(0\.1 MiB\)", lines[0])
    assert lines[1].startswith("loaded 1,000 Gaussians (SH degree 1) in ")
    assert lines[2].startswith("rendering 3 views at ")
    views = [line for line in lines if line.startswith("[")]
    assert [line.split("]")[0] + "]" for line in views] == ["[1/3]", "[2/3]", "[3/3]"]
    assert len(list(tmp_path.glob("*.png"))) == 3


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


@pytest.mark.parametrize("command", ["render", "stylize"])
def test_outputs_checked_before_loading(tmp_path, capsys, command):
    demo = DemoInputs()
    (tmp_path / "file").write_text("x")
    (tmp_path / "taken.contact.png").mkdir()
    cases = [("", "the output (path|folder) is empty"), (tmp_path / "file" / "x.ply", "file is a file, not a folder")]
    cases += [(tmp_path / "file", "exists and is not a folder")] if command == "render" else [
        (tmp_path, "is a folder"), (tmp_path / "taken.ply", r"\(its contact sheet\): .* is a folder")]
    style = ["--style", str(demo.style)] if command == "stylize" else []
    for out, message in cases:
        code = main([command, str(demo.scene), "--cameras", str(demo.cameras), *style, "--out", str(out), "--device", "cpu"])
        captured = capsys.readouterr()
        assert code == 2 and re.search("error: --out.*" + message, captured.err) and "loading" not in captured.out, captured
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "taken.contact.png"]


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
    assert capsys.readouterr().err == f"error: {out}: not written: the scene contains no Gaussians\n"
    assert list(out.parent.iterdir()) == []


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
    assert "error: [Errno 28] No space left on device" in capsys.readouterr().err
    assert [p.name for p in out.parent.iterdir()] == ["stylized.ply"] and out.read_text() == "an earlier result"


@pytest.mark.parametrize("failure", [MemoryError(), RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried")])
def test_out_of_memory_is_an_error_with_advice(tmp_path, capsys, monkeypatch, failure):
    import artnvg_core.cameras

    def exhausted(path):
        raise failure

    monkeypatch.setattr(artnvg_core.cameras, "load_cameras", exhausted)
    assert main(["render", "scene.ply", "--cameras", "t.json", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: out of memory (") and "try a smaller --scale" in err
    monkeypatch.setattr(artnvg_core.cameras, "load_cameras", lambda path: 1 / 0)
    with pytest.raises(ZeroDivisionError):  # other failures are not disguised
        main(["render", "scene.ply", "--cameras", "t.json", "--out", str(tmp_path)])


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
