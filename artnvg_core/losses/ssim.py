"""Structural similarity (SSIM) as used by 3DGS / splatfacto training.

Per channel, local statistics under an 11x11 Gaussian window (sigma 1.5) with zero padding
(output the same size as the input), C1 = 0.01^2, C2 = 0.03^2 (data range 1), averaged over
the SSIM map. Computed in float32 whatever the input dtype or autocast state: on CUDA (with Triton) by
two fused kernels, one forward and one backward (:mod:`.ssim_triton`), elsewhere by PyTorch operations
(:func:`separable_ssim`: the 2D window is separable, so it is applied as two 1D passes). The two agree
to float32 rounding.

The map is written in the equivalent form (l, cs as in the textbook formula)

    l  = 1 - (mu_a - mu_b)^2 / (mu_a^2 + mu_b^2 + C1)
    cs = 1 - var(a - b) / (var_a + var_b + C2)

(2 mu_a mu_b = mu_a^2 + mu_b^2 - (mu_a - mu_b)^2, and likewise for the covariance), whose
gradient is exactly zero for identical images: the textbook form leaves rounding noise
there, which Adam's normalised steps would turn into full-size parameter updates.
"""

from __future__ import annotations

from functools import lru_cache

import torch
import torch.nn.functional as F

from ..devices import triton_available

C1 = 0.01**2
C2 = 0.03**2


def gaussian_window_1d(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Normalised 1D Gaussian ``[size]`` centred on ``size // 2`` (float32)."""
    offsets = torch.arange(size, dtype=torch.float32) - size // 2
    window = torch.exp(-offsets.square() / (2 * sigma**2))
    return window / window.sum()


@lru_cache(maxsize=16)
def window_on(size: int, sigma: float, device: torch.device) -> torch.Tensor:
    """:func:`gaussian_window_1d` on ``device``, copied there once (a copy to a GPU waits for its queued work)."""
    with torch.inference_mode(False):
        return gaussian_window_1d(size, sigma).to(device)


def _blur(maps: torch.Tensor, window: torch.Tensor) -> torch.Tensor:
    """Zero-padded separable Gaussian blur of every channel of ``maps [B, K, H, W]``."""
    channels, size = maps.shape[1], window.numel()
    horizontal = window.view(1, 1, 1, size).expand(channels, 1, 1, size)
    vertical = window.view(1, 1, size, 1).expand(channels, 1, size, 1)
    maps = F.conv2d(maps, horizontal, padding=(0, size // 2), groups=channels)
    return F.conv2d(maps, vertical, padding=(size // 2, 0), groups=channels)


def ssim(
    a: torch.Tensor, b: torch.Tensor, window_size: int = 11, sigma: float = 1.5, per_image: bool = False
) -> torch.Tensor:
    """SSIM of images ``a, b [B, C, H, W]`` in [0, 1]: a scalar, or ``[B]`` if ``per_image``.

    Differentiable in both inputs; 1 for identical images.
    """
    if a.shape != b.shape or a.dim() != 4:
        raise ValueError(
            f"ssim: expected two [B, C, H, W] images of one shape, got {tuple(a.shape)} and {tuple(b.shape)}"
        )
    if window_size < 1 or window_size % 2 == 0:
        raise ValueError(f"ssim: window_size must be a positive odd number, got {window_size}")
    window = window_on(window_size, float(sigma), a.device)
    if a.device.type == "cuda" and triton_available():
        from .ssim_triton import fused_ssim  # imports Triton: only where it runs

        return fused_ssim(a, b, window, C1, C2, per_image)
    return separable_ssim(a, b, window, per_image)


def separable_ssim(a: torch.Tensor, b: torch.Tensor, window: torch.Tensor, per_image: bool = False) -> torch.Tensor:
    """:func:`ssim` of checked ``a, b [B, C, H, W]`` by PyTorch operations: the six maps blurred by two
    separable passes of the 1D ``window [size]`` (on their device), then the map (module docstring)."""
    with torch.autocast(a.device.type, enabled=False):
        a, b = a.float(), b.float()
        channels = a.shape[1]
        diff = a - b
        stats = _blur(torch.cat([a, b, a * a, b * b, diff, diff * diff], dim=1), window)
        mu_a, mu_b, mean_aa, mean_bb, mu_diff, mean_diff_sq = stats.split(channels, dim=1)
        var_a = mean_aa - mu_a.square()
        var_b = mean_bb - mu_b.square()
        luminance = 1 - mu_diff.square() / (mu_a.square() + mu_b.square() + C1)
        contrast_structure = 1 - (mean_diff_sq - mu_diff.square()) / (var_a + var_b + C2)
        ssim_map = luminance * contrast_structure
    return ssim_map.flatten(1).mean(1) if per_image else ssim_map.mean()
