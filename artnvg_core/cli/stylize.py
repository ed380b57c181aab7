"""``python -m artnvg_core stylize``: one scene stylized with a style image, NNFM or diffusion (ArtNVG).

:func:`add_stylize_arguments` gives a parser stylize's options (the command line's ``stylize`` and
each job of ``batch`` are parsed by them); :func:`cmd_stylize` runs the parsed options.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

import torch

from ..counted import counted
from ..diffusion.csgo import CONTENT_ROUTINGS
from ..diffusion.lora import LoRAError, check_lora, parse_lora
from ..diffusion.model_files import ModelFiles
from ..diffusion.settings import SCHEDULER_NAMES
from ..formats import SAVE_SUFFIXES
from ..losses import SEARCH_PRECISIONS
from ..presets import PRESETS, get_preset
from .common import (
    SCENE_FILE_BAR_DELAY,
    ProgressBar,
    load_camera_option,
    load_scene_verbose,
    prepare_rasterizer,
    print_note,
    read_style_image,
)
from .options import (
    SCENE_FILES,
    add_camera_arguments,
    add_device_option,
    add_scene_file_options,
    integer_at_least,
    orbit_from_args,
    orbit_views_ahead,
    parse_device,
    parse_devices,
    positive_number,
    unit_interval,
)
from .region import add_region_arguments, check_region_arguments, check_region_masks, selection_from_args

SAMPLER_OPTIONS = ("scheduler", "steps", "cfg_until")  # stylize options that replace the preset's SamplerSettings


def cmd_stylize(args: argparse.Namespace) -> None:
    # every check that needs no model comes before the diffusion libraries are imported (seconds)
    from ..fileio import check_output_file, refuse_overwrites
    from ..formats import check_geometry_writable, check_scene_path, writable_scene_path
    from ..stylize import DemoInputs, sheet_path

    given = [args.scene, args.style]
    if any(given + [args.cameras]) and not all(given):
        raise ValueError("stylize: give SCENE and --style (and --cameras, else views orbiting the scene are built), "
                         "or none of them for the bundled demo")
    demo = not any(given)
    if demo:
        if getattr(args, "orbit_options", []):
            raise ValueError(f"{args.orbit_options[0]}: the bundled demo renders its own cameras' views; give SCENE "
                             "and --style, without --cameras, for views orbiting a scene")
        inputs = DemoInputs()
        args.scene, args.cameras, args.style = inputs.scene, inputs.cameras, inputs.style
        print(f"no inputs given: running the bundled demo ({inputs.scene.parent})")
    preset = get_preset(args.preset)
    diffusion_free = preset.sampler is None  # the preview: its own length, resolution and stylizer
    if diffusion_free and args.stylizer == "diffusion":
        raise ValueError(f"--preset {args.preset} runs without diffusion: use --stylizer nnfm (or auto), or "
                         "another preset")
    scale = args.scale if args.scale is not None else (preset.scale if diffusion_free else 0.25 if demo else 1.0)
    out = check_output_file(writable_scene_path(args.out, "--out"), "--out")  # the extension first: "out/" is named as no file name
    sheet = check_output_file(sheet_path(out), "--out (its contact sheet)")
    refuse_overwrites([("--out", out), ("--out's contact sheet", sheet)],
                      [("SCENE", args.scene), ("--style", args.style), ("--cameras", args.cameras)])
    style = read_style_image(args.style)  # decoded now: a truncated file is named before the scene loads
    check_scene_path(args.scene)  # e.g. a folder: named before the models load
    check_region_arguments(args, cameras_required=False)
    devices = parse_devices(args.devices)  # a typo is named now, whichever stylizer runs
    for lora in args.lora:
        check_lora(lora)
    capture_cameras = load_camera_option(args)
    if capture_cameras is not None:  # before the models and the scene load
        scaled = capture_cameras.scaled(scale)
        check_region_masks(args, scaled.names, scaled.width, scaled.height)
    else:  # the views built around the scene: their names and size are known before it loads
        check_region_masks(args, *orbit_views_ahead(args, scale))
    if args.preset == "low-memory":  # before the first CUDA allocation: far less fragmentation in 12 GiB
        os.environ.setdefault("PYTORCH_CUDA_ALLOC_CONF", "expandable_segments:True")
    device = parse_device(args.device)
    torch.manual_seed(args.seed)
    from ..stylize import choose_stylizer, prefetch_models, save_result, stylize_diffusion, stylize_nnfm

    files = ModelFiles(args.sdxl, args.controlnet, args.image_encoder, args.csgo)
    if diffusion_free:
        stylizer, reason = "nnfm", f"preset {args.preset}: {preset.summary}"
    else:
        stylizer, reason = choose_stylizer(args.stylizer, files)
        if stylizer == "nnfm" and args.stylizer == "auto" and _diffusion_asked_by(args):
            raise ValueError(f"{_diffusion_asked_by(args)}, and {reason.removeprefix('auto: ')}: give the model files "
                             "(README, 'Model files'), or --preset preview for a first look without diffusion, or "
                             "--stylizer nnfm for the NNFM stylizer's full run")
    if stylizer == "nnfm":  # what only the diffusion stylizer reads would go unread: refused before any work
        for option, given, what in (("--lora", args.lora, "a LoRA changes SDXL"),
                                    ("--devices", args.devices, "the devices share the diffusion stage's groups"),
                                    ("--ray-address", args.ray_address, "the Ray cluster shares the diffusion "
                                     "stage's groups"),
                                    ("--steps", args.steps is not None, "the denoising steps are the diffusion "
                                     "stage's"),
                                    ("--scheduler", args.scheduler is not None, "the sampler is the diffusion "
                                     "stage's"),
                                    ("--cfg-until", args.cfg_until is not None, "classifier-free guidance is the "
                                     "diffusion stage's"),
                                    ("--key-views", args.key_views is not None, "the key views are those the "
                                     "diffusion stage stylizes"),
                                    ("--content-routing", args.content_routing != "released", "the content routing "
                                     "is CSGO's"),
                                    ("--compile", args.compile, "the compiled blocks are SDXL's and the ControlNet's"),
                                    ("--group-multiple", args.group_multiple != 1, "the groups are the diffusion "
                                     "stage's")):
            if given:
                raise ValueError(f"{option}: {what}, which only the diffusion stylizer runs; the NNFM stylizer "
                                 f"would run here ({reason})")
    prefetched = stylizer == "diffusion" and not args.devices and not args.ray_address  # read as the scene loads
    if prefetched:
        print("loading the diffusion models (SDXL, Tile ControlNet, image encoder, CSGO)", flush=True)
        prefetch_models(files, device, preset=args.preset, compile_blocks=args.compile, loras=args.lora,
                        progress=ProgressBar("models", "B"))

    scene = load_scene_verbose(args.scene, device, drop_invalid=args.drop_invalid, spz_axes=args.spz_axes,
                               cameras=capture_cameras, should_stop=args.should_stop, notes=args.notes)
    try:  # the finetune keeps the geometry: a format that cannot hold it is refused now, not after the work
        check_geometry_writable(scene, out)
    except ValueError as error:
        raise ValueError(f"--out: {error}; the stylized scene keeps these positions and scales, so "
                         f"{out.suffix} cannot hold it: choose .ply") from None
    cameras = capture_cameras if capture_cameras is not None else orbit_from_args(args, scene)
    cameras = cameras.scaled(scale)
    selection = selection_from_args(args, scene, cameras)

    from ..diffusion.loader import DiffusionModelsUnavailable
    from ..finetune import FinetuneConfig

    def finetune_config(stylizer: str) -> FinetuneConfig:
        config = FinetuneConfig(iterations=60 if demo else 1000, seed=args.seed, color_transfer=args.color_transfer,
                                nnfm_search=args.nnfm_search)
        if diffusion_free or stylizer == "diffusion":
            config = preset.finetune_config(config)
        return config if args.iters is None else dataclasses.replace(config, iterations=args.iters)

    config = finetune_config(stylizer)
    changes = {name: getattr(args, name) for name in SAMPLER_OPTIONS if getattr(args, name) is not None}
    key_views = preset.key_views if args.key_views is None else args.key_views
    described = (f"; preset {args.preset}: {preset.summary}" + "".join(f"; {k} {v}" for k, v in changes.items())
                 + (f"; {counted(key_views, 'key view')}" if key_views else ""))
    print(f"stylizer: {stylizer} ({reason})" + (described if stylizer == "diffusion" else ""))
    print(f"{counted(len(scene), 'Gaussian')}, {counted(len(cameras), 'view')} at {cameras.width}x{cameras.height}, "
          f"{counted(config.iterations, 'iteration')} on {device}")
    prepare_rasterizer(device)
    start = time.perf_counter()
    if stylizer == "diffusion":
        try:
            result, _ = stylize_diffusion(scene, cameras, style.to(device), config, files, loras=args.lora,
                                          preset=args.preset,
                                          content_routing=args.content_routing, sampler_changes=changes,
                                          key_views=key_views,
                                          devices=devices, ray_address=args.ray_address,
                                          group_multiple=args.group_multiple, compile_blocks=args.compile,
                                          loading_progress=None if prefetched else ProgressBar("models", "B"),
                                          sampling_progress=ProgressBar("diffusion"),
                                          progress=ProgressBar("finetune"), render_progress=ProgressBar("views"),
                                          should_stop=args.should_stop, selection=selection)
        except DiffusionModelsUnavailable as error:
            if args.stylizer != "auto" or _diffusion_asked_by(args):  # diffusion asked for: no NNFM instead
                raise
            stylizer, config = "nnfm", finetune_config("nnfm")
            print(f"stylizer: nnfm (auto: falling back, {error}); {counted(config.iterations, 'iteration')}")
    if stylizer == "nnfm":
        result = stylize_nnfm(scene, cameras, style.to(device), config, progress=ProgressBar("finetune"),
                              render_progress=ProgressBar("views"), should_stop=args.should_stop,
                              selection=selection)
    sheet = save_result(scene, result, cameras, style, out, spz_axes=args.spz_axes,
                        spz_version=args.spz_version, progress=ProgressBar("contact sheet"),
                        should_stop=args.should_stop,
                        scene_progress=ProgressBar("saving", "Gaussian", SCENE_FILE_BAR_DELAY), scene_notes=args.notes)
    print(f"wrote {out} and {sheet} in {time.perf_counter() - start:.0f} s")


MODEL_OPTIONS = ("--sdxl", "--controlnet", "--image-encoder", "--csgo")


def _diffusion_asked_by(args: argparse.Namespace) -> str | None:
    """What asks for the diffusion stylizer by name, so that ``--stylizer auto`` does not fall back to NNFM's long
    run for it: a diffusion preset given (``--preset fast: a diffusion preset``) or a model file named (``--sdxl: a
    diffusion model file named``; a typo in its path); None when neither."""
    if args.preset_given:
        return f"--preset {args.preset}: a diffusion preset"
    named = next((option for option in MODEL_OPTIONS if getattr(args, option[2:].replace("-", "_"))), None)
    return f"{named}: a diffusion model file named" if named else None


class _GivenPreset(argparse.Action):
    """``--preset``, noting that it was given (``preset_given``): a diffusion preset asked for by name wants the
    diffusion stylizer, so ``--stylizer auto`` does not fall back to NNFM for it."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.preset_given = True


def lora_option(text: str):
    """argparse type of ``--lora``: FILE or FILE:STRENGTH (:func:`~artnvg_core.diffusion.lora.parse_lora`)."""
    try:
        return parse_lora(text)
    except LoRAError as error:
        raise argparse.ArgumentTypeError(str(error).removeprefix("--lora ")) from None


def add_stylize_arguments(p: argparse.ArgumentParser) -> None:
    """stylize's options and ``run`` = :func:`cmd_stylize` on ``p``."""
    p.add_argument("scene", nargs="?", help=f"scene file: {SCENE_FILES} (omit all inputs for the demo)")
    add_camera_arguments(p)
    p.add_argument("--style", help="style image file")
    p.add_argument("--out", default="out/stylized.ply",
                   help=f"output scene, {', '.join(SAVE_SUFFIXES)} by extension (default out/stylized.ply); a "
                   "NAME.contact.png is written beside it")
    p.add_argument("--stylizer", choices=("auto", "nnfm", "diffusion"), default="auto",
                   help="auto (default): diffusion when every model file loads, else nnfm, saying why (where "
                   "--preset names a diffusion preset or a model file option is given, a missing file is an error); "
                   "nnfm: the diffusion-free stylizer (ARF's colour transfer and NNFM finetuning); diffusion: the "
                   "full ArtNVG pipeline, which needs the model files")
    p.add_argument("--preset", choices=tuple(PRESETS), default="paper", action=_GivenPreset,
                   help="speed/accuracy preset (docs/presets.md; default paper, the paper's settings); preview: a "
                   "first look in seconds, without diffusion; "
                   "a diffusion preset given here needs the model files (auto then never falls back to NNFM)")
    p.set_defaults(preset_given=False)
    p.add_argument("--content-routing", choices=CONTENT_ROUTINGS, default="released",
                   help="released (default): CSGO's released inference, content only through the Tile ControlNet; "
                   "paper: content tokens into the UNet's down blocks too (needs the CSGO file's content entries)")
    p.add_argument("--scheduler", choices=SCHEDULER_NAMES, default=None,
                   help="diffusion sampler (default: the preset's, DDIM); dpmpp_2m and unipc are multistep solvers "
                        "meant for fewer --steps")
    p.add_argument("--steps", type=integer_at_least(1), default=None, help="denoising steps (default: the preset's)")
    p.add_argument("--cfg-until", type=unit_interval, default=None,
                   help="classifier-free guidance for this fraction of the steps only, then the conditional half "
                        "alone (half the batch); 1 = every step (default: the preset's, 1)")
    p.add_argument("--lora", type=lora_option, action="append", default=[], metavar="FILE[:STRENGTH]",
                   help="diffusion: a LoRA for SDXL (.safetensors, kohya or diffusers keys) fused into its weights at "
                   "STRENGTH (default 1); repeat for several, their changes add up")
    p.add_argument("--key-views", type=integer_at_least(0), default=None, metavar="K",
                   help="diffusion: stylize only K views chosen to cover the scene (farthest camera poses) and "
                        "finetune on them alone; 0 = every view (default: the preset's, every view)")
    p.add_argument("--compile", action="store_true",
                   help="diffusion stage: compile the UNet's and ControlNet's repeated blocks (exact up to bf16 "
                        "rounding; slightly faster steps after a long first call, so it pays back on large scenes only: "
                        "BENCHMARKS.md, Diffusion step; "
                        "not with --preset low-memory)")
    p.add_argument("--devices", help="diffusion stage: comma-separated GPUs sharing the groups, e.g. cuda:0,cuda:1, "
                   "one Ray worker each (pip install \"ray>=2.30\"; default: --device)")
    p.add_argument("--ray-address", help="diffusion stage: spread the groups over the GPUs of a running Ray cluster "
                   "(auto, or HOST:PORT)")
    p.add_argument("--group-multiple", type=integer_at_least(1), default=1, metavar="M",
                   help="diffusion: round the number of neighbouring-view groups up to a multiple of M, e.g. the "
                   "GPUs sharing them, so that none idles in the last round (smaller groups; the result depends on "
                   "M, never on the GPUs; default 1: the fewest groups of at most 15 views)")
    p.add_argument("--iters", type=integer_at_least(0), default=None,
                   help="finetune iterations (default: the preset's for diffusion and preview, 1000 for nnfm; 60 for "
                        "the demo)")
    p.add_argument("--color-transfer", action=argparse.BooleanOptionalAction, default=True,
                   help="nnfm: match the scene's colours to the style image's before and after finetuning, "
                   "as ARF does (default on)")
    p.add_argument("--nnfm-search", choices=SEARCH_PRECISIONS, default="tf32",
                   help="arithmetic of NNFM's nearest-neighbour search (default tf32; BENCHMARKS.md, "
                   "NNFM search precision)")
    p.add_argument("--scale", type=positive_number, default=None,
                   help="render resolution factor (default 1; 0.25 for the demo)")
    add_device_option(p)
    p.add_argument("--seed", type=integer_at_least(0, 2**63 - 1), default=0, help="random seed (default 0)")
    add_region_arguments(p, "stylize")
    add_scene_file_options(p, " (and of --out)")
    models = p.add_argument_group("diffusion models (default: the Hugging Face cache; never downloaded)")
    models.add_argument("--sdxl", help="SDXL 1.0 base: diffusers folder or single-file checkpoint")
    models.add_argument("--controlnet", help="TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors or its folder")
    models.add_argument("--image-encoder", help="IP-Adapter SDXL image encoder folder (ViT-bigG/14)")
    models.add_argument("--csgo", help="csgo_4_32.bin or csgo.bin")
    # a caller (the batch worker) may set a StopFn, and a NoteFn that keeps the scene files' notes
    p.set_defaults(run=cmd_stylize, should_stop=None, notes=print_note)
