"""Quality of the NNFM-only stylizer on the shared scenes and styles, without and with ARF's colour transfer.

    python bench/quality.py [--shared ../shared/data] [--scenes bear,face,garden]
        [--styles starry,hokusai,stripes] [--scale 0.5] [--views 0] [--every 1] [--iters 1000]
        [--color-transfer off,on] [--long-step 7] [--threads 0] [--out DIR]

For each scene (capture views 0, every, 2 every, ...; --views of them, 0: all): the original
renders give the floors; for each style and each colour-transfer setting the scene is finetuned
with NNFM (FinetuneConfig defaults otherwise, no stylized views, the same iterations), then on
the same views: the colour distances of the renders to the style image (joint RGB histogram
total variation; 2-Wasserstein distance of the Gaussian fits, i.e. of means and covariances),
CFSD (content fidelity, lower is better), warp RMSE for adjacent views (step 1) and views
--long-step apart, and the finetune time. One contact sheet per scene goes to --out: the
original renders on top, then per style a row without and a row with colour transfer, the
style image at the right of its rows.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from common import print_table, warp_rmse

from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.formats import load_scene
from artnvg_core.images import load_image, resize_image, save_png
from artnvg_core.metrics import cfsd_scores
from artnvg_core.metrics.color import color_distances
from artnvg_core.raster.views import render_views
from artnvg_core.preview import GAP, evenly_spaced

SHEET_VIEWS = 3


def contact_sheet(rows: list[torch.Tensor], styles: list[torch.Tensor], rows_per_style: int) -> torch.Tensor:
    """Rows of [V, H, W, 3] views, one under the other: the originals, then ``rows_per_style`` rows
    per style with ``styles[i]`` to their right, over their height."""
    views, height, width = rows[0].shape[:3]
    style_height = rows_per_style * (height + GAP) - GAP
    style_width = max(round(s.shape[1] * style_height / s.shape[0]) for s in styles)
    canvas = torch.ones(len(rows) * (height + GAP) - GAP, views * (width + GAP) + style_width, 3)
    for r, row in enumerate(rows):
        top = r * (height + GAP)
        for v in range(views):
            canvas[top:top + height, v * (width + GAP):v * (width + GAP) + width] = row[v].cpu().clamp(0, 1)
    for i, style in enumerate(styles):
        top = (1 + rows_per_style * i) * (height + GAP)
        resized = resize_image(style.cpu(), style_height, round(style.shape[1] * style_height / style.shape[0]))
        canvas[top:top + style_height, views * (width + GAP):views * (width + GAP) + resized.shape[1]] = resized
    return canvas


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--scenes", default="bear,face,garden")
    parser.add_argument("--styles", default="starry,hokusai,stripes")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--views", type=int, default=0, help="how many capture views (0: all)")
    parser.add_argument("--every", type=int, default=1, help="take every k-th capture view")
    parser.add_argument("--iters", type=int, default=1000)
    parser.add_argument("--color-transfer", default="off,on", help="settings to compare: off, on or off,on")
    parser.add_argument("--long-step", type=int, default=7)
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--out", default="out/quality")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    shared, out = Path(args.shared), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    settings = [{"off": False, "on": True}[s] for s in args.color_transfer.split(",")]
    rows = []
    for name in args.scenes.split(","):
        folder = shared / "scenes" / name
        scene = load_scene(folder / "scene.ply").to(device)
        cameras = load_cameras(folder / "transforms.json")
        indices = list(range(0, len(cameras), args.every))
        cameras = cameras.subset(indices[:args.views] if args.views else indices).scaled(args.scale)
        original = render_views(scene, cameras, depth=True)
        sheet_views = evenly_spaced(len(cameras), SHEET_VIEWS)
        sheet_rows, sheet_styles = [original.rgb[sheet_views]], []
        size = f"{len(cameras)} x {cameras.width}x{cameras.height}"
        for style_name in args.styles.split(","):
            style = load_image(shared / "styles" / f"{style_name}.jpg").to(device)
            distances = color_distances(original.rgb, style)
            rows.append([name, style_name, "(original)", size, distances["histogram"], distances["mean_cov"], 0.0,
                         warp_rmse(original.rgb, original.depth, original.alpha, cameras, 1),
                         warp_rmse(original.rgb, original.depth, original.alpha, cameras, args.long_step), None])
            for transfer in settings:
                start = time.perf_counter()
                config = FinetuneConfig(iterations=args.iters, color_transfer=transfer)
                stylized = finetune(scene, cameras, style, config=config)
                seconds = time.perf_counter() - start
                images = render_views(stylized, cameras).rgb
                distances = color_distances(images, style)
                rows.append([name, style_name, "on" if transfer else "off", size, distances["histogram"],
                             distances["mean_cov"], cfsd_scores(original.rgb, images).mean().item(),
                             warp_rmse(images, original.depth, original.alpha, cameras, 1),
                             warp_rmse(images, original.depth, original.alpha, cameras, args.long_step),
                             seconds])
                sheet_rows.append(images[sheet_views])
                print(rows[-1], flush=True)
            sheet_styles.append(style)
        save_png(contact_sheet(sheet_rows, sheet_styles, len(settings)), out / f"{name}.png")
    print_table(f"NNFM-only stylizer quality ({device}, {args.iters} iterations, colour transfer off/on)",
                ["scene", "style", "colour transfer", "views", "histogram distance", "mean/cov distance", "CFSD",
                 "warp RMSE step 1", f"warp RMSE step {args.long_step}", "finetune s"],
                rows, "python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
