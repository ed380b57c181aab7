"""ArtNVG's attention patches on ComfyUI's own models (MODEL and CONTROL_NET), as IPAdapter-style packs patch.

The maths is the core's (:mod:`artnvg_core.diffusion.attention_math`); this module only adapts it to
how ComfyUI calls a patch: ``patch(q, k, v, extra_options)`` with q/k/v ``[B, L, heads*D]`` after the
layer's projections, ``extra_options`` holding ``n_heads``, ``original_shape`` (the latent batch
``[b, C, h, w]``), ``cond_or_uncond`` (which guidance half each of the batch's equal chunks is: 0 the
conditional, 1 the unconditional) and whatever the sampler put in the model's ``transformer_options``
(:data:`VIEW_CENTERS`, :data:`CONTENT_TOKENS`, set by Sample Group for the group it samples). The
views of a group are the latent batch: every chunk of the batch holds all of them, in order.

* :class:`NeighbourViewPatch` (``attn1``): each view attends to all views of its chunk, never across chunks.
* :class:`ImageTokenPatch` (``attn2``): CSGO's decoupled attention of one layer, style or content tokens.
* ComfyUI's ControlNet calls its blocks without ``transformer_options``, so a patched ControlNet gets
  :class:`ControlNetCall` as its model's ``forward`` (ComfyUI hands it the options as an extra condition)
  and :class:`ControlNetAttention` in place of each patched attention module: object patches of the
  ControlNet's own ModelPatcher, applied while it is loaded (:func:`patch_controlnet`).
* :func:`diffusion_unet` and :func:`controlnet_model`: the UNet of a MODEL and the control model of a
  CONTROL_NET that the patches go on, checked (a NodeInputError naming the node's input otherwise).
* :class:`OneSampleAtATime` (low VRAM): a transformer block's feed-forward run one sample at a time, an
  object patch of the UNet's or the ControlNet's ModelPatcher (:func:`feed_forward_one_sample_at_a_time`).

Patches are shared between the clones ComfyUI makes of a MODEL (they are never changed, only moved).
Nothing here imports ComfyUI.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from artnvg_core.diffusion.attention_math import decoupled_attention, neighbour_view_attention
from artnvg_core.diffusion.csgo import ImageTokens
from artnvg_core.grouping import nearest_views

from .node_errors import NodeInputError

VIEW_CENTERS = "artnvg_view_centers"  # transformer_options key: camera centres [N, 3] of the batch's views
CONTENT_TOKENS = "artnvg_content_tokens"  # transformer_options key: ImageTokens [N, Q, D] of the views
CSGO_STATE = "artnvg_csgo"  # transformer_options key: the CSGOState of an Apply CSGO patch
UNCOND = 1  # ComfyUI's mark of an unconditional chunk in cond_or_uncond


class Shared:
    """Base of objects ComfyUI's ``copy.deepcopy`` of a model's options must share, not copy."""

    def __deepcopy__(self, memo):
        return self


def _views(q: torch.Tensor, extra_options: dict) -> int:
    """The latent batch size: the batch holds one chunk of it per entry of ``cond_or_uncond``."""
    return q.shape[0] // len(extra_options["cond_or_uncond"])


@dataclass(frozen=True, eq=False)
class NeighbourViewPatch(Shared):
    """attn1 replacement: neighbouring-view attention over each chunk's views.

    lowest_level_factor: NV only in layers of at most ``ceil(h/f) * ceil(w/f)`` tokens (f: this factor,
        the UNet's total downsampling; None: every layer).
    nearest: each view attends to its k nearest views by camera centre (``VIEW_CENTERS``); None: all.
    kv_downsample: the other views' keys/values average-pooled by this factor per side (1: exact).
    """

    lowest_level_factor: int | None = None
    nearest: int | None = None
    kv_downsample: int = 1

    def __call__(self, q, k, v, extra_options):
        views = _views(q, extra_options)
        height, width = extra_options["original_shape"][2:]
        factor = self.lowest_level_factor
        if factor is not None and q.shape[1] > math.ceil(height / factor) * math.ceil(width / factor):
            views = 1
        neighbours = None
        if views > 1 and self.nearest is not None and self.nearest < views - 1:
            centers = extra_options.get(VIEW_CENTERS)
            if centers is None or len(centers) != views:
                raise ValueError(
                    f"NV-Attention Patch Model: nearest_views {self.nearest} needs the camera centres of the "
                    f"{views} views sampled together: sample with Sample Group, or set nearest_views to 0"
                )
            neighbours = nearest_views(centers, self.nearest)
        return neighbour_view_attention(q, k, v, extra_options["n_heads"], views, neighbours=neighbours,
                                        kv_downsample=self.kv_downsample if views > 1 else 1,
                                        latent_size=(height, width))


@dataclass(eq=False)
class CSGOState(Shared):
    """What every CSGO layer patch of one Apply CSGO reads: the style tokens [1, Q, D] (conditional from the
    style image's features, unconditional from zeros), the scales, the content routing, and the content
    encoder ``IMAGE [N, H, W, 3] -> ImageTokens [N, Q, D]`` that Sample Group calls for the paper routing."""

    style: ImageTokens
    style_scale: float
    content_scale: float
    content_routing: str
    content_encoder: object = None
    _batches: dict = field(default_factory=dict, repr=False)

    def batch_tokens(self, kind: str, tokens: ImageTokens, halves: tuple, views: int, like: torch.Tensor) -> torch.Tensor:
        """``tokens`` laid out as a latent batch [len(halves) * views, Q, D] (per chunk of ``views``, the
        unconditional or conditional tokens as ``halves``, ComfyUI's ``cond_or_uncond``, says) on ``like``'s
        device and dtype. Built once per tokens and layout (ComfyUI may run the halves as separate batches)
        and shared by every layer patch of this state: a copy to the GPU in each layer's call would make the
        host wait for the GPU each time."""
        key = (kind, halves, views, like.device, like.dtype)
        cached = self._batches.get(key)
        if cached is None or cached[0] is not tokens:
            chunks = [(tokens.uncond if half == UNCOND else tokens.cond).expand(views, -1, -1) for half in halves]
            cached = self._batches[key] = (tokens, torch.cat(chunks).to(like))
        return cached[1]


class ImageTokenPatch(Shared):
    """attn2 replacement of one layer: ``SDPA(q, text) + scale * SDPA(q, to_k_ip(tokens), to_v_ip(tokens))``.

    to_k_ip / to_v_ip: the layer's CSGO weights [heads*D, token width]; kind: "style" (the state's style
    tokens) or "content" (the views' tokens Sample Group puts under ``CONTENT_TOKENS``).
    """

    def __init__(self, to_k_ip: torch.Tensor, to_v_ip: torch.Tensor, kind: str, state: CSGOState):
        self.weights = (to_k_ip, to_v_ip)
        self.kind = kind
        self.state = state

    def to(self, *args, **kwargs):
        """ComfyUI's convention for moving a patch with its model (a device or a dtype): in place."""
        self.weights = tuple(w.to(*args, **kwargs) for w in self.weights)
        return self

    def _tokens(self, extra_options: dict) -> tuple[ImageTokens, float]:
        if self.kind == "style":
            return self.state.style, self.state.style_scale
        tokens = extra_options.get(CONTENT_TOKENS)
        if tokens is None:
            raise ValueError("Apply CSGO: content_routing 'paper' needs each view's content tokens: sample with "
                             "Sample Group (which encodes the content views), or use the 'released' routing")
        return tokens, self.state.content_scale

    def __call__(self, q, k, v, extra_options):
        tokens, scale = self._tokens(extra_options)
        tokens = self.state.batch_tokens(self.kind, tokens, tuple(extra_options["cond_or_uncond"]),
                                         _views(q, extra_options), q)
        if self.weights[0].device != q.device or self.weights[0].dtype != q.dtype:
            self.to(q)
        k_ip, v_ip = (F.linear(tokens, w) for w in self.weights)
        return decoupled_attention(q, k, v, extra_options["n_heads"], [(k_ip, v_ip, scale)])


# --------------------------------------------------------------------------- layers of ComfyUI's UNet / ControlNet


@dataclass(frozen=True)
class TransformerLayer:
    """One transformer block of a ComfyUI UNet or ControlNet: its patch key ``(block, number, transformer)``
    (``block`` "input", "middle" or "output"), its module path, and the diffusers name of the same block."""

    block: str
    number: int
    transformer: int
    path: str
    diffusers_name: str


def _diffusers_block(block: str, number: int, per_level: int) -> str:
    """The diffusers name of ComfyUI's ``input_blocks[number]`` / ``output_blocks[number]`` / middle block."""
    if block == "middle":
        return "mid_block.attentions.0"
    if block == "input":
        level, index = divmod(number - 1, per_level + 1)
        return f"down_blocks.{level}.attentions.{index}"
    level, index = divmod(number, per_level + 1)
    return f"up_blocks.{level}.attentions.{index}"


def diffusion_unet(node: str, model) -> torch.nn.Module:
    """The UNet of ComfyUI MODEL ``model`` (SD 1.x/2.x/SDXL: input, middle and output blocks); NodeInputError
    naming input 'model' for any other architecture."""
    unet = model.get_model_object("diffusion_model")
    if not all(hasattr(unet, name) for name in ("input_blocks", "middle_block", "output_blocks", "num_res_blocks")):
        raise NodeInputError(f"{node}: input 'model': a {type(unet).__name__} model; expected a UNet checkpoint "
                             "(SDXL for the ArtNVG method) from Load Checkpoint")
    return unet


def controlnet_model(node: str, control_net) -> torch.nn.Module:
    """The control model of ComfyUI CONTROL_NET ``control_net`` (a ControlNet with a hint encoder, as Load
    ControlNet Model gives); NodeInputError naming input 'control_net' for anything else (a T2I-Adapter, a
    Control-LoRA, another type)."""
    control_model = getattr(control_net, "control_model", None)
    if control_model is None or not hasattr(control_model, "input_hint_block"):
        raise NodeInputError(f"{node}: input 'control_net': a {type(control_model or control_net).__name__}; "
                             "expected an SDXL ControlNet (the TTPlanet tile ControlNet) from Load ControlNet Model")
    return control_model


def transformer_layers(model: torch.nn.Module) -> list[TransformerLayer]:
    """Every transformer block of ComfyUI's UNet or ControlNet ``model`` (its ``diffusion_model`` / control
    model), in the order CSGO's released weights index them: input (down), output (up), middle."""
    per_level = model.num_res_blocks[0]
    layers = []
    for attribute, block in (("input_blocks", "input"), ("output_blocks", "output"), ("middle_block", "middle")):
        blocks = getattr(model, attribute, None)
        if blocks is None:
            continue
        for number, sequence in enumerate(blocks) if block != "middle" else [(0, blocks)]:
            for position, child in enumerate(sequence):
                for index, _ in enumerate(getattr(child, "transformer_blocks", ())):
                    prefix = attribute if block == "middle" else f"{attribute}.{number}"
                    layers.append(TransformerLayer(
                        block, number, index, f"{prefix}.{position}.transformer_blocks.{index}",
                        f"{_diffusers_block(block, number, per_level)}.transformer_blocks.{index}"))
    return layers


# --------------------------------------------------------------------------- the ControlNet


class ControlNetCall(Shared):
    """The ControlNet model's ``forward`` while patched: keeps the sampler's ``transformer_options`` (and the
    latent batch's shape) for the model's :class:`ControlNetAttention` modules during the call."""

    def __init__(self, model: torch.nn.Module):
        self.model = model
        self.options: dict = {}

    def __call__(self, *args, transformer_options=None, **kwargs):
        x = kwargs["x"] if "x" in kwargs else args[0]
        self.options = {**(transformer_options or {}), "original_shape": list(x.shape)}
        try:
            return type(self.model).forward(self.model, *args, **kwargs)
        finally:
            self.options = {}


class ControlNetAttention(torch.nn.Module):
    """Stands in for one attention module of the ControlNet: its own projections around ``patch``."""

    def __init__(self, attention: torch.nn.Module, patch, call: ControlNetCall):
        super().__init__()
        self.attention = attention
        self.patch = patch
        self.call = call

    def forward(self, x, context=None, value=None, mask=None, transformer_options=None):
        attention = self.attention
        context = x if context is None else context
        q, k = attention.to_q(x), attention.to_k(context)
        v = attention.to_v(context if value is None else value)
        return attention.to_out(self.patch(q, k, v, {**self.call.options, "n_heads": attention.heads}))


def _controlnet_copy(control_net):
    """A copy of ComfyUI's ``control_net`` with its own clone of the control model's ModelPatcher (object
    patches added to the copy leave ``control_net`` as it was)."""
    patched = control_net.copy()
    patched.control_model_wrapped = control_net.control_model_wrapped.clone()
    return patched


def patch_controlnet(control_net, patches: dict[str, object]):
    """A copy of ComfyUI's ``control_net`` whose attention modules at ``patches``' module paths (e.g.
    ``input_blocks.4.1.transformer_blocks.0.attn2``) call those patches; earlier patches of the pack stay."""
    patched = _controlnet_copy(control_net)
    wrapped = patched.control_model_wrapped
    call = wrapped.object_patches.get("forward")
    if not isinstance(call, ControlNetCall):
        call = ControlNetCall(patched.control_model)
        wrapped.add_object_patch("forward", call)
        patched.extra_conds = [*patched.extra_conds, "transformer_options"]
    for path, patch in patches.items():
        current = wrapped.get_model_object(path)
        original = current.attention if isinstance(current, ControlNetAttention) else current
        wrapped.add_object_patch(path, ControlNetAttention(original, patch, call))
    return patched


# --------------------------------------------------------------------------- low VRAM


class OneSampleAtATime(torch.nn.Sequential):
    """A transformer block's feed-forward layers (ComfyUI's ``FeedForward.net``, the same child modules under
    the same names, so weight patches and low-VRAM casting still find them) run on one sample of the batch
    at a time: the same result, with the hidden activations of one sample alive at once. SDXL's GEGLU
    holds ``[B, L, 16 x width]`` of them at its peak (its projection to 8 x width, the gate's GELU and the
    product, 4 x width each): 1.1 GiB in fp16 for 14 views at 1024 px (L 4096, width 640), 80 MiB for one."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.nn.Sequential.forward(self, sample) for sample in x.split(1)])


def _feed_forwards(patcher, model: torch.nn.Module, prefix: str) -> None:
    """Object patches on ModelPatcher ``patcher`` running each transformer block's feed-forward of ``model``
    (at ``prefix`` in the patcher's model) one sample at a time."""
    for layer in transformer_layers(model):
        path = f"{prefix}{layer.path}.ff.net"
        layers = patcher.get_model_object(path)
        if not isinstance(layers, OneSampleAtATime):
            patcher.add_object_patch(path, OneSampleAtATime(*layers))


def feed_forward_one_sample_at_a_time(model, control_net) -> tuple:
    """Copies of ComfyUI's SDXL ``model`` (MODEL) and ``control_net`` (CONTROL_NET) whose transformer blocks
    run their feed-forward one sample at a time (:class:`OneSampleAtATime`); their other patches stay."""
    model = model.clone()
    _feed_forwards(model, model.get_model_object("diffusion_model"), "diffusion_model.")
    control_net = _controlnet_copy(control_net)
    _feed_forwards(control_net.control_model_wrapped, control_net.control_model, "")
    return model, control_net
