"""The camera set: C pinhole views of one image size (conventions in :mod:`artnvg_core.cameras`)."""

from __future__ import annotations

import math
import numbers
import operator
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from ..counted import counted
from .geometry import camera_centers

MAX_IMAGE_SIDE = 16384  # pixels; a float32 RGB view this size already takes 3 GiB
MAX_VIEWS = 1_000_000  # views a path or an orbit may be built of: their float64 poses take 128 MB on the way


def scaled_size(width: int, height: int, factor: float) -> tuple[int, int]:
    """(width, height) in pixels at ``factor`` (> 0) times, each side rounded to whole pixels and at least 1: the size
    :meth:`CameraSet.scaled` gives views of ``width`` x ``height``."""
    return max(1, round(width * factor)), max(1, round(height * factor))


def whole_number(value, what: str) -> int:
    """``value`` as an int: an int, numpy's or a 0-d integer tensor; a ValueError naming ``what`` for anything else (a
    bool, a float, text)."""
    if not isinstance(value, bool):
        try:
            return operator.index(value)
        except TypeError:
            pass
    raise ValueError(f"{what}: expected an int, got {value!r}")


def view_count(value, what: str) -> int:
    """``value`` as a number of views to build (a path's, an orbit's): an int (:func:`whole_number`) from 1 to
    :data:`MAX_VIEWS`; a ValueError naming ``what`` otherwise, before they take the memory."""
    count = whole_number(value, what)
    if not 1 <= count <= MAX_VIEWS:
        raise ValueError(f"{what}: expected 1 to {MAX_VIEWS:,}, got {count:,}")
    return count


@dataclass
class CameraSet:
    """C pinhole cameras of one image size (shapes and conventions in :mod:`artnvg_core.cameras`): floating-point
    tensors on one device.

    ``names`` are the views' image file stems (e.g. ``frame_00096``);
    ``image_paths`` the source images when known (else ``None`` entries).
    """

    world_to_cam: torch.Tensor
    intrinsics: torch.Tensor
    width: int
    height: int
    names: list[str]
    image_paths: list[Path | None] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name in ("world_to_cam", "intrinsics"):
            value = getattr(self, name)
            if not (isinstance(value, torch.Tensor) and value.is_floating_point()):
                kind = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
                raise ValueError(f"CameraSet.{name}: expected a floating-point torch.Tensor, got {kind}")
        if self.intrinsics.device != self.world_to_cam.device:
            raise ValueError(f"CameraSet.intrinsics: expected world_to_cam's device ({self.world_to_cam.device}), "
                             f"got {self.intrinsics.device}")
        c = self.world_to_cam.shape[0] if self.world_to_cam.ndim == 3 else -1
        if tuple(self.world_to_cam.shape) != (c, 4, 4) or c < 0:
            raise ValueError(f"CameraSet.world_to_cam: expected shape (C, 4, 4), got {tuple(self.world_to_cam.shape)}")
        if tuple(self.intrinsics.shape) != (c, 3, 3):
            raise ValueError(f"CameraSet.intrinsics: expected shape ({c}, 3, 3), got {tuple(self.intrinsics.shape)}")
        self.width, self.height = whole_number(self.width, "CameraSet.width"), whole_number(self.height, "CameraSet.height")
        if not (0 < self.width <= MAX_IMAGE_SIDE and 0 < self.height <= MAX_IMAGE_SIDE):
            raise ValueError(f"CameraSet: image size must be 1 to {MAX_IMAGE_SIDE} pixels a side, "
                             f"got {self.width}x{self.height}")
        if len(self.names) != c:
            raise ValueError(f"CameraSet.names: expected {counted(c, 'name')}, got {len(self.names)}")
        if not self.image_paths:
            self.image_paths = [None] * c
        if len(self.image_paths) != c:
            raise ValueError(f"CameraSet.image_paths: expected {counted(c, 'entry', 'entries')}, "
                             f"got {len(self.image_paths)}")

    def __len__(self) -> int:
        return self.world_to_cam.shape[0]

    @property
    def centers(self) -> torch.Tensor:
        """Camera centres in world coordinates, [C, 3]."""
        return camera_centers(self.world_to_cam)

    def in_view(self, points: torch.Tensor) -> torch.Tensor:
        """[C, N] bool: whether each world point of ``points`` [N, 3] lies in front of each camera and
        projects inside its image (float64 maths, on the cameras' device)."""
        rot, shift = self.world_to_cam[:, :3, :3].double(), self.world_to_cam[:, None, :3, 3].double()
        cam = torch.einsum("cij,nj->cni", rot, points.to(rot.device, torch.float64)) + shift
        k = self.intrinsics.double()[:, None]
        u = k[..., 0, 0] * cam[..., 0] / cam[..., 2] + k[..., 0, 2]
        v = k[..., 1, 1] * cam[..., 1] / cam[..., 2] + k[..., 1, 2]
        return (cam[..., 2] > 0) & (u >= 0) & (u < self.width) & (v >= 0) & (v < self.height)

    def subset(self, indices, on_device: torch.Tensor | None = None) -> "CameraSet":
        """The views at ``indices`` (a sequence of ints), in that order. ``on_device``: the same indices as
        a long tensor on the cameras' device, which selects without copying indices to it (such a copy
        waits for the device to finish its queued work)."""
        idx = [whole_number(i, "CameraSet.subset: a view index") for i in indices]  # not int(): 0.5 would be view 0
        for i in idx:
            if not -len(self) <= i < len(self):
                raise ValueError(f"CameraSet.subset: view index {i} out of range for {counted(len(self), 'view')}")
        sel = torch.tensor(idx, dtype=torch.long) if on_device is None else on_device
        return replace(
            self,
            world_to_cam=self.world_to_cam[sel],
            intrinsics=self.intrinsics[sel],
            names=[self.names[i] for i in idx],
            image_paths=[self.image_paths[i] for i in idx],
        )

    def scaled(self, factor: float) -> "CameraSet":
        """The same views at ``factor`` times the resolution (rounded to whole pixels).

        Intrinsics scale with the actual per-axis size ratio, so the image
        plane keeps covering the same field of view.
        """
        if isinstance(factor, bool) or not (isinstance(factor, numbers.Real) and math.isfinite(factor) and factor > 0):
            raise ValueError(f"CameraSet.scaled: factor must be a finite number > 0, got {factor}")
        width, height = scaled_size(self.width, self.height, factor)
        if max(width, height) > MAX_IMAGE_SIDE:
            raise ValueError(f"CameraSet.scaled: factor {factor} makes {self.width}x{self.height} views "
                             f"{width}x{height}, above the {MAX_IMAGE_SIDE} pixels a side a view may have")
        k = self.intrinsics.clone()
        k[:, 0, :] *= width / self.width
        k[:, 1, :] *= height / self.height
        return replace(self, intrinsics=k, width=width, height=height)

    def to(self, device=None, dtype=None) -> "CameraSet":
        """The poses and intrinsics on ``device`` and of ``dtype`` (each left as it is when None)."""
        return replace(self, world_to_cam=self.world_to_cam.to(device=device, dtype=dtype),
                       intrinsics=self.intrinsics.to(device=device, dtype=dtype))

