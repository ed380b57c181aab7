"""Atomic file writing (one file, or a group that appears whole or not at all), checks of output
paths before long work, and image I/O in ComfyUI's IMAGE convention.

Images are float32 in [0, 1], [H, W, 3] (one) or [B, H, W, 3] (a batch).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import uuid
import warnings
from collections.abc import Iterator
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


def _temporary_name(path: Path) -> Path:
    """A hidden, unique name beside ``path`` that keeps its suffix (writers may go by it)."""
    return path.with_name(f".{path.stem}.{uuid.uuid4().hex[:12]}.partial{path.suffix}")


def check_output_file(path: str | os.PathLike, option: str) -> Path:
    """``path`` as a file a command will write, checked before any long work: ValueError naming
    ``option`` when it is empty, an existing folder, under a file, or in a folder that cannot be
    written. Creates nothing (a probe file is made and removed)."""
    if not str(path).strip():
        raise ValueError(f"{option}: the output path is empty")
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{option}: {path} is a folder; give a file name (e.g. {path / 'out'}{path.suffix})")
    _check_writable_folder(path.parent, option, path)
    return path


def check_output_folder(path: str | os.PathLike, option: str) -> Path:
    """``path`` as a folder a command will write files into: ValueError naming ``option`` when it
    is empty, an existing file, under a file, or cannot be written. Creates nothing."""
    if not str(path).strip():
        raise ValueError(f"{option}: the output folder is empty")
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{option}: {path} exists and is not a folder")
    _check_writable_folder(path, option, path)
    return path


def _check_writable_folder(folder: Path, option: str, target: Path) -> None:
    existing = folder
    while not existing.exists():  # the folders still to be made must go in one that exists
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{option}: cannot write {target}: {existing} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as error:
        raise ValueError(f"{option}: cannot write {target}: folder {existing} is not writable ({error.strerror})") from None


@contextlib.contextmanager
def written_together(*paths: str | os.PathLike) -> Iterator[list[Path]]:
    """Files that appear together or not at all: yields a temporary path beside each of ``paths``
    (same suffix) for the block to write; when it ends without error every one is renamed onto its
    path, else all are removed and no path is touched. Missing parent folders are created. A
    ValueError raised in the block names the paths, not the temporaries."""
    targets = [Path(p) for p in paths]
    temporaries = [_temporary_name(t) for t in targets]
    try:
        for target in targets:
            target.parent.mkdir(parents=True, exist_ok=True)
        try:
            yield temporaries
        except ValueError as error:
            message = str(error)
            for temporary, target in zip(temporaries, targets):
                message = message.replace(str(temporary), str(target))
            if message == str(error):
                raise
            raise ValueError(message) from error
        missing = [str(t) for t in temporaries if not t.is_file()]
        if missing:
            raise RuntimeError(f"written_together: the block did not write {missing}")
        folders = [str(t) for t in targets if t.is_dir()]
        if folders:
            raise ValueError(f"cannot write over folders {folders}")
        for temporary, target in zip(temporaries, targets):
            os.replace(temporary, target)
    finally:
        for temporary in temporaries:
            temporary.unlink(missing_ok=True)


MAX_IMAGE_PIXELS = Image.MAX_IMAGE_PIXELS  # Pillow's decompression-bomb limit, 89,478,485 pixels


def _open_image(path: Path) -> Image.Image:
    """Pillow's lazy ``Image.open``: the header only; a file over MAX_IMAGE_PIXELS is refused here."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # refused below, with the size
            image = Image.open(path)
    except Image.DecompressionBombError as error:
        raise ValueError(f"{path}: image too large to decode ({error}); downsize it first") from error
    if image.width * image.height > MAX_IMAGE_PIXELS:
        image.close()
        raise ValueError(f"{path}: image of {image.width}x{image.height} pixels is too large to decode "
                         f"(limit {MAX_IMAGE_PIXELS:,} pixels); downsize it first")
    return image


def _single_channel(image: Image.Image, path: Path) -> np.ndarray:
    """[H, W] float32 in [0, 1] of a 16-bit, 32-bit integer or float greyscale image.

    16-bit values are divided by 65535; 32-bit integers by 65535 when all fit 16 bits (Pillow
    reads some 16-bit files so), else by 2^31 - 1; floats are kept when within [0, 1], else
    rescaled from their minimum..maximum. Non-finite floats are an error.
    """
    array = np.asarray(image)
    if image.mode == "F":
        if not np.isfinite(array).all():
            raise ValueError(f"{path}: float image has NaN or infinite pixels")
        low, high = float(array.min()), float(array.max())
        if low >= 0 and high <= 1:
            return array.astype(np.float32)
        return ((array - low) / (high - low) if high > low else np.zeros_like(array)).astype(np.float32)
    scale = 65535.0 if image.mode.startswith("I;16") or array.max() <= 65535 else 2.0**31 - 1
    return (np.clip(array.astype(np.float64), 0, None) / scale).astype(np.float32)


def load_image(path: str | os.PathLike, *, max_side: int | None = None) -> torch.Tensor:
    """Read an image file as [H, W, 3] float32 RGB in [0, 1].

    Any bit depth: 8-bit images of any mode (greyscale, palette, RGBA with its alpha dropped,
    CMYK) are divided by 255; 16-bit, 32-bit integer and float greyscale images (16-bit PNG,
    float TIFF) are scaled as :func:`_single_channel` says. Greyscale becomes three equal
    channels. An image over MAX_IMAGE_PIXELS is refused before it is decoded.
    ``max_side`` downsizes (Lanczos, aspect kept) so the longer side is at most that.
    """
    path = Path(path)
    try:
        with _open_image(path) as image:
            size = image.size
            if max_side is not None and max(size) > max_side:
                scale = max_side / max(size)
                size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
            if image.mode in ("F", "I") or image.mode.startswith("I;16"):
                grey = Image.fromarray(_single_channel(image, path), mode="F")
                grey = np.clip(np.asarray(grey.resize(size, Image.LANCZOS) if size != image.size else grey), 0, 1)
                array = np.repeat(grey[..., None], 3, axis=-1)
            else:
                rgb = image.convert("RGB")
                rgb = rgb.resize(size, Image.LANCZOS) if size != image.size else rgb
                array = np.asarray(rgb, dtype=np.float32) / 255.0
    except FileNotFoundError as error:
        raise ValueError(f"{path}: image file not found") from error
    except (OSError, SyntaxError) as error:  # PIL's errors for unreadable or corrupt files
        raise ValueError(f"{path}: not a readable image ({error})") from error
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float image -> uint8 array, clamped to [0, 1] and rounded."""
    return (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def save_png(image: torch.Tensor, path: str | os.PathLike) -> None:
    """Write a [H, W, 3] float image in [0, 1] as PNG, atomically (zlib level 1: lossless like any level; the
    default level 6 took 1.6 s of a 13 s first look for one contact sheet, BENCHMARKS.md, First look)."""
    pil = Image.fromarray(to_uint8(image))
    write_atomically(path, lambda stream: pil.save(stream, format="PNG", compress_level=1))


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
