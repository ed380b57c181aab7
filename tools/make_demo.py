"""Build the bundled demo (artnvg_core/demo/) from the shared bear scene.

    python tools/make_demo.py ../shared/data

Keeps the Gaussians that contribute most to the capture views at 1/4 resolution, SH degree 1, every
4th capture camera, and a 256-px copy of one style image. Attribution is
written beside the files.
"""

import argparse
import json
import shutil
from pathlib import Path

import torch
from PIL import Image

from artnvg_core.cameras import CameraSet, load_nerfstudio
from artnvg_core.raster import render
from artnvg_core.formats import read_ply, write_ply
from artnvg_core.scene import SH_C0, GaussianScene

DEMO = Path(__file__).resolve().parents[1] / "artnvg_core" / "demo"


def visibility(scene: GaussianScene, cameras: CameraSet) -> torch.Tensor:
    """Per-Gaussian blending weight summed over all pixels of ``cameras`` [N].

    rgb = sum_i w_i c_i, so d(sum rgb) / d(colour_i) = sum of w_i over pixels.
    """
    colour_probe = torch.zeros(len(scene), 1, 3, requires_grad=True)
    probed = GaussianScene(scene.means, scene.quats, scene.log_scales, scene.opacity_logits,
                           torch.cat([scene.sh[:, :1] + colour_probe / SH_C0, scene.sh[:, 1:]], 1))
    render(probed, cameras, sh_degree=0).rgb.sum().backward()
    return colour_probe.grad.sum((1, 2)) / 3


def thin_scene(scene: GaussianScene, cameras: CameraSet, keep: int, sh_degree: int) -> GaussianScene:
    """The ``keep`` most visible Gaussians from ``cameras``, SH truncated to ``sh_degree``."""
    index = torch.sort(torch.topk(visibility(scene, cameras), keep).indices).values
    thin = scene.select(index)
    return GaussianScene(thin.means, thin.quats, thin.log_scales, thin.opacity_logits, thin.sh[:, : (sh_degree + 1) ** 2])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("shared_data", type=Path)
    parser.add_argument("--gaussians", type=int, default=40000)
    parser.add_argument("--camera-step", type=int, default=4)
    parser.add_argument("--style", default="starry.jpg")
    args = parser.parse_args()
    bear = args.shared_data / "scenes" / "bear"
    DEMO.mkdir(parents=True, exist_ok=True)
    cameras = load_nerfstudio(bear / "transforms.json").scaled(0.25)
    cameras = cameras.subset(range(0, len(cameras), args.camera_step))
    write_ply(thin_scene(read_ply(bear / "scene.ply"), cameras, args.gaussians, 1), DEMO / "bear.ply")
    meta = json.loads((bear / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:: args.camera_step]
    for frame in meta["frames"]:
        frame.pop("colmap_im_id", None)
    (DEMO / "transforms.json").write_text(json.dumps(meta, indent=1))
    with Image.open(args.shared_data / "styles" / args.style) as style:
        style = style.convert("RGB")
        style.thumbnail((256, 256), Image.LANCZOS)
        style.save(DEMO / "style.jpg", quality=90)
    shutil.copy(args.shared_data / "scenes" / "LICENSE-gaussctrl.txt", DEMO / "LICENSE-gaussctrl.txt")
    shutil.copy(args.shared_data / "styles" / "LICENSE-style-splat.txt", DEMO / "LICENSE-style-splat.txt")


if __name__ == "__main__":
    main()
