"""Rasterizer benchmark: time, memory and accuracy of each backend.

    python bench/raster.py [--device cpu|cuda] [--sizes 512,1024] [--counts 100000,1000000]
                           [--stages 1000000] [--first-use] [--rounds 20]

Speed: forward and forward+backward time per frame (median of 5 after 1 warm-up,
synchronised on CUDA) and peak CUDA memory, on random scenes viewed from an orbit, for the
backends (torch, triton and, where installed, gsplat), triton as the finetune renders (inputs checked
once, no wait: ``common.finetune_render``) and gsplat's own fused ``rasterization()``.
Accuracy: each backend against the float64 brute-force evaluator (tests/raster_reference.py)
on a small random scene, max abs error and PSNR of the images.
``--stages N``: where the triton backend's time goes for N Gaussians at the largest size (the
fused projection + colours against the reference ones, tile lists, compositing; each timed alone).
``--rounds N``: the Triton paths against gsplat fused (CUDA, forward+backward, the largest size), alternating
N rounds (each a median of 5 after 1 warm-up, the paths' order rotating): the run-to-run spread of a frame of a
few milliseconds is larger than the gaps between the paths, so the ratio is taken within each round.
``--first-use``: each step of the first Triton render (forward+backward: projection, tile lists,
compositing, backward kernels) in a fresh process with an empty Triton cache, then of the second (CUDA).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

import numpy as np
import torch

from common import finetune_render, orbit_cameras, peak_memory, print_table, random_scene, timed
from gsplat_parity import fused_render

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from artnvg_core.raster import render  # noqa: E402
from artnvg_core.raster.gsplat_backend import gsplat_available  # noqa: E402
from artnvg_core.scene import GaussianScene  # noqa: E402
from raster_reference import brute_force_render  # noqa: E402


def backends_for(device: torch.device) -> list[str]:
    if device.type != "cuda":
        return ["torch"]
    return ["torch", "triton"] + (["gsplat"] if gsplat_available() else [])


def render_paths(scene, camera, backends):
    """{path name: render closure (a scene -> rgb [1, H, W, 3])}: ``backends`` through ``render()``, triton as the
    finetune renders, gsplat fused where installed (CUDA)."""
    paths = {name: (lambda s, name=name: render(s, camera, backend=name).rgb) for name in backends}
    if "triton" in paths:
        paths["triton, as the finetune renders"] = finetune_render(scene, camera)
    if camera.world_to_cam.device.type == "cuda" and gsplat_available():
        paths["gsplat fused"] = lambda s: fused_render(s, camera)[0]
    return paths


def paired_rows(device, size, counts, rounds):
    """Forward+backward ms of the Triton paths and gsplat fused, alternating ``rounds`` rounds (each path a median
    of 5 after 1 warm-up per round, the order rotating): per path the median, min and max over the rounds, and its
    ratio to fused within each round (median, max, and the rounds it was at or under fused)."""
    rows = []
    for count in counts:
        scene = random_scene(count, device=device)
        trainable = GaussianScene(**{k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()})
        paths = render_paths(scene, orbit_cameras(1, size).to(device), ["triton"])
        if "gsplat fused" not in paths:
            raise SystemExit("--rounds compares with gsplat fused: it needs CUDA and gsplat")
        names = list(paths)
        times = {name: [] for name in names}
        for r in range(rounds):
            for name in names[r % len(names):] + names[:r % len(names)]:
                times[name].append(timed(lambda: paths[name](trainable).sum().backward(), device, repeats=5, warmup=1))
        for name in names:
            ratios = [t / f for t, f in zip(times[name], times["gsplat fused"])]
            rows.append([name, f"{count:,}", f"{size}x{size}", rounds, statistics.median(times[name]) * 1e3,
                         min(times[name]) * 1e3, max(times[name]) * 1e3, statistics.median(ratios), max(ratios),
                         f"{sum(x <= 1 for x in ratios)}/{rounds}"])
            print(rows[-1], flush=True)
    return rows


def speed_rows(device, sizes, counts):
    rows = []
    for count in counts:
        scene = random_scene(count, device=device)
        params = {k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}
        trainable = GaussianScene(**params)
        for size in sizes:
            camera = orbit_cameras(1, size).to(device)
            paths = render_paths(scene, camera, backends_for(device))
            for backend, run in paths.items():
                def forward(run=run):
                    with torch.no_grad():
                        run(scene)

                def forward_backward(run=run):
                    run(trainable).sum().backward()

                repeats = 5 if device.type == "cuda" else 2
                fwd = timed(forward, device, repeats=repeats, warmup=1)
                both = timed(forward_backward, device, repeats=repeats, warmup=1)
                rows.append([backend, str(device), f"{count:,}", f"{size}x{size}", fwd * 1e3, both * 1e3,
                             peak_memory(forward, device), peak_memory(forward_backward, device)])
                print(rows[-1], flush=True)
    return rows


def accuracy_rows(device, count=2000, size=128):
    scene = random_scene(count, seed=1, device=device)
    cameras = orbit_cameras(2, size).to(device)
    s64 = scene.to("cpu", torch.float64)
    references = [
        brute_force_render(s64.means, s64.quats, s64.log_scales, s64.opacity_logits, s64.sh,
                           cameras.world_to_cam[c].cpu(), cameras.intrinsics[c].cpu(), size, size)[0]
        for c in range(len(cameras))
    ]
    rows = []
    for backend in backends_for(device):
        with torch.no_grad():
            images = render(scene, cameras, backend=backend).rgb.double().cpu().numpy()
        errors = [np.abs(images[c] - references[c]).max() for c in range(len(cameras))]
        mse = np.mean([((images[c] - references[c]) ** 2).mean() for c in range(len(cameras))])
        rows.append([backend, str(device), f"{count:,}", f"{size}x{size}", float(max(errors)),
                     float(-10 * math.log10(max(mse, 1e-30)))])
    return rows


def stage_rows(device, count, size):
    """Milliseconds of each stage of the triton backend, each timed alone, and the whole render; the
    reference projection + colours (what the backend used before its fused kernels) for comparison."""
    from artnvg_core.raster.projection import project
    from artnvg_core.raster.sh import sh_to_color
    from artnvg_core.raster.triton_backend import rasterize_triton
    from artnvg_core.raster.triton_tiles import tile_lists
    from artnvg_core.raster.triton_projection import project_color_triton

    scene = random_scene(count, device=device)
    camera = orbit_cameras(1, size).to(device)
    params = {k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}
    w2c, k, center = camera.world_to_cam[0], camera.intrinsics[0], camera.centers[0]
    fields = ("means", "quats", "log_scales", "opacity_logits", "sh")

    def fused(p=params):
        return project_color_triton(*(p[f] for f in fields), w2c, k, center, size, size, scene.sh_degree)

    def reference(p=params):
        proj = project(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], w2c, k, size, size)
        return proj, sh_to_color(p["sh"][proj.index], p["means"][proj.index] - center, scene.sh_degree)

    def outputs_sum(result):
        proj, colors = result
        return proj.means2d.sum() + proj.conics.sum() + proj.opacities.sum() + colors.sum()

    proj, feats = fused()
    detached = proj.__class__(**{name: v.detach() for name, v in vars(proj).items()})
    feats = feats.detach()
    ids, _ = tile_lists(detached, size, size)
    leaf = [x.clone().requires_grad_(True) for x in (detached.means2d, detached.conics, detached.opacities, feats)]
    leaf_proj = detached.__class__(**{**vars(detached), "means2d": leaf[0], "conics": leaf[1], "opacities": leaf[2]})
    grad_sum = lambda x: sum(t.sum() for t in x) if isinstance(x, tuple) else x.sum()  # noqa: E731
    stages = {
        "reference projection + colours (before)": (reference, lambda: outputs_sum(reference()).backward()),
        "fused projection + colours": (fused, lambda: outputs_sum(fused()).backward()),
        "tile lists (sort)": (lambda: tile_lists(detached, size, size), None),
        "compositing": (lambda: rasterize_triton(detached, feats, size, size),
                        lambda: grad_sum(rasterize_triton(leaf_proj, leaf[3], size, size)).backward()),
        "whole render": (lambda: render(scene, camera, backend="triton"),
                         lambda: render(GaussianScene(**params), camera, backend="triton").rgb.sum().backward()),
    }
    rows = []
    for name, (fwd, both) in stages.items():
        with torch.no_grad():
            forward_ms = timed(fwd, device) * 1e3
        rows.append([name, f"{count:,}", f"{size}x{size}", forward_ms, timed(both, device) * 1e3 if both else None])
        print(rows[-1], flush=True)
    rows.append(["(intersections)", f"{len(ids):,}", "", None, None])
    return rows


FIRST_USE = """
import time, torch, sys
sys.path.insert(0, {bench!r})
from common import orbit_cameras, random_scene
from artnvg_core.raster.triton_backend import rasterize_triton
from artnvg_core.raster.triton_tiles import tile_lists
from artnvg_core.raster.triton_projection import project_color_triton
torch.zeros(1, device="cuda")
scene = random_scene(10000, device="cuda")
camera = orbit_cameras(1, 256).to("cuda")
for _ in range(2):
    p = {{k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}}
    seconds = []
    def step(fn):
        torch.cuda.synchronize(); start = time.perf_counter(); result = fn(); torch.cuda.synchronize()
        seconds.append(time.perf_counter() - start)
        return result
    proj, colors = step(lambda: project_color_triton(p["means"], p["quats"], p["log_scales"], p["opacity_logits"],
                        p["sh"], camera.world_to_cam[0], camera.intrinsics[0], camera.centers[0], 256, 256, 3))
    step(lambda: tile_lists(proj, 256, 256))
    out, trans = step(lambda: rasterize_triton(proj, colors, 256, 256))
    step(lambda: (out.sum() + trans.sum()).backward())
    print(" ".join(f"{{s:.4f}}" for s in seconds))
"""
FIRST_USE_STEPS = ["projection forward", "tile lists", "compositing forward (+ tile lists)",
                   "backward (compositing + projection)"]


def first_use_rows():
    """Seconds of each step of the first triton render (forward+backward: the fused projection, the
    tile lists, the compositing, the backward kernels) in a fresh process with an empty Triton cache
    (the kernels' JIT compilation), and of the second render's."""
    import os
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, TRITON_CACHE_DIR=cache)
        env.pop("TRITON_INTERPRET", None)
        code = FIRST_USE.format(bench=str(Path(__file__).resolve().parent))
        lines = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True,
                               text=True).stdout.splitlines()[-2:]
    first, second = ([float(x) for x in line.split()] for line in lines)
    rows = [["triton", step, a, b] for step, a, b in zip(FIRST_USE_STEPS, first, second)]
    return rows + [["triton", "whole render", sum(first), sum(second)]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--sizes", default="512,1024")
    parser.add_argument("--counts", default="100000,1000000")
    parser.add_argument("--stages", type=int, default=0, help="Gaussians of the stage breakdown (0: none)")
    parser.add_argument("--first-use", action="store_true", help="time the first Triton render (CUDA)")
    parser.add_argument("--rounds", type=int, default=0,
                        help="alternate the Triton paths and gsplat fused this many rounds (CUDA; 0: not)")
    args = parser.parse_args()
    device = torch.device(args.device)
    sizes = [int(s) for s in args.sizes.split(",")]
    counts = [int(c) for c in args.counts.split(",") if c]
    command = "python " + " ".join(sys.argv)
    first = first_use_rows() if args.first_use else []
    accuracy = accuracy_rows(device)
    stages = stage_rows(device, args.stages, max(sizes)) if args.stages else []
    speed = speed_rows(device, sizes, counts) if counts else []
    paired = paired_rows(device, max(sizes), counts, args.rounds) if args.rounds else []
    print_table("Rasterizer accuracy against the float64 brute-force evaluator",
                ["backend", "device", "Gaussians", "size", "max abs error", "PSNR dB"], accuracy, command)
    if speed:
        print_table("Rasterizer speed per frame",
                    ["backend", "device", "Gaussians", "size", "forward ms", "fwd+bwd ms", "peak GiB fwd",
                     "peak GiB fwd+bwd"], speed, command)
    if paired:
        print_table(f"Forward+backward, {args.rounds} alternating rounds",
                    ["path", "Gaussians", "size", "rounds", "median ms", "min ms", "max ms", "ratio to fused (median)",
                     "ratio (max)", "rounds at or under fused"], paired, command)
    if stages:
        print_table("Triton backend: time per stage (each timed alone)",
                    ["stage", "Gaussians", "size", "forward ms", "fwd+bwd ms"], stages, command)
    if first:
        print_table("First use in a fresh process, empty Triton cache (JIT compilation)",
                    ["backend", "step", "first render s", "second render s"], first, command)


if __name__ == "__main__":
    main()
