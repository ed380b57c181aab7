"""Big scenes on the CPU reference backend: load, render and finetune N Gaussians at 512x512.

    python bench/big_scene.py [--gaussians 5000000] [--size 512] [--iters 3] [--shared ../shared/data]

The scene is the shared bear (100k Gaussians, SH degree 3) replicated by jittering: each copy's
means moved by a normal draw of the Gaussian's own scales, every scale divided by the cube
root of the copy count (the same volume filled by more, smaller Gaussians, as denser captures
are). It is written as an INRIA PLY in a temporary folder and read back with ``load_scene``.
Cameras come from the scene alone (``orbit_cameras``: 4 views). Steps, in one process:
load, the orbit cameras, one 512x512 render without gradients (median of 2), and the
finetune (L1 + SSIM + NNFM toward stylized targets; appearance, the default, and ``all``):
seconds per iteration after the first. Peak memory is the process's resident set (sampled
every 20 ms) during each step; "RSS after" what it holds when the step ends.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import torch

from common import print_table

from artnvg_core.orbit import orbit_cameras
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.formats import load_scene, save_scene
from artnvg_core.images import load_image
from artnvg_core.raster import render
from artnvg_core.scene import GaussianScene
from artnvg_core.stylize import DemoInputs


def resident_gib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 2**20
    return float("nan")


class PeakRSS:
    """Context manager: the largest resident set (GiB) seen while the block runs."""

    def __enter__(self):
        self.peak, self.running = resident_gib(), True
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()
        self.start = time.perf_counter()
        return self

    def _sample(self):
        while self.running:
            self.peak = max(self.peak, resident_gib())
            time.sleep(0.02)

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.start
        self.running = False
        self.thread.join()
        self.peak = max(self.peak, resident_gib())


def replicated(scene: GaussianScene, count: int, seed: int = 0) -> GaussianScene:
    """``count`` Gaussians: jittered copies of ``scene`` (module docstring)."""
    copies = math.ceil(count / len(scene))
    g = torch.Generator().manual_seed(seed)
    index = torch.arange(count) % len(scene)
    scales = scene.log_scales[index].exp()
    means = scene.means[index] + torch.randn(count, 3, generator=g) * scales
    return GaussianScene(means, scene.quats[index], scene.log_scales[index] - math.log(copies) / 3,
                         scene.opacity_logits[index], scene.sh[index])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, default=5_000_000)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--iters", type=int, default=3, help="finetune iterations per mode (the first is not timed)")
    parser.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    args = parser.parse_args()
    torch.manual_seed(0)
    rows = []

    def add(row: list[str]) -> None:  # printed at once too: a long run shows its steps as they finish
        rows.append(row)
        print(" | ".join(row), flush=True)

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "big.ply"
        with PeakRSS() as step:
            big = replicated(load_scene(Path(args.shared) / "scenes" / "bear" / "scene.ply"), args.gaussians)
            save_scene(big, path)
            del big
        size_gib = path.stat().st_size / 2**30
        add(["synthesize + write PLY (not a user step)", f"{step.seconds:.1f} s", f"{step.peak:.2f}", f"{resident_gib():.2f}"])

        with PeakRSS() as step:
            scene = load_scene(path)
        add([f"load_scene ({len(scene):,} Gaussians, {size_gib:.2f} GiB PLY)", f"{step.seconds:.1f} s",
                     f"{step.peak:.2f}", f"{resident_gib():.2f}"])

    with PeakRSS() as step:
        cameras = orbit_cameras(scene, 4, width=args.size, height=args.size)
    add(["orbit_cameras (4 views)", f"{step.seconds:.1f} s", f"{step.peak:.2f}", f"{resident_gib():.2f}"])

    times = []
    with PeakRSS() as step, torch.no_grad():
        for view in range(2):
            start = time.perf_counter()
            out = render(scene, cameras.subset([view]), backend="torch")
            times.append(time.perf_counter() - start)
    coverage = float(out.alpha.mean())
    add([f"render {args.size}x{args.size}, no grad (alpha coverage {coverage:.2f})",
                 f"{statistics.median(times):.1f} s / view", f"{step.peak:.2f}", f"{resident_gib():.2f}"])
    with torch.no_grad():
        stylized = render(scene, cameras, backend="torch").rgb.clamp(0, 1).flip(-1)  # colour-swapped targets
    style = load_image(DemoInputs().style)

    for optimize in ("appearance", "all"):
        stamps = []
        config = FinetuneConfig(iterations=args.iters, optimize=optimize, backend="torch")
        with PeakRSS() as step:
            finetune(scene, cameras, style, stylized=stylized, config=config,
                     progress=lambda *_: stamps.append(time.perf_counter()))
        per_iteration = statistics.median(b - a for a, b in zip(stamps, stamps[1:])) if len(stamps) > 1 else float("nan")
        add([f"finetune {args.size}x{args.size}, optimize={optimize!r}, L1+SSIM+NNFM",
                     f"{per_iteration:.1f} s / it", f"{step.peak:.2f}", f"{resident_gib():.2f}"])

    print_table(f"Big scene on the CPU reference backend ({args.gaussians:,} Gaussians)",
                ["step", "time", "peak RSS GiB", "RSS after GiB"], rows, "python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
