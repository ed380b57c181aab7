"""Gaussian Scene to Splat and Splat to Gaussian Scene: the pack's scene to and from ComfyUI's core splat type."""

from __future__ import annotations

from .node_base import ArtNVGNode
from .node_errors import NodeInputError, node_input
from .node_types import SCENE
from .splat_interop import MISSING_SPLAT, SPLAT, SPLAT_CLASS, scene_to_splat, splat_to_scene

_AVAILABILITY = "" if SPLAT_CLASS is not None else f"\n\n{MISSING_SPLAT}"


def _require_core_type(node: str) -> None:
    if SPLAT_CLASS is None:
        raise NodeInputError(f"{node}: {MISSING_SPLAT}")


class SceneToSplat(ArtNVGNode):
    """The scene as ComfyUI's core Gaussian splat, for the core's splat nodes (render, transform, save as
    .ply/.spz/.ksplat). Scales become linear, opacities sigmoid(logit), quaternions unit length; the
    scene's render settings (2D filter, antialiasing) ride along as the splat's render_settings."""

    DISPLAY_NAME = "Gaussian Scene to Splat"
    FUNCTION = "convert"
    RETURN_TYPES = (SPLAT,)
    RETURN_NAMES = ("splat",)
    DESCRIPTION = __doc__ + _AVAILABILITY
    REQUIRED = {"scene": (SCENE,)}

    def convert(self, scene, node_id=None):
        _require_core_type(self.DISPLAY_NAME)
        return (scene_to_splat(scene),)


class SplatToScene(ArtNVGNode):
    """A splat from ComfyUI's core splat nodes (e.g. Get Splat from a .ply/.splat/.ksplat/.spz file) as a
    scene for the ArtNVG nodes. Takes one splat (batch of one, cut to its count); SH degree up to 3. Its
    render_settings, when it has them, become the scene's (classic 3DGS otherwise)."""

    DISPLAY_NAME = "Splat to Gaussian Scene"
    FUNCTION = "convert"
    RETURN_TYPES = (SCENE,)
    RETURN_NAMES = ("scene",)
    DESCRIPTION = __doc__ + _AVAILABILITY
    REQUIRED = {"splat": (SPLAT,)}

    def convert(self, splat, node_id=None):
        _require_core_type(self.DISPLAY_NAME)
        with node_input(self.DISPLAY_NAME):
            return (splat_to_scene(splat, source="input 'splat'"),)
