"""The Triton compositing kernels' settings: time and deviation of each, and where a render's time goes.

    cd bench && python raster_kernels.py [--counts 100000,1000000] [--size 1024] [--profile] [--lists-only]

For each random scene (``common.random_scene``, one orbit camera, the fused projection done once):

- tile lists: each step of ``triton_tiles.tile_lists`` alone (depth order, counting, writing, the
  stable sort by 16-bit and by 32-bit tile keys, the gather, the offsets), the intersections and the
  footprint boxes' tiles (what the lists were before tiles out of a Gaussian's reach were left out);
- the forward kernel for each ``triton_backend.Pass`` (pixel rows per program, Gaussians per block,
  warps) with and without block skipping, and the backward kernel alone (the same forward's graph
  replayed) for each; beside each, the largest deviation of its outputs (blended features,
  transmittance, every gradient) from the shipped settings (``triton_backend.PASSES``), relative to
  the largest magnitude, and the largest relative L2 error of the same against the reference
  compositor in float64 on the same projection; last, the five fastest settings of each kernel.

``--lists-only``: the tile lists alone. ``--profile``: the CUDA kernels of one whole render
forward+backward by total time (torch.profiler), for ``render()``, the finetune's path
(``common.finetune_render``) and, where installed, gsplat's fused ``rasterization()``, each with the sum of
its kernels' times beside its time from CUDA events (the difference: the GPU waiting for the host).
Medians of 10 after 3 warm-ups, CUDA events. Needs CUDA.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys

import torch

from common import finetune_render, orbit_cameras, print_table, random_scene, timed
from gsplat_parity import fused_render

from artnvg_core.raster import render
from artnvg_core.raster.gsplat_backend import gsplat_available
from artnvg_core.raster.torch_backend import rasterize
from artnvg_core.raster.triton_backend import PASSES, Pass, _Composite
from artnvg_core.raster.triton_tiles import TILE, _count_tiles, _write_pairs, tile_lists
from artnvg_core.raster.triton_projection import project_color_triton
from artnvg_core.scene import GaussianScene

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def projected(count: int, size: int):
    """A random scene's fused projection (detached) and colours + depth features on one camera."""
    scene = random_scene(count, device="cuda")
    camera = orbit_cameras(1, size).to("cuda")
    proj, colors = project_color_triton(*(getattr(scene, f) for f in FIELDS), camera.world_to_cam[0],
                                        camera.intrinsics[0], camera.centers[0], size, size, scene.sh_degree)
    proj = proj.__class__(**{k: v.detach() for k, v in vars(proj).items()})
    return scene, camera, proj, torch.cat([colors.detach(), proj.depths[:, None]], 1).contiguous()


def tile_list_rows(name, proj, size):
    """Milliseconds of each step of tile_lists (as it runs them) and of the whole."""
    tiles_x = -(-size // TILE)
    by_depth = torch.argsort(proj.depths, stable=True)
    ends = torch.cumsum(_count_tiles(proj, by_depth, tiles_x, tiles_x, TILE), 0)
    total = int(ends[-1])
    tile16, ids = _write_pairs(proj, by_depth, ends, total, tiles_x, tiles_x, TILE, torch.int16)
    tile32 = tile16.int()
    sorted16, order = torch.sort(tile16, stable=True)
    steps = {
        "depth order (argsort)": lambda: torch.argsort(proj.depths, stable=True),
        "count + cumsum + size": lambda: int(torch.cumsum(_count_tiles(proj, by_depth, tiles_x, tiles_x, TILE), 0)[-1]),
        "write pairs": lambda: _write_pairs(proj, by_depth, ends, total, tiles_x, tiles_x, TILE, torch.int16),
        "stable sort, 16-bit keys (shipped)": lambda: torch.sort(tile16, stable=True),
        "stable sort, 32-bit keys": lambda: torch.sort(tile32, stable=True),
        "gather ids": lambda: ids[order],
        "offsets (searchsorted)": lambda: torch.searchsorted(
            sorted16, torch.arange(tiles_x * tiles_x + 1, device="cuda", dtype=torch.int16), out_int32=True),
        "whole tile_lists": lambda: tile_lists(proj, size, size),
    }
    rows = [[name, step, timed(fn, torch.device("cuda"), repeats=10, warmup=3) * 1e3] for step, fn in steps.items()]
    box = int(((proj.radii[:, 0] >= 0) * _box_tiles(proj, size)).sum())
    rows.append([name, f"({total:,} intersections; footprint boxes: {box:,})", None])
    return rows


def _box_tiles(proj, size):
    """Tiles of each footprint's box (the reference's lists)."""
    radii = proj.radii.double()
    tiles = -(-size // TILE)
    lo = torch.floor((proj.means2d.double() - radii) / TILE).clamp(0, tiles)
    hi = torch.ceil((proj.means2d.double() + radii) / TILE).clamp(0, tiles)
    return (hi - lo).prod(-1).long()


def composite(proj, feats, lists, size, passes, skip, grads):
    """Outputs and the gradients by means2d, conics, opacities, features of a linear loss with
    weights ``grads``; a closure replaying the backward alone."""
    leaves = [x.clone().requires_grad_(True) for x in (proj.means2d, proj.conics, proj.opacities, feats)]
    out, trans = _Composite.apply(*leaves, *lists, size, size, TILE, passes, skip)
    loss = (out * grads[0]).sum() + (trans * grads[1]).sum()
    backward = lambda: torch.autograd.grad(loss, leaves, retain_graph=True)  # noqa: E731
    return [out.detach(), trans.detach(), *backward()], backward


def deviation(got, shipped) -> float:
    return max(float((a - b).abs().max() / b.abs().max().clamp_min(1e-30)) for a, b in zip(got, shipped))


SETTINGS = [Pass(rows, chunk, warps) for rows, chunk, warps in itertools.product((2, 4, 8, 16), (4, 8, 16, 32), (1, 2, 4, 8))
            if 4 * 32 * warps <= 16 * rows * chunk <= 32 * 32 * warps]  # 4 to 32 pixel-Gaussian pairs per thread


def float64_reference(proj, feats, size, grads):
    """The reference compositor (torch backend) in float64 on the same projection: outputs and
    gradients as :func:`composite` returns them (zero gradients for culled rows)."""
    keep = proj.radii[:, 0] >= 0
    leaves = [x[keep].double().requires_grad_(True) for x in (proj.means2d, proj.conics, proj.opacities, feats)]
    kept = dataclasses.replace(proj, means2d=leaves[0], conics=leaves[1], opacities=leaves[2],
                               depths=proj.depths[keep].double(), radii=proj.radii[keep],
                               index=torch.arange(len(leaves[0]), device="cuda"))
    out, trans = rasterize(kept, leaves[3], size, size)
    loss = (out * grads[0].double()).sum() + (trans * grads[1].double()).sum()
    result = [out.detach(), trans.detach()]
    for grad, like in zip(torch.autograd.grad(loss, leaves), (proj.means2d, proj.conics, proj.opacities, feats)):
        result.append(torch.zeros(like.shape, dtype=torch.float64, device="cuda").index_put_((keep,), grad))
    return result


def relative_l2(got, expected) -> float:
    """The largest relative L2 error over the outputs and gradients."""
    return max(float((a.double() - b).norm() / b.norm().clamp_min(1e-300)) for a, b in zip(got, expected))


def kernel_rows(name, proj, feats, size):
    lists = tile_lists(proj, size, size)
    g = torch.Generator(device="cuda").manual_seed(0)
    grads = (torch.randn(size, size, 4, device="cuda", generator=g), torch.randn(size, size, device="cuda", generator=g))
    shipped, _ = composite(proj, feats, lists, size, PASSES, True, grads)
    reference = float64_reference(proj, feats, size, grads)
    device = torch.device("cuda")
    rows = []
    for kernel, setting, skip in itertools.product(("forward", "backward"), SETTINGS, (True, False)):
        if not skip and setting.rows < TILE:
            continue  # walking every block: measured for whole-tile programs only
        passes = (setting, PASSES[1]) if kernel == "forward" else (PASSES[0], setting)
        outputs, backward = composite(proj, feats, lists, size, passes, skip, grads)
        if kernel == "forward":
            run = lambda: _Composite.apply(proj.means2d, proj.conics, proj.opacities, feats, *lists,  # noqa: E731
                                           size, size, TILE, passes, skip)
        ms = timed(run if kernel == "forward" else backward, device, repeats=10, warmup=3) * 1e3
        rows.append([name, kernel, *setting, skip, ms, deviation(outputs, shipped), relative_l2(outputs, reference)])
        print(rows[-1], flush=True)
    return rows


def render_paths(scene, camera) -> dict:
    """Closures (a scene -> rgb) of the renders compared: render(), the finetune's path and, where
    installed, gsplat's fused rasterization()."""
    paths = {"render()": lambda s: render(s, camera, backend="triton").rgb,
             "as the finetune renders": finetune_render(scene, camera)}
    if gsplat_available():
        paths["gsplat fused"] = lambda s: fused_render(s, camera)[0]
    return paths


def profile_rows(name, scene, camera, top=12):
    """The CUDA kernels of one render forward+backward on each path, by total time, then the sum of all
    its kernels and the time from CUDA events (ms per render)."""
    from torch.profiler import ProfilerActivity, profile

    params = {k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}
    rows = []
    for path, render_fn in render_paths(scene, camera).items():
        run = lambda: render_fn(GaussianScene(**params)).sum().backward()  # noqa: E731
        wall = timed(run, torch.device("cuda"), repeats=10, warmup=3) * 1e3
        torch.cuda.synchronize()
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            for _ in range(5):
                run()
            torch.cuda.synchronize()
        events = sorted(prof.key_averages(), key=lambda e: -e.device_time_total)
        rows += [[name, path, e.key[:70], e.count // 5, e.device_time_total / 5 / 1e3] for e in events[:top]]
        rows.append([name, path, "(all kernels)", sum(e.count for e in events) // 5,
                     sum(e.device_time_total for e in events) / 5 / 1e3])
        rows.append([name, path, "(CUDA events, start to end)", None, wall])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--counts", default="100000,1000000")
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--lists-only", action="store_true")
    args = parser.parse_args()
    command = "python " + " ".join(sys.argv)
    lists, kernels, profiles = [], [], []
    for count in map(int, args.counts.split(",")):
        name = f"{count:,} @ {args.size}"
        scene, camera, proj, feats = projected(count, args.size)
        lists += tile_list_rows(name, proj, args.size)
        kernels += [] if args.lists_only else kernel_rows(name, proj, feats, args.size)
        if args.profile:
            profiles += profile_rows(name, scene, camera)
    gpu = torch.cuda.get_device_name()
    if profiles:
        print_table(f"Kernels of one render forward+backward ({gpu})", ["scene", "path", "kernel", "calls", "ms"],
                    profiles, command)
    print_table(f"Tile lists, step by step ({gpu})", ["scene", "step", "ms"], lists, command)
    if args.lists_only:
        return
    print_table(f"Compositing kernels' settings ({gpu}; shipped: forward {tuple(PASSES[0])}, backward "
                f"{tuple(PASSES[1])}, skipping)", ["scene", "kernel", "rows", "chunk", "warps", "skip empty blocks", "ms",
                                                   "max deviation from shipped", "rel. L2 error vs float64"],
                kernels, command)
    for kernel in ("forward", "backward"):
        best = {}
        for row in kernels:
            if row[1] == kernel:
                best.setdefault(tuple(row[2:6]), []).append(row[6])
        ranked = sorted(best.items(), key=lambda item: sum(item[1]))[:5]
        print(f"\nfastest {kernel} (rows, chunk, warps, skip: ms per scene):",
              "; ".join(f"{k}: {', '.join(f'{v:.3f}' for v in ms)}" for k, ms in ranked))


if __name__ == "__main__":
    main()
