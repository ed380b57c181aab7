"""Nearest-neighbour feature matching (NNFM) style loss, as in ARF (Zhang et al., 2022).

For every rendered feature vector, find the style feature vector with the highest cosine
similarity; the loss is the mean over rendered positions of ``1 - max cos`` (or its weighted mean,
with per-pixel weights area-averaged to each group's positions: a region's loss).

As in ARF, the features of the layers of one *group* (ARF's default: VGG block 3,
``relu3_1, relu3_2, relu3_3``) are concatenated along channels before matching, so one match
is made per position and group; the losses of several groups are summed. Positions of all
images in a batch are averaged together; several style images pool their positions.

Memory is bounded: similarities are computed in chunks of at most ``max_chunk_elements``
(rendered x style positions; :func:`default_chunk_elements` unless told) under ``no_grad`` to pick the
matches; the loss is then recomputed with gradient from the gathered matches only, which is exact
since the gradient of a max is the gradient of its argmax. Normalisation and the loss are computed in
float32 whatever the input dtype or autocast state.

The search for the matches (the argmax only) runs in one of :data:`SEARCH_PRECISIONS`:
``"fp32"`` (float32 products), ``"tf32"`` (float32 inputs rounded to TF32's 10-bit mantissa by
the tensor cores of a CUDA GPU; float32 elsewhere) or ``"bf16"`` (unit vectors rounded to
bfloat16, products summed in float32). Where the cheaper search picks the same match the loss is
identical; where it does not, the match it picks has a true cosine within the rounding (about
2^-7 for bf16, 2^-10 for TF32) of the best one's. BENCHMARKS.md prices each on the final scene.
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ..progress import StopFn, check_stop
from .tf32 import matmul_tf32
from .vgg import VGGFeatures

ARF_LAYER_GROUPS = (("relu3_1", "relu3_2", "relu3_3"),)
NORM_EPS = 1e-8  # added to the squared norm: a zero feature vector normalises to zero, no NaN
SEARCH_PRECISIONS = ("fp32", "tf32", "bf16")


def normalize_features(features: torch.Tensor) -> torch.Tensor:
    """``features [..., C]`` scaled to unit length along C (float32; zero stays zero)."""
    features = features.float()
    return features * torch.rsqrt(features.square().sum(-1, keepdim=True) + NORM_EPS)


def _group_positions(feats: Mapping[str, torch.Tensor], group: Sequence[str], what: str) -> torch.Tensor:
    """Features of ``group``'s layers concatenated along channels, as ``[B*h*w, C_total]``."""
    missing = [name for name in group if name not in feats]
    if missing:
        raise ValueError(f"{what}: missing layers {missing} (have {sorted(feats)})")
    maps = [feats[name] for name in group]
    sizes = {(tuple(m.shape[:1]) + tuple(m.shape[2:])) for m in maps}
    if any(m.dim() != 4 for m in maps) or len(sizes) != 1:
        shapes = {name: tuple(feats[name].shape) for name in group}
        raise ValueError(f"{what}: layers of one group must be [B, C, h, w] with equal B, h, w; got {shapes}")
    stacked = torch.cat(maps, dim=1)
    return stacked.permute(0, 2, 3, 1).reshape(-1, stacked.shape[1])


def _check_precision(precision: str) -> str:
    if precision not in SEARCH_PRECISIONS:
        raise ValueError(f"NNFM search precision: expected one of {SEARCH_PRECISIONS}, got {precision!r}")
    return precision


def search_operand(unit: torch.Tensor, precision: str) -> torch.Tensor:
    """Unit rows as the search of ``precision`` multiplies them (bfloat16 for ``"bf16"``, else as given)."""
    return unit.bfloat16() if _check_precision(precision) == "bf16" else unit


def _matmul_precision(precision: str, device: torch.device):
    """float32 CUDA products in TF32 inside, for ``"tf32"`` on a CUDA device; the setting is restored after."""
    return matmul_tf32(True) if precision == "tf32" and device.type == "cuda" else nullcontext()


def default_chunk_elements(device: torch.device) -> int:
    """Similarities a search holds at once unless told: 2^26 (256 MiB of float32) on CUDA; 2^23 elsewhere, where
    a chunk of 2^23 takes about 0.15 s on one CPU core (a stop asked between chunks is that prompt) and the
    search is no slower than in chunks of 2^26 (3.3 s against 3.5 s for 128x128 positions against 12,928)."""
    return 2**26 if device.type == "cuda" else 2**23


@torch.no_grad()
def nearest_style_indices(
    render_unit: torch.Tensor, style_unit: torch.Tensor, max_chunk_elements: int, precision: str = "fp32",
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """Index into ``style_unit [M, C]`` of the most similar row for each ``render_unit [N, C]`` row.

    Both inputs are unit-length rows (float32; ``style_unit`` may already be :func:`search_operand`'s).
    At most ``max_chunk_elements`` similarities are held at once; ties go to the lowest index;
    ``precision``: the products' arithmetic (module docstring); ``should_stop`` is asked before each chunk of rows
    (:class:`~artnvg_core.progress.Cancelled`).
    """
    render_unit, style_unit = search_operand(render_unit, precision), search_operand(style_unit, precision)
    num_style = style_unit.shape[0]
    cols = max(1, min(num_style, max_chunk_elements))
    rows = max(1, max_chunk_elements // cols)
    best_index = torch.empty(render_unit.shape[0], dtype=torch.long, device=render_unit.device)
    with _matmul_precision(precision, render_unit.device):
        for r0 in range(0, render_unit.shape[0], rows):
            check_stop(should_stop)
            chunk = render_unit[r0 : r0 + rows]
            if cols == num_style:  # one block of columns: the argmax is the answer
                best_index[r0 : r0 + rows] = (chunk @ style_unit.T).argmax(dim=1)
                continue
            best_sim = torch.full((chunk.shape[0],), -torch.inf, device=chunk.device, dtype=chunk.dtype)
            best = torch.zeros(chunk.shape[0], dtype=torch.long, device=chunk.device)
            for c0 in range(0, num_style, cols):
                sim, index = (chunk @ style_unit[c0 : c0 + cols].T).max(dim=1)
                better = sim > best_sim
                best_sim = torch.where(better, sim, best_sim)
                best = torch.where(better, index + c0, best)
            best_index[r0 : r0 + rows] = best
    return best_index


class NNFMLoss(nn.Module):
    """NNFM loss against fixed style features.

    ``style_feats``: ``{layer: [B_s, C, h, w]}`` from the same extractor as the renders (see
    :func:`style_image_features`); held as unit vectors without gradient (non-persistent
    buffers, moved by ``.to``). ``layer_groups``: layers matched jointly (concatenated).
    ``precision``: the match search's arithmetic, one of :data:`SEARCH_PRECISIONS` (module docstring).
    ``forward(render_feats {layer: [B, C, h, w]}, weights=None, should_stop=None) -> scalar`` (float32);
    ``weights [B, H, W]`` >= 0 (e.g. at the rendered image's size) weigh the positions, area-averaged to each
    group's ``h x w``; ``should_stop`` is asked within the search (:func:`nearest_style_indices`).
    ``max_chunk_elements``: the search's chunk, None for :func:`default_chunk_elements` of the features' device.
    """

    def __init__(
        self,
        style_feats: Mapping[str, torch.Tensor],
        layer_groups: Sequence[Sequence[str]] = ARF_LAYER_GROUPS,
        max_chunk_elements: int | None = None,
        precision: str = "fp32",
    ):
        super().__init__()
        if not layer_groups or any(not group for group in layer_groups):
            raise ValueError(f"layer_groups: expected non-empty groups of layer names, got {layer_groups}")
        if max_chunk_elements is not None and max_chunk_elements < 1:
            raise ValueError(f"max_chunk_elements: expected >= 1, got {max_chunk_elements}")
        self.layer_groups = tuple(tuple(group) for group in layer_groups)
        self.max_chunk_elements = max_chunk_elements
        self.precision = _check_precision(precision)
        for g, group in enumerate(self.layer_groups):
            with torch.no_grad():
                style = normalize_features(_group_positions(style_feats, group, "style_feats"))
            self.register_buffer(f"style_unit_{g}", style, persistent=False)
            self.register_buffer(f"style_search_{g}", search_operand(style, precision), persistent=False)

    def forward(self, render_feats: Mapping[str, torch.Tensor], weights: torch.Tensor | None = None,
                should_stop: StopFn | None = None) -> torch.Tensor:
        total = 0.0
        for g, group in enumerate(self.layer_groups):
            style = getattr(self, f"style_unit_{g}")
            render = _group_positions(render_feats, group, "render_feats")
            if render.shape[1] != style.shape[1]:
                raise ValueError(
                    f"render_feats: group {group} has {render.shape[1]} channels, style has {style.shape[1]}"
                )
            with torch.autocast(render.device.type, enabled=False):
                render_unit = normalize_features(render)
                searched = getattr(self, f"style_search_{g}")
                chunk = self.max_chunk_elements or default_chunk_elements(render.device)
                matches = nearest_style_indices(render_unit.detach(), searched, chunk, self.precision, should_stop)
                distance = 1.0 - (render_unit * style[matches]).sum(-1)
                if weights is None:
                    total = total + distance.mean()
                else:
                    size = render_feats[group[0]].shape[-2:]
                    w = F.interpolate(weights[:, None].float(), size=size, mode="area").flatten()
                    total = total + (w * distance).sum() / w.sum().clamp_min(1e-12)
        return total


def resize_long_side(images: torch.Tensor, side: int) -> torch.Tensor:
    """``images [B, C, H, W]`` resized so that the longest side is ``side`` (aspect kept, each side rounded,
    at least 1): area-averaged when shrinking (as ARF's ``INTER_AREA``), bilinear when enlarging."""
    height, width = images.shape[-2:]
    factor = side / max(height, width)
    size = (max(1, round(height * factor)), max(1, round(width * factor)))
    if factor < 1:
        return F.interpolate(images, size=size, mode="area")
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False)


def shrink_to_max_side(images: torch.Tensor, max_side: int | None) -> torch.Tensor:
    """``images [B, C, H, W]`` area-averaged so that the longest side is at most ``max_side``
    (:func:`resize_long_side`; never enlarged; None or a small enough image: returned as given). Halving
    is a 2x2 average, the same as ARF's ``interpolate(scale_factor=0.5, mode="bilinear")``."""
    if max_side is None or max(images.shape[-2:]) <= max_side:
        return images
    return resize_long_side(images, max_side)


def style_image_features(
    extractor: VGGFeatures, style_image: torch.Tensor, layers: Sequence[str], max_side: int | None = 1024
) -> dict[str, torch.Tensor]:
    """Features (no gradient) of ``style_image [B, 3, H, W]`` RGB in [0, 1], shrunk first with
    :func:`shrink_to_max_side`. The feature scale matters: NNFM matches local patches, so the style
    should be about the size of the images it is matched against (ARF: both ~half the render).
    """
    if style_image.dim() != 4 or style_image.shape[1] != 3:
        raise ValueError(f"style_image: expected RGB [B, 3, H, W], got {tuple(style_image.shape)}")
    with torch.no_grad():
        return extractor(shrink_to_max_side(style_image, max_side), layers)
