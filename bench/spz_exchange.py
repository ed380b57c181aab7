"""A capture's scene exchanged as .spz with PlayCanvas splat-transform and spz-js (pinned in
tests/npm/package.json, installed on first use by tests/npm_tools.py), default settings everywhere:
PSNR of renders of what comes back against renders of the PLY (reference rasterizer). A scene read
upside down scores about 10 dB; docs/scenes_and_formats.md, "SPZ axes", records a run. The last two rows
show what our writer's moving of far Gaussians onto SPZ's range costs (those beyond the largest |coordinate|
our .spz holds: 2048 at 12 fractional bits): those Gaussians rendered alone, as our .spz holds them against
as the PLY does, and the PLY rendered without them.

    python bench/spz_exchange.py [--capture ../shared/data/scenes/bear] [--views 0,24,48,72] [--scale 0.5]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from artnvg_core.cameras import load_cameras  # noqa: E402
from artnvg_core.cameras.selection import parse_views  # noqa: E402
from artnvg_core.formats import load_scene, save_scene  # noqa: E402
from artnvg_core.formats.spz import write_spz  # noqa: E402
from artnvg_core.raster import render  # noqa: E402
from tests.npm_tools import PINNED, splat_transform, spz_js, unavailable  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--capture", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/scenes/bear",
                        help="folder holding scene.ply and transforms.json")
    parser.add_argument("--views", default="0,24,48,72")
    parser.add_argument("--scale", type=float, default=0.5)
    args = parser.parse_args()
    if (reason := unavailable()) is not None:
        sys.exit(f"the npm tools cannot run: {reason}")
    cameras = load_cameras(args.capture / "transforms.json")
    views = cameras.subset(parse_views(args.views, len(cameras), "--views")).scaled(args.scale)
    ply = load_scene(args.capture / "scene.ply")

    def rgb(scene):
        with torch.no_grad():
            return render(scene, views, backend="torch").rgb

    reference = rgb(ply)

    def psnr(scene, against=reference) -> float:
        return float(-10 * torch.log10(((rgb(scene) - against) ** 2).mean()))

    print(f"{args.capture.name}: {len(ply):,} Gaussians, views {args.views or 'all'} at {views.width}x{views.height}; "
          + ", ".join(f"{name} {version}" for name, version in PINNED.items()), flush=True)
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        splat_transform(args.capture / "scene.ply", folder / "st.spz")
        spz_js(args.capture / "scene.ply", folder / "js.spz")
        save_scene(ply, folder / "ours.spz")
        write_spz(ply, folder / "ours_v2.spz", version=2)
        write_spz(ply, folder / "ours_rub.spz", axes="rub")
        splat_transform(folder / "ours.spz", folder / "ours_st.ply")
        spz_js(folder / "ours_v2.spz", folder / "ours_js.ply")
        splat_transform(folder / "ours_rub.spz", folder / "ours_rub_st.ply")
        rows = [
            ("splat-transform's .spz, read here", lambda: load_scene(folder / "st.spz")),
            ("splat-transform's .spz, read as RUB", lambda: load_scene(folder / "st.spz", spz_axes="rub")),
            ("spz-js's .spz, read here", lambda: load_scene(folder / "js.spz")),
            ("our .spz, read here", lambda: load_scene(folder / "ours.spz")),
            ("our .spz -> splat-transform -> .ply", lambda: load_scene(folder / "ours_st.ply")),
            ("our .spz version 2 -> spz-js -> .ply *", lambda: load_scene(folder / "ours_js.ply", drop_invalid=True)),
            ("our .spz in RUB -> splat-transform -> .ply", lambda: load_scene(folder / "ours_rub_st.ply")),
        ]
        for label, scene in rows:
            print(f"| {label} | {psnr(scene()):.2f} dB |", flush=True)
        ours = load_scene(folder / "ours.spz")
        held = float(ours.means.abs().max())
        far = ply.means.abs().amax(1) > held
        if far.any():
            alone = ours.map(lambda values: values[far])
            print(f"| the {int(far.sum()):,} Gaussians beyond {held:.6g} alone, our .spz's against the PLY's | "
                  f"{psnr(alone, rgb(ply.map(lambda values: values[far]))):.2f} dB |")
            print(f"| the PLY without them | {psnr(ply.map(lambda values: values[~far])):.2f} dB |")
    print("* spz-js writes a stored opacity of 255 as an infinite logit: those Gaussians are dropped")


if __name__ == "__main__":
    try:
        main()
    except (ValueError, subprocess.CalledProcessError, AssertionError) as error:
        sys.exit(f"error: {error}")
