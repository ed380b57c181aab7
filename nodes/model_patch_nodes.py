"""NV-Attention Patch Model, Load CSGO and Apply CSGO: the method's patches on ComfyUI's own MODEL and CONTROL_NET.

The MODEL comes from Load Checkpoint (LoRAs from the stock LoRA loader), the CONTROL_NET from Load
ControlNet Model, the CLIP_VISION (ViT-bigG/14) from Load CLIP Vision. Each node checks what it is given
and names the input and what it expected before any sampling starts. The patches: :mod:`.comfy_patches`.
"""

from __future__ import annotations

import functools
import logging

import torch

from artnvg_core.diffusion.csgo import CONTENT_ROUTINGS, CSGOProjections, released_key_prefix
from artnvg_core.diffusion.csgo_weights import CSGOFile, read_csgo
from artnvg_core.diffusion.model_files import CSGO_WEIGHTS
from artnvg_core.diffusion.settings import NV_LEVELS, SamplerSettings
from artnvg_core.statedict import listed_keys, state_dict_mismatch
from artnvg_core.style_image import check_style_size

from .comfy_bridge import comfy_module
from .comfy_patches import (
    CSGO_STATE,
    CSGOState,
    ImageTokenPatch,
    NeighbourViewPatch,
    controlnet_model,
    diffusion_unet,
    patch_controlnet,
    transformer_layers,
)
from .model_files import CLIP_VISION_FILE, ModelFile
from .node_base import STYLE_IMAGE_INPUT, ArtNVGNode
from .node_errors import NodeInputError, node_input
from .node_types import CSGO

CSGO_FOLDER = "csgo"
CSGO_EXTENSIONS = {".bin", ".safetensors", ".pt", ".pth"}
CSGO_FILE = ModelFile("csgo_name", CSGO_FOLDER, CSGO_WEIGHTS, tooltip=(
    f"A CSGO weight file in models/{CSGO_FOLDER} ({CSGO_WEIGHTS.url}: `{CSGO_WEIGHTS.download_command}`, saved as "
    f"models/{CSGO_FOLDER}/csgo_4_32.bin)."))
UNET_ROUTES = {"input": "content", "output": "style", "middle": None}  # with the paper's content routing
CONTROLNET_ROUTES = {"input": "style", "middle": None}
_log = logging.getLogger("artnvg")


class NVAttentionPatch(ArtNVGNode):
    """Neighbouring-view attention on a MODEL: in every self-attention each view of a group attends to all the
    views of its group (the latent batch), the two guidance halves apart. Sample Group applies the same patch
    to the ControlNet's self-attention.

    The optional inputs trade exactness for speed (docs/presets.md): NV in the lowest-resolution
    level only, each view's k nearest views only (camera centres from Sample Group), the other views'
    keys/values pooled.
    """

    DISPLAY_NAME = "NV-Attention Patch Model"
    FUNCTION = "patch"
    RETURN_TYPES = ("MODEL",)
    RETURN_NAMES = ("model",)
    REQUIRED = {
        "model": ("MODEL",),
        "enabled": ("BOOLEAN", {"default": True, "tooltip": "Off: the model unchanged (each view attends only to "
                                                             "itself)."}),
    }
    OPTIONAL = {
        "levels": (NV_LEVELS, {"default": "all", "tooltip": (
            "lowest: NV attention in the lowest-resolution level only (faster, approximate).")}),
        "nearest_views": ("INT", {"default": 0, "min": 0, "max": 256, "tooltip": (
            "0: all views of the group; k: each view attends to its k nearest views (approximate).")}),
        "kv_downsample": ("INT", {"default": 1, "min": 1, "max": 8, "tooltip": (
            "Pool the other views' keys/values by this factor per side (1: exact).")}),
    }

    def patch(self, model, enabled, levels="all", nearest_views=0, kv_downsample=1, node_id=None):
        if not enabled:
            return (model,)
        unet = diffusion_unet(self.DISPLAY_NAME, model)
        lowest = 2 ** (len(unet.channel_mult) - 1) if levels == "lowest" else None
        patch = NeighbourViewPatch(lowest, nearest_views or None, kv_downsample)
        patched = model.clone()
        for block, number in dict.fromkeys((layer.block, layer.number) for layer in transformer_layers(unet)):
            patched.set_model_attn1_replace(patch, block, number)
        return (patched,)


class LoadCSGO(ArtNVGNode):
    """Load CSGO's weights (csgo_4_32.bin) from ComfyUI's models/csgo folder: the content and style resamplers
    and the cross-attention weights that Apply CSGO puts on the MODEL and the ControlNet."""

    DISPLAY_NAME = "Load CSGO"
    FUNCTION = "load"
    RETURN_TYPES = (CSGO,)
    RETURN_NAMES = ("csgo",)
    REQUIRED = {"csgo_name": CSGO_FILE.list_input}
    REPORTED_INPUT = "csgo_name"

    @classmethod
    def check_files(cls, csgo_name="", **_other_inputs) -> str | None:
        """The message when the chosen file is not in the csgo folder (``prompt_checks``), else None."""
        return CSGO_FILE.check(cls.DISPLAY_NAME, csgo_name)

    def load(self, csgo_name, node_id=None):
        path = CSGO_FILE.path(self.DISPLAY_NAME, csgo_name)
        with node_input(self.DISPLAY_NAME, "csgo_name"):
            return (read_csgo(path),)


def _branch_weights(node: str, csgo: CSGOFile, group: dict, layers: list, routes: dict, what: str,
                    by_path: bool = False) -> dict:
    """``{layer: (to_k_ip, to_v_ip)}`` for the ``layers`` (with their attn2 modules) that ``routes`` give image
    tokens, from CSGO key ``group``; NodeInputError naming input 'csgo' when the file does not fit."""
    expected, chosen = {}, {}
    for position, (layer, attention) in enumerate(layers):
        if routes[layer.block] is None:
            continue
        prefix = f"{layer.diffusers_name}.attn2.processor" if by_path else released_key_prefix(position)
        shape = attention.to_k.weight.shape
        chosen[layer] = (f"{prefix}.to_k_ip.weight", f"{prefix}.to_v_ip.weight")
        expected.update({key: torch.empty(shape, device="meta") for key in chosen[layer]})
    mismatch = state_dict_mismatch(expected, {k: v for k, v in group.items() if k in expected})
    if mismatch:
        raise NodeInputError(f"{node}: input 'csgo': '{csgo.path.name}' does not fit {what}: {mismatch}")
    others = [key for key in group if key not in expected and ".to_k_ip." not in key and ".to_v_ip." not in key]
    if by_path and others:  # CSGO's loader would load them into the ControlNet; the ComfyUI path does not
        _log.warning("%s: '%s' holds %d other ControlNet weights keyed by module path, not applied here %s", node,
                     csgo.path.name, len(others), listed_keys(others))
    return {layer: tuple(group[key] for key in keys) for layer, keys in chosen.items()}


def _conv_in(node: str, csgo: CSGOFile, unet: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The file's ``conv_in_unet_sd`` group, checked against the UNet's first convolution."""
    mismatch = state_dict_mismatch(unet.input_blocks[0][0].state_dict(), csgo.conv_in)
    if mismatch:
        raise NodeInputError(f"{node}: input 'csgo': '{csgo.path.name}', group 'conv_in_unet_sd', does not fit this "
                             f"MODEL's conv_in: {mismatch}")
    return csgo.conv_in


def _attn2_layers(module: torch.nn.Module) -> list:
    """(TransformerLayer, its attn2 module) of every transformer block of ``module`` (ComfyUI's own module where
    a loaded ControlNet holds a :class:`~.comfy_patches.ControlNetAttention` in its place)."""
    found = [(layer, module.get_submodule(f"{layer.path}.attn2")) for layer in transformer_layers(module)]
    return [(layer, getattr(attention, "attention", attention)) for layer, attention in found]  # unwrapped


def _content_tokens(clip_vision, projections: CSGOProjections, images: torch.Tensor):
    """CSGO content tokens of each image of IMAGE batch ``images`` (ComfyUI's CLIP Vision features)."""
    return projections.tokens("content", clip_vision.encode_image(images).penultimate_hidden_states)


class ApplyCSGO(ArtNVGNode):
    """CSGO's content/style control on the MODEL and the ControlNet: the style image's tokens enter every
    cross-attention of the UNet's up blocks and of the ControlNet; content comes through the ControlNet's
    hint (Sample Group gives each view its own), and with the paper routing also as content tokens in the
    UNet's down blocks."""

    DISPLAY_NAME = "Apply CSGO"
    FUNCTION = "apply"
    RETURN_TYPES = ("MODEL", "CONTROL_NET")
    RETURN_NAMES = ("model", "control_net")
    REQUIRED = {
        "model": ("MODEL", {"tooltip": "An SDXL checkpoint (Load Checkpoint; LoRAs applied before)."}),
        "control_net": ("CONTROL_NET", {"tooltip": "The TTPlanet SDXL tile ControlNet (Load ControlNet Model)."}),
        "csgo": (CSGO,),
        "clip_vision": ("CLIP_VISION", {"tooltip": (
            f"ViT-bigG/14, IP-Adapter's SDXL image encoder (Load CLIP Vision). {CLIP_VISION_FILE.where_to_get()}.")}),
        "style_image": STYLE_IMAGE_INPUT,
        "style_scale": ("FLOAT", {"default": SamplerSettings.style_scale, "min": 0.0, "max": 10.0, "step": 0.05,
                                  "tooltip": "Weight of the style tokens (UNet up blocks, ControlNet)."}),
        "content_scale": ("FLOAT", {"default": SamplerSettings.content_scale, "min": 0.0, "max": 10.0, "step": 0.05,
                                    "tooltip": "Weight of the content tokens (content_routing paper only)."}),
        "content_routing": (CONTENT_ROUTINGS, {"default": SamplerSettings.content_routing, "tooltip": (
            "released: as CSGO's released code, the UNet's down blocks read text only (content comes through "
            "the ControlNet; content_scale has no effect). paper: content tokens into every UNet down-block "
            "cross-attention, as the papers describe (needs the CSGO file's content entries).")}),
    }

    def apply(self, model, control_net, csgo, clip_vision, style_image, style_scale, content_scale,
              content_routing=SamplerSettings.content_routing, node_id=None):
        node = self.DISPLAY_NAME
        with node_input(node, "style_image"):  # before any work
            check_style_size(style_image.shape[2], style_image.shape[1])
        model_base = comfy_module("comfy.model_base")
        if model_base is not None and not isinstance(model.model, model_base.SDXL):
            raise NodeInputError(f"{node}: input 'model': a {type(model.model).__name__} checkpoint; CSGO needs SDXL "
                                 "(SDXL 1.0 base or a fine-tune of it, from Load Checkpoint)")
        control_model = controlnet_model(node, control_net)
        unet = diffusion_unet(node, model)
        unet_layers = _attn2_layers(unet)
        routes = UNET_ROUTES if content_routing == "paper" else {**UNET_ROUTES, "input": None}
        if content_routing == "paper" and f"{released_key_prefix(0)}.to_k_ip.weight" not in csgo.unet_branches:
            raise NodeInputError(f"{node}: input 'content_routing': '{csgo.path.name}' holds no content entries for "
                                 "the UNet's down blocks (a file saved by CSGO's released code has none); use 'released'")
        unet_weights = _branch_weights(node, csgo, csgo.unet_branches, unet_layers, routes,
                                       "this MODEL's cross-attention (an SDXL checkpoint expected)")
        control_layers = _attn2_layers(control_model)
        by_path = not all(key.split(".", 1)[0].isdigit() for key in csgo.controlnet_branches)
        control_weights = _branch_weights(node, csgo, csgo.controlnet_branches, control_layers, CONTROLNET_ROUTES,
                                          "this ControlNet's cross-attention (an SDXL ControlNet expected)", by_path)
        projections = CSGOProjections(csgo.content, csgo.style)
        features = clip_vision.encode_image(style_image[:1]).penultimate_hidden_states
        if features.shape[-1] != csgo.style.config.embedding_dim:
            raise NodeInputError(f"{node}: input 'clip_vision': its features are {features.shape[-1]} wide, CSGO's "
                                 f"resamplers read {csgo.style.config.embedding_dim}: use ViT-bigG/14. "
                                 f"{CLIP_VISION_FILE.where_to_get()}")
        state = CSGOState(projections.tokens("style", features), style_scale, content_scale, content_routing,
                          functools.partial(_content_tokens, clip_vision, projections))
        patched = model.clone()
        for layer, (to_k_ip, to_v_ip) in unet_weights.items():
            patch = ImageTokenPatch(to_k_ip, to_v_ip, routes[layer.block], state)
            patched.set_model_attn2_replace(patch, layer.block, layer.number, layer.transformer)
        patched.model_options["transformer_options"][CSGO_STATE] = state
        if csgo.conv_in is not None:  # the file's UNet conv_in replaces the checkpoint's, as CSGO's loader does
            patched.add_patches({f"diffusion_model.input_blocks.0.0.{key}": ("set", (weight,))
                                 for key, weight in _conv_in(node, csgo, unet).items()})
        control_patches = {f"{layer.path}.attn2": ImageTokenPatch(*weights, "style", state)
                           for layer, weights in control_weights.items()}
        return patched, patch_controlnet(control_net, control_patches)
