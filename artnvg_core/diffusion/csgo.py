"""CSGO content/style control on SDXL: token routing, processor installation, projections.

Routing: cross-attention (``attn2``) of the UNet's ``up_blocks`` reads the style tokens, of
its ``mid_block`` text only; the ControlNet's ``down_blocks`` read the style tokens, its
``mid_block`` text only. The UNet's ``down_blocks`` depend on the content routing
(:data:`CONTENT_ROUTINGS`):

* ``"released"``: text only, which is what CSGO's released inference code computes (its
  content loop never marks those layers, so they get a text-only processor): content
  reaches the image through the Tile ControlNet alone and ``content_scale`` has no effect;
* ``"paper"``: the content tokens, as the CSGO and ArtNVG papers describe; needs the
  content entries of the ``ip_adapter`` group, which a file saved from the released
  class does not hold.

Every self-attention (``attn1``) of both models becomes neighbouring-view attention.

Released weight layout (``ip_adapter`` group and the ControlNet's ``controlnet_adapter_modules``):
processors are enumerated in the order of ``model.attn_processors`` — diffusers lists a
UNet's as down_blocks -> up_blocks -> mid_block and a ControlNet's as down_blocks ->
mid_block, each block in module order (attentions.j.transformer_blocks.k.attn1, attn2).
The index ``i`` counts *every* processor, attn1 included, so only odd indices (the
``attn2`` ones) carry ``{i}.to_k_ip.weight`` / ``{i}.to_v_ip.weight``, and only for
processors that read image tokens. For SDXL (transformer depths 1, 2, 10) the UNet keys
are i = 1, 3, ..., 47 (down, content) and 49, ..., 119 (up, style); the mid block
(120-139) has none. See :func:`processor_key_layout`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn.utils import skip_init

from .attention import DecoupledCrossAttention, NeighbourViewSelfAttention
from .resampler import PerceiverResampler

UNET_ROUTES = {"down_blocks": "content", "up_blocks": "style", "mid_block": None}  # with content entries
UNET_STYLE_ROUTES = {**UNET_ROUTES, "down_blocks": None}  # without them
CONTROLNET_ROUTES = {"down_blocks": "style", "mid_block": None}
CONTENT_ROUTINGS = ("released", "paper")


def released_key_prefix(position: int) -> str:
    """The released layout's index prefix of the ``attn2`` of the ``position``-th transformer block (0-based,
    counted down -> up -> mid blocks): every block has an attn1 and an attn2 processor, so ``2 * position + 1``."""
    return str(2 * position + 1)


def route_for(processor_name: str, routes: dict[str, str | None]) -> str | None:
    """Image tokens ("content" / "style" / None) read by the cross-attention ``processor_name``."""
    top = processor_name.split(".", 1)[0]
    if top not in routes:
        raise ValueError(f"attention processor '{processor_name}': block '{top}' has no CSGO route in {sorted(routes)}")
    return routes[top]


def install_processors(
    model: nn.Module,
    routes: dict[str, str | None],
    *,
    image_branches: bool = True,
    query_chunk_size: int | None = None,
    initialise: bool = True,
) -> None:
    """Install NV self-attention on every attn1 and decoupled cross-attention on every attn2.

    image_branches=False installs text-only cross-attention everywhere (no CSGO weights).
    New projection weights take the device and dtype of the layer's ``to_k``; ``initialise=False``
    leaves them uninitialised (no random initialisation) for weights a file fills next.
    """
    build = DecoupledCrossAttention if initialise else functools.partial(skip_init, DecoupledCrossAttention)
    processors = {}
    for name in model.attn_processors:
        layer = model.get_submodule(name.removesuffix(".processor"))
        if name.endswith("attn1.processor"):
            processors[name] = NeighbourViewSelfAttention(query_chunk_size)
        elif name.endswith("attn2.processor"):
            kind = route_for(name, routes) if image_branches else None
            weight = layer.to_k.weight
            processors[name] = build(layer.to_k.out_features, layer.to_k.in_features, kind, device=weight.device,
                                     dtype=weight.dtype)
        else:
            raise ValueError(f"attention processor '{name}': expected only attn1 / attn2 layers")
    model.set_attn_processor(processors)


def routed_keys(model: nn.Module, routes: dict[str, str | None], kind: str, by_index: bool = True) -> list[str]:
    """Released-layout keys (see :func:`processor_key_layout`) of the ``attn2`` layers of ``model`` that
    ``routes`` gives ``kind`` tokens, whatever processors are installed now."""
    keys = []
    for index, name in enumerate(model.attn_processors):
        if name.endswith("attn2.processor") and route_for(name, routes) == kind:
            prefix = str(index) if by_index else name
            keys += [f"{prefix}.to_k_ip.weight", f"{prefix}.to_v_ip.weight"]
    return keys


def processor_key_layout(model: nn.Module, by_index: bool = True) -> dict[str, torch.nn.Parameter]:
    """Released-layout key -> parameter of every installed image branch of ``model``.

    by_index=True gives ``{i}.to_k_ip.weight`` (i over ``model.attn_processors``);
    False gives module paths ``{name}.to_k_ip.weight`` with ``name`` ending in ``.processor``.
    """
    layout = {}
    for index, (name, processor) in enumerate(model.attn_processors.items()):
        if isinstance(processor, DecoupledCrossAttention) and processor.image_tokens is not None:
            prefix = str(index) if by_index else name
            layout[f"{prefix}.to_k_ip.weight"] = processor.to_k_ip.weight
            layout[f"{prefix}.to_v_ip.weight"] = processor.to_v_ip.weight
    return layout


@dataclass
class ImageTokens:
    """Tokens of one kind for classifier-free guidance: ``cond`` from features, ``uncond`` from zeros."""

    cond: torch.Tensor
    uncond: torch.Tensor


class CSGOProjections(nn.Module):
    """CSGO's two resamplers: ``content`` (4 tokens) and ``style`` (32 or 16 tokens).

    unet_content: the UNet's down blocks hold content branches (the file had their entries),
    which the ``"paper"`` content routing needs.
    """

    def __init__(self, content: PerceiverResampler, style: PerceiverResampler, unet_content: bool = True):
        super().__init__()
        self.content = content
        self.style = style
        self.unet_content = unet_content

    @property
    def num_content_tokens(self) -> int:
        return self.content.config.num_queries

    @property
    def num_style_tokens(self) -> int:
        return self.style.config.num_queries

    @torch.no_grad()
    def tokens(self, kind: str, features: torch.Tensor) -> ImageTokens:
        """Encoder features [B, T, E] -> :class:`ImageTokens` [B, Q, D] of ``kind`` ("content"/"style").

        The unconditional tokens are the resampler applied to all-zero features (as CSGO does).
        """
        resampler = {"content": self.content, "style": self.style}.get(kind)
        if resampler is None:
            raise ValueError(f"CSGOProjections.tokens: kind must be 'content' or 'style', got {kind!r}")
        param = resampler.latents
        features = features.to(device=param.device, dtype=param.dtype)
        return ImageTokens(cond=resampler(features), uncond=resampler(torch.zeros_like(features)))
