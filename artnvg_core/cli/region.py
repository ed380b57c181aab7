"""The command line's selections, shared by ``stylize`` and ``blend``: ``--region`` (a box or a sphere) and
``--region-mask VIEW:MASK.png`` (masks painted on rendered views, lifted to the Gaussians they see)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch

from ..counted import counted

if TYPE_CHECKING:
    from ..cameras import CameraSet
    from ..scene import GaussianScene


def add_region_arguments(parser: argparse.ArgumentParser, what: str) -> None:
    """``--region`` and ``--region-mask`` on ``parser``; ``what`` says what the selection limits."""
    from ..selection import REGION_SYNTAX

    group = parser.add_argument_group("region (the Gaussians that may change; default: all)")
    group.add_argument("--region", help=f"{REGION_SYNTAX}: {what} only the Gaussians whose centre lies inside, in "
                       "the scene's units and axes")
    group.add_argument("--region-mask", action="append", default=[], metavar="VIEW:MASK.png",
                       help=f"{what} only the Gaussians that a mask's white pixels see; VIEW: the view (index in "
                       "file order, or image name) the mask was painted on, e.g. on a `render` output of the same "
                       "cameras (of the view's aspect, resized to it); repeat for several views")


def parse_region_mask(text: str, names: Sequence[str]) -> tuple[int, str]:
    """``VIEW:MASK.png`` -> (view index among the views named ``names``, mask path); ValueError naming
    ``--region-mask``."""
    view, sep, path = text.partition(":")
    if not sep or not path:
        raise ValueError(f"--region-mask: expected VIEW:MASK.png, got {text!r}")
    if view in names:
        return list(names).index(view), path
    if view.isdigit() and int(view) < len(names):
        return int(view), path
    raise ValueError(f"--region-mask {text}: {view!r} is neither a view index below {len(names)} nor a view "
                     f"name of the cameras (e.g. {names[0]!r})")


def check_region_arguments(args: argparse.Namespace, cameras_required: bool = True) -> None:
    """Checks made before any scene loads: the region's syntax, one kind of region, masks only with ``--cameras``
    where ``cameras_required`` (stylize's views orbiting the scene can carry masks too), mask files that exist."""
    from ..fileio import require_regular_file
    from ..selection import parse_region

    if args.region and args.region_mask:
        raise ValueError("give --region or --region-mask, not both")
    if args.region:
        parse_region(args.region)
    if args.region_mask and cameras_required and not args.cameras:
        raise ValueError("--region-mask needs --cameras: the views its masks were painted on")
    for text in args.region_mask:
        view, sep, path = text.partition(":")
        if sep and path:  # the form itself is checked with the cameras (parse_region_mask)
            require_regular_file(path, "--region-mask image")


def check_region_masks(args: argparse.Namespace, names: Sequence[str], width: int, height: int) -> None:
    """Before any work: each ``--region-mask``'s view among the views named ``names``, of ``width`` x ``height``
    pixels (the cameras', or those of the views built around the scene: :func:`~.options.orbit_views_ahead`), and
    its image's size (from its header) against theirs (:func:`~artnvg_core.selection.check_mask_size`)."""
    from ..images import image_size
    from ..selection import check_mask_size

    for text in args.region_mask:
        _, path = parse_region_mask(text, names)
        check_mask_size(*image_size(path), width, height, f"--region-mask {text}")


def selection_from_args(args: argparse.Namespace, scene: GaussianScene, cameras: CameraSet | None) -> torch.Tensor | None:
    """The [N] bool selection of ``--region`` / ``--region-mask`` (None for neither; the masked views' renders
    under a bar), printing its size; the masks checked before (:func:`check_region_masks`)."""
    from ..images import load_image, resize_image
    from ..selection import parse_region, select_by_masks, select_region
    from .common import ProgressBar

    if args.region:
        selection = select_region(scene, parse_region(args.region))
    elif args.region_mask:
        views, masks = [], []
        for text in args.region_mask:
            view, path = parse_region_mask(text, cameras.names)
            mask = load_image(path).mean(-1, keepdim=True)  # a regular file: check_region_arguments
            views.append(view)
            masks.append(resize_image(mask, cameras.height, cameras.width)[..., 0])
        selection = select_by_masks(scene, cameras.subset(views), torch.stack(masks),
                                    progress=ProgressBar("region masks"))
    else:
        return None
    count = int(selection.sum())
    if count == 0:
        raise ValueError(f"--region{'-mask' if args.region_mask else ''}: selects no Gaussian of the scene")
    print(f"region: {count:,} of {counted(len(scene), 'Gaussian')} selected", flush=True)
    return selection
