"""Selections: which Gaussians of a scene a stylization may change, and which pixels they cover.

A selection is a boolean tensor [N] over a scene's Gaussians (True: selected). It is made

- from a region of space (:func:`parse_region`: ``box:XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX`` or ``sphere:X,Y,Z,R``
  in the scene's world units and axes; :func:`parse_bounds`: the numbers alone, the kind given apart): the
  Gaussians whose centre lies inside (boundary included);
- from masks painted on rendered views (:func:`select_by_masks`): the Gaussians those pixels see, each
  Gaussian weighed by what it adds to every pixel's colour (its alpha times the transmittance in front
  of it, as the renderer composites); a Gaussian is selected when at least half of its weight over the
  painted views falls on painted pixels. A Gaussian no painted view sees is not selected.

:func:`coverage` gives the pixels a selection covers: per pixel, the selected Gaussians' share of its
colour, in [0, 1] (the finetune of a region weighs its loss by it).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from .cameras import CameraSet
from .counted import counted
from .images import check_image_values, resize_image, same_aspect
from .progress import ProgressFn, StopFn
from .raster import render
from .scene import SH_C0, GaussianScene

MASK_SHARE = 0.5  # a Gaussian is selected by masks when this share of its weight falls on painted pixels


def _finite_point(point) -> bool:
    """Whether ``point`` is 3 finite real numbers."""
    return len(point) == 3 and all(isinstance(v, (int, float)) and math.isfinite(v) for v in point)


@dataclass(frozen=True)
class Box:
    """An axis-aligned box in world units: ``low`` and ``high`` corners (x, y, z), ``low <= high``."""

    low: tuple[float, float, float]
    high: tuple[float, float, float]

    def __post_init__(self) -> None:
        if not (_finite_point(self.low) and _finite_point(self.high)):
            raise ValueError(f"a box's corners must be 3 finite numbers each, got {self.low} and {self.high}")
        if any(a > b for a, b in zip(self.low, self.high)):
            raise ValueError(f"the box's minimum corner {self.low} must not exceed its maximum {self.high}")

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        """[N] bool: which ``points [N, 3]`` lie inside or on the box."""
        low, high = (torch.tensor(corner, dtype=points.dtype, device=points.device) for corner in (self.low, self.high))
        return ((points >= low) & (points <= high)).all(dim=1)


@dataclass(frozen=True)
class Sphere:
    """A ball in world units: ``center`` (x, y, z) and ``radius`` > 0."""

    center: tuple[float, float, float]
    radius: float

    def __post_init__(self) -> None:
        if not _finite_point(self.center):
            raise ValueError(f"the sphere's centre must be 3 finite numbers, got {self.center}")
        if not (isinstance(self.radius, (int, float)) and math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"the sphere's radius must be > 0, got {self.radius!r}")

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        """[N] bool: which ``points [N, 3]`` lie inside or on the sphere (computed in float64)."""
        center = torch.tensor(self.center, dtype=torch.float64, device=points.device)
        return (points.double() - center).square().sum(dim=1) <= self.radius**2


Region = Box | Sphere
REGION_FIELDS = {"box": "XMIN, YMIN, ZMIN, XMAX, YMAX, ZMAX", "sphere": "X, Y, Z, R"}  # kind -> its numbers
REGION_SYNTAX = "box:XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX or sphere:X,Y,Z,R"


def parse_bounds(kind: str, text: str) -> Region:
    """The :class:`Box` (``kind`` "box") or :class:`Sphere` ("sphere") of the comma-separated numbers ``text``
    (:data:`REGION_FIELDS`, in the scene's units); ValueError saying what a ``kind`` takes, naming no input (the
    caller names it)."""
    fields = REGION_FIELDS[kind]
    count = fields.count(",") + 1
    try:
        numbers = [float(part) for part in text.split(",")]
    except ValueError:
        numbers = []
    if len(numbers) != count or not all(map(math.isfinite, numbers)):
        raise ValueError(f"a {kind} takes {count} finite numbers, {fields}, comma-separated in the scene's units; "
                         f"got {text!r}")
    return Box(tuple(numbers[:3]), tuple(numbers[3:])) if kind == "box" else Sphere(tuple(numbers[:3]), numbers[3])


def parse_region(text: str) -> Region:
    """A :class:`Box` or :class:`Sphere` from ``box:...`` / ``sphere:...`` text (module docstring), the command
    line's ``--region``; ValueError naming ``--region`` for anything else."""
    kind, _, values = text.strip().partition(":")
    if kind not in REGION_FIELDS:
        raise ValueError(f"--region: expected {REGION_SYNTAX} (finite numbers in the scene's units), got {text!r}")
    try:
        return parse_bounds(kind, values)
    except ValueError as error:
        raise ValueError(f"--region: {error}") from None


def select_region(scene: GaussianScene, region: Region) -> torch.Tensor:
    """[N] bool on the scene's device: the Gaussians whose centre lies in ``region``."""
    return region.contains(scene.means.detach())


def gaussian_weights(scene: GaussianScene, cameras: CameraSet, pixel_weights: torch.Tensor, backend: str = "auto",
                     progress: ProgressFn | None = None,
                     should_stop: StopFn | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Each Gaussian's compositing weight (alpha times transmittance) summed over the pixels of ``cameras``:
    ``(weighted [N], total [N])``, the sum with each pixel counted ``pixel_weights [C, H, W]`` times, and with
    every pixel counted once. Read from the gradient of a render of flat colours (colour is linear in the
    DC coefficient, the weight its factor), one view at a time: ``progress(views done, C, {})`` as it starts (0)
    and after each, and
    :class:`~artnvg_core.progress.Cancelled` as soon as ``should_stop()`` says so (checked within each render)."""
    weighted = scene.means.new_zeros(len(scene), dtype=torch.float64)
    total = torch.zeros_like(weighted)
    geometry = scene.map(torch.Tensor.detach)
    if progress is not None:
        progress(0, len(cameras), {})
    for view in range(len(cameras)):
        dc = scene.means.new_zeros(len(scene), 1, 3, requires_grad=True)  # colour 0.5: no clamp
        with torch.enable_grad():
            rgb = render(dataclasses.replace(geometry, sh=dc), cameras.subset([view]), backend=backend,
                         should_stop=should_stop).rgb[0]
            (rgb[..., 0] * pixel_weights[view].to(rgb) + rgb[..., 1]).sum().backward()
        weighted += dc.grad[:, 0, 0].double() / SH_C0
        total += dc.grad[:, 0, 1].double() / SH_C0
        if progress is not None:
            progress(view + 1, len(cameras), {})
    return weighted, total


def check_mask_size(mask_width: int, mask_height: int, view_width: int, view_height: int, what: str) -> None:
    """ValueError naming ``what`` (the mask's file or input), its size and the view's unless a mask of
    ``mask_width`` x ``mask_height`` pixels has the aspect of its view's ``view_width`` x ``view_height`` within a
    pixel's rounding: some aspect gives both sizes with each side rounded to whole pixels (a mask painted on a
    render of the view at another scale, :func:`~artnvg_core.images.same_aspect`), and the mask is resized to the view;
    another would be stretched."""
    if not same_aspect(mask_width, mask_height, view_width, view_height):
        raise ValueError(f"{what}: {mask_width}x{mask_height} pixels, not the aspect of its view's "
                         f"{view_width}x{view_height} (it would be stretched); paint the mask on a render of the view, "
                         "at any scale")


def select_by_masks(scene: GaussianScene, cameras: CameraSet, masks: torch.Tensor, backend: str = "auto",
                    progress: ProgressFn | None = None, should_stop: StopFn | None = None) -> torch.Tensor:
    """[N] bool: the Gaussians that the painted pixels of ``masks [C, H', W']`` (floats in [0, 1], 1 painted, or
    bools; one per view of ``cameras``, of their aspect (:func:`check_mask_size`) and resized to their size) see
    (module docstring); ``progress`` and ``should_stop`` as :func:`gaussian_weights` takes them."""
    if masks.ndim != 3 or masks.shape[0] != len(cameras):
        raise ValueError(f"select_by_masks: expected one mask [H, W] per view ({len(cameras)}), "
                         f"got shape {tuple(masks.shape)}")
    check_mask_size(masks.shape[2], masks.shape[1], cameras.width, cameras.height, "select_by_masks: masks")
    masks = masks.float() if masks.dtype == torch.bool else masks
    check_image_values(masks, "select_by_masks: masks")
    masks = resize_image(masks[..., None].float(), cameras.height, cameras.width)[..., 0].clamp(0, 1)
    weighted, total = gaussian_weights(scene, cameras.to(scene.device), masks.to(scene.device), backend, progress,
                                       should_stop)
    return (total > 0) & (weighted >= MASK_SHARE * total)


def check_selection(selection: torch.Tensor, count: int, caller: str) -> None:
    """ValueError naming ``caller`` unless ``selection`` is a boolean mask [count], one entry per Gaussian."""
    if selection.dtype != torch.bool or tuple(selection.shape) != (count,):
        raise ValueError(f"{caller}: selection must be a boolean mask of the scene's {counted(count, 'Gaussian')}, got "
                         f"{selection.dtype} {tuple(selection.shape)}")


def coverage(scene: GaussianScene, selection: torch.Tensor, cameras: CameraSet, backend: str = "auto",
             progress: ProgressFn | None = None, should_stop: StopFn | None = None) -> torch.Tensor:
    """[C, H, W] in [0, 1]: per pixel of each view, the selected Gaussians' share of its colour (their summed
    compositing weights), from a render in which they are white and the others black, one view at a time;
    ``progress`` and ``should_stop`` as :func:`gaussian_weights` takes them."""
    check_selection(selection, len(scene), "coverage")
    dc = ((selection.to(scene.means) - 0.5) / SH_C0)[:, None, None].expand(-1, 1, 3)
    flat = dataclasses.replace(scene.map(torch.Tensor.detach), sh=dc.contiguous())
    cameras = cameras.to(scene.device)
    views = []
    if progress is not None:
        progress(0, len(cameras), {})
    with torch.no_grad():
        for view in range(len(cameras)):
            views.append(render(flat, cameras.subset([view]), backend=backend, should_stop=should_stop).rgb[0, ..., 0])
            if progress is not None:
                progress(view + 1, len(cameras), {})
    return torch.stack(views).clamp(0, 1)
