"""The style image: the one rule of its shape, for the command line and the nodes alike, and its reading from
a file, checked whole before any other work.

A style image may be at most :data:`MAX_STYLE_ASPECT` times as long as it is wide: the finetune sizes it to
the long side of the renders its VGG sees (128 px for the bundled demo), and its relu3 features, two 2x
poolings down, need it 4 px across there.
"""

from __future__ import annotations

import os

import torch

from .images import image_size, load_image

MAX_STYLE_ASPECT = 32


def check_style_size(width: int, height: int) -> None:
    """ValueError (naming the size, not the image: the caller names it) when a style image of ``width`` x
    ``height`` pixels is longer than :data:`MAX_STYLE_ASPECT` times its width."""
    if max(width, height) > MAX_STYLE_ASPECT * min(width, height):
        raise ValueError(f"image size: {width}x{height} pixels; a style image may be at most {MAX_STYLE_ASPECT} "
                         "times as long as it is wide (its features are matched at the renders' size); crop it")


def read_style_image(path: str | os.PathLike) -> torch.Tensor:
    """The style image at ``path`` as [H, W, 3] float32 in [0, 1]; ValueError naming ``path`` for a file that
    is missing, not a regular file or not an image, one over the pixel budget
    (:data:`artnvg_core.images.MAX_IMAGE_PIXELS`) or refused by :func:`check_style_size` (both from its
    header, before it is decoded), or one that does not decode (a truncated or corrupt file)."""
    width, height = image_size(path)
    try:
        check_style_size(width, height)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None
    return load_image(path)
