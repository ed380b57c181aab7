"""``python -m artnvg_core blend``: the strength dial, a stylized scene mixed with its original
(:mod:`artnvg_core.blend`), optionally inside a region only."""

from __future__ import annotations

import argparse
import time

from .common import SCENE_FILE_BAR_DELAY, ProgressBar, load_camera_option, load_scene_verbose, print_note
from .options import SCENE_FILES, add_scene_file_options, unit_interval
from .region import add_region_arguments, check_region_arguments, check_region_masks, selection_from_args


def cmd_blend(args: argparse.Namespace) -> None:
    import torch

    from ..blend import blend
    from ..fileio import check_output_file, refuse_overwrites
    from ..formats import check_scene_path, save_scene, writable_scene_path

    out = check_output_file(writable_scene_path(args.out, "--out"), "--out")  # the extension first: "out/" is named as no file name
    refuse_overwrites([("--out", out)], [("ORIGINAL", args.original), ("STYLIZED", args.stylized)])
    check_region_arguments(args)
    for scene in (args.original, args.stylized):  # both named before either loads
        check_scene_path(scene)
    cameras = load_camera_option(args)
    if cameras is not None:
        check_region_masks(args, cameras.names, cameras.width, cameras.height)
    device = torch.device("cpu")
    original, stylized = (load_scene_verbose(path, device, drop_invalid=args.drop_invalid, spz_axes=args.spz_axes,
                                             cameras=cameras) for path in (args.original, args.stylized))
    selection = selection_from_args(args, original, cameras)
    start = time.perf_counter()
    result = blend(original, stylized, args.strength, selection, names=(str(args.original), str(args.stylized)))
    elapsed = time.perf_counter() - start
    save_scene(result, out, spz_axes=args.spz_axes, spz_version=args.spz_version,
               progress=ProgressBar("saving", "Gaussian", SCENE_FILE_BAR_DELAY), notes=print_note)
    print(f"blended at strength {args.strength:g} in {elapsed * 1000:.0f} ms; wrote {out}")


def add_blend_command(commands) -> None:
    p = commands.add_parser("blend", help="mix a stylized scene with its original at a strength (no re-run)")
    p.add_argument("original", help=f"the scene before stylizing: {SCENE_FILES}")
    p.add_argument("stylized", help="the stylized scene made from it (same Gaussians, same order)")
    p.add_argument("--strength", type=unit_interval, required=True,
                   help="0: the original, 1: the stylized scene, exactly; between: every SH band and opacity "
                   "(and the geometry, where the finetune moved it) mixed Gaussian by Gaussian")
    p.add_argument("--out", required=True, help="output scene, by extension: .ply (exact, full SH), .spz, .splat, "
                   ".ksplat")
    p.add_argument("--cameras", help="transforms.json or a COLMAP sparse folder: the views of --region-mask")
    add_region_arguments(p, "blend")
    add_scene_file_options(p, " (and of --out)")
    p.set_defaults(run=cmd_blend)
