"""Depth-warp consistency: a weight-free multi-view consistency measure.

For view pairs (i, j = i + step) of a sequence, view j's pixels are lifted to 3D with a depth
map, projected into view i, and view i's image is sampled there (bilinear); the error is
the colour difference to view j's own pixel, over co-visible pixels only. Depth and alpha
come from rendering the ORIGINAL scene (``render(..., return_depth=True)``) at the same
cameras, so any image sequence in view order can be scored: renders of a stylized scene,
or the 2D stylized views of the diffusion stage before finetuning. The same number for the
original scene's own renders is the floor (view-dependent colour, interpolation).

A pixel of view j is co-visible when its alpha and view i's alpha (sampled at the
reprojection) exceed ``alpha_threshold``, the point lies in front of camera i and inside
its image (pixel centres 0.5 .. W - 0.5), and its depth in camera i agrees with view i's
rendered depth there within ``depth_tolerance`` (relative): the occlusion test.

Conventions: OpenCV cameras, pixel centres at +0.5, depth = camera-space z; colours in
[0, 1]; RMSE and MAE are over co-visible pixels and the 3 channels.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F

from ..cameras import CameraSet
from ..counted import counted
from ..images import check_image_values
from ..progress import ProgressFn


@dataclass(frozen=True)
class WarpConsistency:
    """Warp errors over all pairs (i, i + step), pooled over their co-visible pixels.

    ``rmse``/``mae`` are in colour units ([0, 1] images); ``coverage`` is the co-visible
    fraction of all view-j pixels; ``pixels`` their count; ``pairs`` the (i, j) view indices.
    """

    step: int
    rmse: float
    mae: float
    coverage: float
    pixels: int
    pairs: list[tuple[int, int]]

    def to_dict(self) -> dict:
        return asdict(self)


def reproject(
    depth: torch.Tensor,
    source_world_to_cam: torch.Tensor,
    source_intrinsics: torch.Tensor,
    target_world_to_cam: torch.Tensor,
    target_intrinsics: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each source pixel lands in the target camera.

    depth [H, W]: source camera-space z per pixel. Poses [4, 4] world-to-camera (OpenCV),
    intrinsics [3, 3]. Returns target pixel coordinates [H, W, 2] (x, y; pixel centres at
    +0.5) and target camera-space z [H, W]. Computed in float64.
    """
    height, width = depth.shape
    f64 = {"dtype": torch.float64, "device": depth.device}
    ys, xs = torch.meshgrid(torch.arange(height, **f64) + 0.5, torch.arange(width, **f64) + 0.5, indexing="ij")
    pixels = torch.stack([xs, ys, torch.ones_like(xs)], dim=-1)  # [H, W, 3]
    rays = pixels @ torch.linalg.inv(source_intrinsics.to(**f64)).T
    points = rays * depth.to(**f64)[..., None]  # source camera coordinates
    relative = target_world_to_cam.to(**f64) @ torch.linalg.inv(source_world_to_cam.to(**f64))
    target = points @ relative[:3, :3].T + relative[:3, 3]
    z = target[..., 2]
    projected = target @ target_intrinsics.to(**f64).T
    uv = projected[..., :2] / torch.where(z.abs() > 1e-12, z, torch.full_like(z, 1e-12))[..., None]
    return uv, z


def _sample(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``image`` [H, W, K] at pixel coordinates ``uv`` [H', W', 2] -> [H', W', K]."""
    height, width = image.shape[:2]
    scale = torch.tensor([2.0 / width, 2.0 / height], dtype=uv.dtype, device=uv.device)
    grid = (uv * scale - 1).to(image.dtype)[None]  # align_corners=False: pixel centres at +0.5
    sampled = F.grid_sample(image.permute(2, 0, 1)[None], grid, mode="bilinear", align_corners=False)
    return sampled[0].permute(1, 2, 0)


def _check_inputs(images, depth, alpha, cameras: CameraSet, step: int, alpha_threshold: float,
                  depth_tolerance: float) -> None:
    if not 0 <= alpha_threshold < 1:
        raise ValueError(f"warp_consistency: alpha_threshold must be in [0, 1), got {alpha_threshold!r}")
    if not depth_tolerance > 0:  # inf: no occlusion test
        raise ValueError(f"warp_consistency: depth_tolerance must be > 0, got {depth_tolerance!r}")
    count = images.shape[0] if images.ndim == 4 else -1
    size = (cameras.height, cameras.width)
    if images.ndim != 4 or images.shape[-1] != 3 or tuple(images.shape[1:3]) != size:
        raise ValueError(f"warp_consistency: images must be [C, {size[0]}, {size[1]}, 3] (the cameras' size), "
                         f"got {tuple(images.shape)}")
    for name, value in (("depth", depth), ("alpha", alpha)):
        if tuple(value.shape) != (count, *size, 1):
            raise ValueError(f"warp_consistency: {name} must be [{count}, {size[0]}, {size[1]}, 1], got {tuple(value.shape)}")
    if len(cameras) != count:
        raise ValueError(f"warp_consistency: {counted(count, 'image')} but {counted(len(cameras), 'camera')}")
    check_image_values(images, "warp_consistency: images")
    if int(step) != step or not 1 <= step < count:
        raise ValueError(f"warp_consistency: step must be an integer in 1..{count - 1} for "
                         f"{counted(count, 'view')}, got {step!r}")


@torch.no_grad()
def warp_consistency(
    images: torch.Tensor,
    depth: torch.Tensor,
    alpha: torch.Tensor,
    cameras: CameraSet,
    *,
    step: int = 1,
    alpha_threshold: float = 0.5,
    depth_tolerance: float = 0.05,
    progress: ProgressFn | None = None,
) -> WarpConsistency:
    """Warp error of ``images`` [C, H, W, 3] (views in sequence order) for pairs (i, i + step).

    depth, alpha [C, H, W, 1]: the original scene rendered at ``cameras`` (C views of the
    images' size). Raises ValueError on mismatched shapes or a step with no pair.
    ``progress(done, total, {})`` is called as the pairs start (0) and after each pair.
    """
    _check_inputs(images, depth, alpha, cameras, step, alpha_threshold, depth_tolerance)
    cameras = cameras.to(images.device)
    squared = absolute = 0.0
    covisible = total = 0
    pairs = [(i, i + int(step)) for i in range(images.shape[0] - int(step))]
    if progress is not None:
        progress(0, len(pairs), {})
    for done, (i, j) in enumerate(pairs, 1):
        uv, z = reproject(depth[j, ..., 0], cameras.world_to_cam[j], cameras.intrinsics[j],
                          cameras.world_to_cam[i], cameras.intrinsics[i])
        target = _sample(torch.cat([images[i], depth[i], alpha[i]], dim=-1).float(), uv)
        target_rgb, target_depth, target_alpha = target[..., :3], target[..., 3].double(), target[..., 4]
        inside = ((uv >= 0.5) & (uv <= torch.tensor([cameras.width - 0.5, cameras.height - 0.5], device=uv.device))).all(-1)
        mask = (
            (alpha[j, ..., 0] > alpha_threshold)
            & (target_alpha > alpha_threshold)
            & (z > 0)
            & inside
            & ((z - target_depth).abs() <= depth_tolerance * target_depth)
        )
        difference = (target_rgb - images[j].float())[mask].double()
        squared += difference.square().sum().item()
        absolute += difference.abs().sum().item()
        covisible += int(mask.sum())
        total += mask.numel()
        if progress is not None:
            progress(done, len(pairs), {})
    values = 3 * covisible
    return WarpConsistency(
        step=int(step),
        rmse=(squared / values) ** 0.5 if values else float("nan"),
        mae=absolute / values if values else float("nan"),
        coverage=covisible / total,
        pixels=covisible,
        pairs=pairs,
    )
