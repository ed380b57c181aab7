"""Colour distances of renders to a style image: zero for the same palette, exact on known cases."""

import math

import numpy as np
import pytest
import scipy.linalg
import torch

from artnvg_core.finetune.color_transfer import color_statistics
from artnvg_core.metrics.color import color_distances, histogram_distance, mean_cov_distance


def colors(seed: int, count: int = 3000) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(count, 3, generator=g, dtype=torch.float64) @ torch.tensor(
        [[0.5, 0.1, 0.0], [0.2, 0.4, 0.1], [0.0, 0.2, 0.3]], dtype=torch.float64).T + 0.1


def test_the_same_palette_is_at_distance_zero_whatever_the_layout():
    a = colors(0)
    shuffled = a[torch.randperm(len(a), generator=torch.Generator().manual_seed(1))].reshape(30, 100, 3)
    assert color_distances(a.reshape(3, 1000, 3), shuffled) == pytest.approx({"histogram": 0.0, "mean_cov": 0.0}, abs=1e-7)


def test_disjoint_palettes_have_histogram_distance_one():
    assert histogram_distance(torch.full((10, 10, 3), 0.05), torch.full((5, 5, 3), 0.95)) == 1.0
    half = torch.cat([torch.full((50, 3), 0.05), torch.full((50, 3), 0.95)])
    assert histogram_distance(half, torch.full((20, 3), 0.95)) == pytest.approx(0.5)
    red, green = torch.tensor([0.95, 0.05, 0.05]).expand(10, 3), torch.tensor([0.05, 0.95, 0.05]).expand(10, 3)
    assert histogram_distance(red, green) == 1.0  # the joint histogram, not the channels' own


def test_mean_cov_distance_matches_scipy_on_non_commuting_covariances():
    """W2^2 = |mu_a - mu_b|^2 + tr(C_a + C_b) - 2 tr(sqrtm(C_a C_b)) (the trace is the same for
    the symmetric form), scipy's matrix square root."""
    a, b = colors(3), torch.rand(2000, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 0.5
    (mean_a, cov_a), (mean_b, cov_b) = color_statistics(a), color_statistics(b)
    cross = np.trace(scipy.linalg.sqrtm(cov_a.numpy() @ cov_b.numpy())).real
    expected = math.sqrt(float((mean_a - mean_b).square().sum() + torch.trace(cov_a + cov_b)) - 2 * cross)
    assert mean_cov_distance(a, b) == pytest.approx(expected, rel=1e-9)


def test_mean_cov_distance_of_a_scaled_and_shifted_copy():
    """b = k a + c has C_b = k^2 C_a, so W2^2 = |mu_b - mu_a|^2 + (1 - k)^2 tr(C_a)."""
    a = colors(2)
    k, shift = 0.6, torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)
    b = k * a + shift
    mean_a, cov_a = color_statistics(a)
    expected = math.sqrt(float(((k - 1) * mean_a + shift).square().sum() + (1 - k) ** 2 * torch.trace(cov_a)))
    assert mean_cov_distance(a, b) == pytest.approx(expected, rel=1e-9)
    assert mean_cov_distance(b, a) == pytest.approx(expected, rel=1e-9)


def test_pixels_other_than_rgb_floats_in_zero_to_one_are_refused():
    """8-bit values were clamped to 0 or 1 (distances of a black-and-white palette); NaN and an alpha channel stopped
    with torch's RuntimeErrors from the histogram."""
    images, style = colors(0).reshape(1, 50, 60, 3), colors(1)
    for bad, got in [((images * 255).round().to(torch.uint8), "expected floats in \\[0, 1\\], got a torch.uint8 tensor"),
                     (images * 255, "expected floats in \\[0, 1\\], got values up to"),
                     (images * float("nan"), "expected floats in \\[0, 1\\], got NaN or infinite values"),
                     (torch.cat([images, torch.ones_like(images[..., :1])], -1), "must be RGB \\[..., 3\\]"),
                     (images[:0], "has no pixels")]:
        for distance in (histogram_distance, mean_cov_distance):
            with pytest.raises(ValueError, match=f"^color distance: images:? {got}"):
                distance(bad, style)
            with pytest.raises(ValueError, match=f"^color distance: style image:? {got}"):
                distance(style, bad)


@pytest.mark.parametrize("bins", [0, 257, 10**4, 8.0, True])
def test_bins_other_than_an_int_from_1_to_256_are_refused(bins):
    """10^4 bins a channel asked for 8 TB of joint histogram counts; 8.0 failed inside torch.bincount."""
    with pytest.raises(ValueError, match=f"^histogram_distance: bins must be an int from 1 to 256, got {bins!r}$"):
        histogram_distance(colors(0), colors(1), bins=bins)
