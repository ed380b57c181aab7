"""Scene files at millions of Gaussians: seconds to write and read each format, and how soon a stop ends them.

    python bench/scene_files.py [--gaussians 3000000] [--degree 3] [--folder /tmp]

A random scene (normal means of spread 5, log-scales about -4, SH coefficients of spread 0.3: random SH
deflates worse than a capture's) is written by ``save_scene`` in each format and read back by ``load_scene``,
one call each. "stop after" asks ``should_stop`` to say stop a quarter of the way through the call's time, and gives
the seconds from then until ``Cancelled`` (empty for a checkout whose readers and writers take no ``should_stop``).
Peak memory is the process's VmHWM over the call (Linux), the scene itself included.
"""

from __future__ import annotations

import argparse
import inspect
import logging
import time
from pathlib import Path

import torch

from common import print_table

from artnvg_core.formats import load_scene, save_scene
from artnvg_core.scene import GaussianScene

FORMATS = {".ply": {}, ".spz (v3)": {"spz_version": 3}, ".spz (v2)": {"spz_version": 2}, ".splat": {}, ".ksplat": {}}


def random_scene(count: int, degree: int) -> GaussianScene:
    g = torch.Generator().manual_seed(0)
    return GaussianScene(means=torch.randn(count, 3, generator=g) * 5, quats=torch.randn(count, 4, generator=g),
                         log_scales=torch.randn(count, 3, generator=g) - 4,
                         opacity_logits=torch.randn(count, generator=g),
                         sh=torch.randn(count, (degree + 1) ** 2, 3, generator=g) * 0.3)


def peak_mb_during(run) -> tuple[object, float, int]:
    """(result, seconds, peak resident MB) of ``run()``; the peak is reset first (Linux's clear_refs)."""
    Path("/proc/self/clear_refs").write_text("5")
    begin = time.perf_counter()
    result = run()
    seconds = time.perf_counter() - begin
    status = Path("/proc/self/status").read_text().splitlines()
    return result, seconds, int(next(line for line in status if line.startswith("VmHWM")).split()[1]) // 1024


def stop_latency(run, after: float) -> float | None:
    """Seconds from ``after`` seconds into ``run(should_stop)`` until it raises Cancelled; None if it never did."""
    from artnvg_core.progress import Cancelled

    deadline = time.perf_counter() + after
    try:
        run(lambda: time.perf_counter() > deadline)
    except Cancelled:
        return time.perf_counter() - deadline
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=3_000_000)
    parser.add_argument("--degree", type=int, default=3)
    parser.add_argument("--folder", default="/tmp")
    args = parser.parse_args()
    logging.disable(logging.WARNING)  # the dropped SH terms of .splat and .ksplat, the SPZ's unnamed axes
    stops = "should_stop" in inspect.signature(save_scene).parameters
    scene = random_scene(args.gaussians, args.degree)
    rows = []
    for name, options in FORMATS.items():
        path = Path(args.folder) / f"bench_scene_files{name.split()[0]}"
        stopped = path.with_name("stopped_" + path.name)
        try:
            _, write_s, write_mb = peak_mb_during(lambda: save_scene(scene, path, **options))
            _, read_s, read_mb = peak_mb_during(lambda: load_scene(path))
            size = path.stat().st_size / 1e6
            write_stop = read_stop = None
            if stops:
                write_stop = stop_latency(lambda stop: save_scene(scene, stopped, **options, should_stop=stop),
                                          write_s / 4)
                read_stop = stop_latency(lambda stop: load_scene(path, should_stop=stop), read_s / 4)
        finally:
            path.unlink(missing_ok=True)
            stopped.unlink(missing_ok=True)
        rows.append([name, f"{size:.0f}", write_s, write_stop, write_mb, read_s, read_stop, read_mb])
    print_table(f"{args.gaussians:,} Gaussians of SH degree {args.degree}",
                ["format", "MB", "write s", "stop after s", "write peak MB", "read s", "stop after s", "read peak MB"],
                rows, f"python bench/scene_files.py --gaussians {args.gaussians} --degree {args.degree}")


if __name__ == "__main__":
    main()
