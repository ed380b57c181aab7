"""A first look: what the diffusion-free preview costs and how far it lands from the full NNFM result.

    cd bench && python first_look.py [--shared ../../shared/data] [--scene bear] [--style starry]
        [--rows 100x1x1,200x0.5x2,...] [--precisions fp32,fp32,tf32,bf16,tf32:bf16] [--hold-every 8] [--out DIR]

The scene's capture views, every ``--hold-every``-th held back (never trained on), the rest trained on
with :func:`artnvg_core.stylize.stylize_nnfm` (ARF's colour transfer, NNFM + content). The reference is
today's full result: 1,000 iterations, one view a step, the views at their own size, fp32 match search.

Two tables:

* **NNFM search precision** (1,000 iterations, full size, one view a step, each ``--precisions`` entry
  ``SEARCH[:VGG]``, the match search's precision and the VGG convolutions' (``FinetuneConfig.vgg_precision``;
  default: its default); one named twice runs twice, the run-to-run floor, since the rasterizer's backward
  sums in no fixed order): time of
  the whole stylize call, ms per iteration, the final scene against the fp32 one (PSNR of the held-back
  renders), and on the fp32 final scene's held-back renders the share of matches the search picks as fp32
  does and the largest loss in cosine of a different pick (against the float64 best).
* **Preview curve** (each ``--rows`` entry ``ITERATIONSxSCALExVIEWS_PER_STEP``, default search): time of the
  whole stylize call (colour transfer, renders, finetune; models loaded and kernels built beforehand),
  PSNR of its final scene's held-back renders (rendered at full size) against the reference's, the palette
  distances of those renders to the style image (``metrics.color``: joint-histogram total variation,
  mean/covariance W2) and the NNFM style distance (texture: VGG19 relu3 nearest-neighbour cosine distance
  to the style image, float64 search), beside the reference's own.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

from common import print_table, synchronize, timed_call

from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig
from artnvg_core.formats import read_ply
from artnvg_core.images import load_image
from artnvg_core.losses import NNFMLoss, load_vgg, nearest_style_indices, normalize_features, style_image_features
from artnvg_core.metrics.color import color_distances
from artnvg_core.raster import prepare_backend
from artnvg_core.raster.views import render_views
from artnvg_core.stylize import stylize_nnfm

LAYERS = ("relu3_1", "relu3_2", "relu3_3")
DEFAULT_ROWS = "50x1x1,100x1x1,150x1x1,200x1x1,100x1x2,100x0.5x1,200x0.5x2"


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.double() - b.double()) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


def style_features(style: torch.Tensor, side: int, device) -> dict:
    vgg = load_vgg("vgg19", device=device)
    image = style.permute(2, 0, 1)[None].to(device)
    factor = side / max(image.shape[-2:])
    size = (round(image.shape[-2] * factor), round(image.shape[-1] * factor))
    return style_image_features(vgg, torch.nn.functional.interpolate(image, size=size, mode="area"), LAYERS, None)


def texture_distance(images: torch.Tensor, style_feats: dict) -> float:
    """NNFM style distance of IMAGE ``images`` to the style (fp32 search, the loss NNFM optimises)."""
    vgg = load_vgg("vgg19", device=images.device)
    loss = NNFMLoss(style_feats, (LAYERS,), precision="fp32")
    with torch.no_grad():
        return sum(float(loss(vgg(image[None].permute(0, 3, 1, 2), LAYERS))) for image in images) / len(images)


def match_agreement(images: torch.Tensor, style_feats: dict, precision: str) -> tuple[float, float]:
    """(share of positions matched as the float64 search matches them, largest cosine lost by a different
    match) for the search of ``precision`` on the relu3 features of ``images``."""
    vgg = load_vgg("vgg19", device=images.device)
    style = normalize_features(torch.cat([style_feats[k] for k in LAYERS], 1).permute(0, 2, 3, 1).flatten(0, 2))
    same, total, worst = 0, 0, 0.0
    with torch.no_grad():
        for image in images:
            feats = vgg(image[None].permute(0, 3, 1, 2), LAYERS)
            render = normalize_features(torch.cat([feats[k] for k in LAYERS], 1).permute(0, 2, 3, 1).flatten(0, 2))
            cos = render.double() @ style.double().T
            best = cos.argmax(1)
            chosen = nearest_style_indices(render, style, 2**26, precision)
            same += int((chosen == best).sum())
            total += len(best)
            worst = max(worst, float((cos.max(1).values - cos.gather(1, chosen[:, None])[:, 0]).max()))
    return same / total, worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--scene", default="bear")
    parser.add_argument("--style", default="starry")
    parser.add_argument("--rows", default=DEFAULT_ROWS)
    parser.add_argument("--precisions", default="fp32,fp32,tf32,bf16,tf32:bf16", help="SEARCH[:VGG], ...")
    parser.add_argument("--hold-every", type=int, default=8)
    parser.add_argument("--reference-iters", type=int, default=1000, help="iterations of the precision runs")
    parser.add_argument("--size", type=float, default=1.0, help="factor on every view's size (a quick smoke run)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--out", default=None, help="folder for the held-back renders of each run (.pt)")
    args = parser.parse_args()
    device = torch.device(args.device)
    folder = Path(args.shared) / "scenes" / args.scene
    scene = read_ply(folder / "scene.ply").to(device)
    cameras = load_cameras(folder / "transforms.json").scaled(args.size)
    held = [i for i in range(len(cameras)) if i % args.hold_every == 0]
    train = cameras.subset([i for i in range(len(cameras)) if i % args.hold_every])
    test = cameras.subset(held).to(device)
    style = load_image(Path(args.shared) / "styles" / f"{args.style}.jpg")
    prepare_backend(device, "auto", announce=lambda message: print(message, flush=True))
    feats = style_features(style, max(cameras.width, cameras.height), device)
    out = Path(args.out) if args.out else None
    if out:
        out.mkdir(parents=True, exist_ok=True)

    def run(iterations: int, scale: float, per_step: int, search: str, vgg: str = FinetuneConfig().vgg_precision):
        config = FinetuneConfig(iterations=iterations, views_per_step=per_step, nnfm_search=search, vgg_precision=vgg)
        result, seconds = timed_call(device, lambda: stylize_nnfm(scene, train.scaled(scale), style.to(device), config))
        images = render_views(result, test).rgb
        synchronize(device)
        if out:
            torch.save(images.cpu(), out / f"{iterations}x{scale}x{per_step}_{search}_{vgg}.pt")
        return images, seconds

    stylize_nnfm(scene, train.scaled(0.25), style.to(device), FinetuneConfig(iterations=5))  # warm-up: VGG, kernels
    finals, seconds = {}, {}
    for entry in args.precisions.split(","):  # an entry named twice runs twice: the run-to-run floor
        search, _, vgg = entry.partition(":")
        label = entry if entry not in finals else f"{entry} (again)"
        finals[label], seconds[label] = run(args.reference_iters, 1.0, 1, search, vgg or FinetuneConfig().vgg_precision)
        print(label, f"{seconds[label]:.2f} s", flush=True)
    reference = finals["fp32"]
    table = []
    for label, images in finals.items():
        share, worst = match_agreement(reference, feats, label.split(":")[0].split()[0])
        table.append([label, f"{seconds[label]:.2f}", f"{psnr(images, reference):.1f}", f"{100 * share:.2f}",
                      f"{worst:.2e}"])
    command = "python " + " ".join(sys.argv)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print_table(f"NNFM search precision ({args.scene}, {len(train)} training views at "
                f"{cameras.width}x{cameras.height}, {args.reference_iters} iterations; {gpu})",
                ["search[:VGG]", "stylize s", "final scene PSNR vs fp32 (dB)", "matches as float64 (%)",
                 "largest cosine lost"], table, command)

    curve = [[f"reference {args.reference_iters}x1x1 fp32", f"{seconds['fp32']:.2f}", "inf"]
             + [f"{v:.4f}" for v in color_distances(reference, style).values()]
             + [f"{texture_distance(reference, feats):.4f}"]]
    for text in filter(None, args.rows.split(",")):
        iterations, scale, per_step = text.split("x")
        images, seconds = run(int(iterations), float(scale), int(per_step), FinetuneConfig().nnfm_search)
        curve.append([text, f"{seconds:.2f}", f"{psnr(images, reference):.1f}"]
                     + [f"{v:.4f}" for v in color_distances(images, style).values()]
                     + [f"{texture_distance(images, feats):.4f}"])
        print(curve[-1], flush=True)
    original = render_views(scene, test).rgb
    curve.append(["(original scene)", "", f"{psnr(original, reference):.1f}"]
                 + [f"{v:.4f}" for v in color_distances(original, style).values()]
                 + [f"{texture_distance(original, feats):.4f}"])
    print_table(f"Preview curve ({args.scene}, style {args.style}, {len(held)} held-back views at "
                f"{cameras.width}x{cameras.height}; default search {FinetuneConfig().nnfm_search})",
                ["iterations x scale x views/step", "stylize s", "PSNR vs reference (dB)", "palette histogram TV",
                 "palette mean/cov W2", "texture (NNFM distance)"], curve, command)


if __name__ == "__main__":
    main()
