"""Command line: ``python -m artnvg_core {render,stylize,blend,evaluate,batch} ...`` (``--help`` on each).

This module holds ``render``, the parser of every command and :func:`main`; ``stylize``, ``blend``,
``evaluate`` and ``batch`` have a module each in this package."""

from __future__ import annotations

import argparse
import atexit
import os
import sys
import time
from typing import NoReturn

import torch

from ..cameras.selection import parse_views
from ..counted import counted
from ..diffusion.lora import keep_peft_out
from .batch import add_batch_command
from .blend import add_blend_command
from .common import (
    close_progress_bars,
    is_out_of_memory,
    load_camera_option,
    load_scene_verbose,
    prepare_rasterizer,
    printed_above_bars,
    terminate_as_interrupt,
)
from .evaluate import add_evaluate_arguments
from .options import (
    SCENE_FILES,
    add_camera_arguments,
    add_device_option,
    add_scene_file_options,
    integer_at_least,
    orbit_from_args,
    orbit_views_ahead,
    parse_device,
    positive_number,
)
from .stylize import add_stylize_arguments


def cmd_render(args: argparse.Namespace) -> None:
    from ..fileio import check_output_folder, check_output_name, refuse_overwrites, sweep_temporaries
    from ..formats import check_scene_path
    from ..images import save_png
    from ..raster import check_render_plan, render

    device = parse_device(args.device)
    out_dir = check_output_folder(args.out, "--out")
    sweep_temporaries(out_dir)  # left by a render that was killed
    if not args.overwrite and out_dir.is_dir() and any(out_dir.iterdir()):
        raise ValueError(f"--out: {out_dir} is not empty; give an empty or new folder, or --overwrite to write into "
                         "it (PNGs of the same views are replaced)")

    def chosen(cameras):
        cameras = cameras.subset(parse_views(args.views, len(cameras), "--views", distinct=True)).scaled(args.scale)
        check_render_plan(len(cameras), cameras.width, cameras.height, kept=1, what="--scale")
        for index, name in enumerate(cameras.names):
            check_output_name(out_dir / f"{name}.png", f"--out (the PNG of view {index})")
        return cameras

    check_scene_path(args.scene)
    inputs = [("SCENE", args.scene), ("--cameras", args.cameras)]
    cameras = chosen(load_camera_option(args)) if args.cameras else None  # bad values fail before the load
    if cameras is not None:  # e.g. --out into the capture's own image folder
        refuse_overwrites([("--out", out_dir / f"{name}.png") for name in cameras.names],
                          inputs + [("the capture's image", image) for image in cameras.image_paths])
    if cameras is None:  # the views made from the scene: their choice and size checked before it loads
        names, width, height = orbit_views_ahead(args, args.scale)
        parse_views(args.views, len(names), "--views", distinct=True)
        check_render_plan(len(names), width, height, kept=1, what="--orbit-size and --scale")
    scene = load_scene_verbose(args.scene, device, drop_invalid=args.drop_invalid, spz_axes=args.spz_axes,
                               cameras=cameras)
    if args.sh_degree is not None and args.sh_degree > scene.sh_degree:
        raise ValueError(f"--sh-degree: {args.sh_degree} is above the SH degree of {args.scene}, "
                         f"{scene.sh_degree}; give 0 to {scene.sh_degree}")
    if cameras is None:
        cameras = chosen(orbit_from_args(args, scene))
        refuse_overwrites([("--out", out_dir / f"{name}.png") for name in cameras.names], inputs)
    out_dir.mkdir(parents=True, exist_ok=True)
    prepare_rasterizer(device, args.backend)
    print(f"rendering {counted(len(cameras), 'view')} at {cameras.width}x{cameras.height} on {device}")
    for i in range(len(cameras)):
        view = cameras.subset([i])
        start = time.perf_counter()
        with torch.no_grad():
            image = render(scene, view, sh_degree=args.sh_degree, backend=args.backend).rgb[0]
        if device.type == "cuda":
            torch.cuda.synchronize()
        elapsed = time.perf_counter() - start
        path = out_dir / f"{view.names[0]}.png"
        save_png(image, path)
        print(f"[{i + 1}/{len(cameras)}] {path}  {elapsed * 1000:.0f} ms", flush=True)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m artnvg_core", description="Stylize 3D Gaussian Splatting "
                                     "scenes with a style image (docs/command_line.md); --help on each command.")
    commands = parser.add_subparsers(dest="command", required=True)

    p = commands.add_parser("render", help="render a scene's views to PNG files")
    p.add_argument("scene", help=f"scene file: {SCENE_FILES}")
    add_camera_arguments(p)
    p.add_argument("--out", required=True, help="output folder, empty or new (see --overwrite); one PNG per view, "
                   "named after its image file")
    p.add_argument("--overwrite", action="store_true", help="write into a folder that is not empty, replacing "
                   "PNGs of the same names")
    p.add_argument("--views", help="comma-separated view indices in file order (default: all)")
    p.add_argument("--scale", type=positive_number, default=1.0, help="resolution factor (default 1)")
    p.add_argument("--backend", choices=("auto", "torch", "triton", "gsplat"), default="auto",
                   help="rasterizer: auto (default): triton on CUDA, else torch; torch: the PyTorch reference; "
                   "triton: CUDA only; gsplat: CUDA only, needs pip install gsplat")
    p.add_argument("--sh-degree", type=integer_at_least(0), default=None, help="SH degree to evaluate (default: the scene's)")
    add_scene_file_options(p)
    add_device_option(p)
    p.set_defaults(run=cmd_render)

    p = commands.add_parser("stylize", help="stylize a scene with a style image (no arguments: the bundled demo)")
    add_stylize_arguments(p)

    add_blend_command(commands)

    p = commands.add_parser("evaluate", help="metrics, comparison strip and preview of a stylized scene or 2D views")
    add_evaluate_arguments(p)

    add_batch_command(commands)
    return parser


def exit_without_teardown(code: int) -> NoReturn:
    """End this process with ``code`` as the interpreter would, less its teardown: the exit handlers run
    (``atexit``: logging's flush, Ray's shutdown, finalizers), the standard streams are flushed, then
    ``os._exit`` leaves the modules, models and tensors to the system, which frees the memory at once
    instead of object by object (after a stylize run: 12 GiB of models on the GPU). For
    ``python -m artnvg_core``, whose work is done when :func:`main` returns."""
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: list[str] | None = None, *, whole_process: bool = False) -> int:
    """Run the command of ``argv`` (default: the process's arguments); its exit status. ``whole_process``
    (``python -m artnvg_core``): the command is all this process runs, so a ``stylize`` without ``--lora``
    keeps PEFT out of it (:func:`~artnvg_core.diffusion.lora.keep_peft_out`)."""
    args = build_parser().parse_args(argv)
    if whole_process and args.command == "stylize" and not args.lora:
        keep_peft_out()
    terminated: list[int] = []
    try:
        with terminate_as_interrupt() as terminated, printed_above_bars():
            try:
                status = args.run(args)
            finally:  # a bar left mid-line would glue the message below to it, and be drawn again after it
                close_progress_bars()
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: every file is written whole or not at all, so no traceback
        print(f"{'terminated' if terminated else 'interrupted'}: stopped; no file was left half-written",
              file=sys.stderr)
        return 143 if terminated else 130
    except (ValueError, OSError) as error:  # bad input, or a file the system would not read or write
        print(f"error: {error}", file=sys.stderr)
        return 2
    except (MemoryError, RuntimeError) as error:  # torch's CPU allocator raises a bare RuntimeError
        if not is_out_of_memory(error):
            raise
        advice = getattr(error, "advice", "try a smaller --scale or fewer --views")
        print(f"error: out of memory ({str(error)[:300]}); {advice}", file=sys.stderr)
        return 2
    return status if isinstance(status, int) else 0  # batch gives its exit status; the others return 0

