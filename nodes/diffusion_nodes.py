"""Sample Group: the content views stylized group by group through ComfyUI's own sampling.

Each group's views form the latent batch that ComfyUI samples (``comfy.sample.sample``: its samplers,
schedulers, memory management and model patches, as KSampler), with the ControlNet applied to each view
from its own content image and the MODEL's neighbouring-view patch (NV-Attention Patch Model) mirrored
onto the ControlNet's self-attention. In ComfyUI's low-VRAM state (``--lowvram``, ``--novram``) the
UNet's and the ControlNet's feed-forward layers run one sample at a time, as the library's ``low-memory``
preset runs them (their activations are a block's largest: where a group at 1024 px ran out of memory
under a 12 GiB cap, BENCHMARKS.md "ComfyUI's native path").
"""

from __future__ import annotations

import torch

from artnvg_core.counted import counted
from artnvg_core.diffusion.images import check_images, resize_images, sampling_size
from artnvg_core.diffusion.settings import SIZE_RULES, SamplerSettings, guided_steps
from artnvg_core.progress import check_stop

from .comfy_bridge import cancellable, comfy_module, interrupt_requested, low_vram_mode, progress_bar
from .comfy_patches import (
    CONTENT_TOKENS,
    CSGO_STATE,
    VIEW_CENTERS,
    NeighbourViewPatch,
    controlnet_model,
    diffusion_unet,
    feed_forward_one_sample_at_a_time,
    patch_controlnet,
    transformer_layers,
)
from .node_base import ArtNVGNode
from .node_errors import NodeInputError, node_input
from .node_types import GROUPS, IMAGE

SAMPLERS, SCHEDULERS = ("ddim",), ("ddim_uniform",)  # ComfyUI's lists replace these inside ComfyUI
SEEDS = 2**64  # the seeds torch.manual_seed takes (ComfyUI's noise): 0 to 2^64 - 1


def _names(kind: str, fallback: tuple) -> tuple:
    """ComfyUI's sampler or scheduler names (``kind``: KSampler's "SAMPLERS" / "SCHEDULERS"); ``fallback`` without it."""
    samplers = comfy_module("comfy.samplers")
    return tuple(getattr(samplers.KSampler, kind)) if samplers is not None else fallback


def _nv_patch(model) -> NeighbourViewPatch | None:
    """The MODEL's NV-Attention patch, if it has one."""
    replaced = model.model_options["transformer_options"].get("patches_replace", {}).get("attn1", {})
    return next((patch for patch in replaced.values() if isinstance(patch, NeighbourViewPatch)), None)


def _with_control(conditioning: list, control, size: tuple[int, int]) -> list:
    """``conditioning`` with ``control`` (chained after any ControlNet it has) and SDXL's size conditioning
    for a ``size`` (h, w) sample, uncropped (as diffusers' SDXL pipelines condition)."""
    height, width = size
    chained = {}
    out = []
    for tensor, options in conditioning:
        previous = options.get("control")
        if id(previous) not in chained:
            chained[id(previous)] = control.copy().set_previous_controlnet(previous) if previous else control
        out.append([tensor, {**options, "control": chained[id(previous)], "control_apply_to_uncond": False,
                             "width": width, "height": height, "target_width": width, "target_height": height,
                             "crop_w": 0, "crop_h": 0}])
    return out


class SampleGroup(ArtNVGNode):
    """Stylize the content views group by group (or one chosen group) with ComfyUI's sampling.

    Returns the stylized IMAGE batch in view order: every view, or the chosen group's views. Group g is
    sampled with seed + g (past the largest seed, 2^64 - 1, counting on from 0), so one group alone matches its
    part of a full run. The views are sampled at the
    working size (resolution, size_rule) and returned at their own size.
    """

    DISPLAY_NAME = "Sample Group"
    FUNCTION = "sample"
    RETURN_TYPES = (IMAGE,)
    RETURN_NAMES = ("stylized_views",)
    REQUIRED = {
        "model": ("MODEL", {"tooltip": "SDXL with Apply CSGO (and NV-Attention Patch Model) on it."}),
        "positive": ("CONDITIONING",),
        "negative": ("CONDITIONING",),
        "vae": ("VAE",),
        "control_net": ("CONTROL_NET", {"tooltip": "From Apply CSGO: applied to each view with its content image."}),
        "content_views": (IMAGE, {"tooltip": "Rendered views, in the cameras' order (from Render Views)."}),
        "groups": (GROUPS, {"tooltip": "Groups of the same cameras (from Group Neighbouring Views)."}),
        "group_index": ("INT", {"default": -1, "min": -1, "max": 9999, "tooltip": (
            "-1: every group; otherwise only this group (0-based).")}),
        "seed": ("INT", {"default": 0, "min": 0, "max": SEEDS - 1, "control_after_generate": True, "tooltip": (
            "Noise seed, drawn as KSampler draws it; group g uses seed + g.")}),
        "steps": ("INT", {"default": SamplerSettings.steps, "min": 1, "max": 10000, "tooltip": (
            "Denoising steps per group (50 as in CSGO's inference script; fewer with a few-step LoRA).")}),
        "cfg": ("FLOAT", {"default": SamplerSettings.guidance_scale, "min": 0.0, "max": 100.0, "step": 0.1, "tooltip": (
            "Classifier-free guidance scale, as KSampler's cfg (10 as in CSGO's inference script).")}),
        "sampler_name": lambda: (_names("SAMPLERS", SAMPLERS), {"default": "ddim", "tooltip": (
            "ComfyUI's sampler, as KSampler's (ddim with ddim_uniform: the paper's).")}),
        "scheduler": lambda: (_names("SCHEDULERS", SCHEDULERS), {"default": "ddim_uniform", "tooltip": (
            "ddim with ddim_uniform: the paper's DDIM (the timesteps of diffusers' DDIM for SDXL).")}),
        "denoise": ("FLOAT", {"default": 1.0, "min": 0.0, "max": 1.0, "step": 0.01, "tooltip": (
            "1: from noise; below 1: from the content views (encoded by the VAE), as KSampler.")}),
        "control_scale": ("FLOAT", {"default": SamplerSettings.control_scale, "min": 0.0, "max": 10.0, "step": 0.05,
                                    "tooltip": "ControlNet strength."}),
        "resolution": ("INT", {"default": SamplerSettings.resolution, "min": 0, "max": 4096, "step": 64, "tooltip": (
            "Sampling size (see size_rule; 1024 for SDXL); 0 keeps the views' size. Outputs keep the views' size.")}),
        "size_rule": (SIZE_RULES, {"default": SamplerSettings.size_rule, "tooltip": (
            "long_side: CSGO's rule, the long side becomes the resolution (16:9 samples at 1024x576); "
            "area: about resolution² pixels (16:9 at 1344x768, 1.75x the tokens, about 3x the NV cost).")}),
    }
    OPTIONAL = {
        "cfg_until": ("FLOAT", {"default": 1.0, "min": 0.0, "max": 1.0, "step": 0.05, "tooltip": (
            "Guidance (cfg) in the first ceil(cfg_until x steps) steps only, none after (half the work per step): "
            "the fast and balanced presets use 0.5. 1: every step.")}),
    }

    @cancellable
    def sample(self, model, positive, negative, vae, control_net, content_views, groups, group_index, seed, steps,
               cfg, sampler_name, scheduler, denoise, control_scale, resolution, size_rule, cfg_until=1.0,
               node_id=None):
        node = self.DISPLAY_NAME
        if len(content_views) != groups.num_views:
            raise NodeInputError(f"{node}: input 'content_views': {counted(len(content_views), 'view')} but the groups "
                                 f"cover {counted(groups.num_views, 'camera')}; render and group the same cameras")
        if not -1 <= group_index < len(groups):
            raise NodeInputError(f"{node}: input 'group_index': {group_index} is out of range for "
                                 f"{counted(len(groups), 'group')}")
        with node_input(node, "content_views"):
            images = check_images(content_views, "the views")
        unet = diffusion_unet(node, model)
        control_model = controlnet_model(node, control_net)
        nv = _nv_patch(model)
        if nv is not None:
            control_net = patch_controlnet(control_net, {f"{layer.path}.attn1": nv
                                                         for layer in transformer_layers(control_model)})
        if low_vram_mode():
            model, control_net = feed_forward_one_sample_at_a_time(model, control_net)
        height, width = images.shape[1:3]
        multiple = vae.downscale_ratio * 2 ** (len(unet.channel_mult) - 1)
        size = sampling_size(height, width, resolution or None, size_rule, multiple)
        chosen = range(len(groups)) if group_index < 0 else [group_index]
        report, output = progress_bar(), images.clone()
        for done, index in enumerate(chosen):
            def step(i, done=done):
                check_stop(interrupt_requested)
                if report is not None:
                    report(done * steps + i + 1, len(chosen) * steps, {})

            group = groups[index]
            owned = self._sample_views(model, positive, negative, vae, control_net, images[list(group.all_views)],
                                       None if groups.centers is None else [groups.centers[v] for v in group.all_views],
                                       size, (seed + index) % SEEDS, steps, cfg, cfg_until, sampler_name, scheduler,
                                       denoise, control_scale, step)
            output[list(group.views)] = resize_images(owned[: len(group.views)], height, width)
        if group_index >= 0:
            output = output[list(groups[group_index].views)]
        return (output,)

    @staticmethod
    def _sample_views(model, positive, negative, vae, control_net, views, centers, size, seed, steps, cfg, cfg_until,
                      sampler_name, scheduler, denoise, control_scale, step) -> torch.Tensor:
        """One group's views [N, H, W, 3] sampled jointly at ``size``; IMAGE [N, h, w, 3] at that size. The
        guided steps and the rest are two runs of ComfyUI's sampler over one schedule, as two chained
        KSampler (Advanced) nodes with start/end steps: the second at cfg 1, which ComfyUI samples without the
        unconditional half; ``step(i)`` is called after step i of ``steps``."""
        sample = comfy_module("comfy.sample")
        work = resize_images(views, *size)
        control = control_net.copy().set_cond_hint(work.movedim(-1, 1), control_scale)
        grouped = model.clone()
        options = grouped.model_options["transformer_options"]
        if centers is not None:
            options[VIEW_CENTERS] = torch.tensor(centers, dtype=torch.float64)
        state = options.get(CSGO_STATE)
        if state is not None and state.content_routing == "paper":
            options[CONTENT_TOKENS] = state.content_encoder(views)
        if denoise < 1:
            latent = vae.encode(work)
        else:
            channels = model.get_model_object("latent_format").latent_channels
            latent = torch.zeros(len(views), channels, size[0] // vae.downscale_ratio, size[1] // vae.downscale_ratio)
        positive, negative = _with_control(positive, control, size), _with_control(negative, control, size)
        guided = guided_steps(steps, cfg_until, cfg) if cfg > 1 else steps  # cfg <= 1: as given at every step
        noise = sample.prepare_noise(latent, seed)
        for first, last, scale in ((0, guided, cfg), (guided, steps, 1.0)):
            if first == last:
                continue
            latent = sample.sample(grouped, torch.zeros_like(noise) if first else noise, steps, scale, sampler_name,
                                   scheduler, positive, negative, latent, denoise=denoise, start_step=first, last_step=last,
                                   force_full_denoise=last == steps, seed=seed, disable_pbar=True,
                                   callback=lambda i, denoised, x, total, first=first: step(first + i))
        return vae.decode(latent)
