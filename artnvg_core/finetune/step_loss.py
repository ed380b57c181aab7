"""The loss of one finetune step, from its renders; on CUDA captured once as a CUDA graph.

:class:`StepLoss` holds what the terms compare against (stylized views, the VGG features of the style,
the original views) and computes, for the step's clamped renders ``image [B, H, W, 3]`` of the views
``views [B]`` (int64 indices on the device), the weighted terms of :mod:`artnvg_core.finetune.loop`'s
docstring (L1 and SSIM toward the stylized views, NNFM toward the style, the content and
total-variation terms without stylized views). With per-pixel ``weights`` (a region's coverage,
:func:`artnvg_core.selection.coverage`) every term is the weighted mean over the pixels (over the VGG
terms' positions, the weights area-averaged to them); SSIM is that of the render composited over the
stylized view by the weights, its dissimilarity divided by the weights' mean.

Its inputs keep their shapes through a finetune (one camera size, one number of views per step) and it
never waits for the device, so :func:`graphed` records its forward and backward once as two CUDA graphs
(``torch.cuda.make_graphed_callables``; where :func:`can_graph` says it may) and replays them every step:
one launch each instead of the about 250 kernels of the VGG, the match search, SSIM and the rest, which the
host would otherwise queue one by one (the loop is bound by that at 512 px). A replay computes what the
eager call computes, with the same kernels (tests/test_finetune_step_loss.py compares them on CUDA).
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

from ..losses import NNFMLoss, VGGFeatures, features_autocast, shrink_to_max_side, ssim
from ..progress import ProgressFn, StopFn, check_stop
from .config import FinetuneConfig

# (loss [], terms [T]) of a step's renders; the terms are detached, named by StepLoss.names
StepLossFn = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]

# Fewest iterations for which recording the graphs pays (FinetuneConfig.cuda_graph None). On an H100 the
# recording costs about 0.43 s (its warm-up calls and capture, with sympy's import that torch.autograd.grad
# brings into a capture) and saves about 1.3 ms a step (BENCHMARKS.md, First look: 0.3 s lost over the
# preview's 100 steps, 0.9 s won over 1,000): even from 325 steps; sympy's bytecode compiled afresh adds 2 s
# (1,800 steps). 500: the preview (100) and `fast` (300) run eagerly, `balanced` and `paper` (1,000) replay.
GRAPH_MIN_ITERATIONS = 500


def nchw(images: torch.Tensor) -> torch.Tensor:
    """[B, H, W, 3] -> [B, 3, H, W] (a view)."""
    return images.permute(0, 3, 1, 2)


def nchw_to_nhwc(maps: torch.Tensor) -> torch.Tensor:
    """[B, C, H, W] -> [B, H, W, C] (a view)."""
    return maps.permute(0, 2, 3, 1)


def vgg_input(images: torch.Tensor, config: FinetuneConfig) -> torch.Tensor:
    """[B, H, W, 3] renders -> [B, 3, h, w], shrunk to ``config.nnfm_max_side``."""
    return shrink_to_max_side(nchw(images), config.nnfm_max_side)


def weighted_mean(values: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
    """The mean of ``values [B, H, W, C]``, each pixel weighed by ``weights [B, H, W]`` (None: plain mean)."""
    if weights is None:
        return values.mean()
    return (values * weights[..., None]).sum() / (weights.sum() * values.shape[-1]).clamp_min(1e-12)


def total_variation(images: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean absolute difference of neighbouring pixels of [B, H, W, 3] images (each pair weighed by its second
    pixel's ``weights [B, H, W]`` when given)."""
    down, right = (None, None) if weights is None else (weights[:, 1:], weights[:, :, 1:])
    return (weighted_mean((images[:, 1:] - images[:, :-1]).abs(), down)
            + weighted_mean((images[:, :, 1:] - images[:, :, :-1]).abs(), right))


def _at(weights: torch.Tensor | None, size: torch.Size) -> torch.Tensor | None:
    """``weights [B, H, W]`` area-averaged to ``size`` (h, w): [B, h, w] (None stays None)."""
    return None if weights is None else F.interpolate(weights[:, None], size=tuple(size), mode="area")[:, 0]


def _cache_budget(device: torch.device) -> int:
    """Bytes :class:`ContentReference` may keep: a quarter of a CUDA device's free memory, 1 GiB elsewhere."""
    return torch.cuda.mem_get_info(device)[0] // 4 if device.type == "cuda" else 2**30


class ContentReference:
    """The original views' VGG features for the content term, by view.

    features(images [B, 3, h, w]) -> {layer: [B, C, h', w']}: the VGG of the step's renders; originals
    [V, 3, h, w]: every view as the VGG sees it. The features of all V views are computed once (a view at a
    time, as a step of one view computes its render's, so that an unchanged render matches exactly) and kept
    when they fit in :func:`_cache_budget` (``cached``); else those of the step's views are computed every
    step: the same values either way. ``progress(views done, V, {})`` follows that first pass (as it starts, after
    each view, and V once done) and ``should_stop`` is checked before each view.
    ``reference(views [B]) -> ({layer: [B, C, h', w'] float32}, {layer: [] their mean square})``.
    """

    def __init__(self, features: Callable[[torch.Tensor], dict[str, torch.Tensor]], originals: torch.Tensor,
                 progress: ProgressFn | None = None, should_stop: StopFn | None = None):
        self.features, self.originals = features, originals
        report, count = progress or (lambda *args: None), len(originals)
        with torch.no_grad():
            report(0, count, {})
            check_stop(should_stop)
            first = features(originals[:1])
            per_view = sum(v.numel() * v.element_size() for v in first.values())
            self.cached = per_view * count <= _cache_budget(originals.device)
            if self.cached:
                views = [first]
                for i in range(1, count):
                    report(i, count, {})
                    check_stop(should_stop)
                    views.append(features(originals[i:i + 1]))
                self.store = {k: torch.cat([view[k] for view in views]) for k in first}
                self.power = {k: v.float().square().flatten(1).mean(1) for k, v in self.store.items()}
            report(count, count, {})

    def __call__(self, views: torch.Tensor) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        if self.cached:
            return ({k: v[views].float() for k, v in self.store.items()},
                    {k: v[views].mean() for k, v in self.power.items()})
        with torch.no_grad():
            reference = {k: v.float() for k, v in self.features(self.originals[views]).items()}
        return reference, {k: v.square().mean() for k, v in reference.items()}


class StepLoss:
    """The weighted loss terms of a step's renders (module docstring).

    config: the finetune's weights, VGG layers, ``nnfm_max_side`` and ``vgg_precision``.
    vgg, nnfm: the VGG and the NNFM loss against the style's features.
    stylized: [C, H, W, 3] stylized views in camera order (L1, SSIM), or None.
    originals: [C, 3, h, w] original views as the VGG sees them (:func:`vgg_input`) for the content term,
        or None.
    weights: [C, H, W] per-pixel weights >= 0 in camera order (module docstring), or None.
    progress, should_stop: follow and can end the content term's first pass over ``originals``
        (:class:`ContentReference`); ``should_stop`` is also asked within each call, in the VGG's convolutions
        and NNFM's search and in their backward pass (:class:`~artnvg_core.progress.Cancelled`; a call at 512 px
        takes seconds on a CPU).
    ``names``: the terms computed, in the order of the returned ``terms``.
    """

    def __init__(self, config: FinetuneConfig, vgg: VGGFeatures, nnfm: NNFMLoss, stylized: torch.Tensor | None,
                 originals: torch.Tensor | None, weights: torch.Tensor | None = None,
                 progress: ProgressFn | None = None, should_stop: StopFn | None = None):
        self.config, self.vgg, self.nnfm, self.stylized, self.weights = config, vgg, nnfm, stylized, weights
        self.should_stop = should_stop
        self.content_reference = (None if originals is None
                                  else ContentReference(self._features, originals, progress, should_stop))
        names = ("l1", "ssim") if stylized is not None else ()
        names += ("nnfm",) if config.nnfm_weight > 0 else ()
        names += ("content",) if originals is not None else ()
        names += ("tv",) if stylized is None and config.tv_weight > 0 else ()
        self.names = names

    def _features(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        """The layers' features of ``images [B, 3, h, w]`` in ``config.vgg_precision`` (bfloat16 for bf16)."""
        with features_autocast(self.config.vgg_precision, images.device):
            return self.vgg(images, self.config.nnfm_layers, self.should_stop)

    def _content(self, feats: dict[str, torch.Tensor], views: torch.Tensor, weights: torch.Tensor | None) -> torch.Tensor:
        """ARF's content term: the features' MSE from the original views', relative to their mean square."""
        reference, power = self.content_reference(views)
        layers = self.config.nnfm_layers
        errors = (weighted_mean(nchw_to_nhwc(feats[k].float() - reference[k]).square(), _at(weights, feats[k].shape[-2:]))
                  / power[k].clamp_min(1e-12) for k in layers)
        return sum(errors) / len(layers)

    def __call__(self, image: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``image [B, H, W, 3]`` in [0, 1] of the views ``views [B]`` -> (loss [], terms [len(names)])."""
        config, terms = self.config, []
        weights = None if self.weights is None else self.weights[views]
        if self.stylized is not None:
            target = self.stylized[views]
            terms.append(config.l1_weight * weighted_mean((image - target).abs(), weights))
            if weights is None:
                terms.append(config.ssim_weight * (1 - ssim(nchw(image), nchw(target))))
            else:
                composite = torch.lerp(target, image, weights[..., None])
                dissimilarity = (1 - ssim(nchw(composite), nchw(target))) / weights.mean().clamp_min(1e-12)
                terms.append(config.ssim_weight * dissimilarity)
        needs_features = config.nnfm_weight > 0 or self.content_reference is not None
        feats = self._features(vgg_input(image, config)) if needs_features else None
        if config.nnfm_weight > 0:
            terms.append(config.nnfm_weight * self.nnfm(feats, weights, self.should_stop))
        if self.content_reference is not None:
            terms.append(config.content_weight * self._content(feats, views, weights))
        if "tv" in self.names:
            terms.append(config.tv_weight * total_variation(image, weights))
        if not terms:
            return image.sum() * 0, image.new_zeros(0)
        values = torch.stack(terms)
        return values.sum(), values.detach()


def can_graph(device: torch.device) -> bool:
    """Whether :func:`graphed` may record on ``device``: a CUDA device under PyTorch's own caching allocator.
    Under ``cudaMallocAsync`` (``PYTORCH_CUDA_ALLOC_CONF=backend:cudaMallocAsync``, which ComfyUI sets unless
    started with ``--disable-cuda-malloc``) memory allocated during a capture is not addressable yet, so Triton
    refuses to launch on it, and a failed capture leaves allocations that crash the process when freed."""
    return device.type == "cuda" and torch.cuda.get_allocator_backend() == "native"


class _Graphed:
    """A :class:`StepLoss`'s CUDA graphs, holding the step loss itself: the graphs read its tensors (the kept
    content features, the stylized views) by address, so they must live as long as the graphs do."""

    def __init__(self, step_loss: StepLoss, replay: StepLossFn):
        self.step_loss, self.replay = step_loss, replay

    def __call__(self, image: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.replay(image, views)


def graphed(step_loss: StepLoss, image_shape: tuple[int, ...], device: torch.device) -> StepLossFn:
    """``step_loss`` for renders of ``image_shape`` ([B, H, W, 3]), recorded as CUDA graphs on ``device``
    (forward and backward; after three eager warm-up calls on view 0). The returned tensors, and the gradient
    the backward gives the image, are the graphs' own buffers, overwritten by the next call: read them (or
    queue their use) before it. A replay runs no Python: ``step_loss`` no longer asks its ``should_stop``
    (a CUDA step takes milliseconds; the caller asks between steps)."""
    step_loss.should_stop = None
    image = torch.zeros(image_shape, device=device, requires_grad=True)
    views = torch.zeros(image_shape[0], dtype=torch.long, device=device)
    return _Graphed(step_loss, torch.cuda.make_graphed_callables(step_loss, (image, views)))
