"""The diffusion pipeline (stylize_diffusion) on tiny model files: presets and devices are wired through."""

import dataclasses
import re

import pytest
import torch

from artnvg_core.cameras import load_cameras
from artnvg_core.diffusion import compile_cache, speed
from artnvg_core.diffusion.sampler import SamplerSettings
from artnvg_core.diffusion.speed import SpeedOptions
from artnvg_core.finetune import FinetuneConfig
from artnvg_core.formats import read_ply
from artnvg_core.images import load_image
from artnvg_core.presets import PRESETS, Preset
from artnvg_core.diffusion.model_files import ModelFiles
from artnvg_core.stylize import DemoInputs, stylize_diffusion
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)
from diffusion_tiny import write_model_files


def _small_inputs(tmp_path, monkeypatch):
    """(scene, 4 cameras at 64 px, style, paths of tiny model files, 2-iteration config); ``paper`` and
    ``low-memory`` reduced to one sampling step."""
    small = Preset(SamplerSettings(steps=1, guidance_scale=3.0, resolution=None), 2, False, "test")
    monkeypatch.setitem(PRESETS, "paper", small)
    monkeypatch.setitem(PRESETS, "low-memory", dataclasses.replace(
        small, low_memory=True, sampler=dataclasses.replace(small.sampler, sequential_cfg=True)))
    demo = DemoInputs()
    cameras = load_cameras(demo.cameras).subset(range(4))
    return (read_ply(demo.scene), cameras.scaled(64 / cameras.width), load_image(demo.style),
            ModelFiles(**write_model_files(tmp_path)), FinetuneConfig(iterations=2, backend="torch"))


@pytest.mark.slow
def test_low_memory_preset_and_compile_are_wired_through(tmp_path, monkeypatch):
    """An exact preset changes no view (beyond float32 rounding); the scene is finetuned; the compile
    switch reaches the loaded models."""
    scene, cameras, style, paths, config = _small_inputs(tmp_path, monkeypatch)
    result, views = stylize_diffusion(scene, cameras, style, config, paths, group_size=2)
    assert views.shape == (4, cameras.height, cameras.width, 3) and 0 <= views.min() and views.max() <= 1
    assert not torch.equal(result.sh, scene.sh) and torch.equal(result.means, scene.means)
    _, low = stylize_diffusion(scene, cameras, style, config, paths, preset="low-memory", group_size=2)
    torch.testing.assert_close(low, views, rtol=0, atol=1e-5)

    # compile_blocks reaches the models (COMPILED_BLOCKS reduced to its exact hint cache: Inductor
    # takes minutes on a CPU); refused with low memory before anything loads
    # and the compile artifacts of an earlier run are loaded after it, this run's saved after sampling
    applied = []
    monkeypatch.setattr(speed, "COMPILED_BLOCKS", SpeedOptions(cache_hint_embedding=True))
    monkeypatch.setattr(speed, "apply_speedups", lambda models, options: applied.append(options))
    monkeypatch.setattr(compile_cache, "load_compile_cache", lambda device: applied.append(("load", device)))
    monkeypatch.setattr(compile_cache, "save_compile_cache", lambda device: applied.append(("save", device)))
    stylize_diffusion(scene, cameras, style, config, paths, group_size=2, compile_blocks=True)
    cpu = torch.device("cpu")
    assert applied == [SpeedOptions(cache_hint_embedding=True), ("load", cpu), ("save", cpu)]
    with pytest.raises(ValueError, match="compile: .* full-memory mode only"):
        stylize_diffusion(scene, cameras, style, config, paths, preset="low-memory", compile_blocks=True)


def test_the_models_load_while_the_content_views_render_and_a_prefetch_is_used(tmp_path, monkeypatch):
    """The model files are read in the background while the content views render (a load that waits for
    the render would otherwise never end); a prefetch's models are the ones the run uses (loaded once)."""
    import threading

    from artnvg_core import stylize
    from artnvg_core.diffusion import loader
    from artnvg_core.diffusion.model_cache import forget_models

    scene, cameras, style, paths, config = _small_inputs(tmp_path, monkeypatch)
    rendering, loads = threading.Event(), []
    load, render_views = loader._load_models, stylize.render_views

    def load_once_rendering(*args):
        assert rendering.wait(timeout=120), "the models were loaded before the content views rendered"
        loads.append(args[0])
        return load(*args)

    monkeypatch.setattr(loader, "_load_models", load_once_rendering)
    monkeypatch.setattr(stylize, "render_views", lambda *args, **kwargs: rendering.set() or render_views(*args, **kwargs))
    for prefetch in (False, True):
        forget_models()
        rendering.clear()
        loads.clear()
        if prefetch:
            stylize.prefetch_models(paths, "cpu")
        stylize_diffusion(scene, cameras, style, config, paths, group_size=2)
        assert loads == [paths], prefetch


def test_the_content_renders_report_progress(monkeypatch):
    """The content views, rendered before sampling (seconds to minutes at a capture's size), once showed no bar."""
    from artnvg_core import stylize

    class Rendered(Exception):
        pass

    def rendered(*args, **kwargs):
        render_views(*args, **kwargs)
        raise Rendered

    render_views, reports = stylize.render_views, []
    monkeypatch.setattr(stylize, "render_views", rendered)
    monkeypatch.setattr(stylize, "_models_loader", lambda *args: lambda device, **kwargs: None)
    demo = DemoInputs()
    cameras = load_cameras(demo.cameras).subset(range(2))
    with pytest.raises(Rendered):
        stylize_diffusion(read_ply(demo.scene), cameras.scaled(32 / cameras.width), load_image(demo.style),
                          FinetuneConfig(iterations=1, backend="torch"), ModelFiles(),
                          render_progress=lambda *report: reports.append(report))
    assert reports == [(0, 2, {"stage": "content"}), (2, 2, {"stage": "content"})]


def test_the_diffusion_libraries_are_imported_beside_the_content_renders_not_before():
    """A process's first stylize_diffusion imports diffusers and transformers (seconds) only after its content
    views: the background load imports them meanwhile (here a stand-in load that imports nothing)."""
    import subprocess
    import sys

    from child_process import child_env

    code = """
import sys
from artnvg_core import stylize
from artnvg_core.cameras import load_cameras
from artnvg_core.diffusion.model_files import ModelFiles
from artnvg_core.finetune import FinetuneConfig
from artnvg_core.formats import read_ply
from artnvg_core.images import load_image

class Rendered(Exception):
    pass

def render_views(*args, **kwargs):
    print(sorted(name for name in ("diffusers", "transformers") if name in sys.modules))
    raise Rendered

stylize.render_views = render_views
stylize._models_loader = lambda *args: lambda device, **kwargs: None
demo = stylize.DemoInputs()
cameras = load_cameras(demo.cameras).subset(range(2))
try:
    stylize.stylize_diffusion(read_ply(demo.scene), cameras, load_image(demo.style),
                              FinetuneConfig(iterations=1, backend="torch"), ModelFiles())
except Rendered:
    pass
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=child_env())
    assert result.stdout == "[]\n", result.stdout + result.stderr


def test_two_devices_spread_the_groups_over_ray_workers_with_the_same_result(tmp_path, monkeypatch, ray_local):
    scene, cameras, style, paths, config = _small_inputs(tmp_path, monkeypatch)
    result, views = stylize_diffusion(scene, cameras, style, config, paths, group_size=2)
    spread_result, spread = stylize_diffusion(scene, cameras, style, config, paths, devices=["cpu", "cpu"],
                                              group_size=4, group_multiple=2)  # 2 groups of 2, as group_size=2
    assert torch.equal(spread, views) and torch.equal(spread_result.sh, result.sh)


def test_auto_falls_back_to_nnfm_when_a_file_is_missing_or_cannot_be_loaded(tmp_path, monkeypatch, capsys):
    """choose_stylizer checks what the load reads; a file that is there but fails to load makes the
    command line fall back too, saying why. ``diffusion`` asked for explicitly fails instead."""
    import shutil

    from artnvg_core.cli import main as cli
    from artnvg_core import stylize
    from artnvg_core.diffusion.loader import DiffusionModelsUnavailable, load_models_for
    from artnvg_core.stylize import choose_stylizer

    files = write_model_files(tmp_path)
    shutil.rmtree(files["sdxl"] / "unet")
    stylizer, reason = choose_stylizer("auto", ModelFiles(**files))
    assert stylizer == "nnfm" and "SDXL diffusers folder component 'unet'" in reason and "csgo" not in reason.lower()

    files = write_model_files(tmp_path / "broken")
    files["csgo"].write_bytes(b"not a torch file")
    paths = ModelFiles(**files)
    assert choose_stylizer("auto", paths) == ("diffusion", "auto: all diffusion model files found")
    with pytest.raises(DiffusionModelsUnavailable, match="could not be loaded: CSGO weights .* not a readable"):
        load_models_for(paths, False, "cpu")

    from huggingface_hub import constants

    from artnvg_core.diffusion.model_files import MODEL_SOURCES, hf_cache_path

    cache = tmp_path / "hf-cache"  # where the files are found when no option names them
    for field, source in MODEL_SOURCES.items():
        (place := hf_cache_path(source, cache)).parent.mkdir(parents=True, exist_ok=True)
        place.symlink_to(files[field])
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    finetuned = []
    monkeypatch.setattr(stylize, "stylize_nnfm", lambda scene, *args, **kwargs: finetuned.append(kwargs) or scene)
    monkeypatch.setattr(stylize, "save_result", lambda *args, **kwargs: tmp_path / "sheet.png")
    demo = DemoInputs()
    common = [str(demo.scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--device", "cpu",
              "--out", str(tmp_path / "out.ply")]
    assert cli.main(["stylize", *common]) == 0 and len(finetuned) == 1
    assert "stylizer: nnfm (auto: falling back, diffusion models could not be loaded: CSGO weights" in \
        capsys.readouterr().out
    assert cli.main(["stylize", *common, "--stylizer", "diffusion"]) == 2
    assert "error: diffusion models could not be loaded" in capsys.readouterr().err
    assert cli.main(["stylize", *common, "--preset", "paper"]) == 2  # a diffusion preset named: no NNFM instead
    assert "error: diffusion models could not be loaded" in capsys.readouterr().err and len(finetuned) == 1
    assert cli.main(["stylize", *common, "--csgo", str(files["csgo"])]) == 2  # a model file named: nor here
    assert "error: diffusion models could not be loaded" in capsys.readouterr().err and len(finetuned) == 1


def test_a_failed_load_or_a_stop_ends_the_content_renders(tmp_path, monkeypatch):
    """The content views render while the model files load: a load that fails ends the renders and its error
    is raised at once; a stop asked during the renders cancels them. (Each render call here waits, up to 60 s,
    for the stop it is given to say stop.)"""
    import time

    from artnvg_core.diffusion.loader import DiffusionModelsUnavailable
    from artnvg_core.progress import Cancelled
    from artnvg_core.raster import views as raster_views

    scene, cameras, style, paths, config = _small_inputs(tmp_path, monkeypatch)
    calls = []

    def render_until_stopped(scene, cameras, should_stop=None, **kwargs):
        calls.append(len(cameras))
        deadline = time.monotonic() + 60
        while not (should_stop is not None and should_stop()):
            assert time.monotonic() < deadline, "the render was never told to stop"
            time.sleep(0.01)
        raise Cancelled("stopped")

    monkeypatch.setattr(raster_views, "render", render_until_stopped)
    paths.csgo.write_bytes(b"not a torch file")
    with pytest.raises(DiffusionModelsUnavailable, match="CSGO weights"):
        stylize_diffusion(scene, cameras, style, config, paths, group_size=2)
    assert calls == [4]
    paths = ModelFiles(**write_model_files(tmp_path / "good"))
    asked = time.monotonic() + 0.5
    with pytest.raises(Cancelled):
        stylize_diffusion(scene, cameras, style, config, paths, group_size=2, should_stop=lambda: time.monotonic() > asked)
    assert calls == [4, 4]


@pytest.mark.slow
def test_command_line_sampler_options_and_key_views_replace_the_preset(tmp_path, monkeypatch):
    """--scheduler, --steps and --cfg-until reach the sampler in place of the preset's values; left out,
    the preset's settings run. --key-views K (or the preset's key_views) stylizes only the K views
    select_key_views picks, grouped among themselves, and the finetune sees only those views.
    --group-multiple M rounds the number of groups up to a multiple of M."""
    from artnvg_core.cli import main as cli
    from artnvg_core import stylize
    from artnvg_core.diffusion import stylize as diffusion_stylize
    from artnvg_core.key_views import select_key_views

    seen, stylized, trained, group_counts = [], [], [], []

    def record(models, images, groups, conditioning, settings, **kwargs):
        seen.append(settings)
        stylized.append((len(images), groups.num_views))
        group_counts.append(len(groups))
        return images

    def finetune(scene, cameras, style_image, stylized=None, **kwargs):
        trained.append((cameras.names, len(stylized)))
        return scene

    monkeypatch.setattr(diffusion_stylize, "stylize_groups", record)
    monkeypatch.setattr(stylize, "finetune", finetune)
    monkeypatch.setattr(stylize, "save_result", lambda *args, **kwargs: tmp_path / "sheet.png")
    files = write_model_files(tmp_path)
    demo = DemoInputs()
    common = [str(demo.scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--device", "cpu",
              "--scale", "0.05", "--iters", "0", "--out", str(tmp_path / "out.ply"), "--stylizer", "diffusion",
              *[f"--{name.replace('_', '-')}={path}" for name, path in files.items()]]
    assert cli.main(["stylize", *common, "--preset", "fast"]) == 0
    assert cli.main(["stylize", *common, "--preset", "fast", "--scheduler", "unipc", "--steps", "7",
                     "--cfg-until", "0.6"]) == 0
    assert seen[0] == PRESETS["fast"].sampler
    assert seen[1] == dataclasses.replace(PRESETS["fast"].sampler, scheduler="unipc", steps=7, cfg_until=0.6)
    cameras = load_cameras(demo.cameras)
    assert stylized[:2] == [(24, 24)] * 2 and trained[:2] == [(cameras.names, 24)] * 2
    keys = [cameras.names[i] for i in select_key_views(cameras, 5)]
    assert cli.main(["stylize", *common, "--key-views", "5"]) == 0
    assert stylized[2] == (5, 5) and trained[2] == (keys, 5)
    monkeypatch.setitem(PRESETS, "fast", dataclasses.replace(PRESETS["fast"], key_views=6))
    assert cli.main(["stylize", *common, "--preset", "fast"]) == 0 and stylized[3] == (6, 6)
    assert cli.main(["stylize", *common, "--preset", "fast", "--key-views", "0"]) == 0 and stylized[4] == (24, 24)
    assert cli.main(["stylize", *common, "--preset", "fast", "--key-views", "0", "--group-multiple", "3"]) == 0
    assert group_counts[4:] == [2, 3]  # 24 views: the fewest groups of at most 15, then a multiple of 3
    for bad in (["--steps", "0"], ["--cfg-until", "1.5"], ["--scheduler", "plms"], ["--key-views", "-1"],
                ["--group-multiple", "0"]):
        with pytest.raises(SystemExit):
            cli.build_parser().parse_args(["stylize", *bad])
    with pytest.raises(ValueError, match="sampler_changes names no SamplerSettings field: \\['stpes'\\]"):
        stylize_diffusion(read_ply(demo.scene), load_cameras(demo.cameras), load_image(demo.style),
                          FinetuneConfig(iterations=0), ModelFiles(**files), sampler_changes={"stpes": 3})


def _terminal(text: str) -> list[str]:
    """The lines a terminal shows once ``text`` is written to it: "\\r" goes back to the line's start, "\\n" to
    the next line's start (as a terminal's output does), ESC[A up a line; characters overwrite."""
    lines, row, column = [""], 0, 0
    for token in re.split(r"(\r|\n|\x1b\[A)", text):
        if token in ("\r", "\n"):
            row, column = row + (token == "\n"), 0
            lines += [""] * (row + 1 - len(lines))
        elif token == "\x1b[A":
            row -= 1
            assert row >= 0, "moved above the first line"
        else:
            line = lines[row].ljust(column)
            lines[row], column = line[:column] + token + line[column + len(token):], column + len(token)
    return [line.rstrip() for line in lines]


def test_the_models_bar_and_the_content_views_bar_each_keep_a_line(tmp_path, monkeypatch, capsys):
    """stylize --stylizer diffusion loads the models in a background thread (the 'models' bar) while the
    content views render (the 'views (content)' bar); here the models' bar starts below the views' and
    ends after it. The terminal then shows each bar's last state on a line of its own, nothing else: the
    views' bar once ended with a newline into the models' line (its stale copy left on screen), and
    transformers' 'Loading weights' bars of the text encoders ended over the views' line."""
    import threading

    from artnvg_core import stylize
    from artnvg_core.cli import main as cli
    from artnvg_core.diffusion import stylize as diffusion_stylize

    views_drawn, models_drawn, views_done = threading.Event(), threading.Event(), threading.Event()
    real_prefetch, real_render_views = stylize.prefetch_models, stylize.render_views

    def prefetch(files, device, progress=None, **options):
        def reported(step, total, info):
            if step == 0:
                views_drawn.wait(60)
            progress(step, total, info)
            models_drawn.set()
            if info.get("loading") == "CSGO":
                views_done.wait(60)

        real_prefetch(files, device, progress=reported, **options)

    def render_views(scene, cameras, progress=None, **options):
        def reported(step, total, info):
            progress(step, total, info)
            if step == 0:
                views_drawn.set()
                models_drawn.wait(60)

        views = real_render_views(scene, cameras, progress=reported, **options)
        views_done.set()
        return views

    monkeypatch.setattr(stylize, "prefetch_models", prefetch)
    monkeypatch.setattr(stylize, "render_views", render_views)
    monkeypatch.setattr(diffusion_stylize, "stylize_groups", lambda models, images, *args, **kwargs: images)
    monkeypatch.setattr(stylize, "finetune", lambda scene, *args, **kwargs: scene)
    monkeypatch.setattr(stylize, "save_result", lambda *args, **kwargs: tmp_path / "sheet.png")
    demo, files = DemoInputs(), write_model_files(tmp_path)
    capsys.readouterr()  # the files' writers' bars
    assert cli.main([
        "stylize", str(demo.scene), "--cameras", str(demo.cameras), "--style", str(demo.style), "--device", "cpu",
        "--scale", "0.05", "--iters", "0", "--out", str(tmp_path / "out.ply"), "--stylizer", "diffusion",
        *[f"--{name.replace('_', '-')}={path}" for name, path in files.items()]]) == 0
    screen = _terminal(capsys.readouterr().err)
    assert len(screen) == 3 and screen[2] == "", screen  # the scene's load, milliseconds, draws no bar
    assert re.fullmatch(r"views \(content\): 100%\|█+\| 24/24 \[[^\]]+\]", screen[0]), screen
    assert re.fullmatch(r"models: 100%\|█+\| [\d.]+M/[\d.]+M \[[^\]]+\]", screen[1]), screen
