"""What every scene file reader and writer shares: file checks, the scene check before writing, 8-bit opacities."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..fileio import require_regular_file
from ..scene import GaussianScene, describe_invalid, invalid_gaussians, logit


def require_file(path: Path) -> None:
    """ValueError naming ``path`` unless it is a regular file (a FIFO would block the read)."""
    require_regular_file(path, "scene file")


def scene_to_write(scene: GaussianScene, path: Path) -> GaussianScene:
    """``scene`` as detached float32 CPU tensors; a ValueError naming ``path`` and the field when
    any Gaussian is non-finite (after the float32 cast) or has a zero quaternion, before anything is written."""
    cpu = scene.map(lambda t: t.detach().to("cpu", torch.float32))
    if len(cpu) == 0:
        raise ValueError(f"{path}: not written: the scene contains no Gaussians")
    for name, problem, bad in invalid_gaussians(cpu):
        if bad.any():
            raise ValueError(f"{path}: not written: {describe_invalid(name, bad, f'have {problem}')}")
    return cpu


# An 8-bit opacity byte b stands for b / 255; the two end bytes are read as b / 255 moved 0.25/255
# inwards (finite logits) and written back as the same byte.
_OPACITY_EDGE = 0.25 / 255


def opacity_logits_from_bytes(values: np.ndarray) -> np.ndarray:
    """Opacity logits [N] (float64) of 8-bit opacities (0..255 for 0..1)."""
    opacities = np.clip(np.asarray(values, np.float64) / 255, _OPACITY_EDGE, 1 - _OPACITY_EDGE)
    return logit(torch.from_numpy(opacities)).numpy()


def opacity_bytes(logits: torch.Tensor) -> np.ndarray:
    """8-bit opacities [N] (0..255 for 0..1, rounded half up) of opacity logits [N] (sigmoid in float64)."""
    return to_bytes(torch.sigmoid(logits.double()).numpy() * 255)


def to_bytes(values: np.ndarray) -> np.ndarray:
    """Values on the 0..255 scale rounded half up and clamped to uint8."""
    return np.clip(np.floor(np.asarray(values, np.float64) + 0.5), 0, 255).astype(np.uint8)
