"""Names shared by every node: the menu category and the custom types passed between nodes.

Images between nodes are always ComfyUI ``IMAGE`` tensors: float32 in [0, 1], [B, H, W, 3], on the CPU.
"""

CATEGORY = "ArtNVG"

SCENE = "ARTNVG_SCENE"      # artnvg_core.scene.GaussianScene (on the CPU)
CAMERAS = "ARTNVG_CAMERAS"  # artnvg_core.cameras.CameraSet (on the CPU)
GROUPS = "ARTNVG_GROUPS"    # artnvg_core.grouping.ViewGroups
CSGO = "ARTNVG_CSGO"        # artnvg_core.diffusion.csgo_weights.CSGOFile
IMAGE = "IMAGE"
SELECTION = "ARTNVG_SELECTION"  # [N] bool tensor over a scene's Gaussians (artnvg_core.selection), on the CPU
