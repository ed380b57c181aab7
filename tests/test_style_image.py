"""The style image's one rule of shape, and its reading checked whole (artnvg_core/style_image.py)."""

import pytest
import torch
from PIL import Image

from artnvg_core.style_image import MAX_STYLE_ASPECT, check_style_size, read_style_image
from artnvg_core.stylize import DemoInputs


def test_a_style_image_may_be_32_times_as_long_as_it_is_wide_either_way():
    for width, height in [(1, 1), (2 * MAX_STYLE_ASPECT, 2), (3, 3 * MAX_STYLE_ASPECT)]:
        check_style_size(width, height)
    for width, height in [(2 * MAX_STYLE_ASPECT + 1, 2), (3, 3 * MAX_STYLE_ASPECT + 1), (20000, 2)]:
        with pytest.raises(ValueError, match=rf"^image size: {width}x{height} pixels; a style image may be at most "
                                             r"32 times as long as it is wide \(its features are matched at the "
                                             r"renders' size\); crop it$"):
            check_style_size(width, height)


def test_a_style_file_is_checked_from_its_header_then_decoded_whole(tmp_path):
    Image.new("RGB", (20000, 2), (200, 30, 30)).save(tmp_path / "line.png")
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'line.png'}: image size: 20000x2 pixels; a style image"):
        read_style_image(tmp_path / "line.png")
    whole = DemoInputs().style.read_bytes()
    (tmp_path / "cut.jpg").write_bytes(whole[:5000])  # its header reads: only decoding finds the cut
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'cut.jpg'}: not a readable image \(image file is truncated"):
        read_style_image(tmp_path / "cut.jpg")
    image = read_style_image(DemoInputs().style)
    assert image.dtype == torch.float32 and image.shape[-1] == 3 and 0 <= image.min() and image.max() <= 1
