"""Full-size model files with random weights (fp16) in the released layouts, for benchmarks that load
them as a user's downloads are loaded.

:func:`write_model_files` writes, where the folder lacks them:

* ``sd_xl_base_1.0.safetensors``: SDXL 1.0 base as one file with the original checkpoint's keys
  (``model.diffusion_model.*``, ``first_stage_model.*``, ``conditioner.embedders.{0,1}.*``);
* ``stable-diffusion-xl-base-1.0/``: the same SDXL as a diffusers folder (``model_index.json``, each
  component's config and fp16 weights, both tokenizers), as ``save_pretrained`` writes it;
* ``TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors``: the Tile ControlNet, diffusers keys;
* ``image_encoder/``: the IP-Adapter SDXL image encoder (ViT-bigG/14), ``config.json`` and
  ``model.safetensors``, as in ``h94/IP-Adapter/sdxl_models/image_encoder``;
* ``csgo_4_32.bin``: CSGO's resamplers (4 content, 32 style tokens) and image-branch projections in
  its ``torch.save`` layout.

The models are built with diffusers' and transformers' own random initialisation on ``device``
(a GPU builds SDXL in seconds, a CPU in minutes) and written one at a time.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from artnvg_core.diffusion.architectures import (
    BIGG_TEXT_CONFIG,
    CLIP_L_TEXT_CONFIG,
    SDXL_SCHEDULER_CONFIG,
    SDXL_UNET_CONFIG,
    SDXL_VAE_CONFIG,
    VIT_BIGG_IMAGE_ENCODER_CONFIG,
    controlnet_config_from_unet,
    transformers_config_kwargs,
)
from artnvg_core.diffusion.resampler import PerceiverResampler, ResamplerConfig
from artnvg_core.diffusion.sdxl_config import built_in_sdxl_config

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from diffusion_tiny import _image_branch_keys, write_single_file_checkpoint  # noqa: E402  (released key layouts)

NAMES = {
    "sdxl": "sd_xl_base_1.0.safetensors",
    "sdxl folder": "stable-diffusion-xl-base-1.0",
    "controlnet": "TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors",
    "image encoder": "image_encoder",
    "csgo": "csgo_4_32.bin",
}


def _built(build, device: torch.device) -> torch.nn.Module:
    """``build()`` initialised on ``device``, then fp16 on the CPU, ready to be written."""
    with torch.device(device):
        model = build()
    return model.half().cpu().eval()


def _sdxl_base(device: torch.device):
    """SDXL base (an :class:`~artnvg_core.diffusion.models.SDXLBase`) with random weights, fp16 on the CPU."""
    from diffusers import AutoencoderKL, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection, CLIPTokenizer

    from artnvg_core.diffusion.models import SDXLBase

    with built_in_sdxl_config() as config:
        tokenizers = [CLIPTokenizer.from_pretrained(config / name) for name in ("tokenizer", "tokenizer_2")]
    clip_l, bigg = (CLIPTextConfig(**transformers_config_kwargs(c)) for c in (CLIP_L_TEXT_CONFIG, BIGG_TEXT_CONFIG))
    return SDXLBase(
        unet=_built(lambda: UNet2DConditionModel(**SDXL_UNET_CONFIG), device),
        vae=_built(lambda: AutoencoderKL(**SDXL_VAE_CONFIG), device),
        text_encoder=_built(lambda: CLIPTextModel(clip_l), device),
        text_encoder_2=_built(lambda: CLIPTextModelWithProjection(bigg), device),
        tokenizer=tokenizers[0],
        tokenizer_2=tokenizers[1],
        scheduler_config=SDXL_SCHEDULER_CONFIG,
    )


def _write_sdxl(single: Path, folder: Path | None, device: torch.device):
    from diffusers import EulerDiscreteScheduler, StableDiffusionXLPipeline

    base = _sdxl_base(device)
    if not single.exists():
        write_single_file_checkpoint(single, base)
    if folder is not None and not folder.exists():
        StableDiffusionXLPipeline(
            vae=base.vae, text_encoder=base.text_encoder, text_encoder_2=base.text_encoder_2,
            tokenizer=base.tokenizer, tokenizer_2=base.tokenizer_2, unet=base.unet,
            scheduler=EulerDiscreteScheduler.from_config(SDXL_SCHEDULER_CONFIG),
        ).save_pretrained(folder)
    return base.unet


def _csgo_state(unet, controlnet) -> dict[str, dict[str, torch.Tensor]]:
    """csgo_4_32.bin's groups: the released resamplers and the UNet's and ControlNet's image branches."""
    def resampler(queries: int) -> dict[str, torch.Tensor]:
        return PerceiverResampler(ResamplerConfig(num_queries=queries)).half().state_dict()

    def half(keys: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return {k: v.half() for k, v in keys.items()}

    return {"content_image_proj": resampler(4), "style_image_proj": resampler(32),
            "ip_adapter": half(_image_branch_keys(unet, ("down_blocks", "up_blocks"), True, seed=8)),
            "controlnet_adapter_modules": half(_image_branch_keys(controlnet, ("down_blocks",), True, seed=9))}


def write_model_files(folder: Path, device: str | torch.device = "cpu", sdxl_folder: bool = True) -> dict[str, Path]:
    """The released files (see the module docstring) in ``folder``, written where missing (SDXL's diffusers
    folder only with ``sdxl_folder``: 6.5 GiB more); paths by role."""
    from diffusers import ControlNetModel, UNet2DConditionModel
    from safetensors.torch import save_file
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    device = torch.device(device)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {role: folder / name for role, name in NAMES.items()}
    unet = None
    if not (paths["sdxl"].exists() and (paths["sdxl folder"].exists() or not sdxl_folder)):
        unet = _write_sdxl(paths["sdxl"], paths["sdxl folder"] if sdxl_folder else None, device)
    if not (paths["controlnet"].exists() and paths["csgo"].exists()):
        if unet is None:
            with torch.device("meta"):  # the CSGO writer needs only the layers' names and shapes
                unet = UNet2DConditionModel(**SDXL_UNET_CONFIG)
        controlnet = _built(lambda: ControlNetModel(**controlnet_config_from_unet(SDXL_UNET_CONFIG)), device)
        if not paths["controlnet"].exists():
            save_file({k: v.contiguous() for k, v in controlnet.state_dict().items()}, str(paths["controlnet"]))
        if not paths["csgo"].exists():
            torch.save(_csgo_state(unet, controlnet), paths["csgo"])
    if not paths["image encoder"].exists():
        config = CLIPVisionConfig(**transformers_config_kwargs(VIT_BIGG_IMAGE_ENCODER_CONFIG))
        _built(lambda: CLIPVisionModelWithProjection(config), device).save_pretrained(paths["image encoder"])
    return paths


LORA_TARGETS = ("to_q", "to_k", "to_v", "to_out.0", "ff.net.0.proj", "ff.net.2", "proj_in", "proj_out")


def write_random_lora(path: Path, rank: int = 64, seed: int = 0) -> Path:
    """A random LoRA for SDXL's UNet of a few-step LoRA's shape (LCM-LoRA SDXL, SDXL-Lightning: rank 64 on
    every attention projection, feed-forward and transformer in/out projection of the UNet), in
    diffusers' layout (``unet.<module>.lora_A/lora_B.weight``), float16; written where missing. Its
    values mean nothing: for timing only."""
    from diffusers import UNet2DConditionModel
    from safetensors.torch import save_file

    if path.exists():
        return path
    with torch.device("meta"):
        unet = UNet2DConditionModel(**SDXL_UNET_CONFIG)
    generator = torch.Generator().manual_seed(seed)
    state = {}
    for name, module in unet.named_modules():
        if isinstance(module, torch.nn.Linear) and name.endswith(LORA_TARGETS) and ".attentions." in name:
            down = torch.randn(rank, module.in_features, generator=generator) / module.in_features ** 0.5
            state[f"unet.{name}.lora_A.weight"] = down.half()
            state[f"unet.{name}.lora_B.weight"] = (1e-3 * torch.randn(module.out_features, rank, generator=generator)).half()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file(state, str(path))
    return path
