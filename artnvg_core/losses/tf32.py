"""PyTorch's TF32 switches for CUDA float32 products and convolutions, set for a block and restored after.

From PyTorch 2.9 on each backend has ``fp32_precision`` (``"tf32"`` or ``"ieee"``); before it, ``allow_tf32``.
The two must not be mixed (reading the legacy flag after setting the new one per operator raises), so the
new one is set wherever it exists.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def _switch(new_owner, legacy_owner, tf32: bool) -> Iterator[None]:
    if new_owner is not None and hasattr(new_owner, "fp32_precision"):
        owner, name, value = new_owner, "fp32_precision", "tf32" if tf32 else "ieee"
    else:
        owner, name, value = legacy_owner, "allow_tf32", tf32
    before = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, before)


def matmul_tf32(enabled: bool):
    """CUDA float32 matrix products (cuBLAS) in TF32 (``enabled``) or IEEE float32 inside the block."""
    matmul = torch.backends.cuda.matmul
    return _switch(matmul, matmul, enabled)


def convolution_tf32(enabled: bool):
    """cuDNN's float32 convolutions, forward and backward, in TF32 (``enabled``) or IEEE float32 inside the block."""
    return _switch(getattr(torch.backends.cudnn, "conv", None), torch.backends.cudnn, enabled)
