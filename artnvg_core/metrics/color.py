"""How far a set of renders' colours are from a style image's palette (lower is closer).

- ``histogram``: total-variation distance between the two joint RGB histograms
  (``bins`` per channel over [0, 1]): 0 for the same palette, 1 for disjoint ones;
- ``mean_cov``: the 2-Wasserstein distance between the Gaussians fitted to the two sets of
  colours, ``sqrt(|mu_a - mu_b|^2 + tr(C_a + C_b - 2 (C_a^1/2 C_b C_a^1/2)^1/2))``, in [0, 1]
  colour units: 0 when means and covariances agree (what ARF's colour transfer achieves).

Both look at colours only, not where they are; they take RGB floats in [0, 1] (8-bit values and NaN are a
ValueError), clamped to [0, 1]; float64.
"""

from __future__ import annotations

import torch

from ..finetune.color_transfer import color_statistics, rgb_pixels


def _sqrtm(matrix: torch.Tensor) -> torch.Tensor:
    """Square root of a symmetric PSD [3, 3] (negative rounding errors clipped)."""
    eigenvalues, vectors = torch.linalg.eigh(matrix)
    return vectors @ torch.diag(eigenvalues.clamp_min(0).sqrt()) @ vectors.T


def _pixels(images: torch.Tensor, name: str) -> torch.Tensor:
    """``images [..., 3]``, floats in [0, 1] (checked: :func:`~artnvg_core.finetune.color_transfer.rgb_pixels`), as
    float64 CPU pixels [P, 3] clamped to [0, 1]."""
    return rgb_pixels(images, f"color distance: {name}").cpu().clamp(0, 1)


MAX_BINS = 256  # per channel: a joint histogram of 256^3 counts takes 128 MB


def histogram_distance(images: torch.Tensor, style: torch.Tensor, bins: int = 8) -> float:
    """Total variation between the joint RGB histograms of ``images [..., 3]`` and ``style [..., 3]``, ``bins``
    (1 to :data:`MAX_BINS`) per channel."""
    if isinstance(bins, bool) or not (isinstance(bins, int) and 1 <= bins <= MAX_BINS):
        raise ValueError(f"histogram_distance: bins must be an int from 1 to {MAX_BINS}, got {bins!r}")

    def histogram(pixels: torch.Tensor) -> torch.Tensor:
        index = (pixels * bins).long().clamp_max(bins - 1)
        flat = (index[:, 0] * bins + index[:, 1]) * bins + index[:, 2]
        return torch.bincount(flat, minlength=bins**3).double() / len(flat)

    return 0.5 * float((histogram(_pixels(images, "images")) - histogram(_pixels(style, "style image"))).abs().sum())


def mean_cov_distance(images: torch.Tensor, style: torch.Tensor) -> float:
    """2-Wasserstein distance between Gaussian fits of the colours of ``images`` and ``style``."""
    mu_a, cov_a = color_statistics(_pixels(images, "images"), "images")
    mu_b, cov_b = color_statistics(_pixels(style, "style image"), "style image")
    root_a = _sqrtm(cov_a)
    cross = _sqrtm(root_a @ cov_b @ root_a)
    squared = (mu_a - mu_b).square().sum() + torch.trace(cov_a + cov_b - 2 * cross)
    return float(squared.clamp_min(0).sqrt())


def color_distances(images: torch.Tensor, style: torch.Tensor) -> dict[str, float]:
    """``{"histogram": ..., "mean_cov": ...}`` of ``images [..., 3]`` to ``style [..., 3]``."""
    return {"histogram": histogram_distance(images, style), "mean_cov": mean_cov_distance(images, style)}
