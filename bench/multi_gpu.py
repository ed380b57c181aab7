"""Scaling of the diffusion stage over several GPUs (:func:`stylize_groups_on_devices`).

Stylizes the same ``--groups`` groups of ``--views`` random ``--size`` px views (NV on, DDIM,
``--steps`` steps, random full-size models, bf16) on one GPU and on ``--workers`` GPUs (default:
all visible), and prints wall time, speedup and the largest difference from the one-GPU output.

Every process builds its models with the same seed (a weight checksum is printed per device).
Wall time excludes building the models: the one-GPU run reuses models built beforehand in this
process and is timed around the call; in the multi-GPU run each worker waits, after building,
at a barrier shared with a timing thread here, and the time runs from the barrier (all workers
ready) to the return of the call (so it includes sending the results back).

    python bench/multi_gpu.py                        # all visible GPUs
    python bench/multi_gpu.py --tiny --device cpu    # smoke test: tiny models, 2 CPU processes
"""

from __future__ import annotations

import argparse
import functools
import sys
import threading
import time
from pathlib import Path

import torch
import torch.multiprocessing as mp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from artnvg_core.diffusion.multi_gpu import stylize_groups_on_devices  # noqa: E402
from artnvg_core.diffusion.sampler import SamplerSettings  # noqa: E402
from artnvg_core.grouping import ViewGroup, ViewGroups  # noqa: E402
from bench.diffusion import (  # noqa: E402
    POOLED_DIM,
    TINY_POOLED_DIM,
    build_models,
    random_conditioning,
)

DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16, "fp32": torch.float32}


def seeded_models(tiny: bool, dtype: torch.dtype, seed: int, ready, device: torch.device):
    """Random models built from ``seed`` on ``device``; prints a weight checksum, then waits at ``ready``."""
    if device.type == "cpu":
        torch.set_num_threads(1)
    torch.manual_seed(seed)
    models = build_models(tiny, device, dtype)
    parts = (models.base.unet, models.controlnet, models.base.vae, models.image_encoder, models.csgo)
    checksum = sum(next(part.parameters()).double().sum().item() for part in parts)
    print(f"{device}: models built, checksum of the first weight of each model {checksum:.17g}", flush=True)
    if ready is not None:
        ready.wait()
    return models


def timed_from_barrier(run, ready) -> tuple[torch.Tensor, float]:
    """``run()`` and the seconds from the release of barrier ``ready`` (one party is this timer) to its return."""
    start = []
    waiter = threading.Thread(target=lambda: (ready.wait(), start.append(time.perf_counter())), daemon=True)
    waiter.start()
    output = run()
    waiter.join()
    return output, time.perf_counter() - start[0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tiny", action="store_true", help="tiny models (CPU smoke test)")
    parser.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    parser.add_argument("--workers", type=int, help="devices of the multi-device run (default: all GPUs; CPU: 2)")
    parser.add_argument("--dtype", choices=list(DTYPES), help="default: bf16 on a GPU, fp32 on the CPU")
    parser.add_argument("--groups", type=int, default=4)
    parser.add_argument("--views", type=int, default=15)
    parser.add_argument("--size", type=int, help="view side in pixels (default 1024, tiny 64)")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    cuda = args.device == "cuda"
    workers = args.workers or (torch.cuda.device_count() if cuda else 2)
    devices = [f"cuda:{i}" for i in range(workers)] if cuda else ["cpu"] * workers
    dtype = DTYPES[args.dtype or ("bf16" if cuda else "fp32")]
    size = args.size or (64 if args.tiny else 1024)
    settings = SamplerSettings(steps=args.steps, resolution=size)
    views = args.groups * args.views
    images = torch.rand(views, size, size, 3, generator=torch.Generator().manual_seed(args.seed))
    groups = ViewGroups([ViewGroup(range(g * args.views, (g + 1) * args.views)) for g in range(args.groups)], views)

    name = torch.cuda.get_device_name(0) if cuda else "CPU (1 thread per process)"
    print(
        f"# Multi-device diffusion: {workers} x {name}, {str(dtype).removeprefix('torch.')}, "
        f"{'tiny' if args.tiny else 'full-size'} random models, {args.groups} groups x {args.views} views "
        f"at {size}x{size}, NV on, DDIM {args.steps} steps, torch {torch.__version__}"
    )
    print("# " + " ".join(["python", *sys.argv]))
    models = seeded_models(args.tiny, dtype, args.seed, None, torch.device(devices[0]))
    conditioning = random_conditioning(models, devices[0], dtype, TINY_POOLED_DIM if args.tiny else POOLED_DIM)
    common = dict(images=images, groups=groups, conditioning=conditioning, settings=settings, seed=args.seed)

    begin = time.perf_counter()
    reference = stylize_groups_on_devices(lambda device, built=models: built, devices=devices[:1], **common)
    rows = [(1, time.perf_counter() - begin, 0.0)]
    del models
    if cuda:
        torch.cuda.empty_cache()
    if workers > 1:
        ready = mp.get_context("spawn").Barrier(workers + 1)
        loader = functools.partial(seeded_models, args.tiny, dtype, args.seed, ready)
        run = functools.partial(stylize_groups_on_devices, loader, devices=devices, **common)
        output, seconds = timed_from_barrier(run, ready)
        rows.append((workers, seconds, (output - reference).abs().max().item()))

    print("\n| devices | wall s (models built) | speedup | max abs diff vs 1 device |")
    print("|---:|---:|---:|---:|")
    for count, seconds, difference in rows:
        print(f"| {count} | {seconds:.1f} | {rows[0][1] / seconds:.2f}x | {difference:.3g} |")


if __name__ == "__main__":
    main()
