"""Atomic file writing and image I/O in ComfyUI's IMAGE convention.

Images are float32 in [0, 1], [H, W, 3] (one) or [B, H, W, 3] (a batch).
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import BinaryIO, Callable

import numpy as np
import torch
from PIL import Image


def write_atomically(path: str | os.PathLike, write: Callable[[BinaryIO], None]) -> None:
    """Call ``write`` on a temporary file beside ``path``, then rename it onto ``path``.

    On any failure (or interruption) the temporary file is removed and
    ``path`` is left untouched.
    """
    path = Path(path)
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(temporary, "xb") as stream:
            write(stream)
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def load_image(path: str | os.PathLike, *, max_side: int | None = None) -> torch.Tensor:
    """Read an image file as [H, W, 3] float32 RGB in [0, 1].

    ``max_side`` downsizes (Lanczos, aspect kept) so the longer side is at most that.
    """
    path = Path(path)
    try:
        with Image.open(path) as image:
            image = image.convert("RGB")
            if max_side is not None and max(image.size) > max_side:
                scale = max_side / max(image.size)
                image = image.resize((max(1, round(image.width * scale)), max(1, round(image.height * scale))), Image.LANCZOS)
            array = np.asarray(image, dtype=np.float32) / 255.0
    except FileNotFoundError as error:
        raise ValueError(f"{path}: image file not found") from error
    except (OSError, SyntaxError) as error:  # PIL's errors for unreadable or corrupt files
        raise ValueError(f"{path}: not a readable image ({error})") from error
    return torch.from_numpy(array)


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float image -> uint8 array, clamped to [0, 1] and rounded."""
    return (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def save_png(image: torch.Tensor, path: str | os.PathLike) -> None:
    """Write a [H, W, 3] float image in [0, 1] as PNG, atomically."""
    pil = Image.fromarray(to_uint8(image))
    write_atomically(path, lambda stream: pil.save(stream, format="PNG"))


def resize_image(image: torch.Tensor, height: int, width: int, *, mode: str = "bilinear") -> torch.Tensor:
    """Resize [H, W, 3] or [B, H, W, 3] (``mode`` "bilinear" or "bicubic", antialiased when
    shrinking, clamped to [0, 1]); an image already of that size is returned as it is."""
    if image.shape[-3:-1] == (height, width):
        return image
    batch = image if image.ndim == 4 else image[None]
    out = torch.nn.functional.interpolate(
        batch.permute(0, 3, 1, 2), size=(height, width), mode=mode, align_corners=False, antialias=True
    ).clamp(0, 1).permute(0, 2, 3, 1)
    return out if image.ndim == 4 else out[0]
