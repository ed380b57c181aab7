"""ARF's colour transfer: match the scene's colour statistics to the style image's, exactly in the SH.

ARF (Zhang et al. 2022, ``match_colors_for_image_set`` in ARF-svox2's ``opt/util/util.py``, called
from ``opt/opt_style.py``) does, with its default flags:

1. **pre-transform**: from all training images' pixels and the style image's (already resized to
   half the render's long side) it takes the means mu_c, mu_s [3] and the covariances C_c, C_s
   [3, 3] (divided by the pixel count); it eigen-decomposes both (``torch.svd`` of the symmetric
   matrices), clamps the eigenvalues to [1e-8, 1e8] and sets
   ``A = C_s^(1/2) C_c^(-1/2)`` (symmetric square roots), ``t = mu_s - A mu_c``. The training
   images become ``clamp(A x + t, 0, 1)``; the radiance grid gets ``apply_ct`` (ARF-svox2's
   ``svox2.py``), which applies ``A`` and ``t`` to *every* SH coefficient, DC and higher bands
   alike: not the exact map of an SH colour (the offset belongs to the colour, that is to the
   DC term divided by the basis constant), so the grid only approximates the recoloured images;
2. **MSE epochs** (``--mse_num_epoches``, 2 in its scripts) fit the grid to the recoloured images;
3. **NNFM epochs**, the content term measured against the recoloured images;
4. **post-transform**: the training views are rendered (clamped to [0, 1]), the transform is
   estimated again from them to the style and applied to the grid the same way.

We follow 1, 3 and 4, with one difference: :func:`recolor_scene` applies the transform *exactly*
to 3D Gaussians (colour = SH . basis + 0.5 is affine in the SH, see there), so the scene renders
the recoloured images without the MSE epochs of step 2, which we skip. Statistics are computed
in float64.

Degenerate inputs stay finite: a flat or greyscale style has a singular covariance, handled by
the eigenvalue floor as in ARF (the scene takes the flat colour, or turns grey); content renders
of a single flat colour (all black, for example) have no covariance to whiten, and ARF's floor
would amplify colours 10^4-fold, so the transform falls back to shifting the mean only
(``A = I``, ``t = mu_s - mu_c``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from ..images import check_image_values
from ..scene import SH_C0, GaussianScene

EIGENVALUE_RANGE = (1e-8, 1e8)  # ARF's clamp on both covariances' eigenvalues


@dataclass(frozen=True)
class ColorTransform:
    """``colour' = matrix @ colour + offset`` for RGB colours in [0, 1] units (float64).

    matrix: [3, 3]; offset: [3].
    """

    matrix: torch.Tensor
    offset: torch.Tensor

    def apply(self, images: torch.Tensor) -> torch.Tensor:
        """``images [..., 3]`` transformed (not clamped), in the images' dtype and device."""
        matrix, offset = self.matrix.to(images), self.offset.to(images)
        return images @ matrix.T + offset


def rgb_pixels(images: torch.Tensor, what: str) -> torch.Tensor:
    """``images [..., 3]`` as float64 pixels [P, 3]; a ValueError naming ``what`` unless they are RGB, some, and
    floats in [0, 1] (:func:`~artnvg_core.images.check_image_values`: not 8-bit values, not NaN)."""
    if images.ndim < 2 or images.shape[-1] != 3:
        raise ValueError(f"{what} must be RGB [..., 3] (an alpha channel dropped), got shape {tuple(images.shape)}")
    if images.numel() == 0:
        raise ValueError(f"{what} has no pixels")
    check_image_values(images, what)
    return images.detach().reshape(-1, 3).to(torch.float64)


def color_statistics(images: torch.Tensor, name: str = "images") -> tuple[torch.Tensor, torch.Tensor]:
    """Mean [3] and covariance [3, 3] (divided by the pixel count, as ARF) of all pixels of
    ``images [..., 3]``, in float64; ``name`` is for error messages."""
    pixels = rgb_pixels(images, f"color transfer: {name}")
    mean = pixels.mean(0)
    centred = pixels - mean
    return mean, centred.T @ centred / len(pixels)


def _matrix_power(covariance: torch.Tensor, power: float) -> torch.Tensor:
    """``covariance^power`` of a symmetric PSD [3, 3], eigenvalues clamped to ARF's range."""
    eigenvalues, vectors = torch.linalg.eigh(covariance)
    return vectors @ torch.diag(eigenvalues.clamp(*EIGENVALUE_RANGE) ** power) @ vectors.T


def match_colors(content: torch.Tensor, style: torch.Tensor) -> ColorTransform:
    """ARF's transform taking the colour statistics of ``content [..., 3]`` (e.g. the scene's
    renders [C, H, W, 3], clamped to [0, 1]) to those of ``style [..., 3]``: the mean and the
    covariance of ``transform.apply(content)`` equal the style's (up to the eigenvalue floor).
    Content of a single flat colour gets the mean shift only (module docstring)."""
    mu_c, cov_c = color_statistics(content, "content renders")
    mu_s, cov_s = color_statistics(style, "style image")
    if torch.linalg.eigvalsh(cov_c).max() <= EIGENVALUE_RANGE[0]:
        matrix = torch.eye(3, dtype=torch.float64, device=mu_c.device)
    else:
        matrix = _matrix_power(cov_s.to(mu_c.device), 0.5) @ _matrix_power(cov_c, -0.5)
    return ColorTransform(matrix, mu_s.to(mu_c.device) - matrix @ mu_c)


def recolor_scene(scene: GaussianScene, transform: ColorTransform) -> GaussianScene:
    """``scene`` with every Gaussian's colour c(dir) = SH_C0 dc + sum_l Y_l(dir) rest_l + 0.5
    replaced by ``matrix @ c(dir) + offset`` for every viewing direction:

        dc'   = matrix @ dc + (matrix @ 0.5 + offset - 0.5) / SH_C0
        rest' = matrix @ rest                                   (every higher band)

    Exact before the renderer's clamp of colours at 0: wherever no Gaussian colour is clamped,
    a render of the result is ``matrix @ rgb + offset * alpha`` (``offset`` itself where the
    pixel is opaque). Computed in float64; the scene's dtype is kept.
    """
    matrix = transform.matrix.to(scene.sh.device)
    offset = transform.offset.to(scene.sh.device)
    sh = scene.sh.detach().to(torch.float64) @ matrix.T
    sh[:, 0] += (matrix @ torch.full_like(offset, 0.5) + offset - 0.5) / SH_C0
    return dataclasses.replace(scene, sh=sh.to(scene.sh.dtype))
