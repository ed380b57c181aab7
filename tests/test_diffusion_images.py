"""IMAGE checks, SDXL sizes, resizing and CLIP preprocessing against transformers' CLIPImageProcessor."""

import numpy as np
import pytest
import torch
from transformers import CLIPImageProcessor

from artnvg_core.diffusion.images import CLIP_STD, check_images, clip_preprocess, csgo_size, resize_images, sdxl_size
from diffusion_tiny import one_cpu_thread  # noqa: F401  (autouse fixture)


@pytest.mark.parametrize(
    "height, width, expected",
    [(1024, 1024, (1024, 1024)), (840, 1297, (832, 1280)), (1080, 1920, (768, 1344)), (3000, 200, (3968, 256))],
)
def test_sdxl_size_keeps_aspect_and_area(height, width, expected):
    h, w = sdxl_size(height, width)
    assert (h, w) == expected and h % 64 == 0 and w % 64 == 0
    assert sdxl_size(640, 480, resolution=768) == (896, 640)


@pytest.mark.parametrize(
    "height, width, expected",
    [
        (512, 512, (1024, 1024)),  # enlarged: CSGO brings the short side up to 1024 first
        (2048, 2048, (1024, 1024)),
        (1080, 1920, (576, 1024)),  # 16:9
        (540, 960, (576, 1024)),
        (1920, 1080, (1024, 576)),
        (768, 1024, (768, 1024)),
        (2000, 3000, (672, 1024)),  # 682.7 floored to 32's
        (200, 3000, (64, 1024)),  # 68.3 -> 64
        (10, 3000, (32, 1024)),  # never below one multiple
    ],
)
def test_csgo_size_puts_the_long_side_at_1024(height, width, expected):
    assert csgo_size(height, width) == expected
    assert csgo_size(1080, 1920, long_side=768) == (416, 768)  # 432 floored to 32's
    assert csgo_size(705, 1000) == (704, 1024) and csgo_size(705, 1000, multiple=16) == (720, 1024)  # 721.9


def test_resize_is_identity_at_same_size_and_stays_in_range():
    images = torch.rand(2, 30, 40, 3)
    assert resize_images(images, 30, 40) is images
    out = resize_images(images, 64, 48)
    assert out.shape == (2, 64, 48, 3) and out.min() >= 0 and out.max() <= 1
    flat = torch.full((1, 30, 40, 3), 0.25)
    torch.testing.assert_close(resize_images(flat, 17, 23), torch.full((1, 17, 23, 3), 0.25))


def test_check_images_rejects_bad_batches():
    with pytest.raises(ValueError, match=r"views: expected an IMAGE batch \[B, H, W, 3\].*\[3, 8, 8\]"):
        check_images(torch.rand(3, 8, 8), "views")
    with pytest.raises(ValueError, match="expected float values"):
        check_images(torch.zeros(1, 8, 8, 3, dtype=torch.uint8), "views")
    with pytest.raises(ValueError, match="must lie in \\[0, 1\\]"):
        check_images(torch.full((1, 8, 8, 3), float("nan")), "views")


def test_clip_preprocess_matches_clip_image_processor():
    """Same recipe as CLIPImageProcessor, which CSGO runs (PIL bicubic on uint8): on a photo the torch
    bicubic differs by 0.3/255 on average and at most 3.1/255 (the figures in clip_preprocess's docstring)."""
    from artnvg_core.images import load_image
    from artnvg_core.stylize import DemoInputs

    photo = load_image(DemoInputs().style)[None]  # 203x256
    ours = clip_preprocess(photo)
    pixels = (photo[0].numpy() * 255).round().astype(np.uint8)
    theirs = CLIPImageProcessor()(images=[pixels], return_tensors="pt").pixel_values
    assert ours.shape == theirs.shape == (1, 3, 224, 224)
    levels = (ours - theirs).abs() * torch.tensor(CLIP_STD).view(1, 3, 1, 1) * 255  # in 0-255 pixel levels
    assert levels.mean() < 0.35 and levels.max() < 3.5
