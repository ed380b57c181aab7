"""How far apart output scenes are: the largest parameter difference and the PSNR of their renders.

    cd bench && python scene_diff.py --cameras T.json [--views 12] A.ply:B.ply [C.ply:D.ply ...]

For each pair A:B (scenes of the same Gaussians, e.g. two ``stylize`` outputs of one scene): the largest
absolute difference over every parameter (means, quaternions, log-scales, opacity logits, SH), and the PSNR
between their renders at ``--views`` cameras of T.json spread evenly (CUDA where present). Two runs of one
program already differ (the finetune's backward adds gradients atomically, in no fixed order): compare a
change's pairs with pairs of one program run twice.
"""

from __future__ import annotations

import argparse

import torch

from common import print_table, psnr  # puts the repository on sys.path
from artnvg_core.cameras import load_cameras
from artnvg_core.formats import load_scene
from artnvg_core.preview import evenly_spaced
from artnvg_core.raster.views import render_views


def scene_diff(first, second, cameras, device: torch.device) -> tuple[float, float]:
    """(largest absolute parameter difference, renders' PSNR in dB) between the scene files ``first`` and
    ``second``."""
    scenes = [load_scene(path).to(device) for path in (first, second)]
    tensors = [scene.tensors() for scene in scenes]
    if tensors[0].keys() != tensors[1].keys() or any(tensors[0][k].shape != tensors[1][k].shape for k in tensors[0]):
        raise ValueError(f"{first} and {second} do not hold the same Gaussians (parameters or counts differ)")
    largest = max(float((tensors[0][k].double() - tensors[1][k].double()).abs().max()) for k in tensors[0])
    renders = [render_views(scene, cameras).rgb for scene in scenes]
    return largest, psnr(renders[0], renders[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("pairs", nargs="+", help="A.ply:B.ply (any scene format the library reads)")
    parser.add_argument("--cameras", required=True, help="the capture's cameras (transforms.json or COLMAP)")
    parser.add_argument("--views", type=int, default=12)
    args = parser.parse_args()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    cameras = load_cameras(args.cameras)
    cameras = cameras.subset(evenly_spaced(len(cameras), args.views))
    rows = []
    for pair in args.pairs:
        first, sep, second = pair.rpartition(":")
        if not sep or not first:
            parser.error(f"{pair!r}: give a pair as A.ply:B.ply")
        rows.append([pair, *scene_diff(first, second, cameras, device)])
    print_table(f"Output scenes compared ({len(cameras)} views, {device.type})",
                ["pair", "params max abs diff", "renders PSNR dB"], rows,
                f"cd bench && python scene_diff.py --cameras {args.cameras} --views {args.views} {' '.join(args.pairs)}")


if __name__ == "__main__":
    main()
