"""Rasterizer benchmark: time, memory and accuracy of each backend.

    python bench/raster.py [--device cpu|cuda] [--sizes 512,1024] [--counts 100000,1000000]

Speed: forward and forward+backward time per frame (median of 5 after 2 warm-ups,
synchronised on CUDA) and peak CUDA memory, on random scenes viewed from an orbit.
Accuracy: each backend against the float64 brute-force evaluator (tests/raster_reference.py)
on a small random scene, max abs error and PSNR of the images.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

from common import orbit_cameras, peak_memory, print_table, random_scene, timed

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from artnvg_core.raster import render  # noqa: E402
from artnvg_core.raster.gsplat_backend import gsplat_available  # noqa: E402
from artnvg_core.scene import GaussianScene  # noqa: E402
from raster_reference import brute_force_render  # noqa: E402


def backends_for(device: torch.device) -> list[str]:
    return ["torch", "gsplat"] if device.type == "cuda" and gsplat_available() else ["torch"]


def speed_rows(device, sizes, counts):
    rows = []
    for count in counts:
        scene = random_scene(count, device=device)
        params = {k: v.clone().requires_grad_(True) for k, v in scene.tensors().items()}
        trainable = GaussianScene(**params)
        for size in sizes:
            camera = orbit_cameras(1, size).to(device)
            for backend in backends_for(device):
                def forward():
                    with torch.no_grad():
                        render(scene, camera, backend=backend)

                def forward_backward():
                    render(trainable, camera, backend=backend).rgb.sum().backward()

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--sizes", default="512,1024")
    parser.add_argument("--counts", default="100000,1000000")
    args = parser.parse_args()
    device = torch.device(args.device)
    sizes = [int(s) for s in args.sizes.split(",")]
    counts = [int(c) for c in args.counts.split(",")]
    command = "python " + " ".join(sys.argv)
    accuracy = accuracy_rows(device)
    speed = speed_rows(device, sizes, counts)
    print_table("Rasterizer accuracy against the float64 brute-force evaluator",
                ["backend", "device", "Gaussians", "size", "max abs error", "PSNR dB"], accuracy, command)
    print_table("Rasterizer speed per frame",
                ["backend", "device", "Gaussians", "size", "forward ms", "fwd+bwd ms", "peak GiB fwd", "peak GiB fwd+bwd"],
                speed, command)


if __name__ == "__main__":
    main()
