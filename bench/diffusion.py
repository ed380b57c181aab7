"""Benchmark of the ArtNVG diffusion stage with full-size, randomly initialised models (no weights).

Builds the SDXL UNet, the SDXL ControlNet, the ViT-bigG image encoder, CSGO's two resamplers
(4 content / 32 style tokens) and the SDXL VAE from their architecture configs, installs
ArtNVG's processors (CSGO image branches active) and prints:

* seconds per denoising step (ControlNet + UNet, classifier-free guidance: batch 2N) and peak
  GPU memory, for N views in a group, image sizes, and NV attention on / off;
* the time of a whole group (content tokens, all steps, VAE decoding) — measured with
  ``--group-steps`` steps and, when that is below 50, extrapolated to 50 steps (labelled);
* image encoder time (one style image + N content views) and VAE decoding time per view.

Timing: CUDA events (perf_counter on CPU), ``--warmup`` untimed runs, median of ``--repeats``.
Compute does not depend on weight values, so random weights give representative numbers.

    python bench/diffusion.py                      # GPU, bf16, full size
    python bench/diffusion.py --tiny --device cpu  # smoke test with tiny models
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel  # noqa: E402
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection  # noqa: E402

from artnvg_core.diffusion.architectures import (  # noqa: E402
    SDXL_UNET_CONFIG,
    SDXL_VAE_CONFIG,
    VIT_BIGG_IMAGE_ENCODER_CONFIG,
    controlnet_config_from_unet,
)
from artnvg_core.diffusion.attention import AttentionControl, attention_kwargs  # noqa: E402
from artnvg_core.diffusion.conditioning import PromptEmbeddings, StyleConditioning, image_features  # noqa: E402
from artnvg_core.diffusion.csgo import (  # noqa: E402
    CONTROLNET_ROUTES,
    UNET_ROUTES,
    CSGOProjections,
    install_processors,
)
from artnvg_core.diffusion.models import DiffusionModels, SDXLBase  # noqa: E402
from artnvg_core.diffusion.resampler import PerceiverResampler, ResamplerConfig  # noqa: E402
from artnvg_core.diffusion.sampler import SamplerSettings, stylize_group  # noqa: E402

POOLED_DIM = 1280
TEXT_TOKENS = 77
DDIM = dict(
    num_train_timesteps=1000,
    beta_start=0.00085,
    beta_end=0.012,
    beta_schedule="scaled_linear",
    steps_offset=1,
    timestep_spacing="leading",
    clip_sample=False,
    set_alpha_to_one=False,
)

# --tiny: the same architectures with a few channels (CPU smoke test of this script)
TINY_UNET = dict(
    block_out_channels=(8, 16, 32),
    attention_head_dim=(2, 4, 8),
    transformer_layers_per_block=(1, 1, 2),
    norm_num_groups=4,
    cross_attention_dim=16,
    addition_time_embed_dim=4,
    projection_class_embeddings_input_dim=6 * 4 + 8,
)
TINY_VAE = dict(block_out_channels=(4, 4, 8, 8), layers_per_block=1, norm_num_groups=2)
TINY_ENCODER = dict(hidden_size=16, intermediate_size=32, num_hidden_layers=2, num_attention_heads=2, projection_dim=8)
TINY_POOLED_DIM = 8


def build_models(tiny: bool, device: torch.device, dtype: torch.dtype) -> DiffusionModels:
    """Random full-size (or tiny) models on ``device`` in ``dtype``, ArtNVG processors installed."""
    with torch.device(device):
        unet = UNet2DConditionModel(**{**SDXL_UNET_CONFIG, **(TINY_UNET if tiny else {})}).to(dtype)
        controlnet = ControlNetModel(**controlnet_config_from_unet(unet.config)).to(dtype)
        vae = AutoencoderKL(**{**SDXL_VAE_CONFIG, **(TINY_VAE if tiny else {})}).to(dtype)
        encoder_config = CLIPVisionConfig(**{**VIT_BIGG_IMAGE_ENCODER_CONFIG, **(TINY_ENCODER if tiny else {})})
        encoder = CLIPVisionModelWithProjection(encoder_config).to(dtype)
        width = unet.config.cross_attention_dim

        def resampler(queries: int) -> PerceiverResampler:
            config = ResamplerConfig(
                num_queries=queries,
                embedding_dim=encoder_config.hidden_size,
                dim=width,
                output_dim=width,
                heads=2 if tiny else 12,
            )
            return PerceiverResampler(config)

        csgo = CSGOProjections(resampler(4), resampler(32)).to(dtype)
    install_processors(unet, UNET_ROUTES)
    install_processors(controlnet, CONTROLNET_ROUTES)
    for model in (unet, controlnet, vae, encoder, csgo):
        model.eval().requires_grad_(False)
    base = SDXLBase(
        unet=unet,
        vae=vae,
        text_encoder=None,
        text_encoder_2=None,
        tokenizer=None,
        tokenizer_2=None,
        scheduler_config=DDIM,
    )
    return DiffusionModels(base=base, controlnet=controlnet, image_encoder=encoder, csgo=csgo)


class Timer:
    """Median wall time of a callable: CUDA events on a GPU, perf_counter on the CPU."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"

    def __call__(self, run, warmup: int, repeats: int) -> float:
        for _ in range(warmup):
            run()
        times = []
        for _ in range(repeats):
            if self.cuda:
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                run()
                end.record()
                torch.cuda.synchronize()
                times.append(start.elapsed_time(end) / 1000)
            else:
                begin = time.perf_counter()
                run()
                times.append(time.perf_counter() - begin)
        return statistics.median(times)


def peak_memory(device: torch.device, run) -> float:
    """Peak GiB allocated while ``run`` runs (nan on the CPU)."""
    if device.type != "cuda":
        run()
        return float("nan")
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    run()
    torch.cuda.synchronize()
    return torch.cuda.max_memory_allocated() / 2**30


def _conditioning(models: DiffusionModels, device, dtype, pooled_dim: int) -> StyleConditioning:
    width = models.base.unet.config.cross_attention_dim
    text = torch.randn(1, TEXT_TOKENS, width, device=device, dtype=dtype)
    pooled = torch.randn(1, pooled_dim, device=device, dtype=dtype)
    style = models.csgo.tokens("style", torch.randn(1, 257, models.image_encoder.config.hidden_size, device=device))
    return StyleConditioning(PromptEmbeddings(text, pooled, torch.zeros_like(text), torch.zeros_like(pooled)), style)


def denoise_step(models: DiffusionModels, views: int, size: int, nv: bool, pooled_dim: int):
    """One ControlNet + UNet evaluation with CFG (batch 2N), as a closure."""
    unet, controlnet = models.base.unet, models.controlnet
    device, dtype, width = unet.device, unet.dtype, unet.config.cross_attention_dim
    batch = 2 * views
    latents = torch.randn(batch, 4, size // 8, size // 8, device=device, dtype=dtype)
    context = torch.randn(batch, TEXT_TOKENS + 4 + 32, width, device=device, dtype=dtype)
    added = {
        "text_embeds": torch.randn(batch, pooled_dim, device=device, dtype=dtype),
        "time_ids": torch.tensor([[size, size, 0, 0, size, size]] * batch, device=device, dtype=dtype),
    }
    hint = torch.rand(batch, 3, size, size, device=device, dtype=dtype)
    control = attention_kwargs(
        AttentionControl(
            views_per_group=views if nv else 1,
            num_content_tokens=4,
            num_style_tokens=32,
            content_scale=1.0,
            style_scale=0.6,
        )
    )
    t = torch.tensor(500, device=device)

    @torch.no_grad()
    def run():
        down, mid = controlnet(
            latents, t, context, hint, added_cond_kwargs=added, cross_attention_kwargs=control, return_dict=False
        )
        unet(
            latents,
            t,
            context,
            added_cond_kwargs=added,
            cross_attention_kwargs=control,
            down_block_additional_residuals=down,
            mid_block_additional_residual=mid,
            return_dict=False,
        )

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tiny", action="store_true", help="tiny models (CPU smoke test)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--dtype", choices=["bf16", "fp16", "fp32"], help="default: bf16 on a GPU, fp32 on the CPU")
    parser.add_argument("--sizes", type=int, nargs="+", default=[768, 1024])
    parser.add_argument("--views", type=int, nargs="+", default=[1, 8, 15])
    parser.add_argument("--group-views", type=int, default=15)
    parser.add_argument("--group-steps", type=int, default=50, help="steps actually run for the whole-group time")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    device = torch.device(args.device)
    args.dtype = args.dtype or ("bf16" if device.type == "cuda" else "fp32")
    dtype = {"bf16": torch.bfloat16, "fp16": torch.float16, "fp32": torch.float32}[args.dtype]
    sizes = [64, 128] if args.tiny and args.sizes == [768, 1024] else args.sizes
    pooled_dim = TINY_POOLED_DIM if args.tiny else POOLED_DIM
    timer = Timer(device)

    begin = time.perf_counter()
    models = build_models(args.tiny, device, dtype)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(
        f"# ArtNVG diffusion benchmark: {gpu}, {args.dtype}, {'tiny' if args.tiny else 'full-size'} random models "
        f"(built in {time.perf_counter() - begin:.0f} s), torch {torch.__version__}, "
        f"SDPA backends: flash={torch.backends.cuda.flash_sdp_enabled()}, "
        f"mem_efficient={torch.backends.cuda.mem_efficient_sdp_enabled()}"
    )
    print("\n| size | N views | NV attention | s / step (CFG, ControlNet + UNet) | peak GiB |")
    print("|---:|---:|---|---:|---:|")
    for size in sizes:
        for views in args.views:
            for nv in (False, True):
                run = denoise_step(models, views, size, nv, pooled_dim)
                seconds = timer(run, args.warmup, args.repeats)
                peak = peak_memory(device, run)
                print(f"| {size} | {views} | {'on' if nv else 'off'} | {seconds:.3f} | {peak:.1f} |", flush=True)

    conditioning = _conditioning(models, device, dtype, pooled_dim)
    print(f"\n| size | whole group of {args.group_views} views, NV on, DDIM | seconds |")
    print("|---:|---|---:|")
    for size in sizes:
        images = torch.rand(args.group_views, size, size, 3)
        settings = SamplerSettings(steps=args.group_steps, resolution=size)
        measured = timer(lambda: stylize_group(models, images, conditioning, settings), 0, 1)
        print(f"| {size} | {args.group_steps} steps, measured | {measured:.1f} |")
        if args.group_steps < 50:
            step = timer(denoise_step(models, args.group_views, size, True, pooled_dim), 1, args.repeats)
            print(
                f"| {size} | 50 steps, EXTRAPOLATED (+{50 - args.group_steps} x {step:.3f} s/step) | "
                f"{measured + (50 - args.group_steps) * step:.1f} |"
            )

    print("\n| component | batch | seconds |")
    print("|---|---:|---:|")
    for count in (1, args.group_views):
        images = torch.rand(count, 512, 512, 3)
        seconds = timer(lambda: image_features(models.image_encoder, images), args.warmup, args.repeats)
        print(f"| image encoder (224 px, penultimate states) | {count} | {seconds:.3f} |")
    vae = models.base.vae
    for size in sizes:
        latents = torch.randn(1, 4, size // 8, size // 8, device=device, dtype=vae.dtype)
        seconds = timer(lambda: vae.decode(latents / vae.config.scaling_factor), args.warmup, args.repeats)
        print(f"| VAE decode {size} px ({str(vae.dtype).removeprefix('torch.')}) | 1 | {seconds:.3f} |")


if __name__ == "__main__":
    main()
