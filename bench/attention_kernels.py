"""Attention kernels at the neighbouring-view shapes: PyTorch's SDPA backends beside kernels from
the package registry (SageAttention's INT8 Triton kernel, FlashAttention 4's CuTe kernels), when
they import.

For each kernel and shape: milliseconds (CUDA events, median), TFLOP/s (4 B H L^2 D / time) and
the error of its output against float32 math attention on a slice of the queries (relative L2,
max abs). ``--group`` then stylizes one group with every large self-attention (NV attention,
L >= 1024 tokens) routed through each lossy kernel that imported, against exact attention with
the same seeds and steps: relative L2 and PSNR of the images (random full-size weights:
numerical deviation, not quality).

    python bench/attention_kernels.py --views 14 --size 1024 --group --group-steps 10 --json $OUT/attention.json
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import timed  # noqa: E402
from bench.diffusion import POOLED_DIM, build_models, random_conditioning, write_json  # noqa: E402

from artnvg_core.diffusion.sampler import SamplerSettings, stylize_group  # noqa: E402
from artnvg_core.diffusion.speed import sdpa_backend  # noqa: E402

EXACT_CHECK_QUERIES = 512


def _sage():
    from sageattention import sageattn

    return lambda q, k, v, scale: sageattn(q, k, v, tensor_layout="HND", is_causal=False, sm_scale=scale)


def _flash4():
    from flash_attn.cute import flash_attn_func  # FlashAttention 4 (package flash-attn-4)

    def run(q, k, v, scale):
        out = flash_attn_func(q.transpose(1, 2), k.transpose(1, 2), v.transpose(1, 2), softmax_scale=scale)
        return (out[0] if isinstance(out, tuple) else out).transpose(1, 2)

    return run


def _sdpa(backend: str):
    def run(q, k, v, scale):
        with sdpa_backend(backend):
            return F.scaled_dot_product_attention(q, k, v, scale=scale)

    return run


def kernels() -> dict:
    """name -> (callable(q, k, v, scale) on [B, H, L, D], exact?) for every kernel that imports."""
    found = {"sdpa cudnn": (_sdpa("cudnn"), True), "sdpa flash": (_sdpa("flash"), True)}
    for name, make in (("sageattention int8 (Triton)", _sage), ("flash-attn-4 (CuTe)", _flash4)):
        try:
            found[name] = (make(), False if name.startswith("sage") else True)
        except Exception as error:  # not installed, no kernel for this GPU
            print(f"{name}: not available ({type(error).__name__}: {str(error).splitlines()[0][:120]})")
    return found


def nv_shapes(views: int, size: int) -> list[tuple[int, int, int, int]]:
    """(B, H, L, D) of SDXL's two self-attention levels under NV attention with CFG at ``size`` px."""
    latent = size // 8
    return [(2, 10, views * (latent // 2) ** 2, 64), (2, 20, views * (latent // 4) ** 2, 64)]


def exact_slice(q, k, v, scale) -> torch.Tensor:
    """float32 math attention for the first EXACT_CHECK_QUERIES queries."""
    q = q[:, :, :EXACT_CHECK_QUERIES].float()
    weights = torch.softmax(q @ k.float().transpose(-1, -2) * scale, dim=-1)
    return weights @ v.float()


def kernel_table(found: dict, args, report: dict) -> None:
    device = torch.device("cuda")
    print(f"\n| kernel | shape B x H x L x D | ms | TFLOP/s | rel L2 vs fp32 (first {EXACT_CHECK_QUERIES} queries) "
          "| max abs |")
    print("|---|---|---:|---:|---:|---:|")
    rows = report.setdefault("kernels", [])
    for shape in nv_shapes(args.views, args.size):
        generator = torch.Generator(device).manual_seed(0)
        q, k, v = (torch.randn(shape, device=device, dtype=torch.bfloat16, generator=generator) for _ in range(3))
        scale = 1 / math.sqrt(shape[-1])
        reference = exact_slice(q, k, v, scale)
        for name, (run, _) in found.items():
            row = {"kernel": name, "shape": list(shape)}
            try:
                out = run(q, k, v, scale)
                difference = out[:, :, :EXACT_CHECK_QUERIES].float() - reference
                seconds = timed(lambda: run(q, k, v, scale), device, repeats=args.repeats, warmup=2)
                flops = 4 * shape[0] * shape[1] * shape[2] ** 2 * shape[3]
                row.update(ms=seconds * 1e3, tflops=flops / seconds / 1e12,
                           rel_l2=(difference.norm() / reference.norm()).item(), max_abs=difference.abs().max().item())
                print(f"| {name} | {' x '.join(map(str, shape))} | {row['ms']:.2f} | {row['tflops']:.0f} | "
                      f"{row['rel_l2']:.2e} | {row['max_abs']:.2e} |", flush=True)
            except Exception as error:
                row["error"] = f"{type(error).__name__}: {str(error).strip().splitlines()[0][:160]}"
                print(f"| {name} | {' x '.join(map(str, shape))} | {row['error']} | | | |", flush=True)
            rows.append(row)
            write_json(args.json, report)


@contextlib.contextmanager
def self_attention_through(kernel):
    """Route every scaled_dot_product_attention with >= 1024 keys and queries and head dimension 64
    (the UNet's and the ControlNet's self-attention; cross-attention has <= 113 keys, the VAE's
    attention one head of 512) through ``kernel``."""
    original = F.scaled_dot_product_attention

    def patched(q, k, v, attn_mask=None, dropout_p=0.0, is_causal=False, scale=None, **kwargs):
        if attn_mask is None and not is_causal and q.shape[-1] == 64 and min(q.shape[-2], k.shape[-2]) >= 1024:
            return kernel(q, k, v, scale if scale is not None else q.shape[-1] ** -0.5)
        return original(q, k, v, attn_mask=attn_mask, dropout_p=dropout_p, is_causal=is_causal, scale=scale, **kwargs)

    F.scaled_dot_product_attention = patched
    try:
        yield
    finally:
        F.scaled_dot_product_attention = original


def group_table(found: dict, args, report: dict) -> None:
    device, dtype = torch.device("cuda"), torch.bfloat16
    torch.manual_seed(0)
    models = build_models(False, device, dtype)
    conditioning = random_conditioning(models, device, dtype, POOLED_DIM)
    images = torch.rand(args.views, args.size, args.size, 3, generator=torch.Generator().manual_seed(1))
    settings = SamplerSettings(steps=args.group_steps, resolution=args.size)
    print(f"\nOne group: {args.views} views at {args.size}x{args.size}, {args.group_steps} DDIM steps, NV attention, "
          "random full-size weights; images against exact attention (cuDNN)")
    print("\n| self-attention kernel | s / group | rel L2 vs exact | PSNR dB |")
    print("|---|---:|---:|---:|")
    rows = report.setdefault("group", [])
    reference = None
    plan = [("sdpa cudnn (exact)", None)] + [(name, run) for name, (run, exact) in found.items() if not exact]
    for name, kernel in plan:
        row = {"kernel": name}
        try:
            with self_attention_through(kernel) if kernel else contextlib.nullcontext():
                torch.cuda.synchronize()
                begin = time.perf_counter()
                out = stylize_group(models, images, conditioning, settings, seed=0)
                torch.cuda.synchronize()
                row["seconds"] = time.perf_counter() - begin
            reference = out if reference is None else reference
            difference = (out.double() - reference.double())
            mse = difference.square().mean().item()
            row.update(rel_l2=(difference.norm() / reference.double().norm()).item(),
                       psnr_db=math.inf if mse == 0 else 10 * math.log10(1 / mse))
            print(f"| {name} | {row['seconds']:.1f} | {row['rel_l2']:.4f} | {row['psnr_db']:.1f} |", flush=True)
        except Exception as error:
            row["error"] = f"{type(error).__name__}: {str(error).strip().splitlines()[0][:160]}"
            print(f"| {name} | {row['error']} | | |", flush=True)
        rows.append(row)
        write_json(args.json, report)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=14, help="views per group (N)")
    parser.add_argument("--size", type=int, default=1024, help="square view side in pixels")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--group", action="store_true", help="also stylize one group with each lossy kernel")
    parser.add_argument("--group-steps", type=int, default=10)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    print(f"# Attention kernels at the NV shapes: {torch.cuda.get_device_name()}, torch {torch.__version__}\n\n"
          f"`python {' '.join(sys.argv)}`")
    report = {"setup": {"device": torch.cuda.get_device_name(), "command": " ".join(sys.argv)}}
    found = kernels()
    kernel_table(found, args, report)
    if args.group:
        group_table(found, args, report)


if __name__ == "__main__":
    main()
