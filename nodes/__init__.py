"""ComfyUI nodes of the ArtNVG pack: thin adapters over ``artnvg_core``.

Public contract: node type names (the keys of :data:`NODE_CLASS_MAPPINGS`), and each
node's inputs and their order (saved workflows store widget values by position) and
outputs. Add new inputs only at the end of a node's ``optional`` inputs.
"""

from __future__ import annotations

from .blend_nodes import BlendStylization
from .camera_nodes import CamerasAroundScene, GroupNeighbouringViews, LoadCameras
from .comfy_bridge import comfy_module, input_directory, register_model_folder
from .demo_inputs import install_demo_inputs
from .diffusion_nodes import SampleGroup
from .finetune_nodes import FinetuneGaussians
from .model_patch_nodes import CSGO_EXTENSIONS, CSGO_FOLDER, ApplyCSGO, LoadCSGO, NVAttentionPatch
from .prompt_checks import register_prompt_check
from .render_nodes import RenderCameraPath, RenderViews
from .scene_nodes import LoadGaussianScene, SaveGaussianScene
from .selection_nodes import SelectGaussians
from .splat_nodes import SceneToSplat, SplatToScene

register_model_folder(CSGO_FOLDER, CSGO_EXTENSIONS)
if comfy_module("folder_paths") is not None:  # inside ComfyUI: the shipped workflows' inputs, whole-prompt checks
    install_demo_inputs(input_directory())
    register_prompt_check()

NODE_CLASS_MAPPINGS = {
    "ArtNVGLoadGaussianScene": LoadGaussianScene,
    "ArtNVGLoadCameras": LoadCameras,
    "ArtNVGCamerasAroundScene": CamerasAroundScene,
    "ArtNVGRenderViews": RenderViews,
    "ArtNVGRenderCameraPath": RenderCameraPath,
    "ArtNVGGroupNeighbouringViews": GroupNeighbouringViews,
    "ArtNVGLoadCSGO": LoadCSGO,
    "ArtNVGApplyCSGO": ApplyCSGO,
    "ArtNVGNVAttentionPatch": NVAttentionPatch,
    "ArtNVGSampleGroup": SampleGroup,
    "ArtNVGFinetuneGaussians": FinetuneGaussians,
    "ArtNVGSelectGaussians": SelectGaussians,
    "ArtNVGBlendStylization": BlendStylization,
    "ArtNVGSaveGaussianScene": SaveGaussianScene,
    "ArtNVGSceneToSplat": SceneToSplat,
    "ArtNVGSplatToScene": SplatToScene,
}

NODE_DISPLAY_NAME_MAPPINGS = {name: node.DISPLAY_NAME for name, node in NODE_CLASS_MAPPINGS.items()}
