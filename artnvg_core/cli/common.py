"""What the ``python -m artnvg_core`` commands share: parsing of values, progress bars, verbose loading."""

from __future__ import annotations

import argparse
import math
import os
import time
from typing import TYPE_CHECKING

import torch

from ..devices import device_for

if TYPE_CHECKING:
    import argparse

    from ..cameras import CameraSet
    from ..scene import GaussianScene


def parse_device(name: str) -> torch.device:
    """``--device``: ``auto`` -> CUDA, else MPS, else the CPU; a device that is not present is a ValueError."""
    try:
        return device_for(name)
    except ValueError as error:
        raise ValueError(f"--device {error}") from error


def _number(text: str) -> float:
    """``float(text)``, or the argparse error every number option gives."""
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def positive_number(text: str) -> float:
    """argparse type of ``--scale`` and the like: a finite number > 0."""
    value = _number(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def integer_at_least(minimum: int):
    """argparse type of ``--steps`` and the like: an integer >= ``minimum``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}")
        return value

    return parse


def unit_interval(text: str) -> float:
    """argparse type of ``--cfg-until``: a number in [0, 1]."""
    value = _number(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"expected a number from 0 to 1, got {text!r}")
    return value


def fraction(text: str) -> float:
    """argparse type of a threshold: a number in [0, 1)."""
    value = _number(text)
    if not 0 <= value < 1:
        raise argparse.ArgumentTypeError(f"expected a number from 0 up to (not including) 1, got {text!r}")
    return value


def parse_devices(text: str | None) -> list[torch.device] | None:
    """Devices from ``--devices`` text such as ``cuda:0,cuda:1`` (None when not given)."""
    if not text:
        return None
    devices = []
    for part in text.split(","):
        try:
            devices.append(torch.device(part.strip()))
        except RuntimeError as error:
            raise ValueError(f"--devices: {part.strip()!r} is not a device (expected e.g. cuda:0,cuda:1)") from error
    return devices


class ProgressBar:
    """A tqdm bar (rate and ETA, on stderr) fed by core progress callbacks; float ``info`` values follow it."""

    def __init__(self, description: str):
        self.description = description
        self.bar = None

    def __call__(self, step: int, total: int, info: dict) -> None:
        from tqdm import tqdm

        if self.bar is None:
            self.bar = tqdm(total=total, desc=self.description, unit="it", dynamic_ncols=True)
        self.bar.set_postfix({k: f"{v:.4g}" for k, v in info.items() if isinstance(v, float)}, refresh=False)
        self.bar.update(step - self.bar.n)
        if step >= total:
            self.bar.close()


def prepare_rasterizer(device: torch.device, backend: str = "auto") -> None:
    """Load the rasterizer ``backend`` renders with on ``device`` before the first render; gsplat's
    first-use kernel build (minutes; BENCHMARKS.md, "First look") is announced on stdout before it starts."""
    from ..raster import prepare_backend

    prepare_backend(device, backend, announce=lambda message: print(message, flush=True))


def load_scene_verbose(path: str | os.PathLike, device: torch.device) -> GaussianScene:
    """:func:`~artnvg_core.formats.load_scene` onto ``device``, printing the file size first and the count and time after."""
    from ..formats import load_scene

    print(f"loading {path} ({os.path.getsize(path) / 2**20:,.1f} MiB)" if os.path.isfile(path) else f"loading {path}",
          flush=True)
    start = time.perf_counter()
    scene = load_scene(path).to(device)
    print(f"loaded {len(scene):,} Gaussians (SH degree {scene.sh_degree}) in {time.perf_counter() - start:.1f} s",
          flush=True)
    return scene


def add_camera_arguments(parser: argparse.ArgumentParser) -> None:
    """``--cameras`` (optional) and the options of the cameras built from the scene when it is left out."""
    from ..cameras import UP_AXES

    parser.add_argument("--cameras", help="transforms.json or a COLMAP sparse folder; left out: views orbiting "
                        "the scene, built from the Gaussians alone (docs/scenes_and_formats.md)")
    orbit = parser.add_argument_group("cameras from the scene alone (when --cameras is left out)")
    orbit.add_argument("--orbit-views", type=int, default=60, help="number of views (default 60: four groups of 15)")
    orbit.add_argument("--fov", type=float, default=50.0, help="horizontal field of view in degrees (default 50)")
    orbit.add_argument("--up", default="auto", choices=("auto", *UP_AXES),
                       help="the scene's up axis, e.g. --up=-y (default auto: detected; COLMAP scenes are often -y)")
    orbit.add_argument("--orbit-size", default="512", help="image size WIDTHxHEIGHT or N for NxN (default 512)")
    orbit.add_argument("--orbit-around", default="auto", choices=("auto", "full"),
                       help="auto (default): views on the side the capture looked from (all round for a 360 capture); "
                       "full: all round always")


def orbit_from_args(args: argparse.Namespace, scene: GaussianScene) -> CameraSet:
    """:func:`~artnvg_core.orbit.orbit_cameras` around ``scene`` with the options of :func:`add_camera_arguments`."""
    from ..orbit import orbit_cameras

    parts = args.orbit_size.lower().split("x")
    if len(parts) not in (1, 2) or not all(part.strip().isdigit() and int(part) > 0 for part in parts):
        raise ValueError(f"--orbit-size: expected WIDTHxHEIGHT or N in pixels, e.g. 512x384, got {args.orbit_size!r}")
    width, height = int(parts[0]), int(parts[-1])
    cameras = orbit_cameras(scene, args.orbit_views, fov_deg=args.fov, width=width, height=height, up=args.up,
                            around=args.orbit_around)
    print(f"no --cameras: {len(cameras)} views orbiting the scene at {width}x{height}, field of view {args.fov:g} deg",
          flush=True)
    return cameras
