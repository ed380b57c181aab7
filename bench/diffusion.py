"""Benchmark of the ArtNVG diffusion stage with full-size, randomly initialised models (no weights).

Builds the SDXL UNet, the SDXL ControlNet, the ViT-bigG image encoder, CSGO's two resamplers
(4 content / 32 style tokens) and the SDXL VAE from their architecture configs, installs
ArtNVG's processors (CSGO image branches active) and prints:

* seconds per denoising step (ControlNet + UNet, classifier-free guidance: batch 2N) and peak
  GPU memory, for N views in a group, image sizes, and NV attention on / off;
* the time of a whole group (content tokens, all steps, VAE decoding) — measured with
  ``--group-steps`` steps and, when that is below 50, extrapolated to 50 steps (labelled);
* image encoder time (one style image + N content views) and VAE decoding time per view.

Sections (no section flag = ``--timing --group``):

* ``--timing``: the seconds-per-step table above;
* ``--flops``: FLOPs of one step per configuration (counted on the meta device, no memory), the
  floor time at the measured bf16 matmul rate (``--matmul-size``^3) and, with ``--timing``, the gap
  of the measured time to that floor;
* ``--variants``: one NV step (``--variant-views`` N at ``--variant-size``, CFG) for the eager
  baseline, each exact speedup of :mod:`artnvg_core.diffusion.speed` alone (SDPA backends,
  channels-last, fused projections, the cached hint embedding, ``torch.compile`` unless
  ``--compile none``, with static and with dynamic shapes) and all combined (with the fastest
  backend): time, peak memory and deviation of the noise prediction from the baseline; for the
  compiled rows also the first call, and the first call at N-1 views after it (a group of another
  size: the recompilation); details to ``--json``;
* ``--group``: whole-group and component tables.

Timing: CUDA events (perf_counter on CPU), ``--warmup`` untimed runs, median of ``--repeats``.
Compute does not depend on weight values, so random weights give representative numbers.

    python bench/diffusion.py                      # GPU, bf16, full size
    python bench/diffusion.py --tiny --device cpu  # smoke test with tiny models
    python bench/diffusion.py --timing --flops --variants --views 1 15 --json out/variants.json
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import gc
import json
import sys
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel  # noqa: E402
from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection  # noqa: E402

from bench.common import peak_memory, timed  # noqa: E402

from artnvg_core.diffusion.architectures import (  # noqa: E402
    SDXL_SCHEDULER_CONFIG,
    SDXL_UNET_CONFIG,
    SDXL_VAE_CONFIG,
    VIT_BIGG_IMAGE_ENCODER_CONFIG,
    controlnet_config_from_unet,
)
from artnvg_core.diffusion.attention import AttentionControl, attention_kwargs  # noqa: E402
from artnvg_core.diffusion.conditioning import (  # noqa: E402
    PromptEmbeddings,
    StyleConditioning,
    image_features,
)
from artnvg_core.diffusion.csgo import (  # noqa: E402
    CONTROLNET_ROUTES,
    UNET_ROUTES,
    CSGOProjections,
    install_processors,
)
from artnvg_core.diffusion.models import DiffusionModels, SDXLBase  # noqa: E402
from artnvg_core.diffusion.resampler import PerceiverResampler, ResamplerConfig  # noqa: E402
from artnvg_core.diffusion.sampler import SamplerSettings, stylize_group  # noqa: E402
from artnvg_core.diffusion.speed import (  # noqa: E402
    COMPILE_MODES,
    COMPILE_SCOPES,
    SDPA_BACKENDS,
    SpeedOptions,
    apply_speedups,
    sdpa_backend,
)
from artnvg_core.fileio import write_atomically  # noqa: E402

POOLED_DIM = 1280
TEXT_TOKENS = 77

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
        scheduler_config=SDXL_SCHEDULER_CONFIG,
    )
    return DiffusionModels(base=base, controlnet=controlnet, image_encoder=encoder, csgo=csgo)


def random_conditioning(models: DiffusionModels, device, dtype, pooled_dim: int) -> StyleConditioning:
    width = models.base.unet.config.cross_attention_dim
    text = torch.randn(1, TEXT_TOKENS, width, device=device, dtype=dtype)
    pooled = torch.randn(1, pooled_dim, device=device, dtype=dtype)
    style = models.csgo.tokens("style", torch.randn(1, 257, models.image_encoder.config.hidden_size, device=device))
    return StyleConditioning(PromptEmbeddings(text, pooled, torch.zeros_like(text), torch.zeros_like(pooled)), style)


def step_inputs(models: DiffusionModels, views: int, size: int, nv: bool, pooled_dim: int, seed: int = 0) -> dict:
    """Seeded inputs of one ControlNet + UNet evaluation with CFG (batch 2N), on the models' device."""
    unet = models.base.unet
    device, dtype, width = unet.device, unet.dtype, unet.config.cross_attention_dim
    batch = 2 * views
    generator = torch.Generator().manual_seed(seed)

    def rand(*shape, normal=True):
        values = torch.randn(shape, generator=generator) if normal else torch.rand(shape, generator=generator)
        return values.to(device=device, dtype=dtype)

    control = AttentionControl(
        views_per_group=views if nv else 1,
        num_content_tokens=4,
        num_style_tokens=32,
        content_scale=1.0,
        style_scale=0.6,
    )
    return {
        "latents": rand(batch, 4, size // 8, size // 8),
        "t": torch.tensor(500, device=device),
        "context": rand(batch, TEXT_TOKENS + 4 + 32, width),
        "hint": rand(batch, 3, size, size, normal=False),
        "added": {
            "text_embeds": rand(batch, pooled_dim),
            "time_ids": torch.tensor([[size, size, 0, 0, size, size]] * batch, device=device, dtype=dtype),
        },
        "control": attention_kwargs(control),
    }


@torch.no_grad()
def run_step(unet, controlnet, inputs: dict) -> torch.Tensor:
    """ControlNet then UNet on ``inputs`` (see :func:`step_inputs`); returns the noise prediction [2N, 4, h, w]."""
    common = dict(added_cond_kwargs=inputs["added"], cross_attention_kwargs=inputs["control"], return_dict=False)
    down, mid = controlnet(inputs["latents"], inputs["t"], inputs["context"], inputs["hint"], **common)
    return unet(
        inputs["latents"],
        inputs["t"],
        inputs["context"],
        down_block_additional_residuals=down,
        mid_block_additional_residual=mid,
        **common,
    )[0]


def denoise_step(models: DiffusionModels, views: int, size: int, nv: bool, pooled_dim: int):
    """One ControlNet + UNet evaluation with CFG (batch 2N), as a closure."""
    inputs = step_inputs(models, views, size, nv, pooled_dim)
    return lambda: run_step(models.base.unet, models.controlnet, inputs)


def write_json(path: Path | None, data: dict) -> None:
    """Write ``data`` to ``path`` atomically (no-op for None)."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda stream: stream.write(json.dumps(data, indent=2).encode()))


def matmul_rate(device: torch.device, dtype: torch.dtype, size: int) -> float:
    """Measured FLOP/s of a ``size``^3 matrix product in ``dtype`` (median of 20)."""
    generator = torch.Generator().manual_seed(0)
    a, b = (torch.randn(size, size, generator=generator).to(device=device, dtype=dtype) for _ in range(2))
    return 2 * size**3 / timed(lambda: a @ b, device, repeats=20, warmup=3)


FLOP_KINDS = {"attention": ("bmm", "baddbmm"), "linear": ("mm", "addmm"), "convolution": ("convolution",)}


def step_flops(meta_models: DiffusionModels, views: int, size: int, nv: bool, pooled_dim: int) -> dict[str, int]:
    """FLOPs of one denoising step (ControlNet + UNet, CFG, 113-token context) counted on the meta device.

    On meta tensors scaled-dot-product attention runs PyTorch's math path, so the counter sees its two
    batched matmuls (4 B H Lq Lk D FLOPs, the same formula it applies to the CUDA SDPA kernels): the
    "attention" entry is every attention product, self (NV) and cross (text + CSGO branches).
    """
    inputs = step_inputs(meta_models, views, size, nv, pooled_dim)
    with FlopCounterMode(display=False) as counter:
        run_step(meta_models.base.unet, meta_models.controlnet, inputs)
    counts = {str(op).removeprefix("aten."): n for op, n in counter.get_flop_counts()["Global"].items()}
    kinds = {kind: sum(counts.get(op, 0) for op in ops) for kind, ops in FLOP_KINDS.items()}
    return {"total": counter.get_total_flops(), **kinds}


def flops_table(args, dtype, timings: dict, pooled_dim: int) -> dict:
    """Print FLOPs per configuration, the floor at the measured matmul rate and the gap to measured times."""
    device = torch.device(args.device)
    rate = matmul_rate(device, dtype, args.matmul_size)
    meta_models = build_models(args.tiny, torch.device("meta"), dtype)
    print(
        f"\nMeasured {args.matmul_size}^3 {args.dtype} matmul: {rate / 1e12:.1f} TFLOP/s. FLOPs counted with "
        "torch.utils.flop_counter on the meta device (attention = SDPA products incl. CSGO branches)."
    )
    print("\n| size | N views | NV attention | TFLOP / step | attention | linear | conv | floor s | s / step | gap |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    rows = []
    for size in args.sizes:
        for views in args.views:
            for nv in (False, True):
                if not (nv and views == 1):  # one view: NV attention is per-view attention, same count
                    flops = step_flops(meta_models, views, size, nv, pooled_dim)
                floor = flops["total"] / rate
                measured = timings.get((size, views, nv))
                rows.append(dict(size=size, views=views, nv=nv, flops=flops, floor_s=floor, measured_s=measured))
                tera = {kind: f"{value / 1e12:.3g}" for kind, value in flops.items()}
                timing = "| - | -" if measured is None else f"| {measured:.3f} | {measured / floor:.2f}x"
                print(
                    f"| {size} | {views} | {'on' if nv else 'off'} | {tera['total']} | {tera['attention']} | "
                    f"{tera['linear']} | {tera['convolution']} | {floor:.3f} {timing} |",
                    flush=True,
                )
    return {"matmul_tflops": rate / 1e12, "matmul_size": args.matmul_size, "configurations": rows}


def _copy_models(models: DiffusionModels) -> DiffusionModels:
    """Independent copies of the UNet and the ControlNet (same weights), for one variant."""
    return DiffusionModels(
        base=dataclasses.replace(models.base, unet=copy.deepcopy(models.base.unet)),
        controlnet=copy.deepcopy(models.controlnet),
    )


def measure_variant(models, inputs, backend: str, options: SpeedOptions, args,
                    resized_inputs: dict) -> tuple[dict, torch.Tensor]:
    """Time one step of a speedup variant on copies of ``models``, then the first step on
    ``resized_inputs`` (another group size: what a recompilation costs); returns (row, noise prediction)."""
    variant = _copy_models(models)
    apply_speedups(variant, options)
    device = torch.device(args.device)

    def run(step_inputs=inputs):
        return run_step(variant.base.unet, variant.controlnet, step_inputs)

    with sdpa_backend(backend):
        begin = time.perf_counter()
        noise = run().float()
        first = time.perf_counter() - begin
        seconds = timed(run, device, repeats=args.repeats, warmup=args.warmup)
        peak = peak_memory(run, device)
        resized_first = timed(lambda: run(resized_inputs), device, repeats=1, warmup=0)
    return {"seconds": seconds, "first_call_s": first, "resized_first_call_s": resized_first,
            "peak_extra_gib": peak}, noise


def release(device: torch.device) -> None:
    """Free what the last variant left: its models (garbage), compiled code and cached GPU blocks."""
    gc.collect()
    torch._dynamo.reset()
    if device.type == "cuda":
        torch.cuda.empty_cache()


def deviation(noise: torch.Tensor, reference: torch.Tensor) -> dict:
    difference = noise - reference
    return {
        "max_abs": difference.abs().max().item(),
        "rel_l2": (difference.norm() / reference.norm()).item(),
    }


def variants_table(models: DiffusionModels, args, pooled_dim: int, report: dict) -> None:
    """Time one NV + CFG step for the eager baseline, each exact speedup alone, and all combined.

    Each variant runs on copies of the same weights with the same inputs; its noise prediction is
    compared with the baseline's (the baseline row compares two baseline runs: run-to-run noise).
    """
    size, views = args.variant_size, args.variant_views
    inputs = step_inputs(models, views, size, True, pooled_dim, seed=1)
    resized_inputs = step_inputs(models, views - 1, size, True, pooled_dim, seed=1)
    compile_mode = None if args.compile == "none" else args.compile
    backends = ["auto"] + [name for name in SDPA_BACKENDS if name != "auto"]
    plan = [(f"sdpa {name}" if name != "auto" else "eager baseline", name, SpeedOptions()) for name in backends]
    plan += [
        ("channels_last", "auto", SpeedOptions(channels_last=True)),
        ("fused projections", "auto", SpeedOptions(fuse_projections=True)),
        ("hint embedding cached", "auto", SpeedOptions(cache_hint_embedding=True)),
    ]
    scopes = COMPILE_SCOPES if args.compile_scope == "both" else (args.compile_scope,)
    if compile_mode is not None:
        plan += [(f"torch.compile {compile_mode}, {'whole models' if scope == 'model' else 'repeated blocks'}"
                  f"{', dynamic shapes' if dynamic else ''}", "auto",
                  SpeedOptions(compile=compile_mode, compile_scope=scope, compile_dynamic=dynamic))
                 for scope in scopes for dynamic in (False, True)]
    print(
        f"\nExact speedups, one step: N={views}, {size}x{size}, NV on, CFG (batch {2 * views}), "
        f"ControlNet + UNet; deviation of the noise prediction from the eager baseline ({args.dtype})."
    )
    print("\n| variant | SDPA backend | s / step | speedup | peak GiB above weights | max abs diff | rel L2 | note |")
    print("|---|---|---:|---:|---:|---:|---:|---|")
    rows = report.setdefault("variants", [])
    reference = None
    combined = SpeedOptions(channels_last=True, fuse_projections=True, compile=compile_mode, compile_scope=scopes[-1],
                            cache_hint_embedding=compile_mode is None or scopes[-1] == "blocks")
    plan += [("all combined", None, combined)]
    if args.only:
        plan = [row for row in plan if row[0] == "eager baseline" or any(text in row[0] for text in args.only)]
    for name, backend, options in plan:
        if backend is None:
            timed = [r for r in rows if r["options"] == dataclasses.asdict(SpeedOptions()) and "seconds" in r]
            backend = min(timed, key=lambda r: r["seconds"])["backend"]
        row = {"variant": name, "backend": backend, "options": dataclasses.asdict(options)}
        try:
            measured, noise = measure_variant(models, inputs, backend, options, args, resized_inputs)
            row.update(measured)
            if reference is None:
                reference = noise
                noise = run_step(models.base.unet, models.controlnet, inputs).float()
            row.update(deviation(noise, reference))
        except Exception as error:  # a backend without a kernel, out of memory, a compile failure
            row["error"] = f"{type(error).__name__}: {str(error).strip().splitlines()[0][:160]}"
        release(torch.device(args.device))
        rows.append(row)
        write_json(args.json, report)
        if "error" in row:
            print(f"| {name} | {backend} | - | - | - | - | - | {row['error']} |", flush=True)
            continue
        speedup = rows[0]["seconds"] / row["seconds"] if "seconds" in rows[0] else float("nan")
        note = (f"first call {row['first_call_s']:.1f} s, then at N={views - 1}: {row['resized_first_call_s']:.1f} s"
                if options.compile else "")
        print(
            f"| {name} | {backend} | {row['seconds']:.3f} | {speedup:.2f}x | {row['peak_extra_gib']:.1f} | "
            f"{row['max_abs']:.3g} | {row['rel_l2']:.3g} | {note} |",
            flush=True,
        )


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
    parser.add_argument("--timing", action="store_true", help="seconds per step table")
    parser.add_argument("--flops", action="store_true", help="FLOP count, floor time and gap table")
    parser.add_argument("--variants", action="store_true", help="exact speedup variants table")
    parser.add_argument("--group", action="store_true", help="whole-group and component tables")
    parser.add_argument("--matmul-size", type=int, help="side of the matmul rate probe (default 8192, CPU 1024)")
    parser.add_argument("--variant-size", type=int, help="image side for --variants (default 1024, tiny 128)")
    parser.add_argument("--variant-views", type=int, default=15)
    parser.add_argument(
        "--compile",
        choices=["none", *COMPILE_MODES],
        help="torch.compile mode of the --variants compile rows (default: 'default' on CUDA, 'none' on the CPU)",
    )
    parser.add_argument("--only", nargs="+", metavar="TEXT",
                        help="--variants rows whose name contains one of these (the eager baseline always runs)")
    parser.add_argument("--compile-scope", choices=["both", *COMPILE_SCOPES], default="both",
                        help="what the --variants compile rows compile: whole models, repeated blocks, or both")
    parser.add_argument("--json", type=Path, help="write the results of this run as JSON here")
    args = parser.parse_args()
    if not (args.timing or args.flops or args.variants or args.group):
        args.timing = args.group = True
    device = torch.device(args.device)
    args.dtype = args.dtype or ("bf16" if device.type == "cuda" else "fp32")
    dtype = {"bf16": torch.bfloat16, "fp16": torch.float16, "fp32": torch.float32}[args.dtype]
    if args.tiny and args.sizes == [768, 1024]:
        args.sizes = [64, 128]
    args.matmul_size = args.matmul_size or (8192 if device.type == "cuda" else 1024)
    args.variant_size = args.variant_size or (128 if args.tiny else 1024)
    args.compile = args.compile or ("default" if device.type == "cuda" else "none")
    pooled_dim = TINY_POOLED_DIM if args.tiny else POOLED_DIM

    begin = time.perf_counter()
    torch.manual_seed(0)
    models = build_models(args.tiny, device, dtype)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    weights = sum(p.numel() * p.element_size() for m in (models.base.unet, models.controlnet) for p in m.parameters())
    print(
        f"# ArtNVG diffusion benchmark: {gpu}, {args.dtype}, {'tiny' if args.tiny else 'full-size'} random models "
        f"(built in {time.perf_counter() - begin:.0f} s; UNet + ControlNet {weights / 2**30:.1f} GiB), "
        f"torch {torch.__version__}, SDPA backends: flash={torch.backends.cuda.flash_sdp_enabled()}, "
        f"mem_efficient={torch.backends.cuda.mem_efficient_sdp_enabled()}"
    )
    report = {"setup": {"device": gpu, "dtype": args.dtype, "tiny": args.tiny, "torch": torch.__version__}}
    timings = {}
    if args.timing:
        print("\n| size | N views | NV attention | s / step (CFG, ControlNet + UNet) | peak GiB |")
        print("|---:|---:|---|---:|---:|")
        for size in args.sizes:
            for views in args.views:
                for nv in (False, True):
                    run = denoise_step(models, views, size, nv, pooled_dim)
                    seconds = timings[(size, views, nv)] = timed(run, device, args.repeats, args.warmup)
                    peak = peak_memory(run, device, absolute=True)
                    print(f"| {size} | {views} | {'on' if nv else 'off'} | {seconds:.3f} | {peak:.1f} |", flush=True)
        report["timing"] = [dict(size=k[0], views=k[1], nv=k[2], seconds=v) for k, v in timings.items()]
        write_json(args.json, report)
    if args.flops:
        report["flops"] = flops_table(args, dtype, timings, pooled_dim)
        write_json(args.json, report)
    if args.variants:
        variants_table(models, args, pooled_dim, report)
    if args.group:
        group_tables(models, args, dtype, pooled_dim)


def group_tables(models: DiffusionModels, args, dtype: torch.dtype, pooled_dim: int) -> None:
    """Whole-group time (all steps, decoding) and the image encoder / VAE component times."""
    device = torch.device(args.device)
    conditioning = random_conditioning(models, device, dtype, pooled_dim)
    print(f"\n| size | whole group of {args.group_views} views, NV on, DDIM | seconds |")
    print("|---:|---|---:|")
    for size in args.sizes:
        images = torch.rand(args.group_views, size, size, 3)
        settings = SamplerSettings(steps=args.group_steps, resolution=size)
        measured = timed(lambda: stylize_group(models, images, conditioning, settings), device, repeats=1, warmup=0)
        print(f"| {size} | {args.group_steps} steps, measured | {measured:.1f} |")
        if args.group_steps < 50:
            step = timed(denoise_step(models, args.group_views, size, True, pooled_dim), device, args.repeats, warmup=1)
            print(
                f"| {size} | 50 steps, EXTRAPOLATED (+{50 - args.group_steps} x {step:.3f} s/step) | "
                f"{measured + (50 - args.group_steps) * step:.1f} |"
            )

    print("\n| component | batch | seconds |")
    print("|---|---:|---:|")
    for count in (1, args.group_views):
        images = torch.rand(count, 512, 512, 3)
        seconds = timed(lambda: image_features(models.image_encoder, images), device, args.repeats, args.warmup)
        print(f"| image encoder (224 px, penultimate states) | {count} | {seconds:.3f} |")
    vae = models.base.vae
    for size in args.sizes:
        latents = torch.randn(1, 4, size // 8, size // 8, device=device, dtype=vae.dtype)
        seconds = timed(lambda: vae.decode(latents / vae.config.scaling_factor), device, args.repeats, args.warmup)
        print(f"| VAE decode {size} px ({str(vae.dtype).removeprefix('torch.')}) | 1 | {seconds:.3f} |")


if __name__ == "__main__":
    main()
