"""Load ArtNVG Models, CSGO Style/Content Encode, NV-Attention Patch Model and Sample Group.

The ``ARTNVG_MODELS`` value is a :class:`LoadedModels`: the core's ``DiffusionModels`` plus
where they run, whether they stay there between runs, the memory mode, and the
neighbouring-view attention settings (off until NV-Attention Patch Model turns it on).
"""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager
from pathlib import Path

import torch

from artnvg_core.devices import DEVICE_CHOICES, device_for
from artnvg_core.diffusion.compile_cache import save_compile_cache
from artnvg_core.diffusion.conditioning import prepare_conditioning
from artnvg_core.diffusion.csgo import CONTENT_ROUTINGS
from artnvg_core.diffusion.memory import enable_low_memory
from artnvg_core.diffusion.model_files import MODEL_SOURCES, ModelFiles, ModelSource, locate, missing_model
from artnvg_core.diffusion.models import DiffusionModels
from artnvg_core.diffusion.settings import NV_LEVELS, SCHEDULER_NAMES, SIZE_RULES, SamplerSettings
from artnvg_core.diffusion.stylize import (
    DEFAULT_NEGATIVE_PROMPT,
    DEFAULT_PROMPT,
    stylize_groups,
)
from artnvg_core.diffusion.loader import load_models_for

from .comfy_bridge import (
    cancellable,
    comfy_module,
    compute_device,
    interrupt_requested,
    model_file_path,
    model_files,
    model_folder_paths,
    progress_bar,
)
from .node_base import STYLE_IMAGE_INPUT, ArtNVGNode
from .node_errors import NodeInputError, node_input
from .node_types import EMBEDS, GROUPS, IMAGE, MODELS
from .prompt_checks import HIDDEN, check_result

CSGO_FOLDER = "csgo"
CSGO_EXTENSIONS = {".bin", ".safetensors", ".pt", ".pth"}
HF_CACHE = "(huggingface cache)"
DTYPES = {"float16": torch.float16, "bfloat16": torch.bfloat16, "float32": torch.float32}
MEMORY_MODES = ("full", "low")


@dataclasses.dataclass(frozen=True)
class ModelInput:
    """One model of the loader: list input ``name`` over ComfyUI model ``folder``, text input ``<name>_path``;
    ``field``: its :class:`~artnvg_core.diffusion.model_files.ModelFiles` field."""

    name: str
    folder: str
    field: str

    @property
    def source(self) -> ModelSource:
        return MODEL_SOURCES[self.field]

    @property
    def path_input(self) -> str:
        return f"{self.name}_path"

    def list_input(self) -> tuple:
        """The declaration of input ``name``: the folder's files, listed now, after the Hugging Face cache (a COMBO,
        whose value ComfyUI leaves to the loader's check: see ``prompt_checks``)."""
        return ("COMBO", {"options": [HF_CACHE, *model_files(self.folder)], "tooltip": (
            f"{self.source.description}: a file in models/{self.folder}, or {HF_CACHE} ({self.source.url}).")})


MODEL_INPUTS = (
    ModelInput("sdxl_checkpoint", "checkpoints", "sdxl"),
    ModelInput("controlnet", "controlnet", "controlnet"),
    ModelInput("image_encoder", "clip_vision", "image_encoder"),
    ModelInput("csgo_weights", CSGO_FOLDER, "csgo"),
)


def _model_path(node: str, model: ModelInput, listed: str, path: str) -> Path:
    """The existing file or folder for ``model``: ``path`` when not blank, else the listed file, else
    (``HF_CACHE``) the Hugging Face cache. Raises NodeInputError saying where it looked and where to get it."""
    if path.strip():
        with node_input(node, model.path_input):
            return locate(model.source, path.strip())
    if listed == HF_CACHE:
        with node_input(node, model.name):
            return locate(model.source, None)
    found = model_file_path(model.folder, listed)
    if found is None:
        folders = ", ".join(model_folder_paths(model.folder)) or f"ComfyUI's models/{model.folder}"
        raise NodeInputError(
            f"{node}: input '{model.name}': {model.source.description} '{listed}' not found in the "
            f"'{model.folder}' model folder ({folders}). Get it from {model.source.url} and put it there."
        )
    return found


def _model_paths(node: str, inputs: dict[str, str]) -> ModelFiles:
    """:func:`_model_path` of every entry of :data:`MODEL_INPUTS`, from the node's inputs by name."""
    return ModelFiles(**{model.field: _model_path(node, model, inputs[model.name], inputs.get(model.path_input, ""))
                         for model in MODEL_INPUTS})


def missing_models(node: str, inputs: dict[str, str], config_dir: str | None) -> str | None:
    """None when every model file the loader reads is there, else one message naming each missing one once
    (input, file, where it was looked for, where to get it); ``inputs``: the node's inputs by name."""
    problems, found = [], {}
    for model in MODEL_INPUTS:
        try:
            found[model.field] = _model_path(node, model, inputs[model.name], inputs.get(model.path_input, ""))
        except NodeInputError as error:
            problems.append(str(error).removeprefix(f"{node}: "))
    if not problems and (missing := missing_model(ModelFiles(**found), sdxl_config_dir=config_dir)):
        problems.append(missing)
    if not problems:
        return None
    count = f"{len(problems)} model file{'s' if len(problems) > 1 else ''}"
    return f"{node}: {count} missing, so nothing was run:\n" + "\n".join(f"- {problem}" for problem in problems)


@dataclasses.dataclass
class LoadedModels:
    """The ``ARTNVG_MODELS`` value (see the module docstring); ``compiled``: the loader compiled the blocks (Sample
    Group then saves the compile artifacts for the next run)."""

    models: DiffusionModels
    device: torch.device
    keep_loaded: bool
    low_memory: bool = False
    neighbour_views: bool = False
    nv_levels: str = "all"
    nv_nearest: int | None = None
    nv_kv_downsample: int = 1
    compiled: bool = False


def _move(value, device: torch.device) -> None:
    """Move every torch module held by ``value`` (a dataclass, possibly nested) to ``device``."""
    for field in dataclasses.fields(value):
        member = getattr(value, field.name)
        if isinstance(member, torch.nn.Module):
            member.to(device)
        elif dataclasses.is_dataclass(member):
            _move(member, device)


@contextmanager
def models_on_device(loaded: LoadedModels):
    """The models on their compute device for the block (in low memory: only the UNet, the rest visits);
    afterwards back on the CPU unless ``keep_loaded``."""
    if loaded.low_memory:
        enable_low_memory(loaded.models, loaded.device)
    elif not loaded.keep_loaded:
        _move(loaded.models, loaded.device)
    try:
        yield loaded.models
    finally:
        if not loaded.keep_loaded:
            _move(loaded.models, torch.device("cpu"))
            model_management = comfy_module("comfy.model_management")
            if model_management is not None:
                model_management.soft_empty_cache()


class LoadArtNVGModels(ArtNVGNode):
    """SDXL 1.0 base, the TTPlanet tile ControlNet, the IP-Adapter SDXL image encoder and CSGO weights.

    Each model comes from its ComfyUI model folder, from the Hugging Face cache, or from the
    path typed into its ``*_path`` input (a file or a diffusers/transformers folder).
    """

    DISPLAY_NAME = "Load ArtNVG Models"
    FUNCTION = "load"
    RETURN_TYPES = (MODELS,)
    RETURN_NAMES = ("models",)
    REQUIRED = {
        **{model.name: model.list_input for model in MODEL_INPUTS},
        "dtype": (tuple(DTYPES), {"default": "float16", "tooltip": "Diffusion precision."}),
        "device": (DEVICE_CHOICES, {"default": "auto", "tooltip": (
            "auto: ComfyUI's device (CUDA, Apple MPS or the CPU).")}),
        "keep_loaded": ("BOOLEAN", {"default": True, "tooltip": (
            "Keep the models on the device between runs; off moves them to the CPU after each node.")}),
    }
    OPTIONAL = {
        **{model.path_input: ("STRING", {"default": "", "tooltip": f"Path overriding {model.name} when not blank."})
           for model in MODEL_INPUTS},
        "sdxl_config_dir": ("STRING", {"default": "", "tooltip": (
            "A diffusers-format SDXL folder (model_index.json, configs, tokenizers) for a single-file "
            "checkpoint; blank: SDXL 1.0 base's configs and CLIP tokenizers shipped with the pack (no download).")}),
        "memory": (MEMORY_MODES, {"default": "full", "tooltip": (
            "low: a 15-view group at 1024 px within 12 GiB, same result, a little slower (BENCHMARKS.md, "
            "Memory): only the UNet stays on the GPU, the rest visits it; guidance halves one at a time. Start "
            "ComfyUI with PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True.")}),
        "compile": ("BOOLEAN", {"default": False, "tooltip": (
            "Compile the UNet's and ControlNet's repeated blocks (full memory only): same result up to bf16 "
            "rounding, slightly faster steps after a long first run, so it pays back on large scenes only "
            "(BENCHMARKS.md, Diffusion step). Keeps the last group's ControlNet hint features (~0.3 GiB for "
            "14 views at 1024 px).")}),
    }

    HIDDEN = HIDDEN

    @classmethod
    def check_files(cls, sdxl_checkpoint=HF_CACHE, controlnet=HF_CACHE, image_encoder=HF_CACHE, csgo_weights=HF_CACHE,
                    sdxl_checkpoint_path="", controlnet_path="", image_encoder_path="", csgo_weights_path="",
                    sdxl_config_dir="", **_other_inputs) -> str | None:
        """:func:`missing_models` of the node's values (``prompt_checks``)."""
        inputs = locals()
        return missing_models(cls.DISPLAY_NAME, inputs, sdxl_config_dir.strip() or None)

    @classmethod
    def VALIDATE_INPUTS(cls, files=None):
        return check_result(files)

    @cancellable
    def load(self, sdxl_checkpoint, controlnet, image_encoder, csgo_weights, dtype, device, keep_loaded,
             sdxl_checkpoint_path="", controlnet_path="", image_encoder_path="", csgo_weights_path="",
             sdxl_config_dir="", memory="full", compile=False, files=None):
        problem = missing_models(self.DISPLAY_NAME, locals(), sdxl_config_dir.strip() or None)
        if problem:
            raise NodeInputError(problem)
        files = _model_paths(self.DISPLAY_NAME, locals())
        with node_input(self.DISPLAY_NAME, "device"):
            target = compute_device() if device == "auto" else device_for(device)
        low_memory = memory == "low"
        with node_input(self.DISPLAY_NAME):  # the core's refusal of compile with low memory names the input
            models = load_models_for(files, low_memory, target, compile, dtype=DTYPES[dtype],
                                     sdxl_config_dir=sdxl_config_dir.strip() or None,
                                     on_cpu=not keep_loaded or low_memory, progress=progress_bar(),
                                     should_stop=interrupt_requested)
        return (LoadedModels(models, target, keep_loaded, low_memory, compiled=compile),)


class NVAttentionPatch(ArtNVGNode):
    """Turn neighbouring-view attention on: every view of a group attends to all views of the group.

    The optional inputs trade exactness for speed (docs/presets.md): NV in the lowest-resolution
    level only, each view's k nearest views only, the other views' keys/values pooled.
    """

    DISPLAY_NAME = "NV-Attention Patch Model"
    FUNCTION = "patch"
    RETURN_TYPES = (MODELS,)
    RETURN_NAMES = ("models",)
    REQUIRED = {
        "models": (MODELS,),
        "enabled": ("BOOLEAN", {"default": True, "tooltip": "Off: each view attends only to itself."}),
    }
    OPTIONAL = {
        "levels": (NV_LEVELS, {"default": "all", "tooltip": (
            "lowest: NV attention in the lowest-resolution level only (faster, approximate).")}),
        "nearest_views": ("INT", {"default": 0, "min": 0, "max": 256, "tooltip": (
            "0: all views of the group; k: each view attends to its k nearest views (approximate).")}),
        "kv_downsample": ("INT", {"default": 1, "min": 1, "max": 8, "tooltip": (
            "Pool the other views' keys/values by this factor per side (1: exact).")}),
    }

    def patch(self, models, enabled, levels="all", nearest_views=0, kv_downsample=1):
        return (dataclasses.replace(models, neighbour_views=enabled, nv_levels=levels,
                                    nv_nearest=nearest_views or None, nv_kv_downsample=kv_downsample),)


class CSGOEncode(ArtNVGNode):
    """Encode the style image (CSGO style tokens) and the prompt, shared by every group.

    Content tokens come from each view's content image and are encoded by Sample Group.
    """

    DISPLAY_NAME = "CSGO Style/Content Encode"
    FUNCTION = "encode"
    RETURN_TYPES = (EMBEDS,)
    RETURN_NAMES = ("embeds",)
    REQUIRED = {
        "models": (MODELS,),
        "style_image": STYLE_IMAGE_INPUT,
        "prompt": ("STRING", {"default": DEFAULT_PROMPT, "multiline": True}),
        "negative_prompt": ("STRING", {"default": DEFAULT_NEGATIVE_PROMPT, "multiline": True, "tooltip": (
            "Blank: zero negative embeddings (SDXL's default for an empty negative prompt).")}),
    }

    def encode(self, models, style_image, prompt, negative_prompt):
        with node_input(self.DISPLAY_NAME), models_on_device(models) as diffusion:
            return (prepare_conditioning(diffusion, style_image[:1], prompt, negative_prompt.strip() or None),)


_SAMPLER = SamplerSettings()  # Sample Group's defaults


def _scale(default: float, tooltip: str) -> tuple:
    """A FLOAT input for a conditioning strength in [0, 10]."""
    return ("FLOAT", {"default": default, "min": 0.0, "max": 10.0, "step": 0.05, "tooltip": tooltip})


class SampleGroup(ArtNVGNode):
    """Stylize the content views group by group (or one chosen group) with CSGO control.

    Returns the stylized IMAGE batch in view order: every view, or the chosen group's views.
    Group g is sampled with seed + g, so one group alone matches its part of a full run.
    """

    DISPLAY_NAME = "Sample Group"
    FUNCTION = "sample"
    RETURN_TYPES = (IMAGE,)
    RETURN_NAMES = ("stylized_views",)
    REQUIRED = {
        "models": (MODELS,),
        "embeds": (EMBEDS,),
        "content_views": (IMAGE, {"tooltip": "Rendered views, in the cameras' order (from Render Views)."}),
        "groups": (GROUPS, {"tooltip": "Groups of the same cameras (from Group Neighbouring Views)."}),
        "group_index": ("INT", {"default": -1, "min": -1, "max": 9999, "tooltip": (
            "-1: every group; otherwise only this group (0-based).")}),
        "seed": ("INT", {"default": 0, "min": 0, "max": 2**31 - 1}),
        "steps": ("INT", {"default": _SAMPLER.steps, "min": 1, "max": 1000}),
        "guidance_scale": ("FLOAT", {"default": _SAMPLER.guidance_scale, "min": 0.0, "max": 50.0, "step": 0.1}),
        "content_scale": _scale(_SAMPLER.content_scale, (
            "Weight of the CSGO content tokens (down blocks; content_routing paper only).")),
        "style_scale": _scale(_SAMPLER.style_scale, "Weight of the CSGO style tokens (up blocks, ControlNet)."),
        "control_scale": _scale(_SAMPLER.control_scale, "Tile ControlNet strength."),
        "resolution": ("INT", {"default": _SAMPLER.resolution, "min": 0, "max": 4096, "step": 64, "tooltip": (
            "Sampling size (see size_rule; 1024 for SDXL); 0 keeps the views' size. Outputs keep the "
            "views' size.")}),
        "scheduler": (SCHEDULER_NAMES, {"default": _SAMPLER.scheduler}),
    }
    OPTIONAL = {
        "size_rule": (SIZE_RULES, {"default": _SAMPLER.size_rule, "tooltip": (
            "long_side: CSGO's rule, the long side becomes the resolution (16:9 samples at 1024x576); "
            "area: about resolution² pixels (16:9 at 1344x768, 1.75x the tokens, about 3x the NV cost).")}),
        "content_routing": (CONTENT_ROUTINGS, {"default": _SAMPLER.content_routing, "tooltip": (
            "released: as CSGO's released code, the UNet's down blocks read text only (content comes through "
            "the Tile ControlNet; content_scale has no effect). paper: content tokens into every UNet "
            "down-block cross-attention, as the papers describe (needs the CSGO file's content entries).")}),
        "cfg_until": ("FLOAT", {"default": _SAMPLER.cfg_until, "min": 0.0, "max": 1.0, "step": 0.05, "tooltip": (
            "Classifier-free guidance for this fraction of the steps only, then the conditional half alone "
            "(half the work per step); 1: every step (exact).")}),
    }

    @cancellable
    def sample(self, models, embeds, content_views, groups, group_index, seed, steps, guidance_scale,
               content_scale, style_scale, control_scale, resolution, scheduler, size_rule=SamplerSettings.size_rule,
               content_routing=SamplerSettings.content_routing, cfg_until=SamplerSettings.cfg_until):
        if len(content_views) != groups.num_views:
            raise NodeInputError(
                f"{self.DISPLAY_NAME}: input 'content_views': {len(content_views)} views but the groups cover "
                f"{groups.num_views} cameras; render and group the same cameras"
            )
        if not -1 <= group_index < len(groups):
            raise NodeInputError(
                f"{self.DISPLAY_NAME}: input 'group_index': {group_index} is out of range for {len(groups)} groups"
            )
        with node_input(self.DISPLAY_NAME):
            settings = SamplerSettings(
                steps=steps, guidance_scale=guidance_scale, content_scale=content_scale, style_scale=style_scale,
                control_scale=control_scale, neighbour_views=models.neighbour_views,
                content_routing=content_routing, resolution=resolution or None, size_rule=size_rule,
                scheduler=scheduler, cfg_until=cfg_until,
                sequential_cfg=models.low_memory,
                nv_levels=models.nv_levels, nv_nearest=models.nv_nearest, nv_kv_downsample=models.nv_kv_downsample,
            )
        chosen = None if group_index < 0 else [group_index]
        with node_input(self.DISPLAY_NAME), models_on_device(models) as diffusion:
            output = stylize_groups(diffusion, content_views, groups, embeds, settings, seed=seed, group_indices=chosen,
                                    progress=progress_bar(), should_stop=interrupt_requested)
        if models.compiled:
            save_compile_cache(models.device)
        if group_index >= 0:
            output = output[list(groups[group_index].views)]
        return (output,)
