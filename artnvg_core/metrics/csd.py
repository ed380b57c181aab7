"""CSD score (Somepalli et al. 2024, Contrastive Style Descriptors): style similarity.

The CSD model is OpenAI's CLIP ViT-L/14 image tower without its contrastive projection,
followed by a learned style projection ``last_layer_style`` [1024, 768] (a plain matrix,
applied as ``pooled @ last_layer_style``) and L2 normalisation. The score of a stylized view
is the cosine similarity of its descriptor with the style image's.

The released checkpoint (``pytorch_model.bin`` of ``tomg-group-umd/CSD-ViT-L``, a training
checkpoint) holds ``model_state_dict`` with DDP ``module.`` prefixes: ``backbone.*`` in
OpenAI CLIP's ``VisionTransformer`` naming (``conv1``, ``class_embedding``,
``positional_embedding``, ``ln_pre``, ``transformer.resblocks.{i}.{ln_1, attn.in_proj_*,
attn.out_proj, ln_2, mlp.c_fc, mlp.c_proj}``, ``ln_post``; no ``proj``), plus
``last_layer_style`` and ``last_layer_content`` (unused here). :class:`CSDStyleEncoder`
uses the same parameter names, so the file loads strictly after removing the prefix. A
plain state dict or a ``.safetensors`` file with those keys loads too.
"""

from __future__ import annotations

import argparse
import pickle
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..diffusion.images import check_images, clip_preprocess
from ..diffusion.model_files import ModelSource, locate
from ..statedict import is_state_dict, state_dict_mismatch
from ..tensor_files import load_failure, read_tensors

CSD_WEIGHTS = ModelSource("CSD style descriptor weights (ViT-L/14)", "tomg-group-umd/CSD-ViT-L", "pytorch_model.bin")
_STYLE_HEAD = "last_layer_style"
_UNUSED_KEYS = ("last_layer_content",)
_HEAD_WIDTH = 64  # OpenAI CLIP ViTs: heads = width // 64
_numpy_scalar = (np._core if hasattr(np, "_core") else np.core).multiarray.scalar  # numpy 2 / numpy 1


@dataclass(frozen=True)
class CSDConfig:
    """Vision transformer shape: ``image_size``/``patch_size`` in pixels, ``width`` channels,
    ``layers`` blocks, ``heads`` attention heads, ``embed_dim`` style descriptor size."""

    image_size: int = 224
    patch_size: int = 14
    width: int = 1024
    layers: int = 24
    heads: int = 16
    embed_dim: int = 768


class _QuickGELU(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(1.702 * x)


class _ResidualAttentionBlock(nn.Module):
    """Pre-LayerNorm transformer block with OpenAI CLIP's parameter names."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.ln_1 = nn.LayerNorm(width)
        self.attn = nn.MultiheadAttention(width, heads, batch_first=True)
        self.ln_2 = nn.LayerNorm(width)
        self.mlp = nn.Sequential(OrderedDict(
            c_fc=nn.Linear(width, 4 * width), gelu=_QuickGELU(), c_proj=nn.Linear(4 * width, width)
        ))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.ln_1(x)
        x = x + self.attn(h, h, h, need_weights=False)[0]
        return x + self.mlp(self.ln_2(x))


class _Transformer(nn.Module):
    def __init__(self, width: int, layers: int, heads: int):
        super().__init__()
        self.resblocks = nn.Sequential(*(_ResidualAttentionBlock(width, heads) for _ in range(layers)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.resblocks(x)


class _VisionTransformer(nn.Module):
    """CLIP image tower without projection: [B, 3, S, S] normalised -> pooled [B, width]."""

    def __init__(self, config: CSDConfig):
        super().__init__()
        width, grid = config.width, config.image_size // config.patch_size
        self.conv1 = nn.Conv2d(3, width, config.patch_size, stride=config.patch_size, bias=False)
        scale = width**-0.5  # random initialisation as in CLIP; real weights replace it
        self.class_embedding = nn.Parameter(scale * torch.randn(width))
        self.positional_embedding = nn.Parameter(scale * torch.randn(grid * grid + 1, width))
        self.ln_pre = nn.LayerNorm(width)
        self.transformer = _Transformer(width, config.layers, config.heads)
        self.ln_post = nn.LayerNorm(width)

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        patches = self.conv1(pixels).flatten(2).transpose(1, 2)  # [B, grid^2, width]
        cls = self.class_embedding.expand(patches.shape[0], 1, -1)
        x = self.ln_pre(torch.cat([cls, patches], dim=1) + self.positional_embedding)
        return self.ln_post(self.transformer(x)[:, 0])


class CSDStyleEncoder(nn.Module):
    """CSD style descriptors: ``forward(pixels [B, 3, S, S] CLIP-normalised) -> [B, embed_dim]`` unit vectors."""

    def __init__(self, config: CSDConfig = CSDConfig()):
        super().__init__()
        self.config = config
        self.backbone = _VisionTransformer(config)
        self.last_layer_style = nn.Parameter(config.width**-0.5 * torch.randn(config.width, config.embed_dim))

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.backbone(pixels) @ self.last_layer_style, dim=-1)


# --------------------------------------------------------------------------- loading


def _read_state(path: Path) -> dict:
    """The raw tensor mapping of a CSD weights file (safetensors, or a torch checkpoint / state dict)."""
    if path.suffix == ".safetensors":
        return read_tensors(path)  # ValueError naming the file for a malformed header
    # The released training checkpoint pickles its argparse options, which hold numpy scalars.
    allowed = [argparse.Namespace, np.dtype, np.dtypes.Float64DType,
               _numpy_scalar, (_numpy_scalar, "numpy.core.multiarray.scalar")]
    try:
        with torch.serialization.safe_globals(allowed):
            checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)  # skips optimizer states
    except (pickle.UnpicklingError, RuntimeError, EOFError, OSError) as error:
        raise ValueError(f"{path}: not a loadable CSD checkpoint ({load_failure(error)})") from error
    if isinstance(checkpoint, dict) and isinstance(checkpoint.get("model_state_dict"), dict):
        checkpoint = checkpoint["model_state_dict"]
    if not is_state_dict(checkpoint):
        raise ValueError(f"{path}: expected a state dict (names to tensors) or a dict with 'model_state_dict'")
    return checkpoint


def _tensor(path: Path, state: dict, key: str, ndim: int) -> torch.Tensor:
    value = state.get(key)
    if not isinstance(value, torch.Tensor) or value.ndim != ndim:
        got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ValueError(f"{path}: '{key}': expected a {ndim}-d tensor, got {got}")
    return value


def _config_from_state(path: Path, state: dict) -> CSDConfig:
    """Model shape inferred from the checkpoint's tensor shapes (heads = width // 64)."""
    conv = _tensor(path, state, "backbone.conv1.weight", 4)
    positions = _tensor(path, state, "backbone.positional_embedding", 2)
    head = _tensor(path, state, _STYLE_HEAD, 2)
    width, patch = conv.shape[0], conv.shape[-1]
    grid = round((positions.shape[0] - 1) ** 0.5)
    if grid * grid + 1 != positions.shape[0] or head.shape[0] != width or width % _HEAD_WIDTH:
        raise ValueError(
            f"{path}: inconsistent shapes: conv1 {tuple(conv.shape)}, positional_embedding {tuple(positions.shape)}, "
            f"{_STYLE_HEAD} {tuple(head.shape)}; expected (grid^2 + 1, width) positions and (width, dim) head"
        )
    prefix = "backbone.transformer.resblocks."
    layers = len({key[len(prefix):].split(".")[0] for key in state if key.startswith(prefix)})
    return CSDConfig(grid * patch, patch, width, layers, width // _HEAD_WIDTH, head.shape[1])


def load_csd(path: str | Path | None = None, *, device: str | torch.device = "cpu") -> CSDStyleEncoder:
    """A frozen :class:`CSDStyleEncoder` in eval mode from a CSD weights file (module docstring).

    path: the file; None looks for ``pytorch_model.bin`` of ``tomg-group-umd/CSD-ViT-L`` in
    the Hugging Face cache. Missing files raise :class:`MissingModelError`; unreadable files
    or missing / unexpected keys a ValueError naming the file and the keys.
    """
    path = locate(CSD_WEIGHTS, path)
    if path.is_dir():
        raise ValueError(f"{path}: is a folder; pass the CSD weights file itself (e.g. {CSD_WEIGHTS.repo_path})")
    state = {key.removeprefix("module."): value for key, value in _read_state(path).items()}
    for key in _UNUSED_KEYS:
        state.pop(key, None)
    model = CSDStyleEncoder(_config_from_state(path, state))
    mismatch = state_dict_mismatch(model.state_dict(), state)
    if mismatch:
        raise ValueError(f"{path}: not a CSD ViT checkpoint: {mismatch}")
    model.load_state_dict({k: v.float() for k, v in state.items()})
    return model.to(device).eval().requires_grad_(False)


@torch.no_grad()
def csd_descriptors(model: CSDStyleEncoder, images: torch.Tensor, *, batch_size: int = 16) -> torch.Tensor:
    """Unit style descriptors [B, embed_dim] of ``images`` [B, H, W, 3] in [0, 1] (CLIP preprocessing)."""
    images = check_images(images, "csd_descriptors: images")
    device = next(model.parameters()).device
    out = [model(clip_preprocess(images[s:s + batch_size].to(device), model.config.image_size))
           for s in range(0, images.shape[0], batch_size)]
    return torch.cat(out)


def csd_scores(model: CSDStyleEncoder, style: torch.Tensor, stylized: torch.Tensor) -> torch.Tensor:
    """Cosine similarity [B] of the style image [H, W, 3] with each stylized view [B, H', W', 3]."""
    if style.ndim != 3:
        raise ValueError(f"csd_scores: style must be one image [H, W, 3], got {tuple(style.shape)}")
    return csd_descriptors(model, stylized) @ csd_descriptors(model, style[None])[0]
