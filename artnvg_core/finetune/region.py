"""A finetune limited to a region: what :mod:`artnvg_core.finetune.loop` does differently with a selection.

A selection is a boolean tensor [N] over the scene's Gaussians (:mod:`artnvg_core.selection`). The loop trains
the selected Gaussians alone and renders them with the others; these helpers choose the views that see them and
their per-pixel weights (:func:`region_views`), the pixels the colour transfer is measured on
(:func:`region_pixels`), recolour the selected Gaussians alone (:func:`recolor`) and put the trained ones back
among the others (:func:`placed`).
"""

from __future__ import annotations

import dataclasses
import logging

import torch

from ..cameras import CameraSet
from ..counted import counted
from ..progress import ProgressFn, StopFn
from ..scene import GaussianScene
from ..selection import check_selection, coverage
from .color_transfer import ColorTransform, recolor_scene

_log = logging.getLogger(__name__)


def placed(every: torch.Tensor, selected: torch.Tensor, selection: torch.Tensor) -> torch.Tensor:
    """A copy of ``every [N, ...]`` with the rows of ``selection [N]`` replaced by ``selected``."""
    result = every.clone()
    result[selection] = selected
    return result


def recolor(scene: GaussianScene, transform: ColorTransform, selection: torch.Tensor | None) -> GaussianScene:
    """``scene`` recoloured by ``transform`` (:func:`recolor_scene`), the selected Gaussians only when given."""
    recolored = recolor_scene(scene, transform)
    if selection is None:
        return recolored
    return dataclasses.replace(scene, sh=torch.where(selection[:, None, None], recolored.sh, scene.sh))


def region_pixels(images: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """The pixels [P, 3] of ``images [C, H, W, 3]`` whose region ``weights [C, H, W]`` are at least 0.5 (all
    without weights); ValueError when there are none."""
    if weights is None:
        return images
    pixels = images[weights >= 0.5]
    if len(pixels) == 0:
        raise ValueError("finetune: the selection covers no pixel of the views by half or more; choose a larger "
                         "region or switch off the colour transfer")
    return pixels


def region_views(scene: GaussianScene, selection: torch.Tensor, cameras: CameraSet, stylized: torch.Tensor | None,
                  backend: str, progress: ProgressFn | None = None, should_stop: StopFn | None = None
                  ) -> tuple[CameraSet, torch.Tensor | None, torch.Tensor]:
    """The views where ``selection`` covers at least a pixel's worth, their stylized views (when given) and
    their coverage [C', H, W] (:func:`coverage`, which ``progress`` and ``should_stop`` follow); ValueError for a
    selection of the wrong size or one no view sees."""
    check_selection(selection, len(scene), "finetune")
    weights = coverage(scene, selection, cameras, backend, progress, should_stop)
    seen = (weights.flatten(1).sum(1) >= 1).nonzero()[:, 0].tolist()
    if not seen:
        raise ValueError(f"finetune: no pixel of any of the {counted(len(cameras), 'view')} sees the "
                         f"{counted(int(selection.sum()), 'selected Gaussian')}")
    if len(seen) < len(cameras):
        _log.info("finetune: %d of %s the selection; the others are left out", len(seen),
                  counted(len(cameras), "view") + (" sees" if len(seen) == 1 else " see"))
    return cameras.subset(seen), None if stylized is None else stylized[seen], weights[seen]
