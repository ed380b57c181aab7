"""Quality of the NNFM-only stylizer on the shared scenes and styles: CFSD and depth-warp consistency.

    python bench/quality.py [--shared ../shared/data] [--scenes bear,face,garden]
        [--styles starry,hokusai,stripes] [--scale 0.5] [--iters 1000] [--out DIR]

For each scene: the original renders give the warp-consistency floor; for each style the scene
is finetuned with NNFM (FinetuneConfig defaults, no stylized views) on all capture views, then
CFSD (content fidelity, lower is better) and warp RMSE for adjacent views (step 1) and views 7
apart are measured on the same views. A contact sheet per run goes to --out.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from common import print_table

from artnvg_core.cameras import load_cameras
from artnvg_core.fileio import load_image, save_png
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.metrics import cfsd_scores, warp_consistency
from artnvg_core.metrics.report import render_views
from artnvg_core.scene import read_ply
from artnvg_core.stylize import contact_sheet

LONG_STEP = 7


def warp_rmse(images, reference, cameras, step):
    return warp_consistency(images, reference.depth, reference.alpha, cameras, step=step).rmse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--scenes", default="bear,face,garden")
    parser.add_argument("--styles", default="starry,hokusai,stripes")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--out", default="out/quality")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    device = torch.device(args.device)
    shared, out = Path(args.shared), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.scenes.split(","):
        folder = shared / "scenes" / name
        scene = read_ply(folder / "scene.ply").to(device)
        cameras = load_cameras(folder / "transforms.json").scaled(args.scale)
        original = render_views(scene, cameras, depth=True)
        rows.append([name, "(original)", f"{cameras.width}x{cameras.height}", 0.0,
                     warp_rmse(original.rgb, original, cameras, 1), warp_rmse(original.rgb, original, cameras, LONG_STEP), None])
        for style_name in args.styles.split(","):
            style = load_image(shared / "styles" / f"{style_name}.jpg").to(device)
            start = time.perf_counter()
            stylized = finetune(scene, cameras, style, config=FinetuneConfig(iterations=args.iters))
            seconds = time.perf_counter() - start
            images = render_views(stylized, cameras).rgb
            cfsd = cfsd_scores(original.rgb, images).mean().item()
            rows.append([name, style_name, f"{cameras.width}x{cameras.height}", cfsd,
                         warp_rmse(images, original, cameras, 1), warp_rmse(images, original, cameras, LONG_STEP), seconds])
            save_png(contact_sheet(scene, stylized, cameras, style), out / f"{name}_{style_name}.png")
            print(rows[-1], flush=True)
    print_table(f"NNFM-only stylizer quality ({device}, {args.iters} iterations)",
                ["scene", "style", "size", "CFSD", "warp RMSE step 1", f"warp RMSE step {LONG_STEP}", "finetune s"],
                rows, "python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
