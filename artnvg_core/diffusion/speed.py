"""Exact speedups of the diffusion models: each changes no result beyond floating-point rounding.

* :func:`sdpa_backend` — a context in which every ``scaled_dot_product_attention`` (our
  processors included) runs on one named PyTorch backend: ``"flash"``, ``"cudnn"``,
  ``"efficient"``, ``"math"``, or ``"auto"`` (PyTorch's own choice). The sampler enters it
  around the denoising loop (:attr:`SamplerSettings.attention_backend`).
* :func:`cudnn_attention_first` — a context in which attention on a GPU tries cuDNN's kernel first
  among the backends enabled; ArtNVG's attention maths runs every call in it.
* :class:`SpeedOptions` / :func:`apply_speedups` — one-off transformations of the UNet and
  the ControlNet, applied in place after loading:

  - ``channels_last``: NHWC memory layout for the convolutions;
  - ``fuse_projections``: one ``to_qkv`` matmul per self-attention and one ``to_kv`` per text
    cross-attention (diffusers' ``Attention.fuse_projections``); the original ``to_q`` /
    ``to_k`` / ``to_v`` weights become views of the fused weight, so no memory is added.
    ArtNVG's processors use the fused layers when ``attn.fused_projections`` is set;
  - ``compile``: ``torch.compile`` with the given mode, e.g. ``"default"`` or
    ``"max-autotune-no-cudagraphs"``, in place (``nn.Module.compile``) of what ``compile_scope``
    names: ``"model"``, both models' whole forward (the first call of each input shape compiles:
    minutes for full-size SDXL), or ``"blocks"``, only the repeated blocks
    (:data:`REPEATED_BLOCKS`: transformer and ResNet blocks), regional compilation: blocks of the
    same class and shapes share one compiled graph, so it compiles far fewer graphs;
    ``compile_dynamic`` compiles with symbolic shapes from the start (``dynamic=True``), so a new
    group size or resolution reuses the graphs instead of compiling them again;
  - ``cache_hint_embedding``: the ControlNet's hint embedding (a stack of convolutions on the
    full-resolution content image, the same at every denoising step of a group) is computed
    once per hint tensor and reused while that tensor is unchanged (the same object, same
    ``_version``, or the same object alone for an inference tensor; at most two hints are kept,
    the two guidance halves of sequential CFG).
    Only under ``torch.no_grad``; the results are bit-identical.

All are off by default (:data:`COMPILED_BLOCKS` is the set users can switch on); none changes
any parameter value.
"""

from __future__ import annotations

import contextlib
import inspect
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel

SDPA_BACKENDS = {
    "auto": None,
    "flash": SDPBackend.FLASH_ATTENTION,
    "cudnn": SDPBackend.CUDNN_ATTENTION,
    "efficient": SDPBackend.EFFICIENT_ATTENTION,
    "math": SDPBackend.MATH,
}
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
COMPILE_SCOPES = ("model", "blocks")
REPEATED_BLOCKS = ("BasicTransformerBlock", "ResnetBlock2D")
BLOCK_RECOMPILE_LIMIT = 64  # Dynamo graphs per block class (see compile_repeated_blocks)


def check_sdpa_backend(name: str, field: str) -> str:
    """``name`` if it is a key of :data:`SDPA_BACKENDS`, else ValueError naming ``field``."""
    if name not in SDPA_BACKENDS:
        raise ValueError(f"{field} must be one of {sorted(SDPA_BACKENDS)}, got {name!r}")
    return name


def sdpa_backend(name: str) -> contextlib.AbstractContextManager:
    """Context restricting scaled-dot-product attention to backend ``name`` ("auto": no restriction).

    Inside it, a call the backend cannot serve (e.g. "cudnn" on the CPU) raises RuntimeError.
    """
    backend = SDPA_BACKENDS[check_sdpa_backend(name, "sdpa_backend: name")]
    return contextlib.nullcontext() if backend is None else sdpa_kernel(backend)


CUDNN_FIRST = (SDPBackend.CUDNN_ATTENTION, SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH)
_ENABLED = ("cudnn_sdp_enabled", "flash_sdp_enabled", "mem_efficient_sdp_enabled", "math_sdp_enabled")  # as CUDNN_FIRST
_ORDERS = "set_priority" in inspect.signature(sdpa_kernel).parameters


def cudnn_attention_first(device: torch.device) -> contextlib.AbstractContextManager:
    """On a CUDA ``device``, a context in which scaled-dot-product attention tries the backends enabled now
    (an :func:`sdpa_backend` restriction holds) in the order :data:`CUDNN_FIRST`; elsewhere, or where
    PyTorch's ``sdpa_kernel`` takes no ``set_priority``, nothing. PyTorch's own choice depends on what ran
    before in the process: in a ComfyUI process (whose attention sets its own order, cuDNN first, around
    each of its calls) a balanced group's NV attention ran on flash attention, 16.9 s of GPU time on an
    H200 against 11.4 s on cuDNN's kernel (BENCHMARKS.md, "ComfyUI's native path")."""
    if device.type != "cuda" or not _ORDERS:
        return contextlib.nullcontext()
    enabled = [backend for backend, name in zip(CUDNN_FIRST, _ENABLED) if getattr(torch.backends.cuda, name)()]
    return sdpa_kernel(enabled, set_priority=True) if enabled else contextlib.nullcontext()


@dataclass(frozen=True)
class SpeedOptions:
    """Which exact speedups :func:`apply_speedups` applies (see the module docstring).

    compile: None (eager) or a ``torch.compile`` mode from :data:`COMPILE_MODES`.
    compile_scope: what is compiled, one of :data:`COMPILE_SCOPES`.
    compile_dynamic: compile with symbolic shapes (``dynamic=True``) instead of Dynamo's default
        (static first, dynamic after a shape change).
    """

    channels_last: bool = False
    fuse_projections: bool = False
    compile: str | None = None
    compile_scope: str = "model"
    compile_dynamic: bool = False
    cache_hint_embedding: bool = False

    def __post_init__(self) -> None:
        if self.compile is not None and self.compile not in COMPILE_MODES:
            raise ValueError(f"SpeedOptions.compile must be None or one of {COMPILE_MODES}, got {self.compile!r}")
        if self.compile_scope not in COMPILE_SCOPES:
            raise ValueError(f"SpeedOptions.compile_scope must be one of {COMPILE_SCOPES}, got {self.compile_scope!r}")
        if self.compile_dynamic and self.compile is None:
            raise ValueError("SpeedOptions.compile_dynamic needs a compile mode")
        if self.cache_hint_embedding and self.compile is not None and self.compile_scope == "model":
            raise ValueError("SpeedOptions.cache_hint_embedding needs compile_scope='blocks' or no compile: "
                             "a whole-model graph cannot keep a cache between calls")


@torch.no_grad()
def fuse_attention_projections(model: nn.Module) -> None:
    """Fuse the q/k/v (self-attention) and k/v (cross-attention) projections of every diffusers
    ``Attention`` in ``model``, keeping the separate layers as views of the fused weight."""
    from diffusers.models.attention_processor import Attention  # here: the settings import this module

    for layer in model.modules():
        if not isinstance(layer, Attention) or layer.fused_projections:
            continue
        layer.fuse_projections()
        if layer.is_cross_attention:
            fused, names = layer.to_kv, ("to_k", "to_v")
        else:
            fused, names = layer.to_qkv, ("to_q", "to_k", "to_v")
        sizes = [getattr(layer, name).out_features for name in names]
        weights = fused.weight.split(sizes)
        biases = fused.bias.split(sizes) if fused.bias is not None else [None] * len(names)
        for name, weight, bias in zip(names, weights, biases):
            linear = getattr(layer, name)
            linear.weight = nn.Parameter(weight, requires_grad=linear.weight.requires_grad)
            if bias is not None:
                linear.bias = nn.Parameter(bias, requires_grad=linear.bias.requires_grad)


def cache_hint_embedding(controlnet: nn.Module, capacity: int = 2) -> None:
    """Make ``controlnet.controlnet_cond_embedding`` reuse its output for a hint tensor it has seen
    (same object, unchanged ``_version``), keeping the ``capacity`` latest; computed afresh when
    gradients are enabled. An inference tensor (``torch.inference_mode``, as in ComfyUI) has no
    version counter and is matched by identity alone: the sampler never changes a hint in place.
    The module and its parameters (state dict) are untouched."""
    embedding = controlnet.controlnet_cond_embedding
    compute = embedding.forward
    cache: list[tuple[torch.Tensor, int | None, torch.Tensor]] = []

    def version_of(hint: torch.Tensor) -> int | None:
        return None if hint.is_inference() else hint._version

    def forward(hint: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled():
            return compute(hint)
        for seen, version, output in cache:
            if seen is hint and version == version_of(hint):
                return output
        output = compute(hint)
        cache.append((hint, version_of(hint), output))
        del cache[:-capacity]
        return output

    embedding.forward = forward


def _raise_recompile_limit(at_least: int) -> None:
    """Raise ``torch._dynamo.config.recompile_limit`` to ``at_least`` graphs per function; older
    PyTorch releases name it ``cache_size_limit`` (newer ones keep that name as an alias)."""
    config = torch._dynamo.config
    name = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"
    setattr(config, name, max(getattr(config, name), at_least))


def compile_repeated_blocks(model: nn.Module, **compile_kwargs) -> int:
    """``torch.compile(**compile_kwargs)`` in place every submodule of ``model`` whose class is in
    :data:`REPEATED_BLOCKS`; returns how many.

    All blocks of a class share one ``forward`` and so one Dynamo cache, which holds a graph per
    shape variant (SDXL's UNet and ControlNet have about 20 ResNet-block variants: channels,
    resolution, batch). Dynamo's default limit of 8 graphs per function would leave the rest
    eager, so this raises Dynamo's recompile limit (process-wide) to at least
    :data:`BLOCK_RECOMPILE_LIMIT`.
    """
    _raise_recompile_limit(BLOCK_RECOMPILE_LIMIT)
    blocks = [module for module in model.modules() if type(module).__name__ in REPEATED_BLOCKS]
    for block in blocks:
        block.compile(**compile_kwargs)
    return len(blocks)


def apply_speedups(models, options: SpeedOptions) -> None:
    """Apply ``options`` in place to ``models.base.unet`` and ``models.controlnet``
    (a :class:`artnvg_core.diffusion.models.DiffusionModels`). Call once, after loading."""
    for model in (models.base.unet, models.controlnet):
        if options.channels_last:
            model.to(memory_format=torch.channels_last)
        if options.fuse_projections:
            fuse_attention_projections(model)
        if options.compile is not None:
            compile_kwargs = {"mode": options.compile, "dynamic": True if options.compile_dynamic else None}
            if options.compile_scope == "model":
                model.compile(**compile_kwargs)
            else:
                compile_repeated_blocks(model, **compile_kwargs)
    if options.cache_hint_embedding:
        cache_hint_embedding(models.controlnet)


# What users switch on (command line ``--compile``): regional
# compilation with dynamic shapes and the cached hint embedding; exact up to bf16 rounding.
# Its speed-up, first-call cost and pay-back: BENCHMARKS.md, "Diffusion step".
COMPILED_BLOCKS = SpeedOptions(compile="default", compile_scope="blocks", compile_dynamic=True,
                               cache_hint_embedding=True)
