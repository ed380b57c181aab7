"""Blend Stylization: the strength dial, a stylized scene mixed with its original, with a preview."""

from __future__ import annotations

from artnvg_core.blend import blend, render_strengths
from artnvg_core.orbit import orbit_cameras
from artnvg_core.preview import side_by_side

from .comfy_bridge import cancellable, interrupt_requested, progress_bar, render_device, shown_notes
from .node_base import ArtNVGNode, ViewInput
from .node_errors import node_input
from .node_types import CAMERAS, IMAGE, SCENE, SELECTION


def parse_strengths(text: str) -> list[float]:
    """``"0, 0.5, 1"`` -> [0.0, 0.5, 1.0]: comma-separated numbers in [0, 1], at least one."""
    try:
        strengths = [float(part) for part in text.split(",") if part.strip()]
    except ValueError:
        strengths = []
    if not strengths or not all(0 <= s <= 1 for s in strengths):
        raise ValueError(f"expected comma-separated numbers from 0 to 1, e.g. 0, 0.5, 1; got {text!r}")
    return strengths


class BlendStylization(ArtNVGNode):
    """Turn the stylization up or down without a re-run: the stylized scene (a finetune of the original)
    mixed with the original Gaussian by Gaussian, every SH band and opacity (and the geometry where the
    finetune moved it). strength 0 is the original, 1 the stylized scene, exactly. With a selection, only
    the selected Gaussians are mixed.

    The preview shows one view at each of preview_strengths, side by side (left to right)."""

    DISPLAY_NAME = "Blend Stylization"
    FUNCTION = "blend"
    RETURN_TYPES = (SCENE, IMAGE)
    RETURN_NAMES = ("scene", "preview")
    REQUIRED = {
        "original": (SCENE, {"tooltip": "The scene before stylizing."}),
        "stylized": (SCENE, {"tooltip": "The stylized scene finetuned from it (same Gaussians, same order)."}),
        "strength": ("FLOAT", {"default": 0.5, "min": 0.0, "max": 1.0, "step": 0.01, "display": "slider",
                               "tooltip": "0: the original, 1: the stylized scene."}),
    }
    OPTIONAL = {
        "selection": (SELECTION, {"tooltip": "Only these Gaussians are mixed (from Select Gaussians)."}),
        "cameras": (CAMERAS, {"tooltip": "The preview's view comes from these; unconnected: a view around the scene."}),
        "view": ("INT", {"default": 0, "min": 0, "max": 100000, "tooltip": "The camera of the preview."}),
        "preview_strengths": ("STRING", {"default": "0, 0.25, 0.5, 0.75, 1", "tooltip": (
            "Strengths shown side by side in the preview, comma-separated.")}),
    }
    VALUE_CHECKS = {"preview_strengths": parse_strengths}
    VIEW_INPUTS = {"view": ViewInput()}

    @cancellable
    def blend(self, original, stylized, strength, selection=None, cameras=None, view=0,
              preview_strengths="0, 0.25, 0.5, 0.75, 1", node_id=None):
        with node_input(self.DISPLAY_NAME, "preview_strengths"):
            strengths = parse_strengths(preview_strengths)
        with node_input(self.DISPLAY_NAME):  # blend's messages name what they refuse: the two scenes, selection...
            result = blend(original, stylized, strength, selection)
            notes: list[str] = []
            camera = cameras.subset([view]) if cameras is not None else orbit_cameras(
                original, 1, notes=notes.append,
                up_option="connect cameras, e.g. Cameras Around Scene's with its up input set to -y or another axis")
            shown_notes(notes, self.DISPLAY_NAME)
            with render_device() as device:
                previews = render_strengths(original.to(device), stylized.to(device), camera, strengths,
                                            None if selection is None else selection.to(device),
                                            progress=progress_bar(), should_stop=interrupt_requested)
        return result, side_by_side(previews)[None]
