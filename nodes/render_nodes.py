"""Render Views and Render Camera Path: scene + cameras -> ComfyUI IMAGE batches."""

from __future__ import annotations

import functools

import torch

from artnvg_core.cameras import CameraSet, NoOrbit, interpolate_path, orbit_path
from artnvg_core.cameras.paths import check_key_views
from artnvg_core.cameras.selection import listed_views, parse_views
from artnvg_core.key_views import select_key_views
from artnvg_core.raster import check_render_plan
from artnvg_core.raster.views import render_views
from artnvg_core.scene import GaussianScene

from .comfy_bridge import cancellable, interrupt_requested, progress_bar, render_device
from .node_base import ArtNVGNode, ViewInput
from .node_errors import NodeInputError, node_input
from .node_types import CAMERAS, IMAGE, SCENE

# a view list's text check when each view may come once: as render --views (a file per view) and evaluate --views,
# whose path passes through its views (a key view twice would make a zero-length segment; loop returns to the first)
EACH_VIEW_ONCE = functools.partial(listed_views, distinct=True)
SCALE_INPUT = ("FLOAT", {"default": 0.5, "min": 0.01, "max": 4.0, "step": 0.005, "tooltip": (
    "Resolution factor applied to the cameras' image size (0.5 renders 512x512 views at 256x256).")})


def render_frames(scene: GaussianScene, cameras: CameraSet) -> torch.Tensor:
    """Every view of ``cameras`` as an IMAGE batch [C, H, W, 3] in [0, 1] on the CPU.

    Renders one view at a time on ComfyUI's device, updating the progress bar and
    stopping (core ``Cancelled``) when the user cancels, inside a view as between views.
    """
    with render_device() as device:
        return render_views(scene.to(device), cameras.to(device), chunk=1, cpu=True, progress=progress_bar(),
                            should_stop=interrupt_requested).rgb


def render_scaled(node: str, scene: GaussianScene, cameras: CameraSet, scale: float) -> tuple[torch.Tensor, CameraSet]:
    """(:func:`render_frames` of ``cameras`` at ``scale`` times their size, those cameras), errors naming ``node``'s
    inputs ``scale`` and ``scene``: the outputs of the render nodes. A plan whose images would not fit in memory
    (:func:`~artnvg_core.raster.check_render_plan`) is refused before the first view."""
    with node_input(node, "scale"):
        cameras = cameras.scaled(scale)
        check_render_plan(len(cameras), cameras.width, cameras.height)
    with node_input(node, "scene"):
        return render_frames(scene, cameras), cameras


class RenderViews(ArtNVGNode):
    """Render the scene from chosen capture cameras; also returns those cameras at the rendered size."""

    DISPLAY_NAME = "Render Views"
    FUNCTION = "render"
    RETURN_TYPES = (IMAGE, CAMERAS)
    RETURN_NAMES = ("images", "cameras")
    REQUIRED = {
        "scene": (SCENE,),
        "cameras": (CAMERAS,),
        "scale": SCALE_INPUT,
        "stride": ("INT", {"default": 1, "min": 1, "max": 10000, "tooltip": (
            "Use every stride-th camera (0, stride, 2*stride, ...) when views is blank.")}),
        "views": ("STRING", {"default": "", "tooltip": (
            "Comma-separated camera indices in file order (e.g. 0,5,9), each once; blank: every view, thinned by "
            "stride.")}),
    }
    OPTIONAL = {
        "key_views": ("INT", {"default": 0, "min": 0, "max": 10000, "tooltip": (
            "0: every chosen view; K: only K of them that cover the scene (farthest camera poses), for a "
            "diffusion stage and finetune on key views alone. The cameras output holds the same views.")}),
    }
    VALUE_CHECKS = {"views": EACH_VIEW_ONCE}
    VIEW_INPUTS = {"views": ViewInput()}

    @cancellable
    def render(self, scene, cameras, scale, stride, views, key_views=0, node_id=None):
        with node_input(self.DISPLAY_NAME, "views"):
            listed = parse_views(views, len(cameras), distinct=True)
            chosen = cameras.subset(listed if views.strip() else listed[::stride])
        with node_input(self.DISPLAY_NAME, "key_views"):
            chosen = chosen.subset(select_key_views(chosen, key_views))
        return render_scaled(self.DISPLAY_NAME, scene, chosen, scale)


PATH_KINDS = ("orbit", "interpolate")


class RenderCameraPath(ArtNVGNode):
    """Render preview frames along an orbit around the scene or a smooth path through chosen views.

    The IMAGE frames suit stock image and video save nodes.
    """

    DISPLAY_NAME = "Render Camera Path"
    FUNCTION = "render"
    RETURN_TYPES = (IMAGE, CAMERAS)
    RETURN_NAMES = ("frames", "path_cameras")
    REQUIRED = {
        "scene": (SCENE,),
        "cameras": (CAMERAS,),
        "path": (PATH_KINDS, {"default": "orbit", "tooltip": (
            "orbit: a horizontal circle around the scene centre; "
            "interpolate: a spline through key_views.")}),
        "scale": SCALE_INPUT,
        "num_frames": ("INT", {"default": 60, "min": 1, "max": 10000, "tooltip": "Frames of the orbit."}),
        "key_views": ("STRING", {"default": "", "tooltip": (
            "interpolate: comma-separated camera indices the path passes through, in order, each once (at least "
            "two; turn loop on to return to the first); blank: every view.")}),
        "frames_per_segment": ("INT", {"default": 30, "min": 1, "max": 10000, "tooltip": (
            "interpolate: frames between consecutive key views.")}),
        "loop": ("BOOLEAN", {"default": False, "tooltip": "interpolate: return to the first key view."}),
    }
    VALUE_CHECKS = {"key_views": EACH_VIEW_ONCE}
    VIEW_INPUTS = {"key_views": ViewInput(mode=("path", "interpolate"))}

    @classmethod
    def _value_problems(cls, values: dict):
        """The base's problems, then an interpolated path's key_views that list fewer than two views (checked with
        the prompt's values too, though it reads the path; blank, every view, is left to the camera count)."""
        yield from super()._value_problems(values)
        passed = cls.passed_values(values)
        key_views = passed.get("key_views")
        if passed.get("path") != "interpolate" or not isinstance(key_views, str) or not key_views.strip():
            return
        try:
            listed = EACH_VIEW_ONCE(key_views)
        except ValueError:  # the base refused it
            return
        try:
            check_key_views(listed)
        except ValueError as error:
            yield f"{cls.DISPLAY_NAME}: input 'key_views': {error}", False

    @cancellable
    def render(self, scene, cameras, path, scale, num_frames, key_views, frames_per_segment, loop, node_id=None):
        if path not in PATH_KINDS:
            raise NodeInputError(f"{self.DISPLAY_NAME}: input 'path': expected one of {PATH_KINDS}, got {path!r}")
        if path == "orbit":
            with node_input(self.DISPLAY_NAME, "cameras"):
                try:
                    path_cameras = orbit_path(cameras, num_frames)
                except NoOrbit as error:  # its advice names orbit_path's own arguments, which the node lacks
                    raise ValueError(f"no orbit around these cameras ({error.reason}); set 'path' to interpolate, "
                                     "through two views or more") from None
        else:
            with node_input(self.DISPLAY_NAME, "key_views"):
                path_cameras = interpolate_path(
                    cameras, parse_views(key_views, len(cameras), distinct=True), frames_per_segment, loop=loop
                )
        return render_scaled(self.DISPLAY_NAME, scene, path_cameras, scale)
