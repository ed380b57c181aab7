"""What the strength dial and a region cost, and what a region keeps: two tables and the seam's pictures.

    cd bench && python region.py [--shared ../../shared/data] [--scene bear] [--style starry]
        [--region sphere:0.823,0.238,-1.130,1.2] [--iters 100] [--scale 0.25] [--every 1] [--gaussians 1000000] [--out DIR]

* **Blend**: :func:`artnvg_core.blend.blend` of a ``--gaussians`` scene (SH degree 3) with a stylized copy (every
  SH band and opacity changed), geometry unchanged (an appearance finetune) and moved (``optimize="all"``), whole
  and in a selection of half the Gaussians: the median of 5 calls after one warm-up, on the CPU, wall time and
  the process's CPU time (on a machine shared with other jobs, the CPU time is what the blend itself costs).
* **Region finetune**: the NNFM stylizer (:func:`artnvg_core.stylize.stylize_nnfm`, ARF's colour transfer) of the
  scene's capture views (every ``--every``-th) at ``--scale``, ``--iters`` steps, the whole scene and ``--region`` alone: the time of the
  call; on every view, the PSNR against the original's renders of the pixels the region covers less than 1e-3 of
  (:func:`artnvg_core.selection.coverage`: the unselected Gaussians' own pixels), and the mean/covariance colour
  distance to the style (``metrics.color``) of the pixels it covers half or more of, before and after.
* Pictures in ``--out``: for three views, original | whole-scene run | region run | region blended at 0.5.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from pathlib import Path

import torch

from common import print_table, psnr, random_scene  # puts the repository on sys.path
from artnvg_core.blend import blend
from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig
from artnvg_core.formats import load_scene
from artnvg_core.images import load_image, save_png
from artnvg_core.metrics.color import mean_cov_distance
from artnvg_core.preview import side_by_side
from artnvg_core.raster.views import render_views
from artnvg_core.selection import coverage, parse_region, select_region
from artnvg_core.stylize import stylize_nnfm


def _median_times(fn, repeats: int = 5) -> tuple[float, float]:
    """Median (wall, process CPU) seconds of ``fn()`` after one warm-up call."""
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return statistics.median(walls), statistics.median(cpus)


def blend_table(count: int) -> None:
    original = random_scene(count, degree=3)
    stylized = dataclasses.replace(original, sh=original.sh + 0.1, opacity_logits=original.opacity_logits - 0.5)
    moved = dataclasses.replace(stylized, means=original.means + 1e-3, log_scales=original.log_scales + 0.01,
                                quats=original.quats * 1.01)
    half = torch.arange(count) % 2 == 0
    rows = []
    for name, other, selection in (("appearance changed", stylized, None), ("geometry moved too", moved, None),
                                   ("appearance changed, half the Gaussians selected", stylized, half)):
        wall, cpu = _median_times(lambda: blend(original, other, 0.5, selection))
        rows.append([name, wall * 1000, cpu * 1000])
    print_table(f"Blend of {count:,} Gaussians (SH degree 3), CPU, {torch.get_num_threads()} torch threads",
                ["scenes", "wall ms (median of 5)", "process CPU ms"], rows,
                f"cd bench && python region.py --gaussians {count}")


def region_table(args) -> None:
    folder = Path(args.shared) / "scenes" / args.scene
    scene, cameras = load_scene(folder / "scene.ply"), load_cameras(folder).scaled(args.scale)
    cameras = cameras.subset(list(range(0, len(cameras), args.every)))
    style = load_image(next((Path(args.shared) / "styles").glob(f"{args.style}.*")))
    selection = select_region(scene, parse_region(args.region))
    covered = coverage(scene, selection, cameras)
    outside, inside = covered < 1e-3, covered >= 0.5

    def renders(s):
        with torch.no_grad():
            return render_views(s, cameras, chunk=1).rgb.clamp(0, 1)

    before = renders(scene)
    config = FinetuneConfig(iterations=args.iters)
    print(f"\n{args.scene}: {len(scene):,} Gaussians, {len(cameras)} views at {cameras.width}x{cameras.height}, "
          f"{args.iters} iterations; region {args.region}: {int(selection.sum()):,} Gaussians; "
          f"{int(outside.sum()):,} pixels it covers < 1e-3, {int(inside.sum()):,} >= 0.5")
    print("| run | s | PSNR outside (dB) | colour distance inside |\n|---|---|---|---|")
    print(f"| original | | | {mean_cov_distance(before[inside], style):.3f} |")
    results = {}
    for name, chosen in (("whole scene", None), ("region", selection)):
        start = time.perf_counter()
        results[name] = stylize_nnfm(scene, cameras, style, config, selection=chosen)
        elapsed = time.perf_counter() - start
        after = renders(results[name])
        print(f"| {name} | {elapsed:.0f} | {psnr(after[outside], before[outside]):.1f} | "
              f"{mean_cov_distance(after[inside], style):.3f} |", flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    half = blend(scene, results["region"], 0.5, selection)
    views = [0, len(cameras) // 3, 2 * len(cameras) // 3]
    shown = (scene, results["whole scene"], results["region"], half)
    rows = [side_by_side(torch.stack([renders_of(s, cameras, v) for s in shown])) for v in views]
    save_png(torch.cat(rows), out / f"{args.scene}_region_seam.png")
    print(f"wrote {out / f'{args.scene}_region_seam.png'} (views {views}: original | whole | region | region at 0.5)")


def renders_of(scene, cameras, view: int) -> torch.Tensor:
    with torch.no_grad():
        return render_views(scene, cameras.subset([view]), chunk=1).rgb[0].clamp(0, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shared", default="../../shared/data")
    parser.add_argument("--scene", default="bear")
    parser.add_argument("--style", default="starry")
    parser.add_argument("--region", default="sphere:0.823,0.238,-1.130,1.2")
    parser.add_argument("--iters", type=int, default=100)
    parser.add_argument("--scale", type=float, default=0.25)
    parser.add_argument("--every", type=int, default=1, help="every N-th capture view (default 1: all)")
    parser.add_argument("--gaussians", type=int, default=1_000_000)
    parser.add_argument("--out", default="region_out")
    parser.add_argument("--skip-blend", action="store_true")
    args = parser.parse_args()
    if not args.skip_blend:
        blend_table(args.gaussians)
    region_table(args)


if __name__ == "__main__":
    main()
