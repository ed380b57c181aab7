"""Perceiver Resampler: image-encoder features -> a few cross-attention tokens.

CSGO's content and style projections are Perceiver Resamplers of the IP-Adapter Plus kind:
``num_queries`` learnt latents attend (jointly with themselves) to the projected
image features, through ``depth`` blocks of attention + feed-forward, then are
projected to the UNet's cross-attention width.

Parameter names follow the released ``content_image_proj`` / ``style_image_proj``
state dicts exactly::

    latents                      [1, num_queries, dim]
    proj_in.{weight,bias}        Linear(embedding_dim -> dim)
    layers.{i}.0.norm1/norm2     LayerNorm(dim)  (image features / latents)
    layers.{i}.0.to_q            Linear(dim -> heads*dim_head, no bias)
    layers.{i}.0.to_kv           Linear(dim -> 2*heads*dim_head, no bias)
    layers.{i}.0.to_out          Linear(heads*dim_head -> dim, no bias)
    layers.{i}.1.0               LayerNorm(dim)
    layers.{i}.1.1 / .1.3        Linear(dim -> ff_mult*dim) / Linear(ff_mult*dim -> dim), no bias
    proj_out.{weight,bias}       Linear(dim -> output_dim)
    norm_out.{weight,bias}       LayerNorm(output_dim)

CSGO's sizes: embedding_dim 1664 (ViT-bigG penultimate hidden states), dim = output_dim
= 2048 (SDXL cross-attention width), depth 4, 12 heads of 64, ff_mult 4, num_queries 4
(content) and 32 or 16 (style).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass(frozen=True)
class ResamplerConfig:
    """Sizes of a :class:`PerceiverResampler` (see the module docstring)."""

    num_queries: int
    embedding_dim: int = 1664
    dim: int = 2048
    output_dim: int = 2048
    depth: int = 4
    heads: int = 12
    dim_head: int = 64
    ff_mult: int = 4


class PerceiverAttention(nn.Module):
    """Latents attend to ``[image features, latents]`` (multi-head, softmax scale dim_head^-1/2)."""

    def __init__(self, dim: int, heads: int, dim_head: int):
        super().__init__()
        self.heads = heads
        inner = heads * dim_head
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.to_q = nn.Linear(dim, inner, bias=False)
        self.to_kv = nn.Linear(dim, 2 * inner, bias=False)
        self.to_out = nn.Linear(inner, dim, bias=False)

    def forward(self, features: torch.Tensor, latents: torch.Tensor) -> torch.Tensor:
        """features [B, T, dim], latents [B, Q, dim] -> attention output [B, Q, dim]."""
        features = self.norm1(features)
        latents = self.norm2(latents)
        batch, queries, _ = latents.shape
        q = self.to_q(latents)
        k, v = self.to_kv(torch.cat([features, latents], dim=1)).chunk(2, dim=-1)
        q, k, v = (t.unflatten(-1, (self.heads, -1)).transpose(1, 2) for t in (q, k, v))
        out = F.scaled_dot_product_attention(q, k, v)
        return self.to_out(out.transpose(1, 2).reshape(batch, queries, -1))


def _feed_forward(dim: int, mult: int) -> nn.Sequential:
    """LayerNorm -> Linear -> GELU -> Linear (indices 0, 1, 2, 3 as in the released weights)."""
    return nn.Sequential(
        nn.LayerNorm(dim),
        nn.Linear(dim, dim * mult, bias=False),
        nn.GELU(),
        nn.Linear(dim * mult, dim, bias=False),
    )


class PerceiverResampler(nn.Module):
    """Image features [B, T, embedding_dim] -> tokens [B, num_queries, output_dim]."""

    def __init__(self, config: ResamplerConfig):
        super().__init__()
        self.config = config
        self.latents = nn.Parameter(torch.randn(1, config.num_queries, config.dim) / config.dim**0.5)
        self.proj_in = nn.Linear(config.embedding_dim, config.dim)
        self.layers = nn.ModuleList(
            nn.ModuleList(
                [
                    PerceiverAttention(config.dim, config.heads, config.dim_head),
                    _feed_forward(config.dim, config.ff_mult),
                ]
            )
            for _ in range(config.depth)
        )
        self.proj_out = nn.Linear(config.dim, config.output_dim)
        self.norm_out = nn.LayerNorm(config.output_dim)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        if features.ndim != 3 or features.shape[-1] != self.config.embedding_dim:
            raise ValueError(
                f"PerceiverResampler: features must be [B, T, {self.config.embedding_dim}], got {list(features.shape)}"
            )
        features = self.proj_in(features)
        latents = self.latents.expand(features.shape[0], -1, -1)
        for attention, feed_forward in self.layers:
            latents = attention(features, latents) + latents
            latents = feed_forward(latents) + latents
        return self.norm_out(self.proj_out(latents))


def resampler_config_from_state_dict(state: dict[str, torch.Tensor], dim_head: int = 64) -> ResamplerConfig:
    """Infer a :class:`ResamplerConfig` from released weights (head width ``dim_head`` is not stored).

    Raises ValueError naming the key when a shape needed for the inference is missing or odd.
    """

    def shape(key: str, ndim: int) -> torch.Size:
        if key not in state:
            raise ValueError(f"resampler weights: key '{key}' is missing")
        if state[key].ndim != ndim:
            raise ValueError(f"resampler weights: '{key}' must have {ndim} dims, got {list(state[key].shape)}")
        return state[key].shape

    _, num_queries, dim = shape("latents", 3)
    _, embedding_dim = shape("proj_in.weight", 2)
    output_dim, _ = shape("proj_out.weight", 2)
    inner, _ = shape("layers.0.0.to_q.weight", 2)
    hidden, _ = shape("layers.0.1.1.weight", 2)
    if inner % dim_head or hidden % dim:
        raise ValueError(
            f"resampler weights: to_q width {inner} is not a multiple of dim_head {dim_head}, "
            f"or feed-forward width {hidden} not a multiple of dim {dim}"
        )
    depth = 1 + max(int(key.split(".")[1]) for key in state if re.match(r"layers\.\d+\.", key))
    return ResamplerConfig(
        num_queries=num_queries,
        embedding_dim=embedding_dim,
        dim=dim,
        output_dim=output_dim,
        depth=depth,
        heads=inner // dim_head,
        dim_head=dim_head,
        ff_mult=hidden // dim,
    )
