"""ArtNVG's attention processors for diffusers' ``Attention`` layers.

Two processors, installed by module name (see :mod:`artnvg_core.diffusion.csgo`); their maths
is :mod:`.attention_math`'s, which ComfyUI's patches of the node pack share:

* :class:`NeighbourViewSelfAttention` for every self-attention (``attn1``). The batch
  is read as consecutive groups of ``views_per_group`` samples (the sampler lays a
  batch out as ``[uncond view 1..N, cond view 1..N]``, so a group never straddles the
  two classifier-free-guidance halves). Each view's queries attend to the keys and
  values of all views of its group, ``Attn(Q_i, [K_1..K_N], [V_1..V_N])``, computed as
  one scaled-dot-product attention over the group's concatenated tokens.
  ``views_per_group = 1`` is plain per-view self-attention (the "w/o NV" ablation).
  Three approximations, all off by default, trade exactness for speed:
  ``nv_max_tokens`` keeps NV attention only in layers with at most that many tokens per
  view (the low-resolution levels) and attends per view elsewhere; ``neighbours`` lets
  each view attend to its own tokens and those of a few chosen views of its group only;
  ``kv_downsample`` average-pools the other views' keys and values by that factor per
  side (a view's own keys stay full resolution). With either of the last two a view's
  keys are ``[own tokens, chosen other views' (pooled) tokens]``.
* :class:`DecoupledCrossAttention` for every cross-attention (``attn2``). The context
  is ``[text tokens, content tokens, style tokens]``; the counts of the last two come
  from :class:`AttentionControl`, the text takes the rest. The output is
  ``SDPA(q, text) + scale * SDPA(q, k_ip(tokens), v_ip(tokens))`` where ``tokens`` are
  the content or the style tokens (the processor's ``image_tokens``), or text only
  when ``image_tokens`` is None. A zero scale skips the image branch entirely.

Per-call settings travel in diffusers' ``cross_attention_kwargs`` as one
:class:`AttentionControl` under the key ``"control"`` (see :func:`attention_kwargs`);
without it the processors act as plain self-attention and text-only cross-attention.
Both processors use the fused ``to_qkv`` / ``to_kv`` projections when the layer's
``fused_projections`` is set (see :func:`artnvg_core.diffusion.speed.fuse_attention_projections`).
Attention masks are not supported (SDXL does not use them).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from ..counted import counted
from .attention_math import Neighbours, check_neighbours, decoupled_attention, neighbour_view_attention

IMAGE_TOKEN_KINDS = ("content", "style")


@dataclass(frozen=True)
class AttentionControl:
    """Per-call settings read by the processors.

    views_per_group: N, the number of consecutive batch samples that share self-attention.
    num_content_tokens / num_style_tokens: counts of image tokens appended to the text context.
    content_scale / style_scale: weights of the content and style attention branches.
    nv_max_tokens: NV attention only in layers with at most this many tokens per view (None: all).
    neighbours: for each of the N views of a group, the indices (0..N-1) of the other views whose
        tokens it attends to, the same count for every view (None: all other views).
    kv_downsample: average-pooling factor per side of the other views' keys and values (1: none).
    latent_size: (h, w) of the latent grid, which gives each layer's token grid; required when
        kv_downsample > 1.
    """

    views_per_group: int = 1
    num_content_tokens: int = 0
    num_style_tokens: int = 0
    content_scale: float = 1.0
    style_scale: float = 0.6
    nv_max_tokens: int | None = None
    neighbours: Neighbours | None = None
    kv_downsample: int = 1
    latent_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.views_per_group < 1:
            raise ValueError(f"AttentionControl.views_per_group must be >= 1, got {self.views_per_group}")
        if self.nv_max_tokens is not None and self.nv_max_tokens < 1:
            raise ValueError(f"AttentionControl.nv_max_tokens must be None or >= 1, got {self.nv_max_tokens}")
        if self.kv_downsample < 1:
            raise ValueError(f"AttentionControl.kv_downsample must be >= 1, got {self.kv_downsample}")
        if self.kv_downsample > 1 and self.latent_size is None:
            raise ValueError("AttentionControl.latent_size is required when kv_downsample > 1")
        if self.neighbours is not None:
            check_neighbours(self.neighbours, self.views_per_group, "AttentionControl.neighbours")
        if self.num_content_tokens < 0 or self.num_style_tokens < 0:
            raise ValueError(
                "AttentionControl.num_content_tokens / num_style_tokens must be >= 0, got "
                f"{self.num_content_tokens} / {self.num_style_tokens}"
            )


def attention_kwargs(control: AttentionControl) -> dict:
    """The ``cross_attention_kwargs`` that hand ``control`` to every ArtNVG processor."""
    return {"control": control}


def _begin(attn, hidden_states: torch.Tensor, temb: torch.Tensor | None, attention_mask) -> tuple:
    """Shared prologue of diffusers' processors: optional norms and [B, C, H, W] -> [B, HW, C]."""
    if attention_mask is not None:
        raise ValueError("ArtNVG attention processors do not support attention masks (SDXL passes none)")
    residual = hidden_states
    if attn.spatial_norm is not None:
        hidden_states = attn.spatial_norm(hidden_states, temb)
    spatial_shape = hidden_states.shape if hidden_states.ndim == 4 else None
    if spatial_shape is not None:
        hidden_states = hidden_states.flatten(2).transpose(1, 2)
    if attn.group_norm is not None:
        hidden_states = attn.group_norm(hidden_states.transpose(1, 2)).transpose(1, 2)
    return hidden_states, residual, spatial_shape


def _end(attn, out: torch.Tensor, residual: torch.Tensor, spatial_shape) -> torch.Tensor:
    """Shared epilogue: output projection, dropout, shape restore, residual and rescale."""
    out = attn.to_out[1](attn.to_out[0](out))
    if spatial_shape is not None:
        out = out.transpose(1, 2).reshape(spatial_shape)
    if attn.residual_connection:
        out = out + residual
    return out / attn.rescale_output_factor


def _qk_norm(attn, q: torch.Tensor, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The layer's per-head query/key norms (if any) on [B, L, heads*D] tensors."""
    if attn.norm_q is not None:
        q = attn.norm_q(q.unflatten(-1, (attn.heads, -1))).flatten(2)
    if attn.norm_k is not None:
        k = attn.norm_k(k.unflatten(-1, (attn.heads, -1))).flatten(2)
    return q, k


class NeighbourViewSelfAttention:
    """Self-attention over all views of a group (see the module docstring).

    query_chunk_size: process queries in chunks of this many tokens (per group) to bound
    the memory of SDPA backends that materialise the score matrix; None = one call
    (CUDA flash / memory-efficient kernels never materialise it).
    """

    def __init__(self, query_chunk_size: int | None = None):
        if query_chunk_size is not None and query_chunk_size < 1:
            raise ValueError(f"NeighbourViewSelfAttention.query_chunk_size must be >= 1, got {query_chunk_size}")
        self.query_chunk_size = query_chunk_size

    def __call__(
        self,
        attn,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor | None = None,
        attention_mask: torch.Tensor | None = None,
        temb: torch.Tensor | None = None,
        control: AttentionControl | None = None,
    ) -> torch.Tensor:
        if encoder_hidden_states is not None:
            raise ValueError("NeighbourViewSelfAttention is a self-attention processor: got encoder_hidden_states")
        control = control or AttentionControl()
        x, residual, spatial_shape = _begin(attn, hidden_states, temb, attention_mask)
        batch, length, _ = x.shape
        views = control.views_per_group
        if batch % views:
            raise ValueError(f"NeighbourViewSelfAttention: batch {batch} is not a multiple of views_per_group {views}")
        if control.nv_max_tokens is not None and length > control.nv_max_tokens:
            views = 1
        if attn.fused_projections:
            q, k, v = attn.to_qkv(x).chunk(3, dim=-1)
        else:
            q, k, v = attn.to_q(x), attn.to_k(x), attn.to_v(x)
        q, k = _qk_norm(attn, q, k)
        out = neighbour_view_attention(q, k, v, attn.heads, views, neighbours=control.neighbours,
                                       kv_downsample=control.kv_downsample, latent_size=control.latent_size,
                                       scale=attn.scale, query_chunk=self.query_chunk_size)
        return _end(attn, out.to(q.dtype), residual, spatial_shape)


class DecoupledCrossAttention(nn.Module):
    """Text cross-attention plus one decoupled image-token branch (see the module docstring).

    hidden_size: the layer's attention width (output of to_k_ip / to_v_ip).
    cross_attention_dim: the context width (input of to_k_ip / to_v_ip).
    image_tokens: "content", "style" or None (text only; no parameters).
    device, dtype: of the parameters (as for ``nn.Linear``).
    Parameter names ``to_k_ip.weight`` / ``to_v_ip.weight`` match CSGO's released weights.
    """

    def __init__(self, hidden_size: int, cross_attention_dim: int, image_tokens: str | None, *,
                 device: torch.device | str | None = None, dtype: torch.dtype | None = None):
        super().__init__()
        if image_tokens is not None and image_tokens not in IMAGE_TOKEN_KINDS:
            raise ValueError(
                f"DecoupledCrossAttention.image_tokens must be one of {IMAGE_TOKEN_KINDS} or None, got {image_tokens!r}"
            )
        self.image_tokens = image_tokens
        if image_tokens is not None:
            self.to_k_ip = nn.Linear(cross_attention_dim, hidden_size, bias=False, device=device, dtype=dtype)
            self.to_v_ip = nn.Linear(cross_attention_dim, hidden_size, bias=False, device=device, dtype=dtype)

    def __call__(
        self,
        attn,
        hidden_states: torch.Tensor,
        encoder_hidden_states: torch.Tensor | None = None,
        attention_mask: torch.Tensor | None = None,
        temb: torch.Tensor | None = None,
        control: AttentionControl | None = None,
    ) -> torch.Tensor:
        if encoder_hidden_states is None:
            raise ValueError("DecoupledCrossAttention is a cross-attention processor: encoder_hidden_states is None")
        control = control or AttentionControl()
        num_content, num_style = control.num_content_tokens, control.num_style_tokens
        num_text = encoder_hidden_states.shape[1] - num_content - num_style
        if num_text < 1:
            raise ValueError(
                f"DecoupledCrossAttention: context of {counted(encoder_hidden_states.shape[1], 'token')} cannot hold "
                f"{num_content} content + {num_style} style tokens and at least one text token"
            )
        text, content, style = encoder_hidden_states.split([num_text, num_content, num_style], dim=1)
        x, residual, spatial_shape = _begin(attn, hidden_states, temb, attention_mask)
        if attn.norm_cross:
            text = attn.norm_encoder_hidden_states(text)
        q = attn.to_q(x)
        k, v = attn.to_kv(text).chunk(2, dim=-1) if attn.fused_projections else (attn.to_k(text), attn.to_v(text))
        q, k = _qk_norm(attn, q, k)
        tokens, scale = {
            "content": (content, control.content_scale),
            "style": (style, control.style_scale),
            None: (None, 0.0),
        }[self.image_tokens]
        branches = [] if tokens is None else [(self.to_k_ip(tokens), self.to_v_ip(tokens), scale)]
        out = decoupled_attention(q, k, v, attn.heads, branches, scale=attn.scale)
        return _end(attn, out.to(q.dtype), residual, spatial_shape)
