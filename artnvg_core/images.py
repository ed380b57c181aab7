"""Images in ComfyUI's IMAGE convention: read from a file (any bit depth, its size checked from the header
before it is decoded), written as PNG, resized.

Images are float32 in [0, 1], [H, W, 3] (one) or [B, H, W, 3] (a batch).
"""

from __future__ import annotations

import os
import struct
import warnings
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from .counted import counted
from .fileio import require_regular_file, write_atomically

_PILLOW_ERRORS = (OSError, SyntaxError, ValueError)  # what Pillow raises for unreadable or corrupt files

# Pixels an image may have, read from its header before it is decoded (8000 x 8000). This is what bounds the
# memory a small file can make a read take, as compressed data legitimately expands: a read peaks at 18 to 22
# bytes a pixel (the decoded pixels, Pillow's bytes of them, float32 RGB), measured above the process's size
# at the cap: 1.16 GB for an RGB JPEG of 376 KB, 1.22 GB for a 16-bit greyscale PNG of 124 KB or a float
# TIFF, 1.40 GB for an RGBA PNG of 249 KB.
MAX_IMAGE_PIXELS = 64_000_000
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# The largest value an image tensor is taken with: [0, 1] and room for a resampler's overshoot (bicubic); an image
# of 8-bit values (0 to 255) given as floats lies far beyond it.
MAX_IMAGE_VALUE = 2.0


def _check_png_chunks(path: Path) -> None:
    """Each chunk of a PNG, up to IEND, within the file: its length field checked against the bytes left
    before Pillow reads it (Pillow reserves what an IDAT chunk declares, up to 4 GB for a 69-byte file);
    ValueError naming the file, the chunk and its offset. Other files, and a PNG that ends between chunks,
    are left to Pillow."""
    with open(path, "rb") as stream:
        if stream.read(len(_PNG_SIGNATURE)) != _PNG_SIGNATURE:
            return
        size = os.fstat(stream.fileno()).st_size
        while len(header := stream.read(8)) == 8:
            length, kind = struct.unpack(">I4s", header)
            left = size - stream.tell() - 4  # the chunk's data, then a 4-byte checksum
            if length > left:
                raise ValueError(f"{path}: PNG chunk {kind.decode('latin-1')!r} at byte {stream.tell() - 8:,} "
                                 f"declares {counted(length, 'byte')} of data, more than the "
                                 f"{counted(max(left, 0), 'byte')} left in the file (a truncated or corrupt file)")
            if kind == b"IEND":
                return
            stream.seek(length + 4, os.SEEK_CUR)


def _check_data_offsets(image: Image.Image, path: Path) -> None:
    """Every block of the image's data (a TIFF's strips or tiles, ...) starts within the file: Pillow reserves
    the distance from one block to the next before reading it (2 GB for a TIFF of 204 bytes whose second strip
    lay at byte 2**31); ValueError naming the file, the block and its offset."""
    size = path.stat().st_size
    for number, tile in enumerate(image.tile, start=1):
        if tile.offset > size:
            raise ValueError(f"{path}: {image.format} header: image data block {number} of {len(image.tile)} "
                             f"starts at byte {tile.offset:,}, past the end of the file ({counted(size, 'byte')})")


def _open_image(path: Path) -> Image.Image:
    """Pillow's lazy ``Image.open`` of a regular file: the header only; an image of more than
    MAX_IMAGE_PIXELS pixels, or whose chunks or data blocks lie past the file's end, is refused here, before
    it is decoded."""
    require_regular_file(path, "image file")
    _check_png_chunks(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # refused below, with the size
            image = Image.open(path)
    except Image.DecompressionBombError as error:
        raise ValueError(f"{path}: image too large to decode ({error}); downsize it first") from error
    except _PILLOW_ERRORS as error:
        raise ValueError(f"{path}: not a readable image ({error})") from error
    try:
        if image.width * image.height > MAX_IMAGE_PIXELS:
            raise ValueError(f"{path}: image size: {image.width}x{image.height} pixels, more than the "
                             f"{MAX_IMAGE_PIXELS:,} pixels (e.g. 8000x8000) decoded at most; downsize it first")
        _check_data_offsets(image, path)
    except ValueError:
        image.close()
        raise
    return image


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file from its header, without decoding it; ValueError naming ``path``
    for a file that is missing, not a regular file, not an image, or over MAX_IMAGE_PIXELS."""
    with _open_image(Path(path)) as image:
        return image.size


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
        if high == low:
            return np.zeros_like(array, dtype=np.float32)
        scaled = array.astype(np.float64)  # in float32, high - low overflows for pixels from -3e38 to 3e38
        scaled -= low
        scaled /= high - low
        return scaled.astype(np.float32)
    scale = 65535.0 if image.mode.startswith("I;16") or array.max() <= 65535 else 2.0**31 - 1
    return (np.clip(array.astype(np.float64), 0, None) / scale).astype(np.float32)


def load_image(path: str | os.PathLike, *, max_side: int | None = None) -> torch.Tensor:
    """Read an image file as [H, W, 3] float32 RGB in [0, 1].

    Any bit depth: 8-bit images of any mode (greyscale, palette, RGBA with its alpha dropped,
    CMYK) are divided by 255; 16-bit, 32-bit integer and float greyscale images (16-bit PNG,
    float TIFF) are scaled as :func:`_single_channel` says. Greyscale becomes three equal
    channels. A file that is not a regular file (a FIFO), or an image over MAX_IMAGE_PIXELS, is refused
    before it is read or decoded.
    ``max_side`` downsizes (Lanczos, aspect kept) so the longer side is at most that.
    """
    path = Path(path)
    with _open_image(path) as image:
        try:
            image.load()  # decoded here, where a corrupt file's errors are named
        except _PILLOW_ERRORS as error:
            raise ValueError(f"{path}: not a readable image ({error})") from error
        size = image.size
        if max_side is not None and max(size) > max_side:
            scale = max_side / max(size)
            size = (max(1, round(image.width * scale)), max(1, round(image.height * scale)))
        if image.mode in ("F", "I") or image.mode.startswith("I;16"):
            grey = Image.fromarray(_single_channel(image, path), mode="F")
            grey = np.clip(np.asarray(grey.resize(size, Image.LANCZOS) if size != image.size else grey), 0, 1)
            array = np.repeat(grey[..., None], 3, axis=-1)
        else:
            rgb = image if image.mode == "RGB" else image.convert("RGB")
            rgb = rgb.resize(size, Image.LANCZOS) if size != image.size else rgb
            return torch.from_numpy(np.asarray(rgb, dtype=np.float32)).div_(255)  # Pillow's bytes, then float32
    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


def check_image_values(image: torch.Tensor, name: str) -> None:
    """ValueError naming ``name`` unless ``image`` holds finite floats of at most :data:`MAX_IMAGE_VALUE`: an
    integer tensor or floats from 0 to 255 (8-bit values, which the image convention's [0, 1] would read as a
    white image) are refused, saying to divide by 255."""
    if not image.is_floating_point():
        raise ValueError(f"{name}: expected floats in [0, 1], got a {image.dtype} tensor (divide 8-bit values by 255)")
    if not bool(torch.isfinite(image).all()):
        raise ValueError(f"{name}: expected floats in [0, 1], got NaN or infinite values")
    peak = image.max().item() if image.numel() else 0.0
    if peak > MAX_IMAGE_VALUE:
        raise ValueError(f"{name}: expected floats in [0, 1], got values up to {peak:g} (divide 8-bit values by 255)")


def to_uint8(image: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float image -> uint8 array, clamped to [0, 1] and rounded."""
    return (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def save_png(image: torch.Tensor, path: str | os.PathLike) -> None:
    """Write a [H, W, 3] float image in [0, 1] as PNG, atomically (zlib level 1: lossless like any level; the
    default level 6 took 1.6 s of a 13 s first look for one contact sheet, BENCHMARKS.md, First look)."""
    pil = Image.fromarray(to_uint8(image))
    write_atomically(path, lambda stream: pil.save(stream, format="PNG", compress_level=1))


def same_aspect(width: int, height: int, other_width: int, other_height: int) -> bool:
    """Whether ``width`` x ``height`` pixels and ``other_width`` x ``other_height`` pixels can have one aspect
    within a pixel's rounding: some aspect gives both sizes with each side rounded to whole pixels (an image of a
    view rendered at another scale), so that resizing one to the other stretches neither."""
    def aspects(w: int, h: int) -> tuple[float, float]:  # those whose sides round to w x h
        return (w - 0.5) / (h + 0.5), (w + 0.5) / (h - 0.5)

    low, high = aspects(width, height)
    other_low, other_high = aspects(other_width, other_height)
    return low <= other_high and other_low <= high


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
