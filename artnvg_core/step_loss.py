"""The loss of one finetune step, from its renders; on CUDA captured once as a CUDA graph.

:class:`StepLoss` holds what the terms compare against (stylized views, the VGG features of the style,
the original views) and computes, for the step's clamped renders ``image [B, H, W, 3]`` of the views
``views [B]`` (int64 indices on the device), the weighted terms of :mod:`artnvg_core.finetune`'s
docstring (L1 and SSIM toward the stylized views, NNFM toward the style, the content and
total-variation terms without stylized views).

Its inputs keep their shapes through a finetune (one camera size, one number of views per step) and it
never waits for the device, so :func:`graphed` records its forward and backward once as two CUDA graphs
(``torch.cuda.make_graphed_callables``) and replays them every step: one launch each instead of the
about 250 kernels of the VGG, the match search, SSIM and the rest, which the host would otherwise queue
one by one (the loop is bound by that at 512 px). A replay computes what the eager call computes, with
the same kernels (tests/test_step_loss.py compares them on CUDA).
"""

from __future__ import annotations

from typing import Callable

import torch

from .finetune_config import FinetuneConfig
from .losses import NNFMLoss, VGGFeatures, features_autocast, shrink_to_max_side, ssim

# (loss [], terms [T]) of a step's renders; the terms are detached, named by StepLoss.names
StepLossFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


def nchw(images: torch.Tensor) -> torch.Tensor:
    """[B, H, W, 3] -> [B, 3, H, W] (a view)."""
    return images.permute(0, 3, 1, 2)


def vgg_input(images: torch.Tensor, config: FinetuneConfig) -> torch.Tensor:
    """[B, H, W, 3] renders -> [B, 3, h, w], shrunk to ``config.nnfm_max_side``."""
    return shrink_to_max_side(nchw(images), config.nnfm_max_side)


def total_variation(images: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference of neighbouring pixels of [B, H, W, 3] images."""
    return (images[:, 1:] - images[:, :-1]).abs().mean() + (images[:, :, 1:] - images[:, :, :-1]).abs().mean()


class StepLoss:
    """The weighted loss terms of a step's renders (module docstring).

    config: the finetune's weights, VGG layers, ``nnfm_max_side`` and ``vgg_precision``.
    vgg, nnfm: the VGG and the NNFM loss against the style's features.
    stylized: [C, H, W, 3] stylized views in camera order (L1, SSIM), or None.
    originals: [C, 3, h, w] original views as the VGG sees them (:func:`vgg_input`) for the content term,
        or None.
    ``names``: the terms computed, in the order of the returned ``terms``.
    """

    def __init__(self, config: FinetuneConfig, vgg: VGGFeatures, nnfm: NNFMLoss, stylized: torch.Tensor | None,
                 originals: torch.Tensor | None):
        self.config, self.vgg, self.nnfm, self.stylized, self.originals = config, vgg, nnfm, stylized, originals
        names = ("l1", "ssim") if stylized is not None else ()
        names += ("nnfm",) if config.nnfm_weight > 0 else ()
        names += ("content",) if originals is not None else ()
        names += ("tv",) if stylized is None and config.tv_weight > 0 else ()
        self.names = names

    def _features(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        """The layers' features of ``images [B, 3, h, w]`` in ``config.vgg_precision`` (bfloat16 for bf16)."""
        with features_autocast(self.config.vgg_precision, images.device):
            return self.vgg(images, self.config.nnfm_layers)

    def _content(self, feats: dict[str, torch.Tensor], views: torch.Tensor) -> torch.Tensor:
        """ARF's content term: the features' MSE from the original views', relative to their mean square."""
        with torch.no_grad():
            reference = {k: v.float() for k, v in self._features(self.originals[views]).items()}
        layers = self.config.nnfm_layers
        return sum(((feats[k].float() - reference[k]) ** 2).mean() / (reference[k] ** 2).mean().clamp_min(1e-12)
                   for k in layers) / len(layers)

    def __call__(self, image: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``image [B, H, W, 3]`` in [0, 1] of the views ``views [B]`` -> (loss [], terms [len(names)])."""
        config, terms = self.config, []
        if self.stylized is not None:
            target = self.stylized[views]
            terms.append(config.l1_weight * (image - target).abs().mean())
            terms.append(config.ssim_weight * (1 - ssim(nchw(image), nchw(target))))
        needs_features = config.nnfm_weight > 0 or self.originals is not None
        feats = self._features(vgg_input(image, config)) if needs_features else None
        if config.nnfm_weight > 0:
            terms.append(config.nnfm_weight * self.nnfm(feats))
        if self.originals is not None:
            terms.append(config.content_weight * self._content(feats, views))
        if "tv" in self.names:
            terms.append(config.tv_weight * total_variation(image))
        if not terms:
            return image.sum() * 0, image.new_zeros(0)
        values = torch.stack(terms)
        return values.sum(), values.detach()


def graphed(step_loss: StepLoss, image_shape: tuple[int, ...], device: torch.device) -> StepLossFn:
    """``step_loss`` for renders of ``image_shape`` ([B, H, W, 3]), recorded as CUDA graphs on ``device``
    (forward and backward; after three eager warm-up calls on view 0). The returned tensors are the graphs'
    own buffers, overwritten by the next call: read them (or queue their use) before it."""
    image = torch.zeros(image_shape, device=device, requires_grad=True)
    views = torch.zeros(image_shape[0], dtype=torch.long, device=device)
    return torch.cuda.make_graphed_callables(step_loss, (image, views))
