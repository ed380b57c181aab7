"""Evaluation metrics of a stylization (the ``evaluate`` command that reports them: :mod:`artnvg_core.cli.evaluate`).

- :mod:`.cfsd`    -- ``cfsd_scores``: content fidelity (VGG19 relu3_1 self-similarity KL), real weights offline
- :mod:`.warp`    -- ``warp_consistency``: weight-free multi-view consistency via depth reprojection
- :mod:`.clip_dc` -- ``clip_dc_scores``: CLIP direction consistency along a camera path (CLIP weights needed)
- :mod:`.csd`     -- ``csd_scores``: CSD style similarity to the style image (CSD weights needed)
"""

from .cfsd import CFSD_LAYER, cfsd_scores
from .clip_dc import (
    CLIP_VIT_L,
    clip_dc_scores,
    clip_image_embeddings,
    direction_consistency,
    load_clip_image_encoder,
)
from .csd import (
    CSD_WEIGHTS,
    CSDConfig,
    CSDStyleEncoder,
    csd_descriptors,
    csd_scores,
    load_csd,
)
from .warp import WarpConsistency, reproject, warp_consistency

__all__ = [
    "CFSD_LAYER",
    "CLIP_VIT_L",
    "CSD_WEIGHTS",
    "CSDConfig",
    "CSDStyleEncoder",
    "WarpConsistency",
    "cfsd_scores",
    "clip_dc_scores",
    "clip_image_embeddings",
    "csd_descriptors",
    "csd_scores",
    "direction_consistency",
    "load_clip_image_encoder",
    "load_csd",
    "reproject",
    "warp_consistency",
]
