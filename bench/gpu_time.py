"""Where the GPU time goes: kernel time by kind for one denoising step and one finetune iteration.

    python bench/gpu_time.py --diffusion --finetune --scene .devdata/scenes/bear --json out/profile.json

* ``--diffusion``: one ControlNet + UNet evaluation with CFG (``bench/diffusion.py``'s random
  full-size bf16 models), N views at ``--size``, NV attention on: wall time per step, the sum of
  kernel times (the difference is time the GPU waits for the CPU), kernel time by kind, and the
  rate scaled-dot-product attention reaches alone at the step's two NV shapes per backend.
* ``--finetune``: the finetune loop on the scene at 1024x1024 (cameras scaled x2) with random
  stylized targets (L1 + SSIM + NNFM) and without them (NNFM + content term): time per
  iteration and kernel time by kind; then the SSIM term alone, forward + backward.

Kernel kinds are read from kernel names (attention, convolution, matrix product, normalisation,
elementwise, reduction, copy/fill, other); the ten longest kernels are printed to check them.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.profiler import ProfilerActivity, profile, schedule

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import print_table, timed  # noqa: E402
from bench.diffusion import POOLED_DIM, build_models, run_step, step_inputs, write_json  # noqa: E402

from artnvg_core.cameras import load_cameras  # noqa: E402
from artnvg_core.finetune import FinetuneConfig, finetune  # noqa: E402
from artnvg_core.formats import read_ply  # noqa: E402
from artnvg_core.images import load_image  # noqa: E402
from artnvg_core.losses import ssim  # noqa: E402
from artnvg_core.stylize import DemoInputs  # noqa: E402

CUDA = torch.device("cuda")
KINDS = (  # first match wins: cuDNN attention kernels also say "fprop", cuDNN convolutions also say "gemm"
    ("attention", ("sdpa", "fmha", "flash", "attention")),
    ("convolution", ("conv", "dgrad", "wgrad", "fprop", "implicit", "winograd")),
    ("matrix product", ("gemm", "nvjet", "xmma", "cutlass", "matmul")),
    ("normalisation", ("norm",)),
    ("reduction", ("reduce",)),
    ("copy/fill", ("copy", "cat", "memcpy", "memset", "fill")),
    ("elementwise", ("elementwise", "vectorized", "unrolled")),
)


def kernel_kind(name: str) -> str:
    lower = name.lower()
    return next((kind for kind, keys in KINDS if any(key in lower for key in keys)), "other")


def kernel_times(run, active: int, skip: int = 1) -> dict[str, float]:
    """GPU seconds per unit of work for every kernel name.

    ``run(step)`` does ``skip + 1 + active`` units of work, calling ``step()`` after each: the first
    ``skip`` are not recorded, the next one warms the profiler up, the last ``active`` are averaged.
    """
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA], schedule=schedule(wait=skip, warmup=1, active=active)) as prof:
        run(prof.step)
    times = {}
    for event in prof.key_averages():
        micros = event.self_device_time_total
        if micros > 0 and event.device_type == torch.autograd.DeviceType.CUDA:
            times[event.key] = times.get(event.key, 0.0) + micros / 1e6 / active
    return times


def by_kind(times: dict[str, float]) -> dict[str, float]:
    kinds: dict[str, float] = {}
    for name, seconds in times.items():
        kinds[kernel_kind(name)] = kinds.get(kernel_kind(name), 0.0) + seconds
    return dict(sorted(kinds.items(), key=lambda item: -item[1]))


def report(title: str, wall: float, times: dict[str, float], command: str) -> dict:
    """Print the kind table and the ten longest kernels; return both as data."""
    kernels = sum(times.values())
    kinds = by_kind(times)
    rows = [[kind, seconds * 1e3, 100 * seconds / wall] for kind, seconds in kinds.items()]
    rows += [["all kernels", kernels * 1e3, 100 * kernels / wall], ["wall time", wall * 1e3, 100.0]]
    print_table(title, ["kernel kind", "ms", "% of wall"], rows, command)
    longest = sorted(times.items(), key=lambda item: -item[1])[:10]
    print("\nlongest kernels: " + "; ".join(f"{seconds * 1e3:.1f} ms [{kernel_kind(name)}] {name[:90]}"
                                             for name, seconds in longest))
    return {"wall_s": wall, "kernels_s": kernels, "kinds_s": kinds, "longest": longest}


def sdpa_rates(views: int, size: int) -> list[list]:
    """TFLOP/s of SDPA alone at the step's two NV shapes (CFG batch 2), per backend, in the layout the
    processor passes ([B, L, H, D] memory seen as [B, H, L, D]) and contiguous."""
    rows = []
    for heads, side in ((10, size // 16), (20, size // 32)):
        length = views * side * side
        flops = 4 * 2 * heads * length * length * 64
        for layout in ("processor", "contiguous"):
            q, k, v = (torch.randn(2, length, heads, 64, device="cuda", dtype=torch.bfloat16).transpose(1, 2)
                       for _ in range(3))
            if layout == "contiguous":
                q, k, v = q.contiguous(), k.contiguous(), v.contiguous()
            for backend in (SDPBackend.CUDNN_ATTENTION, SDPBackend.FLASH_ATTENTION):
                with sdpa_kernel(backend):
                    seconds = timed(lambda: torch.nn.functional.scaled_dot_product_attention(q, k, v), CUDA, 5, 2)
                rows.append([f"2 x {heads} x {length} x 64", layout, backend.name, seconds * 1e3,
                             flops / seconds / 1e12])
    return rows


def step_profile(args, command: str) -> dict:
    """Wall time and kernel times of one denoising step (the models are freed on return)."""
    models = build_models(False, CUDA, torch.bfloat16)
    inputs = step_inputs(models, args.views, args.size, True, POOLED_DIM)

    def run() -> None:
        run_step(models.base.unet, models.controlnet, inputs)

    def steps(step) -> None:
        for _ in range(4):
            run()
            torch.cuda.synchronize()
            step()

    wall = timed(run, CUDA, repeats=3, warmup=1)
    return report(f"One denoising step: N={args.views}, {args.size}x{args.size}, NV on, CFG, bf16, eager",
                  wall, kernel_times(steps, active=2), command)


def diffusion(args, command: str) -> dict:
    data = step_profile(args, command)
    torch.cuda.empty_cache()
    rates = sdpa_rates(args.views, args.size)
    print_table("SDPA alone at the NV shapes", ["shape (B x H x L x D)", "layout", "backend", "ms", "TFLOP/s"],
                rates, command)
    return {**data, "sdpa": rates}


def finetune_profile(args, command: str) -> dict:
    device = CUDA
    scene = read_ply(args.scene / "scene.ply").to(device)
    cameras = load_cameras(args.scene / "transforms.json").scaled(2.0)
    style = load_image(DemoInputs().style).to(device)
    targets = torch.rand(len(cameras), cameras.height, cameras.width, 3, generator=torch.Generator().manual_seed(0))
    results = {}
    for name, stylized in (("with stylized targets", targets), ("without (NNFM + content)", None)):
        stamps = []

        def stamp(*_):
            torch.cuda.synchronize()
            stamps.append(time.perf_counter())

        config = FinetuneConfig(iterations=args.finetune_iters + 5, backend="gsplat")
        finetune(scene, cameras, style, stylized=stylized, config=config, progress=stamp)
        wall = statistics.median(b - a for a, b in zip(stamps[5:], stamps[6:]))
        profiled = FinetuneConfig(iterations=12, backend="gsplat")
        times = kernel_times(lambda step: finetune(scene, cameras, style, stylized=stylized, config=profiled,
                                                   progress=lambda *_: step()), active=10)
        results[name] = report(f"Finetune iteration {name}, bear {cameras.width}x{cameras.height}, gsplat",
                               wall, times, command)
    a = torch.rand(1, 3, cameras.height, cameras.width, device=device, requires_grad=True)
    b = torch.rand_like(a)
    seconds = timed(lambda: ssim(a, b).backward(), device, repeats=10, warmup=3)
    print(f"\nSSIM alone, forward + backward at {cameras.width}x{cameras.height}: {seconds * 1e3:.2f} ms")
    results["ssim_s"] = seconds
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--diffusion", action="store_true")
    parser.add_argument("--finetune", action="store_true")
    parser.add_argument("--views", type=int, default=15)
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--scene", type=Path, default=Path(".devdata/scenes/bear"))
    parser.add_argument("--finetune-iters", type=int, default=30)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not torch.cuda.is_available():
        sys.exit("bench/gpu_time.py profiles CUDA kernels: it needs a GPU")
    command = "python " + " ".join(sys.argv)
    print(f"{torch.cuda.get_device_name()}, torch {torch.__version__}")
    results = {"device": torch.cuda.get_device_name(), "command": command}
    if args.finetune:
        results["finetune"] = finetune_profile(args, command)
    if args.diffusion:
        results["diffusion"] = diffusion(args, command)
    write_json(args.json, results)


if __name__ == "__main__":
    main()
