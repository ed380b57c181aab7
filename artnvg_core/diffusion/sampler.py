"""The group sampler: stylize the N views of one neighbouring-view group jointly.

For a group of content images [N, H, W, 3] (ComfyUI IMAGE layout, values in [0, 1]):

1. resize to an SDXL-friendly size (aspect kept, area about ``resolution``², multiples of 64);
2. conditioning context per view: ``[text (77), content tokens (4), style tokens (32/16)]``
   for the conditional half, ``[negative text, tokens of zero features]`` for the
   unconditional half; the ControlNet hint is the content image itself;
3. SDXL micro-conditioning: ``add_time_ids = (h, w, 0, 0, h, w)`` and the pooled text embedding;
4. denoise from seeded Gaussian latents with a diffusers scheduler (DDIM by default) and
   classifier-free guidance; the batch is ``[uncond view 1..N, cond view 1..N]`` and
   neighbouring-view attention groups the N views of each half;
5. decode each view with the VAE and resize back to H x W.

With neighbouring-view attention off and zero CSGO scales this is exactly diffusers'
``StableDiffusionXLControlNetPipeline`` (same scheduler, seed and inputs).
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass

import torch
from diffusers import (
    DDIMScheduler,
    DPMSolverMultistepScheduler,
    EulerAncestralDiscreteScheduler,
    EulerDiscreteScheduler,
    UniPCMultistepScheduler,
)

from ..progress import ProgressFn, StopFn, check_stop
from .attention import AttentionControl, attention_kwargs
from .conditioning import StyleConditioning, content_tokens
from .images import check_images, resize_images, sdxl_size
from .models import DiffusionModels
from .speed import check_sdpa_backend, sdpa_backend

SCHEDULERS = {
    "ddim": DDIMScheduler,
    "euler": EulerDiscreteScheduler,
    "euler_ancestral": EulerAncestralDiscreteScheduler,
    "dpmpp_2m": DPMSolverMultistepScheduler,
    "unipc": UniPCMultistepScheduler,
}


@dataclass(frozen=True)
class SamplerSettings:
    """Sampling parameters. Defaults: the paper's scales (content 1.0, style 0.6, control 1.0) and
    DDIM; guidance 10 and 50 steps as in CSGO's inference script.

    resolution: target side of the square of equal area (None: keep the content size, rounded to 64).
    neighbour_views: neighbouring-view attention on (False: the paper's "w/o NV" ablation).
    attention_backend: scaled-dot-product attention backend of the denoising loop, one of
        ``speed.SDPA_BACKENDS`` ("auto" = PyTorch's choice; every backend is exact up to rounding).
    """

    steps: int = 50
    guidance_scale: float = 10.0
    content_scale: float = 1.0
    style_scale: float = 0.6
    control_scale: float = 1.0
    neighbour_views: bool = True
    resolution: int | None = 1024
    scheduler: str = "ddim"
    attention_backend: str = "auto"

    def __post_init__(self) -> None:
        check_sdpa_backend(self.attention_backend, "SamplerSettings.attention_backend")
        if self.steps < 1:
            raise ValueError(f"SamplerSettings.steps must be >= 1, got {self.steps}")
        if self.scheduler not in SCHEDULERS:
            raise ValueError(f"SamplerSettings.scheduler must be one of {sorted(SCHEDULERS)}, got {self.scheduler!r}")
        if self.resolution is not None and self.resolution < 64:
            raise ValueError(f"SamplerSettings.resolution must be >= 64 or None, got {self.resolution}")


def _time_ids(models: DiffusionModels, height: int, width: int, pooled_dim: int) -> torch.Tensor:
    unet = models.base.unet
    expected = unet.add_embedding.linear_1.in_features
    if unet.config.addition_time_embed_dim * 6 + pooled_dim != expected:
        raise ValueError(
            f"UNet expects an added embedding of {expected} values, but 6 time ids x "
            f"{unet.config.addition_time_embed_dim} + pooled text {pooled_dim} differ"
        )
    return torch.tensor([[height, width, 0, 0, height, width]], dtype=torch.float32)


def _step_kwargs(scheduler, generator: torch.Generator) -> dict:
    accepted = set(inspect.signature(scheduler.step).parameters)
    return {key: value for key, value in (("eta", 0.0), ("generator", generator)) if key in accepted}


@torch.no_grad()
def _decode(models: DiffusionModels, latents: torch.Tensor) -> torch.Tensor:
    """Latents [N, 4, h, w] -> IMAGE [N, 8h, 8w, 3] float32 on the CPU, one view at a time."""
    vae = models.base.vae
    config = vae.config
    latents = latents.to(vae.dtype)
    if getattr(config, "latents_mean", None) is not None and getattr(config, "latents_std", None) is not None:
        mean = torch.tensor(config.latents_mean, device=latents.device, dtype=latents.dtype).view(1, -1, 1, 1)
        std = torch.tensor(config.latents_std, device=latents.device, dtype=latents.dtype).view(1, -1, 1, 1)
        latents = latents * std / config.scaling_factor + mean
    else:
        latents = latents / config.scaling_factor
    views = [vae.decode(view, return_dict=False)[0] for view in latents.split(1)]
    return (torch.cat(views) / 2 + 0.5).clamp(0, 1).float().permute(0, 2, 3, 1).cpu()


def _model_inputs(
    models: DiffusionModels,
    images: torch.Tensor,
    work: torch.Tensor,
    conditioning: StyleConditioning,
    settings: SamplerSettings,
    halves: int,
) -> dict:
    """ControlNet/UNet keyword inputs for a batch of ``halves`` x N views (uncond half first)."""
    unet, views = models.base.unet, len(images)
    device, dtype = unet.device, unet.dtype
    prompt, style = conditioning.prompt, conditioning.style
    content = content_tokens(models, images)
    cond, uncond = [prompt.text], [prompt.negative_text]
    for tokens in (content, style):
        if tokens is not None:
            cond.append(tokens.cond.to(prompt.text))
            uncond.append(tokens.uncond.to(prompt.text))
    cond, uncond = (torch.cat([t.expand(views, -1, -1) for t in parts], 1) for parts in (cond, uncond))
    pooled = torch.cat([prompt.negative_pooled, prompt.pooled][2 - halves :])
    control = AttentionControl(
        views_per_group=views if settings.neighbour_views else 1,
        num_content_tokens=0 if content is None else content.cond.shape[1],
        num_style_tokens=0 if style is None else style.cond.shape[1],
        content_scale=settings.content_scale,
        style_scale=settings.style_scale,
    )
    time_ids = _time_ids(models, *work.shape[1:3], pooled.shape[-1])
    return {
        "encoder_hidden_states": torch.cat([uncond, cond][2 - halves :]).to(device=device, dtype=dtype),
        "added_cond_kwargs": {
            "text_embeds": pooled.repeat_interleave(views, dim=0).to(device=device, dtype=dtype),
            "time_ids": time_ids.to(device=device, dtype=dtype).expand(halves * views, -1),
        },
        "cross_attention_kwargs": attention_kwargs(control),
        "hint": work.permute(0, 3, 1, 2).to(device=device, dtype=models.controlnet.dtype).repeat(halves, 1, 1, 1),
    }


@torch.no_grad()
def stylize_group(
    models: DiffusionModels,
    content_images: torch.Tensor,
    conditioning: StyleConditioning,
    settings: SamplerSettings = SamplerSettings(),
    *,
    seed: int = 0,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """Stylize one group of views jointly; returns IMAGE [N, H, W, 3] in the input order and size.

    Latents stay in float32 between steps; the models run in their own dtype.
    progress(step, steps, info) is called after every denoising step; should_stop() is checked
    before every step and raises :class:`artnvg_core.progress.Cancelled` when it returns True.
    """
    images = check_images(content_images, "stylize_group: content_images")
    views, height, width = images.shape[:3]
    unet, controlnet = models.base.unet, models.controlnet
    if settings.resolution is None:
        size = (max(64, round(height / 64) * 64), max(64, round(width / 64) * 64))
    else:
        size = sdxl_size(height, width, settings.resolution)
    work = resize_images(images, *size)
    halves = 2 if settings.guidance_scale > 1 else 1
    inputs = _model_inputs(models, images, work, conditioning, settings, halves)
    hint = inputs.pop("hint")

    scheduler = SCHEDULERS[settings.scheduler].from_config(models.base.scheduler_config)
    scheduler.set_timesteps(settings.steps, device=unet.device)
    generator = torch.Generator().manual_seed(seed)
    scale = 2 ** (len(models.base.vae.config.block_out_channels) - 1)
    latent_shape = (views, unet.config.in_channels, size[0] // scale, size[1] // scale)
    latents = (torch.randn(latent_shape, generator=generator) * scheduler.init_noise_sigma).to(unet.device)
    step_kwargs = _step_kwargs(scheduler, generator)
    timesteps = scheduler.timesteps
    for step, t in enumerate(timesteps):
        check_stop(should_stop)
        model_input = scheduler.scale_model_input(torch.cat([latents] * halves), t).to(unet.dtype)
        with sdpa_backend(settings.attention_backend):
            down, mid = controlnet(
                model_input,
                t,
                controlnet_cond=hint,
                conditioning_scale=settings.control_scale,
                return_dict=False,
                **inputs,
            )
            noise = unet(
                model_input,
                t,
                down_block_additional_residuals=down,
                mid_block_additional_residual=mid,
                return_dict=False,
                **inputs,
            )[0].float()
        if halves == 2:
            noise_uncond, noise_cond = noise.chunk(2)
            noise = noise_uncond + settings.guidance_scale * (noise_cond - noise_uncond)
        latents = scheduler.step(noise, t, latents, **step_kwargs, return_dict=False)[0]
        if progress is not None:
            progress(step + 1, len(timesteps), {"stage": "denoise", "views": views})
    return resize_images(_decode(models, latents), height, width)
