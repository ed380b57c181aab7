"""ArtNVG's attention maths as functions of projected queries, keys and values.

The one home of the two attentions the method changes; the diffusers processors
(:mod:`.attention`) and the ComfyUI patches of the node pack both call these functions.
Tensors are ``[B, L, heads * D]`` (tokens after the layer's ``to_q`` / ``to_k`` / ``to_v``,
before ``to_out``); the softmax scale defaults to ``D ** -0.5``. No masks (SDXL uses none).

* :func:`neighbour_view_attention`: the batch is read as consecutive groups of ``views``
  samples; each view's queries attend to the keys and values of all views of its group,
  ``Attn(Q_i, [K_1..K_N], [V_1..V_N])``, one scaled-dot-product attention over the group's
  concatenated tokens. ``views = 1`` is plain self-attention. The approximations: ``neighbours``
  (each view attends to its own tokens and those of a few chosen views only), ``kv_downsample``
  (the other views' keys and values average-pooled by that factor per side; a view's own stay
  full resolution). With either, a view's keys are ``[own tokens, chosen views' (pooled) tokens]``.
* :func:`decoupled_attention`: CSGO's (IP-Adapter's) decoupled cross-attention,
  ``SDPA(q, k, v) + sum_i scale_i * SDPA(q, k_i, v_i)`` over image-token branches.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from ..counted import counted
from .speed import cudnn_attention_first

Neighbours = tuple[tuple[int, ...], ...]


def check_neighbours(neighbours: Neighbours, views: int, name: str = "neighbours") -> None:
    """ValueError naming ``name`` unless ``neighbours`` holds one row per view of equal length, each of
    distinct views in 0..views-1 other than its own."""
    counts = {len(row) for row in neighbours}
    if len(neighbours) != views or len(counts) != 1:
        raise ValueError(
            f"{name} must hold one row per view ({views}) of equal length, "
            f"got {counted(len(neighbours), 'row')} of lengths {sorted(counts)}"
        )
    for view, row in enumerate(neighbours):
        if len(set(row)) != len(row) or view in row or any(not 0 <= j < views for j in row):
            raise ValueError(f"{name}[{view}] must hold distinct views in 0..{views - 1} other than {view}, got {row}")


def split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """[B, L, heads*D] -> [B, heads, L, D]."""
    return x.unflatten(-1, (heads, -1)).transpose(1, 2)


def merge_heads(x: torch.Tensor) -> torch.Tensor:
    """[B, heads, L, D] -> [B, L, heads*D]."""
    return x.transpose(1, 2).flatten(2)


def attend(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, heads: int, scale: float | None = None,
           query_chunk: int | None = None) -> torch.Tensor:
    """Multi-head SDPA of [B, Lq, heads*D] queries over [B, Lk, heads*D] keys/values -> [B, Lq, heads*D],
    optionally in chunks of ``query_chunk`` queries (bounds the score matrix of backends that build it); on a
    GPU cuDNN's kernel first (:func:`.speed.cudnn_attention_first`)."""
    q, k, v = (split_heads(t, heads) for t in (q, k, v))
    with cudnn_attention_first(q.device):
        if query_chunk is None or q.shape[2] <= query_chunk:
            out = F.scaled_dot_product_attention(q, k, v, scale=scale)
        else:
            out = torch.cat([F.scaled_dot_product_attention(part, k, v, scale=scale)
                             for part in q.split(query_chunk, dim=2)], dim=2)
    return merge_heads(out)


def token_grid(latent_size: tuple[int, int], length: int) -> tuple[int, int]:
    """(h, w) of a layer's token grid: the latent grid downsampled by a power of two, ``h * w = length``."""
    height, width = latent_size
    factor = 2 ** round(math.log2(math.sqrt(height * width / length)))
    grid = (math.ceil(height / factor), math.ceil(width / factor))
    if grid[0] * grid[1] != length:
        raise ValueError(f"latent_size {latent_size} does not fit a layer of {counted(length, 'token')}")
    return grid


def _neighbour_tokens(x: torch.Tensor, views: int, neighbours: Neighbours | None, kv_downsample: int,
                      latent_size: tuple[int, int] | None) -> torch.Tensor:
    """Keys or values [G*N, L, C] -> [G*N, L + m*Lp, C]: each view's own tokens, then the (pooled)
    tokens of its m chosen neighbours (default all other views)."""
    others = x
    if kv_downsample > 1:
        grid = x.unflatten(1, token_grid(latent_size, x.shape[1])).permute(0, 3, 1, 2)
        others = F.avg_pool2d(grid, kv_downsample, ceil_mode=True).flatten(2).transpose(1, 2)
    rows = neighbours or tuple(tuple(j for j in range(views) if j != i) for i in range(views))
    index = torch.tensor(rows, device=x.device)
    others = others.unflatten(0, (-1, views))[:, index]  # [G, N, m, Lp, C]
    return torch.cat([x, others.flatten(2, 3).flatten(0, 1)], dim=1)


def neighbour_view_attention(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    heads: int,
    views: int,
    *,
    neighbours: Neighbours | None = None,
    kv_downsample: int = 1,
    latent_size: tuple[int, int] | None = None,
    scale: float | None = None,
    query_chunk: int | None = None,
) -> torch.Tensor:
    """Neighbouring-view self-attention (module docstring): [B, L, heads*D] -> [B, L, heads*D].

    views: N, the group size; B must be a multiple of it (groups of consecutive samples).
    neighbours: for each of the N views, the other views (0..N-1) it attends to, as many for each (None: all).
    kv_downsample: pooling factor per side of the other views' keys and values (1: none); needs
        ``latent_size``, the (h, w) latent grid the layer's token grid is a power-of-two reduction of.
    query_chunk: queries per SDPA call (per group), None: one call.
    """
    batch, length, _ = q.shape
    if views < 1 or batch % views:
        raise ValueError(f"neighbour_view_attention: batch {batch} is not a multiple of {views} views per group")
    if kv_downsample < 1 or (kv_downsample > 1 and latent_size is None):
        raise ValueError(f"neighbour_view_attention: kv_downsample {kv_downsample} must be >= 1 (> 1 needs latent_size)")
    if views > 1 and neighbours is not None:
        check_neighbours(neighbours, views)
    if views > 1 and (neighbours is not None or kv_downsample > 1):
        k, v = (_neighbour_tokens(t, views, neighbours, kv_downsample, latent_size) for t in (k, v))
        return attend(q, k, v, heads, scale, query_chunk)
    q, k, v = (t.reshape(batch // views, views * length, -1) for t in (q, k, v))  # each group one sequence
    return attend(q, k, v, heads, scale, query_chunk).reshape(batch, length, -1)


def decoupled_attention(
    q: torch.Tensor,
    k: torch.Tensor,
    v: torch.Tensor,
    heads: int,
    branches: Sequence[tuple[torch.Tensor, torch.Tensor, float]] = (),
    *,
    scale: float | None = None,
) -> torch.Tensor:
    """``SDPA(q, k, v) + sum scale_i * SDPA(q, k_i, v_i)`` for ``branches`` of ``(k_i, v_i, scale_i)``:
    q [B, L, heads*D], k/v [B, T, heads*D] (text), k_i/v_i [B, Q_i, heads*D] (image tokens after the
    branch's ``to_k_ip`` / ``to_v_ip``). A branch with a zero scale or no tokens is skipped."""
    out = attend(q, k, v, heads, scale)
    for k_ip, v_ip, weight in branches:
        if weight != 0 and k_ip.shape[1] > 0:
            out = out + weight * attend(q, k_ip, v_ip, heads, scale)
    return out
