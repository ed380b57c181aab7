"""Why a process's first group samples slower than the next ones: the bear's first groups, one after another.

Renders the bear's content views, groups them as ``stylize --group-multiple M`` does, builds random
full-size models (bf16; ``--tiny``: tiny ones) and samples groups 0 to ``--groups - 1`` at a preset's
settings in this process, the GPU waited for around each (seconds). With ``--profile``,
``torch.profiler`` records the first group and the last one: the operations whose self CPU time and
self GPU time differ most between the two (milliseconds, call counts), which is where the first
group's extra time goes (plans built at a shape's first call, kernels' modules loaded at their first
launch). ``--attention`` picks the scaled-dot-product backend (``SamplerSettings.attention_backend``).
One process measures one setting: run it once per environment (``CUDA_MODULE_LOADING``, ...).

    cd bench && python first_group.py --profile                       # ~1 min on an H200
    cd bench && python first_group.py --attention flash
    cd bench && python first_group.py --tiny --device cpu --views 8   # CPU smoke test
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import time
from pathlib import Path

import torch

from common import print_table
from multi_gpu import SHARED, content_views, seeded_models

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from artnvg_core.diffusion.sampler import stylize_group  # noqa: E402
from artnvg_core.diffusion.speed import SDPA_BACKENDS  # noqa: E402
from artnvg_core.diffusion.stylize import group_members  # noqa: E402
from artnvg_core.presets import DIFFUSION_PRESETS, PRESETS  # noqa: E402
from bench.diffusion import POOLED_DIM, TINY_POOLED_DIM, random_conditioning  # noqa: E402


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def profiled_totals(profile) -> dict[str, tuple[float, float, int]]:
    """Per operation name: (self CPU ms, self device ms, calls)."""
    return {event.key: (event.self_cpu_time_total / 1e3, event.self_device_time_total / 1e3, event.count)
            for event in profile.key_averages()}


def differences(first: dict, last: dict, column: int, top: int) -> list[list]:
    """The ``top`` operations whose ``column`` (0: CPU, 1: device) grew most from ``last`` to ``first``."""
    none = (0.0, 0.0, 0)
    names = sorted(set(first) | set(last), key=lambda name: -(first.get(name, none)[column] - last.get(name, none)[column]))
    return [[name[:90], first.get(name, none)[column], last.get(name, none)[column],
             f"{first.get(name, none)[2]} / {last.get(name, none)[2]}"] for name in names[:top]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=DIFFUSION_PRESETS, default="fast")
    parser.add_argument("--groups", type=int, default=4, help="groups sampled one after another (at least 2)")
    parser.add_argument("--group-multiple", type=int, default=4, help="as stylize's (the groups of bench/multi_gpu.py)")
    parser.add_argument("--views", type=int, help="this many evenly spaced cameras of the bear (default all 96)")
    parser.add_argument("--attention", choices=sorted(SDPA_BACKENDS), default="auto")
    parser.add_argument("--profile", action="store_true", help="profile the first and the last group")
    parser.add_argument("--top", type=int, default=12, help="operations listed per profile table")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--tiny", action="store_true", help="tiny models (smoke test)")
    parser.add_argument("--shared", type=Path, default=SHARED)
    args = parser.parse_args()
    if args.groups < 2:
        parser.error("--groups must be at least 2: the first group is compared with the later ones")
    device = torch.device(args.device)
    command = "python " + " ".join(sys.argv)
    images, groups = content_views(args.shared / "scenes" / "bear", args.views, None, args.group_multiple)
    count = min(args.groups, len(groups))
    models = seeded_models(args.tiny, 0, device)
    with torch.no_grad():
        conditioning = random_conditioning(models, device, models.base.unet.dtype,
                                           TINY_POOLED_DIM if args.tiny else POOLED_DIM)
    settings = dataclasses.replace(PRESETS[args.preset].sampler, attention_backend=args.attention)
    if args.tiny:
        settings = dataclasses.replace(settings, resolution=None)
    seconds, totals = [], {}
    for index in range(count):
        members, centers = group_members(images, groups, index)
        profiled = args.profile and index in (0, count - 1)
        activities = [torch.profiler.ProfilerActivity.CPU] + (
            [torch.profiler.ProfilerActivity.CUDA] if device.type == "cuda" else [])
        profile = torch.profiler.profile(activities=activities) if profiled else contextlib.nullcontext()
        with profile:
            synchronize(device)
            start = time.perf_counter()
            stylize_group(models, members, conditioning, settings, seed=index, view_centers=centers)
            synchronize(device)
            seconds.append(time.perf_counter() - start)
        if profiled:
            totals[index] = profiled_totals(profile)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print_table(f"Groups one after another in one process ({name}, {args.preset}, attention {args.attention}, "
                f"{len(groups[0].views)} views a group; seconds)", [f"group {i}" for i in range(count)],
                [seconds], command)
    if totals:
        columns = ((0, "self CPU"), (1, "self GPU")) if device.type == "cuda" else ((0, "self CPU"),)
        for column, what in columns:
            print_table(f"Where group 0 spends more than group {count - 1}: {what} ms",
                        ["operation", "group 0", f"group {count - 1}", "calls"],
                        differences(totals[0], totals[count - 1], column, args.top), command)
        print(f"\nself CPU in all: group 0 {sum(v[0] for v in totals[0].values()):.0f} ms, "
              f"group {count - 1} {sum(v[0] for v in totals[count - 1].values()):.0f} ms")


if __name__ == "__main__":
    main()
