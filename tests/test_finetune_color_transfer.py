"""ARF's colour transfer: the statistics it matches, its exact SH mapping, degenerate inputs."""

import math

import numpy as np
import pytest
import scipy.linalg
import torch

from artnvg_core.cameras import CameraSet, look_at
from artnvg_core.finetune.color_transfer import ColorTransform, color_statistics, match_colors, recolor_scene
from artnvg_core.raster import render
from artnvg_core.scene import SH_C0, GaussianScene


def correlated_colors(seed: int, count: int = 4000) -> torch.Tensor:
    """[count, 3] colours in [0, 1] with a full, non-diagonal covariance."""
    g = torch.Generator().manual_seed(seed)
    mixing = torch.rand(3, 3, generator=g, dtype=torch.float64) * 0.3 + 0.05 * torch.eye(3, dtype=torch.float64)
    return (torch.rand(count, 3, generator=g, dtype=torch.float64) @ mixing.T + 0.1).clamp(0, 1)


def test_transformed_content_has_the_style_statistics_and_matches_an_independent_formula():
    content, style = correlated_colors(0), correlated_colors(1, 3000).reshape(50, 60, 3)
    transform = match_colors(content.reshape(2, 40, 50, 3), style)
    mean, cov = color_statistics(transform.apply(content))
    style_mean, style_cov = color_statistics(style)
    torch.testing.assert_close(mean, style_mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(cov, style_cov, rtol=0, atol=1e-12)
    # ARF's choice among the maps with these statistics: C_s^1/2 C_c^-1/2 (scipy's matrix square roots)
    content_mean, content_cov = color_statistics(content)
    expected = scipy.linalg.sqrtm(style_cov.numpy()) @ np.linalg.inv(scipy.linalg.sqrtm(content_cov.numpy()))
    np.testing.assert_allclose(transform.matrix.numpy(), expected.real, rtol=0, atol=1e-9)
    np.testing.assert_allclose(transform.offset.numpy(), (style_mean.numpy() - expected.real @ content_mean.numpy()),
                               rtol=0, atol=1e-9)


def _scene(n: int = 60, degree: int = 2) -> GaussianScene:
    """Random float64 Gaussians in front of the cameras, colours in about [0.2, 0.8] from every direction."""
    g = torch.Generator().manual_seed(3)
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.04
    sh[:, 0] = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 0.5 - 0.25) / SH_C0
    return GaussianScene(
        means=torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5,
        quats=torch.randn(n, 4, generator=g, dtype=torch.float64),
        log_scales=torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.3 - 2.0,
        opacity_logits=torch.randn(n, generator=g, dtype=torch.float64),
        sh=sh,
    )


def _cameras(size: int = 40) -> CameraSet:
    eyes = torch.tensor([[0.0, 0.0, -3.0], [2.0, -0.5, -2.0]], dtype=torch.float64)
    w2c = look_at(eyes, torch.zeros(3, dtype=torch.float64), torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    k = torch.tensor([[45.0, 0, size / 2], [0, 45.0, size / 2], [0, 0, 1]], dtype=torch.float64)
    return CameraSet(w2c, k.expand(2, 3, 3).clone(), size, size, ["a", "b"])


def test_recoloured_scene_renders_the_recoloured_images_exactly():
    """Colour is affine in the SH, so the recoloured Gaussians render ``A rgb + t alpha`` exactly
    (no Gaussian colour reaches the renderer's clamp at 0 here), view-dependent bands included."""
    scene, cameras = _scene(), _cameras()
    transform = ColorTransform(torch.tensor([[0.8, 0.15, -0.05], [0.1, 0.7, 0.2], [-0.1, 0.2, 0.9]], dtype=torch.float64),
                               torch.tensor([0.12, -0.03, 0.08], dtype=torch.float64))
    with torch.no_grad():
        before, after = render(scene, cameras), render(recolor_scene(scene, transform), cameras)
    assert before.alpha.max() > 0.9 and before.alpha.min() < 0.1  # opaque and transparent pixels both tested
    expected = transform.apply(before.rgb) + (before.alpha - 1) * transform.offset
    torch.testing.assert_close(after.rgb, expected, rtol=0, atol=1e-12)
    torch.testing.assert_close(after.alpha, before.alpha, rtol=0, atol=0)


def test_recoloured_scene_keeps_dtype_and_other_fields():
    scene = _scene().to(dtype=torch.float32)
    result = recolor_scene(scene, ColorTransform(torch.eye(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)))
    assert result.sh.dtype == torch.float32
    torch.testing.assert_close(result.sh, scene.sh, rtol=0, atol=1e-7)
    assert result.means is scene.means and result.opacity_logits is scene.opacity_logits


def test_flat_style_gives_its_colour_and_greyscale_style_gives_grey():
    content = correlated_colors(4).reshape(40, 100, 3)
    flat = torch.tensor([0.2, 0.5, 0.7], dtype=torch.float64).expand(30, 30, 3)
    recoloured = match_colors(content, flat).apply(content)
    assert torch.isfinite(recoloured).all()
    torch.testing.assert_close(recoloured, flat[:1, :1].expand_as(recoloured), rtol=0, atol=2e-3)
    grey = correlated_colors(5, 900).mean(-1, keepdim=True).expand(900, 3).reshape(30, 30, 3)
    recoloured = match_colors(content, grey).apply(content)
    assert torch.isfinite(recoloured).all()
    assert (recoloured - recoloured.mean(-1, keepdim=True)).abs().max() < 2e-3
    assert recoloured.std() > 0.05  # still has its contrast, in grey


def test_all_black_content_gets_the_mean_shift_only():
    style = correlated_colors(6).reshape(40, 100, 3)
    transform = match_colors(torch.zeros(3, 16, 16, 3), style)
    torch.testing.assert_close(transform.matrix, torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(transform.offset, style.reshape(-1, 3).mean(0))


@pytest.mark.parametrize("content, style, name", [
    (torch.rand(2, 8, 8, 3), torch.rand(8, 8, 4), "style image"),
    (torch.rand(2, 8, 8, 4), torch.rand(8, 8, 3), "content renders"),
    (torch.rand(2, 8, 8, 3), torch.full((8, 8, 3), math.nan), "style image"),
    (torch.rand(0, 8, 8, 3), torch.rand(8, 8, 3), "content renders"),
])
def test_bad_inputs_rejected(content, style, name):
    with pytest.raises(ValueError, match=name):
        match_colors(content, style)
