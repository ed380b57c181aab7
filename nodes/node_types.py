"""Names shared by every node: the menu category, the custom types passed between nodes, and what a value of
each is when a node runs (:data:`RUN_TYPES`).

Images between nodes are always ComfyUI ``IMAGE`` tensors: float32 in [0, 1], [B, H, W, 3], on the CPU.
"""

from typing import NamedTuple

import torch

from artnvg_core.cameras import CameraSet
from artnvg_core.diffusion.csgo_weights import CSGOFile
from artnvg_core.grouping import ViewGroups
from artnvg_core.scene import GaussianScene

CATEGORY = "ArtNVG"

SCENE = "ARTNVG_SCENE"      # artnvg_core.scene.GaussianScene (on the CPU)
CAMERAS = "ARTNVG_CAMERAS"  # artnvg_core.cameras.CameraSet (on the CPU)
GROUPS = "ARTNVG_GROUPS"    # artnvg_core.grouping.ViewGroups
CSGO = "ARTNVG_CSGO"        # artnvg_core.diffusion.csgo_weights.CSGOFile
IMAGE = "IMAGE"
MASK = "MASK"               # ComfyUI's mask: [B, H, W] (or [H, W]) in [0, 1]
SELECTION = "ARTNVG_SELECTION"  # [N] bool tensor over a scene's Gaussians (artnvg_core.selection), on the CPU


class RunType(NamedTuple):
    """What a node is given on an input of one type when it runs: an instance of ``cls``; a tensor with one of
    ``ranks`` dimensions, laid out as ``layout`` says."""

    cls: type
    ranks: tuple[int, ...] = ()
    layout: str = ""


RUN_TYPES = {  # input type -> RunType; types not listed (MODEL, VAE, ...) are ComfyUI's to check
    SCENE: RunType(GaussianScene),
    CAMERAS: RunType(CameraSet),
    GROUPS: RunType(ViewGroups),
    CSGO: RunType(CSGOFile),
    SELECTION: RunType(torch.Tensor, (1,), "[N]"),
    IMAGE: RunType(torch.Tensor, (4,), "[B, H, W, C]"),
    MASK: RunType(torch.Tensor, (2, 3), "[B, H, W] or [H, W]"),
    "INT": RunType(int),  # or a whole float (3.0), given as an int; never a bool (node_base)
    "FLOAT": RunType(float),  # or an int, given as a float; never a bool
    "STRING": RunType(str),
    "BOOLEAN": RunType(bool),
}
