"""The options of the ``python -m artnvg_core`` commands: argparse types of their values (numbers in range,
devices, image sizes) and the options several commands share (how a scene file is read, the cameras, or
views orbiting the scene when there are none)."""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING

import torch

from ..cameras.camera_set import MAX_IMAGE_SIDE, scaled_size
from ..cameras.framing import parse_up
from ..counted import counted
from ..devices import DEVICE_CHOICES, device_for
from .common import print_note

if TYPE_CHECKING:
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


def integer_at_least(minimum: int, maximum: int | None = None):
    """argparse type of ``--steps`` and the like: an integer >= ``minimum`` (and <= ``maximum`` when given)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < minimum or (maximum is not None and value > maximum):
            upper = f" and <= {maximum}" if maximum is not None else ""
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}{upper}, got {text!r}")
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


def field_of_view(text: str) -> float:
    """argparse type of ``--fov``: degrees strictly between 0 and 180."""
    value = _number(text)
    if not 0 < value < 180:
        raise argparse.ArgumentTypeError(f"expected degrees between 0 and 180 (both excluded), got {text!r}")
    return value


def up_direction(text: str) -> str:
    """argparse type of ``--up``: the text as :func:`~artnvg_core.cameras.parse_up` reads it (auto, an axis such as
    -y, or 3 comma-separated numbers), as given."""
    try:
        parse_up(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return text


def image_size(text: str) -> tuple[int, int]:
    """argparse type of ``--orbit-size``: WIDTHxHEIGHT or N (NxN) in pixels, each 1 to the largest view side
    -> (width, height)."""
    parts = text.lower().split("x")
    if len(parts) not in (1, 2) or not all(part.strip().isdigit() and 1 <= int(part) <= MAX_IMAGE_SIDE
                                           for part in parts):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT or N, each 1 to {MAX_IMAGE_SIDE} pixels, "
                                         f"e.g. 512x384, got {text!r}")
    return int(parts[0]), int(parts[-1])


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


SCENE_FILES = ".ply (INRIA or compressed), .splat, .spz, .ksplat or splatfacto .ckpt"


def add_scene_file_options(parser: argparse.ArgumentParser, written: str = "") -> None:
    """``--drop-invalid`` and ``--spz-axes``: how the scene file is read (and ``written``, when the command
    writes one, with ``--spz-version``)."""
    from ..formats import SPZ_AXES, SPZ_VERSIONS

    parser.add_argument("--drop-invalid", action="store_true",
                        help="drop Gaussians with non-finite values or zero quaternions from the scene (with a "
                        "warning) instead of refusing the file")
    parser.add_argument("--spz-axes", choices=SPZ_AXES, default="auto",
                        help=f"axes of a .spz scene{written} that names none of its own: ply, the PLY's (x right, "
                        "y down, z forward), as splat-transform, SuperSplat, spz-js and Niantic's ply-to-spz write "
                        "them; rub (x right, y up, z back), the SPZ description's; auto (default): read in the one "
                        "that puts the scene in front of --cameras when given, else ply; written in ply")
    if written:
        parser.add_argument("--spz-version", type=int, choices=SPZ_VERSIONS, default=3,
                            help="SPZ version of a .spz --out: 3 (default; Niantic's library, splat-transform, "
                            "SuperSplat) or 2 (also spz-js and other readers of versions 1-2 only)")


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """``--device``: where the command computes."""
    parser.add_argument("--device", choices=DEVICE_CHOICES, default="auto",
                        help="auto (default): CUDA, else Apple MPS, else the CPU")


class _OrbitOption(argparse.Action):
    """An option of the views built around the scene: its value stored, the option noted as given
    (``orbit_options``), since ``--cameras`` would leave it unread (:func:`~.common.load_camera_option`)."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, values)
        namespace.orbit_options = [*namespace.orbit_options, option_string]


def add_camera_arguments(parser: argparse.ArgumentParser) -> None:
    """``--cameras`` (optional) and the options of the cameras built from the scene when it is left out."""
    parser.add_argument("--cameras", help="transforms.json or a COLMAP sparse folder; left out: views orbiting "
                        "the scene, built from the Gaussians alone (docs/scenes_and_formats.md)")
    orbit = parser.add_argument_group("cameras from the scene alone (when --cameras is left out)")
    orbit.add_argument("--orbit-views", type=integer_at_least(1), default=60, action=_OrbitOption,
                       help="number of views (default 60: four groups of 15)")
    orbit.add_argument("--fov", type=field_of_view, default=50.0, action=_OrbitOption,
                       help="horizontal field of view in degrees (default 50)")
    orbit.add_argument("--up", default="auto", type=up_direction, action=_OrbitOption,
                       help="the world direction shown up in every view: auto (default: detected), an axis such as "
                       "--up=-y (COLMAP scenes are often -y) or 3 comma-separated numbers such as --up=0,-1,0")
    orbit.add_argument("--orbit-size", type=image_size, default="512", action=_OrbitOption,
                       help="image size WIDTHxHEIGHT or N for NxN (default 512)")
    orbit.add_argument("--orbit-around", default="auto", choices=("auto", "full"), action=_OrbitOption,
                       help="auto (default): views on the side the capture looked from (all round for a 360 capture); "
                       "full: all round always")
    parser.set_defaults(orbit_options=[])


def orbit_from_args(args: argparse.Namespace, scene: GaussianScene) -> CameraSet:
    """:func:`~artnvg_core.orbit.orbit_cameras` around ``scene`` with the options of :func:`add_camera_arguments`."""
    from ..orbit import orbit_cameras

    width, height = args.orbit_size
    cameras = orbit_cameras(scene, args.orbit_views, fov_deg=args.fov, width=width, height=height, up=args.up,
                            around=args.orbit_around, notes=getattr(args, "notes", None) or print_note,
                            up_option="--up=-y or another axis (with '=')")
    print(f"no --cameras: {counted(len(cameras), 'view')} orbiting the scene at {width}x{height}, field of view {args.fov:g} deg",
          flush=True)
    return cameras


def orbit_views_ahead(args: argparse.Namespace, scale: float = 1.0) -> tuple[list[str], int, int]:
    """The names and the image size (width, height, at ``scale`` as :meth:`~artnvg_core.cameras.CameraSet.scaled`
    rounds it) of the views :func:`orbit_from_args` builds: known before the scene loads, so the options that name
    those views (``--views``, ``--region-mask``, ``--stylized-images``) are checked before it does."""
    from ..orbit import orbit_view_names

    return orbit_view_names(args.orbit_views), *scaled_size(*args.orbit_size, scale)
