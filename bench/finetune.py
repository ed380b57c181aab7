"""Finetune benchmark: iterations per second of the Gaussian finetuning loop.

    python bench/finetune.py [--device cpu|cuda] [--iters N] [--shared ../shared/data]

Cases: the bundled demo scene (128x128); on CUDA also the bear scene at 512x512 and
1024x1024 (cameras scaled x2; when ``--shared`` holds it) and a random 1M-Gaussian scene at 1024x1024, with each
available backend, without stylized views (NNFM + content term, the NNFM-only stylizer) and
with random ones (L1 + SSIM + NNFM, the ArtNVG finetune), the VGG terms at ARF's resolution
(the default ``nnfm_max_side`` 512) and, at 1024, at full resolution; and the NNFM term alone
(VGG forward+backward + matching) per size. The style image is the demo style resized (area /
bilinear) to half the render's long side, as ARF sizes it. Time per iteration is the median gap
between progress callbacks after 3 warm-up steps.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import statistics
import sys
import time
from pathlib import Path

import torch

from common import orbit_cameras, print_table, random_scene, timed

from artnvg_core.cameras import load_cameras
from artnvg_core.fileio import load_image, resize_image
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.formats import read_ply
from artnvg_core.losses import NNFMLoss, load_vgg, style_image_features
from artnvg_core.raster.gsplat_backend import gsplat_available
from artnvg_core.stylize import DemoInputs


def seconds_per_iteration(scene, cameras, style, config: FinetuneConfig, targets: bool, device) -> float:
    stamps = []
    stylized = torch.rand(len(cameras), cameras.height, cameras.width, 3, device=device) if targets else None
    config = dataclasses.replace(config, iterations=config.iterations + 3)
    finetune(scene, cameras, style, stylized=stylized, config=config,
             progress=lambda *_: (torch.cuda.synchronize(device) if device.type == "cuda" else None,
                                  stamps.append(time.perf_counter())))
    return statistics.median(b - a for a, b in zip(stamps[3:], stamps[4:]))


def resized_style(style: torch.Tensor, side: int) -> torch.Tensor:
    """``style [H, W, 3]`` resized so that its long side is ``side`` (ARF: half the render's long side)."""
    factor = side / max(style.shape[:2])
    return resize_image(style, round(style.shape[0] * factor), round(style.shape[1] * factor))


def nnfm_seconds(size: int, style, device) -> float:
    vgg = load_vgg("vgg19", device=device)
    layers = ("relu3_1", "relu3_2", "relu3_3")
    style = resized_style(style, size).permute(2, 0, 1)[None].to(device)
    loss = NNFMLoss(style_image_features(vgg, style, layers, None), layer_groups=(layers,))
    image = torch.rand(1, 3, size, size, device=device, requires_grad=True)
    return timed(lambda: loss(vgg(image, layers)).backward(), device)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    args = parser.parse_args()
    device = torch.device(args.device)
    demo = DemoInputs()
    style = load_image(demo.style).to(device)
    backends = ["gsplat", "torch"] if device.type == "cuda" and gsplat_available() else ["torch"]
    cases = [("demo (40k)", read_ply(demo.scene), load_cameras(demo.cameras).scaled(0.25))]
    if device.type == "cuda":
        bear = Path(args.shared) / "scenes" / "bear"
        if bear.is_dir():
            scene, cams = read_ply(bear / "scene.ply"), load_cameras(bear / "transforms.json")
            cases += [("bear (100k)", scene, cams), ("bear (100k)", scene, cams.scaled(2.0))]
        else:
            print(f"no bear scene at {bear}: its cases are left out", flush=True)
        cases += [("random (1M)", random_scene(1_000_000), orbit_cameras(16, 1024))]
    rows = []
    for name, scene, cams in cases:
        sides = [512, None] if cams.width >= 1024 else [512]
        combos = itertools.product(backends, (False, True), sides)
        for backend, targets, side in [c for c in combos if c[0] == backends[0] or c[1:] == (False, 512)]:
            config = FinetuneConfig(iterations=args.iters, backend=backend, nnfm_max_side=side)
            arf_style = resized_style(style, max(cams.width, cams.height) // 2)
            sec = seconds_per_iteration(scene.to(device), cams, arf_style, config, targets, device)
            rows.append([name, backend, f"{cams.width}x{cams.height}", "L1+SSIM+NNFM" if targets else "NNFM+content",
                         side or "full", sec * 1e3, sec * 1000 / 60])
            print(rows[-1], flush=True)
    nnfm_rows = [[f"{size}x{size}", nnfm_seconds(size, style, device) * 1e3] for size in
                 ((128, 512, 1024) if device.type == "cuda" else (128,))]
    command = "python " + " ".join(sys.argv)
    print_table(f"Finetune speed ({device})", ["scene", "backend", "size", "loss", "VGG terms' max side",
                                                "ms / iteration", "min per 1,000 it"], rows, command)
    print_table(f"NNFM term alone ({device}: VGG19 relu3 forward+backward + matching, style of the same size)",
                ["size", "ms"], nnfm_rows, command)


if __name__ == "__main__":
    main()
