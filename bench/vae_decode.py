"""Decoding a group's latents with SDXL's VAE: how the sampler does it beside batched and channels-last variants.

    cd bench && python vae_decode.py [--views 14] [--sizes 768,1024] [--batches 1,2,7] [--dtypes fp32,bf16]
                                     [--device cuda]

A random-weight full-size SDXL VAE decodes ``--views`` random latents of one group (96x96 for 768 px,
128x128 for 1024 px): the sampler's own ``_decode`` (one view at a time, NCHW) with the VAE in each of
``--dtypes`` (its deviation from the first dtype's images: what a VAE dtype costs), then, in the last dtype,
for each batch size, NCHW and channels-last (NHWC) decoding, with and without cuDNN's autotuner. Prints ms
per view (median of 3 after a warm-up), peak GiB and each row's deviation (largest absolute difference,
PSNR; images in [0, 1]). Random weights: the deviations only indicate the arithmetic's error.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import print_table, timed_call  # noqa: E402
from diffusers import AutoencoderKL  # noqa: E402

from artnvg_core.diffusion.sampler import _decode  # noqa: E402
from artnvg_core.diffusion.sdxl_config import SDXL_VAE_CONFIG  # noqa: E402


DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}


class _Base:
    def __init__(self, vae):
        self.vae = vae


class _Models:
    """What ``_decode`` reads of the models: ``models.base.vae``."""

    def __init__(self, vae):
        self.base = _Base(vae)


@torch.no_grad()
def decode(vae, latents: torch.Tensor, batch: int, channels_last: bool) -> torch.Tensor:
    """IMAGE [N, H, W, 3] on the CPU, ``batch`` views a call (the sampler's scaling)."""
    latents = latents.to(vae.dtype) / vae.config.scaling_factor
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    views = [vae.decode(part.contiguous(memory_format=fmt), return_dict=False)[0].float().cpu()
             for part in latents.split(batch)]
    return (torch.cat(views) / 2 + 0.5).clamp(0, 1).permute(0, 2, 3, 1)


def deviation(images: torch.Tensor, reference: torch.Tensor) -> tuple[float, float]:
    difference = (images.double() - reference.double())
    mse = difference.square().mean().item()
    return difference.abs().max().item(), math.inf if mse == 0 else 10 * math.log10(1 / mse)


def median_seconds(device, run, repeats: int = 3) -> tuple[torch.Tensor, float]:
    result, _ = timed_call(device, run)  # warm-up (and cuDNN's autotuning when on)
    times = []
    for _ in range(repeats):
        result, seconds = timed_call(device, run)
        times.append(seconds)
    return result, statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=14)
    parser.add_argument("--sizes", default="768,1024")
    parser.add_argument("--batches", default="1,2,7")
    parser.add_argument("--dtypes", default=None, help="the VAE's dtypes for the sampler's decoding "
                        "(default bf16 on CUDA, else fp32); the variants use the last")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    dtypes = (args.dtypes or ("bf16" if device.type == "cuda" else "fp32")).split(",")
    if set(dtypes) - set(DTYPES):
        parser.error(f"--dtypes: each of {', '.join(DTYPES)}")
    torch.manual_seed(0)
    with torch.device(device):
        vae = AutoencoderKL(**SDXL_VAE_CONFIG).eval()
    rows = []
    for size in [int(s) for s in args.sizes.split(",")]:
        latents = torch.randn(args.views, 4, size // 8, size // 8, generator=torch.Generator().manual_seed(size))
        latents = latents.to(device) * vae.config.scaling_factor
        vae.to(memory_format=torch.contiguous_format)
        first = None
        for dtype in dtypes:
            vae.to(DTYPES[dtype])
            reference, seconds = median_seconds(device, lambda: _decode(_Models(vae), latents))
            first = reference if first is None else first
            largest, psnr = deviation(reference, first)
            rows.append([size, f"sampler (_decode), {dtype}", 1, "NCHW", "off",
                         1000 * seconds / args.views, None, largest, "exact" if math.isinf(psnr) else f"{psnr:.1f}"])
            print(rows[-1], flush=True)
        for channels_last in (False, True):
            vae.to(memory_format=torch.channels_last if channels_last else torch.contiguous_format)
            for benchmark in (False, True):
                torch.backends.cudnn.benchmark = benchmark
                for batch in [int(b) for b in args.batches.split(",")]:
                    if device.type == "cuda":
                        torch.cuda.empty_cache()
                        torch.cuda.reset_peak_memory_stats(device)
                    images, seconds = median_seconds(device, lambda: decode(vae, latents, batch, channels_last))
                    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None
                    largest, psnr = deviation(images, reference)
                    rows.append([size, "variant", batch, "NHWC" if channels_last else "NCHW",
                                 "on" if benchmark else "off", 1000 * seconds / args.views, peak, largest,
                                 "exact" if math.isinf(psnr) else f"{psnr:.1f}"])
                    print(rows[-1], flush=True)
        torch.backends.cudnn.benchmark = False
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print_table(f"VAE decoding of {args.views} views, {name}, variants in {dtypes[-1]}, torch {torch.__version__}",
                ["px", "path", "views a call", "layout", "cuDNN autotune", "ms / view", "peak GiB",
                 "max abs diff", "PSNR dB"], rows, "python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
