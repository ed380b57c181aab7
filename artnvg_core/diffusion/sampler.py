"""The group sampler: stylize the N views of one neighbouring-view group jointly.

For a group of content images [N, H, W, 3] (ComfyUI IMAGE layout, values in [0, 1]):

1. resize to the working size (aspect kept; by default CSGO's: long side ``resolution``);
2. conditioning context per view: ``[text (77), content tokens (4), style tokens (32/16)]``
   for the conditional half, ``[negative text, tokens of zero features]`` for the
   unconditional half; the ControlNet hint is the content image itself. With the
   ``"released"`` content routing no layer reads content tokens, so they are left out;
3. SDXL micro-conditioning: ``add_time_ids = (h, w, 0, 0, h, w)`` and the pooled text embedding;
4. denoise from seeded Gaussian latents with a diffusers scheduler (DDIM by default) and
   classifier-free guidance; the batch is ``[uncond view 1..N, cond view 1..N]`` and
   neighbouring-view attention groups the N views of each half;
5. decode each view with the VAE and resize back to H x W.

Approximations (each off by default; see :class:`SamplerSettings` and
:mod:`artnvg_core.diffusion.attention`): NV attention on the lowest-resolution level only
(``nv_levels="lowest"``), with each view's ``nv_nearest`` nearest views only, or with the
other views' keys and values pooled by ``nv_kv_downsample``; fewer steps, another scheduler
(DPM-Solver++(2M), UniPC), guidance truncated after the ``cfg_until`` fraction of the steps
(the conditional half alone afterwards: half the batch), or a lower ``resolution``.
``sequential_cfg`` saves memory and is exact.

With neighbouring-view attention off and zero CSGO scales this is exactly diffusers'
``StableDiffusionXLControlNetPipeline`` (same scheduler, seed and inputs).
"""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from dataclasses import replace

import torch
from diffusers import (
    DDIMScheduler,
    DPMSolverMultistepScheduler,
    EulerAncestralDiscreteScheduler,
    EulerDiscreteScheduler,
    UniPCMultistepScheduler,
)

from ..counted import counted
from ..grouping import nearest_views
from ..progress import ProgressFn, StopFn, check_stop
from .attention import AttentionControl, attention_kwargs
from .conditioning import StyleConditioning, content_tokens
from .images import check_images, resize_images, sampling_size
from .memory import visiting
from .models import DiffusionModels
from .settings import SamplerSettings, guided_steps
from .speed import sdpa_backend

SCHEDULERS = {
    "ddim": DDIMScheduler,
    "euler": EulerDiscreteScheduler,
    "euler_ancestral": EulerAncestralDiscreteScheduler,
    "dpmpp_2m": DPMSolverMultistepScheduler,
    "unipc": UniPCMultistepScheduler,
}  # keys: settings.SCHEDULER_NAMES, in that order


def _time_ids(models: DiffusionModels, height: int, width: int, pooled_dim: int) -> torch.Tensor:
    unet = models.base.unet
    expected = unet.add_embedding.linear_1.in_features
    if unet.config.addition_time_embed_dim * 6 + pooled_dim != expected:
        raise ValueError(
            f"UNet expects an added embedding of {expected} values, but 6 time ids x "
            f"{unet.config.addition_time_embed_dim} + pooled text {pooled_dim} differ"
        )
    return torch.tensor([[height, width, 0, 0, height, width]], dtype=torch.float32)


def working_size(models: DiffusionModels, settings: SamplerSettings, height: int, width: int) -> tuple[int, int]:
    """(height, width) at which a ``height`` x ``width`` view is sampled (see ``SamplerSettings.size_rule``)."""
    vae_scale = 2 ** (len(models.base.vae.config.block_out_channels) - 1)
    unet_scale = 2 ** (len(models.base.unet.config.block_out_channels) - 1)
    return sampling_size(height, width, settings.resolution, settings.size_rule, vae_scale * unet_scale)


def resample_noise(noise: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Gaussian noise [B, C, h, w] on another grid ``size`` (h', w'): area-averaged (each output cell the mean
    of the input cells it covers; copied cells when enlarging), then every (view, channel) map shifted and
    scaled to mean 0 and standard deviation 1, the statistics the sampler's initial noise has. The same
    tensor when ``size`` is its own."""
    if tuple(noise.shape[2:]) == tuple(size):
        return noise
    resampled = torch.nn.functional.interpolate(noise, size=size, mode="area")
    mean = resampled.mean(dim=(2, 3), keepdim=True)
    std = resampled.std(dim=(2, 3), keepdim=True).clamp_min(1e-12)
    return (resampled - mean) / std


def _initial_noise(
    models: DiffusionModels,
    settings: SamplerSettings,
    latent_shape: tuple[int, int, int, int],
    image_size: tuple[int, int],
    generator: torch.Generator,
    noise_seeds,
) -> torch.Tensor:
    """Standard Gaussian noise of ``latent_shape`` [N, C, h, w] (CPU, float32): from ``generator`` for the whole
    group, or one generator per view seeded ``noise_seeds[i]``; on the grid of ``settings.noise_resolution``
    and resampled to (h, w) when it is set."""
    views, channels, height, width = latent_shape
    grid = (height, width)
    if settings.noise_resolution is not None:
        size = working_size(models, replace(settings, resolution=settings.noise_resolution), *image_size)
        scale = 2 ** (len(models.base.vae.config.block_out_channels) - 1)
        grid = (size[0] // scale, size[1] // scale)
    if noise_seeds is None:
        noise = torch.randn((views, channels, *grid), generator=generator)
    else:
        if len(noise_seeds) != views:
            raise ValueError(f"stylize_group: {len(noise_seeds)} noise_seeds for {counted(views, 'view')}")
        noise = torch.cat([torch.randn((1, channels, *grid), generator=torch.Generator().manual_seed(int(s)))
                           for s in noise_seeds])
    return resample_noise(noise, (height, width))


def _step_kwargs(scheduler, generator: torch.Generator) -> dict:
    accepted = set(inspect.signature(scheduler.step).parameters)
    return {key: value for key, value in (("eta", 0.0), ("generator", generator)) if key in accepted}


@torch.no_grad()
def _decode(models: DiffusionModels, latents: torch.Tensor) -> torch.Tensor:
    """Latents [N, 4, h, w] -> IMAGE [N, 8h, 8w, 3] float32 on the CPU, one view at a time."""
    vae = models.base.vae
    config = vae.config
    with visiting(vae, latents.device):
        latents = latents.to(vae.dtype)
        if getattr(config, "latents_mean", None) is not None and getattr(config, "latents_std", None) is not None:
            mean = torch.tensor(config.latents_mean, device=latents.device, dtype=latents.dtype).view(1, -1, 1, 1)
            std = torch.tensor(config.latents_std, device=latents.device, dtype=latents.dtype).view(1, -1, 1, 1)
            latents = latents * std / config.scaling_factor + mean
        else:
            latents = latents / config.scaling_factor
        views = [vae.decode(view, return_dict=False)[0].float().cpu() for view in latents.split(1)]
    return (torch.cat(views) / 2 + 0.5).clamp(0, 1).permute(0, 2, 3, 1)


def _attention_control(
    models: DiffusionModels,
    conditioning: StyleConditioning,
    settings: SamplerSettings,
    latent_size: tuple[int, int],
    view_centers: torch.Tensor | None,
    views: int,
) -> AttentionControl:
    """The processors' settings for a group of ``views`` views on a latent grid of ``latent_size``."""
    if not settings.neighbour_views:
        views = 1
    neighbours = None
    if views > 1 and settings.nv_nearest is not None and settings.nv_nearest < views - 1:
        if view_centers is None:
            raise ValueError("stylize_group: SamplerSettings.nv_nearest needs view_centers (each view's camera centre)")
        neighbours = nearest_views(view_centers, settings.nv_nearest)
    num_content_tokens = 0
    if models.csgo is not None and settings.content_routing == "paper":
        if not models.csgo.unet_content:
            raise ValueError(
                "SamplerSettings.content_routing 'paper' needs the CSGO file's content entries for the UNet's "
                "down blocks, which the loaded file does not hold (a file saved by the released code has none); "
                "use 'released'"
            )
        num_content_tokens = models.csgo.num_content_tokens
    nv_max_tokens = None
    if settings.nv_levels == "lowest":
        factor = 2 ** (len(models.base.unet.config.block_out_channels) - 1)
        nv_max_tokens = -(-latent_size[0] // factor) * -(-latent_size[1] // factor)
    return AttentionControl(
        views_per_group=views,
        num_content_tokens=num_content_tokens,
        num_style_tokens=0 if conditioning.style is None else conditioning.style.cond.shape[1],
        content_scale=settings.content_scale,
        style_scale=settings.style_scale,
        nv_max_tokens=nv_max_tokens,
        neighbours=neighbours,
        kv_downsample=settings.nv_kv_downsample,
        latent_size=latent_size,
    )


def _model_inputs(
    models: DiffusionModels,
    images: torch.Tensor,
    work: torch.Tensor,
    conditioning: StyleConditioning,
    halves: int,
    control: AttentionControl,
) -> dict:
    """ControlNet/UNet keyword inputs for a batch of ``halves`` x N views (uncond half first)."""
    unet, views = models.base.unet, len(images)
    device, dtype = unet.device, unet.dtype
    prompt, style = conditioning.prompt, conditioning.style
    content = content_tokens(models, images) if control.num_content_tokens else None
    cond, uncond = [prompt.text], [prompt.negative_text]
    for tokens in (content, style):
        if tokens is not None:
            cond.append(tokens.cond.to(prompt.text))
            uncond.append(tokens.uncond.to(prompt.text))
    cond, uncond = (torch.cat([t.expand(views, -1, -1) for t in parts], 1) for parts in (cond, uncond))
    pooled = torch.cat([prompt.negative_pooled, prompt.pooled][2 - halves :])
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


def _split_batch(value, parts: int) -> list:
    """``value`` (a tensor or nested dicts of them) as ``parts`` pieces split along dim 0;
    anything else is shared by every piece."""
    if isinstance(value, torch.Tensor):
        return list(value.chunk(parts))
    if isinstance(value, dict):
        split = {key: _split_batch(item, parts) for key, item in value.items()}
        return [{key: items[i] for key, items in split.items()} for i in range(parts)]
    return [value] * parts


def _predict_noise(models: DiffusionModels, latents: torch.Tensor, t, batch: dict, control_scale: float) -> torch.Tensor:
    """Noise prediction [B, 4, h, w] (float32) of ControlNet + UNet for one batch of :func:`_model_inputs`
    (B views: the scaled latents [N, 4, h, w] repeated over the batch's guidance halves)."""
    inputs = dict(batch)
    hint = inputs.pop("hint")
    x = latents.repeat(len(hint) // len(latents), 1, 1, 1)
    with visiting(models.controlnet, x.device):
        down, mid = models.controlnet(
            x, t, controlnet_cond=hint, conditioning_scale=control_scale, return_dict=False, **inputs
        )
    return models.base.unet(
        x, t, down_block_additional_residuals=down, mid_block_additional_residual=mid, return_dict=False, **inputs
    )[0].float()


@torch.no_grad()
def stylize_group(
    models: DiffusionModels,
    content_images: torch.Tensor,
    conditioning: StyleConditioning,
    settings: SamplerSettings = SamplerSettings(),
    *,
    seed: int = 0,
    noise_seeds: Sequence[int] | None = None,
    view_centers: torch.Tensor | None = None,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """Stylize one group of views jointly; returns IMAGE [N, H, W, 3] in the input order and size.

    seed: the group's generator (initial noise, and the noise of stochastic schedulers' steps).
    noise_seeds: one seed per view for its initial noise instead (a view then starts from the same noise in
        whatever group it is sampled).
    view_centers: camera centres [N, 3] of the views (world units); needed by ``settings.nv_nearest``.
    Latents stay in float32 between steps; the models run in their own dtype.
    progress(step, steps, info) is called after every denoising step; should_stop() is checked
    before every step and raises :class:`artnvg_core.progress.Cancelled` when it returns True.
    """
    images = check_images(content_images, "stylize_group: content_images")
    views, height, width = images.shape[:3]
    unet = models.base.unet
    size = working_size(models, settings, height, width)
    work = resize_images(images, *size)
    scale = 2 ** (len(models.base.vae.config.block_out_channels) - 1)
    latent_shape = (views, unet.config.in_channels, size[0] // scale, size[1] // scale)
    control = _attention_control(models, conditioning, settings, latent_shape[2:], view_centers, views)
    halves = 2 if settings.guidance_scale > 1 else 1
    inputs = _model_inputs(models, images, work, conditioning, halves, control)
    per_half = _split_batch(inputs, halves)  # [uncond, cond] or [cond]
    guided_batches = per_half if settings.sequential_cfg else [inputs]

    scheduler = SCHEDULERS[settings.scheduler].from_config(models.base.scheduler_config)
    scheduler.set_timesteps(settings.steps, device=unet.device)
    generator = torch.Generator().manual_seed(seed)
    noise = _initial_noise(models, settings, latent_shape, (height, width), generator, noise_seeds)
    latents = (noise * scheduler.init_noise_sigma).to(unet.device)
    step_kwargs = _step_kwargs(scheduler, generator)
    timesteps = scheduler.timesteps
    guided = guided_steps(len(timesteps), settings.cfg_until, settings.guidance_scale)
    for step, t in enumerate(timesteps):
        check_stop(should_stop)
        model_input = scheduler.scale_model_input(latents, t).to(unet.dtype)
        batches = guided_batches if step < guided else per_half[-1:]
        with sdpa_backend(settings.attention_backend):
            noise = torch.cat([_predict_noise(models, model_input, t, b, settings.control_scale) for b in batches])
        if step < guided:
            noise_uncond, noise_cond = noise.chunk(2)
            noise = noise_uncond + settings.guidance_scale * (noise_cond - noise_uncond)
        latents = scheduler.step(noise, t, latents, **step_kwargs, return_dict=False)[0]
        if progress is not None:
            progress(step + 1, len(timesteps), {"stage": "denoise", "views": views})
    return resize_images(_decode(models, latents), height, width)
