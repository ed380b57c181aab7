"""Pictures for people: a comparison strip (PNG) and an animated preview (GIF).

Images are float [H, W, 3] / [B, H, W, 3] in [0, 1]; files are written atomically.
"""

from __future__ import annotations

import os

import torch
from PIL import Image

from .fileio import write_atomically
from .images import resize_image, save_png, to_uint8

GAP = 4  # white pixels between the tiles of a strip


def evenly_spaced(count: int, limit: int) -> list[int]:
    """At most ``limit`` indices spread evenly over ``range(count)``, first and last included."""
    if count <= limit:
        return list(range(count))
    if limit == 1:
        return [0]
    return [round(k * (count - 1) / (limit - 1)) for k in range(limit)]


def comparison_strip(original: torch.Tensor, stylized: torch.Tensor, style: torch.Tensor) -> torch.Tensor:
    """One image: the original views on top, the stylized views below, the style image at the right.

    original, stylized [V, H, W, 3]; style [h, w, 3], resized to fit a tile as high as the two rows and at
    most twice as wide (aspect kept, centred on white: a 80000x1 image becomes a line, not a 10 GB strip).
    Returns [2H + GAP, V (W + GAP) + w', 3] on a white background, w' <= 2 (2H + GAP).
    """
    if original.shape != stylized.shape or original.ndim != 4:
        raise ValueError(f"comparison_strip: expected two [V, H, W, 3] batches of one shape, "
                         f"got {tuple(original.shape)} and {tuple(stylized.shape)}")
    views, height, width = original.shape[:3]
    tile_height = 2 * height + GAP
    factor = min(tile_height / style.shape[0], 2 * tile_height / style.shape[1])
    style_height, style_width = (max(1, round(side * factor)) for side in style.shape[:2])
    style = resize_image(style.float().cpu(), style_height, style_width).clamp(0, 1)
    canvas = torch.ones(tile_height, views * (width + GAP) + style_width, 3)
    for v in range(views):
        left = v * (width + GAP)
        canvas[:height, left:left + width] = original[v].float().cpu().clamp(0, 1)
        canvas[height + GAP:, left:left + width] = stylized[v].float().cpu().clamp(0, 1)
    top = (tile_height - style_height) // 2
    canvas[top:top + style_height, views * (width + GAP):] = style
    return canvas


def side_by_side(images: torch.Tensor) -> torch.Tensor:
    """``images [K, H, W, 3]`` in one row, left to right, :data:`GAP` white pixels apart: [H, K (W + GAP) - GAP, 3]."""
    if images.ndim != 4 or images.shape[0] < 1:
        raise ValueError(f"side_by_side: expected images [K, H, W, 3] with K >= 1, got {tuple(images.shape)}")
    count, height, width = images.shape[:3]
    canvas = torch.ones(height, count * (width + GAP) - GAP, 3)
    for k in range(count):
        canvas[:, k * (width + GAP):k * (width + GAP) + width] = images[k].float().cpu().clamp(0, 1)
    return canvas


def save_strip(original: torch.Tensor, stylized: torch.Tensor, style: torch.Tensor, path: str | os.PathLike) -> None:
    """Write :func:`comparison_strip` as a PNG."""
    save_png(comparison_strip(original, stylized, style), path)


def save_gif(frames: torch.Tensor, path: str | os.PathLike, *, fps: float = 12.0) -> None:
    """Write frames [F, H, W, 3] as a looping animated GIF (Pillow, adaptive palette per frame)."""
    if frames.ndim != 4 or frames.shape[0] < 1 or frames.shape[-1] != 3:
        raise ValueError(f"save_gif: expected frames [F, H, W, 3] with F >= 1, got {tuple(frames.shape)}")
    if not fps > 0:
        raise ValueError(f"save_gif: fps must be positive, got {fps}")
    images = [Image.fromarray(to_uint8(frame)) for frame in frames]
    duration = max(20, round(1000 / fps))  # ms per frame; browsers clamp shorter delays

    def write(stream) -> None:
        images[0].save(stream, format="GIF", save_all=True, append_images=images[1:], duration=duration, loop=0)

    write_atomically(path, write)
