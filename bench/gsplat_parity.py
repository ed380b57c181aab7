"""Parity sweep: how the triton and gsplat backends agree with the float64 references on the hard cases.

    python bench/gsplat_parity.py [--out DIR] [--large 5000000] [--speed 100000,1000000]

For every hard case of tests/raster_scenes.py (extreme but finite Gaussians: log-scales 45 and 88,
a needle, anisotropy 1e6, zero and tiny quaternions, SH 3e38, a camera inside a Gaussian, Gaussians
across the near plane, floaters 1e6 away, antialiased and blur modes) and a scene of ``--large``
random Gaussians, prints the PSNR of the renders against the brute-force float64 evaluator
(tests/raster_reference.py; the float32 reference rasterizer for the large scene) and the largest
relative gradient error against the reference rasterizer in float64, for

- ``triton`` (this project's default on CUDA: Triton compositing over the reference projection),
- ``gsplat`` (this project's backend: gsplat's compositor over the reference projection),
- ``gsplat fused`` (gsplat's own ``rasterization()`` fed as the backend fed it before: exp of the
  log-scales, unit quaternions, raw SH), to show what the backend no longer does,
- ``torch`` (the reference rasterizer in float32, the float32 floor).

With ``--speed``: forward and forward+backward milliseconds per 512x512 and 1024x1024 frame of
random scenes for ``triton`` (``render()``, which checks its inputs and waits for the intersection
count), ``triton, as the finetune renders`` (inputs checked once, tile lists sized from earlier
counts: no wait; ``common.finetune_render``), ``gsplat``, ``gsplat fused`` and ``torch``. ``--out``
gets the rows as JSON.
Needs CUDA and gsplat.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
import torch

from common import finetune_render, orbit_cameras, print_table, random_scene, timed

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from artnvg_core.cameras import normalize_quats  # noqa: E402
from artnvg_core.raster import render  # noqa: E402
from raster_scenes import (  # noqa: E402
    gradients,
    hard_cases,
    loss_weights,
    many_gaussians,
    parity,
    psnr,
    relative_error,
)


def fused_render(scene, cameras):
    """gsplat's own ``rasterization()`` as the backend called it before (rgb [C, H, W, 3], alpha)."""
    from gsplat import rasterization

    colors, alpha, _ = rasterization(
        means=scene.means, quats=normalize_quats(scene.quats), scales=torch.exp(scene.log_scales),
        opacities=torch.sigmoid(scene.opacity_logits), colors=scene.sh, viewmats=cameras.world_to_cam,
        Ks=cameras.intrinsics, width=cameras.width, height=cameras.height, near_plane=0.01,
        sh_degree=scene.sh_degree, eps2d=scene.blur_px2,
        rasterize_mode="antialiased" if scene.antialiased else "classic")
    return colors, alpha


def fused_parity(case, reference_rgb, reference_grads) -> dict:
    """``parity`` for :func:`fused_render` (the same loss, the same references)."""
    import dataclasses

    params = {k: v.cuda().detach().clone().requires_grad_(True) for k, v in case.scene.tensors().items()}
    cams = case.cameras.to("cuda")
    rgb, alpha = fused_render(dataclasses.replace(case.scene, **params), cams)
    w_rgb, w_alpha = (w.cuda().float() for w in loss_weights(case.cameras))
    ((rgb.clamp(0, 1) * w_rgb).sum() + (alpha * w_alpha).sum()).backward()
    grads = {k: (p.grad if p.grad is not None else torch.zeros_like(p)).double().cpu() for k, p in params.items()}
    return {
        "psnr": psnr(np.nan_to_num(rgb.detach().double().cpu().numpy(), nan=0.0), reference_rgb),
        "grad_error": max(relative_error(torch.nan_to_num(grads[k]), reference_grads[k]) for k in grads),
        "finite": all(bool(torch.isfinite(g).all()) for g in grads.values()),
    }


def parity_rows(large: int) -> list[list]:
    rows = []
    cases = hard_cases() + ([many_gaussians(large)] if large else [])
    for case in cases:
        ours = parity(case, "gsplat", "cuda")
        triton = parity(case, "triton", "cuda")
        floor = parity(case, "torch", "cuda")
        # the fused path against the same references parity used
        if len(case.scene) <= 10_000:
            from raster_reference import brute_force_render

            s = case.scene.to(dtype=torch.float64)
            reference_rgb = np.stack([brute_force_render(
                s.means, s.quats, s.log_scales, s.opacity_logits, s.sh, case.cameras.world_to_cam[c].double(),
                case.cameras.intrinsics[c].double(), case.cameras.width, case.cameras.height,
                blur=s.blur_px2, antialiased=s.antialiased)[0] for c in range(len(case.cameras))])
            _, reference_grads = gradients(case.scene, case.cameras, "torch", "cuda", torch.float64)
        else:
            reference_rgb, reference_grads = gradients(case.scene, case.cameras, "torch", "cuda")
        before = fused_parity(case, reference_rgb, reference_grads)
        rows.append([case.name, f"{len(case.scene):,}", triton["psnr"], triton["grad_error"], triton["finite"],
                     ours["psnr"], ours["grad_error"], ours["finite"],
                     before["psnr"], before["grad_error"], before["finite"], floor["psnr"], floor["grad_error"]])
        print(rows[-1], flush=True)
    return rows


def speed_rows(counts: list[int], sizes=(512, 1024)) -> list[list]:
    device = torch.device("cuda")
    rows = []
    for count in counts:
        scene = random_scene(count, device=device)
        for size in sizes:
            camera = orbit_cameras(1, size).to(device)
            runs = {"triton": lambda s: render(s, camera, backend="triton").rgb,
                    "triton, as the finetune renders": finetune_render(scene, camera),
                    "gsplat": lambda s: render(s, camera, backend="gsplat").rgb,
                    "gsplat fused": lambda s: fused_render(s, camera)[0],
                    "torch": lambda s: render(s, camera, backend="torch").rgb}
            for name, run in runs.items():
                params = {k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}
                trainable = scene.__class__(**params)

                def forward(run=run):
                    with torch.no_grad():
                        run(scene)

                def forward_backward(run=run, trainable=trainable):
                    run(trainable).sum().backward()

                rows.append([name, f"{count:,}", f"{size}x{size}", timed(forward, device) * 1e3,
                             timed(forward_backward, device) * 1e3])
                print(rows[-1], flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", help="folder for parity.json (and speed.json)")
    parser.add_argument("--large", type=int, default=5_000_000, help="Gaussians of the large case (0: none)")
    parser.add_argument("--speed", default="", help="comma-separated Gaussian counts to time (default: none)")
    args = parser.parse_args()
    command = "python " + " ".join(sys.argv)
    from artnvg_core.raster import prepare_backend

    prepare_backend("cuda", "gsplat", announce=print)
    rows = parity_rows(args.large)
    header = ["case", "Gaussians", "triton PSNR dB", "triton grad rel err", "triton grads finite", "gsplat PSNR dB", "gsplat grad rel err", "gsplat grads finite",
              "fused PSNR dB", "fused grad rel err", "fused grads finite", "torch f32 PSNR dB", "torch f32 grad rel err"]
    print_table("Parity on hard cases (PSNR vs float64, gradient error vs float64 reference)",
                header, rows, command)
    speed = speed_rows([int(c) for c in args.speed.split(",") if c]) if args.speed else []
    if speed:
        print_table("Speed per frame (ms)", ["path", "Gaussians", "size", "forward ms", "fwd+bwd ms"], speed, command)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        clean = [[None if isinstance(v, float) and not math.isfinite(v) else v for v in row] for row in rows]
        (out / "parity.json").write_text(json.dumps({"header": header, "rows": clean, "command": command}, indent=1))
        if speed:
            (out / "speed.json").write_text(json.dumps({"rows": speed, "command": command}, indent=1))


if __name__ == "__main__":
    main()
