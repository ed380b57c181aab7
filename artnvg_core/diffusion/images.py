"""Image batches for the diffusion stage: validation, working sizes, resizing, CLIP preprocessing.

Images are ComfyUI IMAGE batches: float tensors ``[B, H, W, 3]`` with values in [0, 1].
Resizing is bicubic with antialiasing (torch only), clamped back to [0, 1].
"""

from __future__ import annotations

import math

import torch

from ..images import resize_image

CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)


def check_images(images: torch.Tensor, name: str) -> torch.Tensor:
    """Return ``images`` as float32 ``[B, H, W, 3]``; ValueError naming ``name`` otherwise."""
    if not isinstance(images, torch.Tensor) or images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] < 1:
        shape = list(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(f"{name}: expected an IMAGE batch [B, H, W, 3] with B >= 1, got {shape}")
    if not images.is_floating_point():
        raise ValueError(f"{name}: expected float values in [0, 1], got dtype {images.dtype}")
    images = images.float()
    low, high = images.min().item(), images.max().item()
    if not (math.isfinite(low) and math.isfinite(high)) or low < -1e-3 or high > 1 + 1e-3:
        raise ValueError(f"{name}: values must lie in [0, 1], got range [{low:.4g}, {high:.4g}]")
    return images.clamp(0, 1)


def csgo_size(height: int, width: int, long_side: int = 1024, multiple: int = 32) -> tuple[int, int]:
    """(height, width) by CSGO's ``resize_content``: the long side becomes ``long_side``, the short
    side scales with it, both floored to multiples of ``multiple`` (at least ``multiple``).

    CSGO floors to multiples of 16; a UNet whose grid halves k times needs multiples of
    8·2^k (32 for SDXL) for every level to halve exactly. A 16:9 view gives 1024x576.
    The ratio is exact here; CSGO's float arithmetic truncates the long side to 1023 for some
    sizes (then 1008 after flooring).
    """
    if min(height, width, long_side, multiple) < 1:
        raise ValueError(
            f"csgo_size: sizes must be positive, got {height}x{width}, long side {long_side}, multiple {multiple}"
        )
    longest = max(height, width)

    def floor(side: int) -> int:
        return max(multiple, side * long_side // longest // multiple * multiple)

    return floor(height), floor(width)


def sdxl_size(height: int, width: int, resolution: int = 1024, multiple: int = 64) -> tuple[int, int]:
    """(height, width) with the aspect ratio of the input, area about ``resolution``², multiples of ``multiple``."""
    if min(height, width, resolution, multiple) < 1:
        raise ValueError(
            f"sdxl_size: sizes must be positive, got {height}x{width}, resolution {resolution}, multiple {multiple}"
        )
    scale = resolution / math.sqrt(height * width)
    return (
        max(multiple, round(height * scale / multiple) * multiple),
        max(multiple, round(width * scale / multiple) * multiple),
    )


def sampling_size(height: int, width: int, resolution: int | None, size_rule: str, multiple: int) -> tuple[int, int]:
    """(height, width) at which a ``height`` x ``width`` view is sampled: ``resolution`` None keeps its size
    rounded to multiples of 64; else ``size_rule`` "area" gives :func:`sdxl_size`, "long_side" :func:`csgo_size`
    with sides that are multiples of ``multiple`` (the VAE's and UNet's downsampling together)."""
    if resolution is None:
        return max(64, round(height / 64) * 64), max(64, round(width / 64) * 64)
    if size_rule == "area":
        return sdxl_size(height, width, resolution)
    return csgo_size(height, width, resolution, multiple)


def resize_images(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """[B, H, W, 3] -> [B, height, width, 3], bicubic (unchanged when the size already matches)."""
    return resize_image(images, height, width, mode="bicubic")


def clip_preprocess(images: torch.Tensor, size: int = 224) -> torch.Tensor:
    """CLIP image preprocessing: shortest side to ``size``, centre crop ``size``², OpenAI mean/std.

    [B, H, W, 3] in [0, 1] -> [B, 3, size, size] normalised (CLIPImageProcessor's recipe, in torch).
    CSGO runs CLIPImageProcessor itself (PIL bicubic on uint8); on photos (the demo style image, bear
    views) this differs from it by 0.3/255 on average and at most 3.1/255 per pixel before normalising.
    """
    height, width = images.shape[1:3]
    short = min(height, width)
    new_h, new_w = (size, int(size * width / height)) if height == short else (int(size * height / width), size)
    resized = resize_images(images, new_h, new_w)
    top, left = (new_h - size) // 2, (new_w - size) // 2
    crop = resized[:, top : top + size, left : left + size].permute(0, 3, 1, 2)
    mean = torch.tensor(CLIP_MEAN, dtype=crop.dtype, device=crop.device).view(1, 3, 1, 1)
    std = torch.tensor(CLIP_STD, dtype=crop.dtype, device=crop.device).view(1, 3, 1, 1)
    return (crop - mean) / std
