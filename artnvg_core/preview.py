"""Pictures for people: comparison sheets of original vs stylized views."""

from __future__ import annotations

import torch

from .fileio import resize_image


def comparison_sheet(originals: torch.Tensor, stylized: torch.Tensor, style_image: torch.Tensor, *, gap: int = 4) -> torch.Tensor:
    """One image: a row of originals over a row of stylized views, the style image at the right.

    originals, stylized: [V, H, W, 3] in [0, 1], the same views in the same order.
    style_image: [h, w, 3], scaled to the sheet's height (two rows) keeping its aspect.
    Returns [2H + gap, V(W + gap) + style width, 3] on a white background.
    """
    if originals.shape != stylized.shape or originals.ndim != 4:
        raise ValueError(f"comparison_sheet: originals {tuple(originals.shape)} and stylized {tuple(stylized.shape)} must match as [V, H, W, 3]")
    views, height, width, _ = originals.shape
    sheet_h = 2 * height + gap
    style_w = max(1, round(style_image.shape[1] * sheet_h / style_image.shape[0]))
    sheet = torch.ones(sheet_h, views * (width + gap) + style_w, 3)
    for v in range(views):
        x = v * (width + gap)
        sheet[:height, x : x + width] = originals[v].detach().float().cpu().clamp(0, 1)
        sheet[height + gap :, x : x + width] = stylized[v].detach().float().cpu().clamp(0, 1)
    sheet[:, views * (width + gap) :] = resize_image(style_image.detach().float().cpu(), sheet_h, style_w).clamp(0, 1)
    return sheet
