"""Select Gaussians: a selection of a scene's Gaussians (box, sphere, or masks painted on views)."""

from __future__ import annotations

import torch

from artnvg_core.cameras.framing import scene_frame
from artnvg_core.cameras.selection import listed_views, parse_views
from artnvg_core.counted import counted
from artnvg_core.selection import check_mask_size, parse_bounds, select_by_masks, select_region

from .comfy_bridge import (
    autograd_enabled,
    cancellable,
    interrupt_requested,
    progress_bar,
    progress_text,
    render_device,
    trainable_copy,
)
from .node_base import ArtNVGNode, ViewInput
from .node_errors import node_input
from .node_types import CAMERAS, MASK, SCENE, SELECTION

MODES = ("box", "sphere", "mask")


def _where_to_look(scene, mode: str, masks: torch.Tensor | None) -> str:
    """What to change when a selection is empty: for a box or sphere, where the scene's middle is (the subject
    sphere of :func:`~artnvg_core.cameras.framing.scene_frame`, as sphere bounds); for masks, whether any pixel
    is painted."""
    if mode == "mask":
        if not bool((masks > 0).any()):
            return "the mask has no painted pixel: paint the region in Load Image's mask editor"
        return "its painted pixels see no Gaussian: paint over the scene where the views show it"
    frame = scene_frame(scene)
    sphere = ", ".join(f"{value:.3g}" for value in (*frame.center.tolist(), frame.radius))
    return f"the middle of the scene (the bulk of its Gaussians) is the sphere {sphere} (X, Y, Z, R)"


class SelectGaussians(ArtNVGNode):
    """Choose the Gaussians that Finetune Gaussians may change and Blend Stylization mixes.

    box: the Gaussians whose centre lies in XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX; sphere: in X,Y,Z,R (the scene's units
    and axes). mask: the Gaussians that a mask's painted pixels see, for masks painted on rendered views (e.g.
    with the mask editor on a Render Views image saved and loaded again); views says which cameras they were
    painted on. Shows how many Gaussians it selected."""

    DISPLAY_NAME = "Select Gaussians"
    FUNCTION = "select"
    RETURN_TYPES = (SELECTION,)
    RETURN_NAMES = ("selection",)
    REQUIRED = {
        "scene": (SCENE,),
        "mode": (MODES, {"default": "box", "tooltip": (
            "box or sphere: the Gaussians whose centre lies inside bounds; mask: those the painted pixels of mask "
            "see (connect cameras and mask).")}),
        "bounds": ("STRING", {"default": "-1, -1, -1, 1, 1, 1", "tooltip": (
            "box: XMIN, YMIN, ZMIN, XMAX, YMAX, ZMAX; sphere: X, Y, Z, R; in the scene's units (unused for mask).")}),
    }
    OPTIONAL = {
        "cameras": (CAMERAS, {"tooltip": "mask: the cameras of the views the masks were painted on."}),
        "mask": (MASK, {"tooltip": "mask: painted pixels (1) of one or more views, e.g. Load Image's mask; of the views' aspect, at any size."}),
        "views": ("STRING", {"default": "0", "tooltip": (
            "mask: the camera index of each mask in the batch, comma-separated, in the cameras' order.")}),
    }
    VALUE_CHECKS = {"views": listed_views}  # a view may hold several masks
    VIEW_INPUTS = {"views": ViewInput(mode=("mode", "mask"))}
    NEEDS_LINKS = {"mode": {"mask": ("cameras", "mask")}}

    @classmethod
    def _value_problems(cls, values: dict):
        """The base's problems, then bounds that its mode, box or sphere, cannot read (checked with the prompt's
        values too, as a text check, though it reads the mode)."""
        yield from super()._value_problems(values)
        passed = cls.passed_values(values)
        mode, bounds = passed.get("mode"), passed.get("bounds")
        if mode in ("box", "sphere") and isinstance(bounds, str):
            try:
                parse_bounds(mode, bounds)
            except ValueError as error:
                yield f"{cls.DISPLAY_NAME}: input 'bounds': {error}", False

    @cancellable
    def select(self, scene, mode, bounds, cameras=None, mask=None, views="0", node_id=None):
        with node_input(self.DISPLAY_NAME, "mode"):
            if mode not in MODES:
                raise ValueError(f"expected one of {MODES}, got {mode!r}")
        if mode != "mask":
            with node_input(self.DISPLAY_NAME, "bounds"):
                selection = select_region(scene, parse_bounds(mode, bounds))
        else:  # cameras and mask connected (NEEDS_LINKS)
            masks = mask if mask.ndim == 3 else mask[None]
            with node_input(self.DISPLAY_NAME, "views"):
                indices = parse_views(views, len(cameras))
                if len(indices) != len(masks):
                    raise ValueError(f"{counted(len(masks), 'mask')} but {counted(len(indices), 'view')} ({views!r}): "
                                     "give one view per mask")
            with node_input(self.DISPLAY_NAME, "mask"):  # before the rasterizer loads
                check_mask_size(masks.shape[2], masks.shape[1], cameras.width, cameras.height, "the masks")
            with render_device() as device, node_input(self.DISPLAY_NAME, "mask"), autograd_enabled():
                # the Gaussians' weights are read from a render's gradient
                selection = select_by_masks(trainable_copy(scene).to(device), trainable_copy(cameras.subset(indices)),
                                            masks.clone().to(device), progress=progress_bar(),
                                            should_stop=interrupt_requested).cpu()
        count = int(selection.sum())
        progress_text(f"selected {count:,} of {counted(len(scene), 'Gaussian')}", self.DISPLAY_NAME)
        with node_input(self.DISPLAY_NAME, "bounds" if mode != "mask" else "mask"):
            if count == 0:
                raise ValueError(f"selects no Gaussian of the scene; {_where_to_look(scene, mode, masks=mask)}")
        return (selection.to(torch.bool),)
