"""Optional gsplat backend (CUDA only), same semantics as the reference backend."""

from __future__ import annotations

import importlib.util

import torch


def gsplat_available() -> bool:
    """True when the ``gsplat`` package can be imported."""
    return importlib.util.find_spec("gsplat") is not None


def render_gsplat(scene, world_to_cam, intrinsics, width, height, sh_degree, background, return_depth, near_plane):
    """Render with ``gsplat.rasterization`` in the scene's mode ("classic", or "antialiased"), blur ``eps2d``.

    Returns rgb [C, H, W, 3], alpha [C, H, W, 1], depth [C, H, W, 1] or None
    (expected depth normalised by alpha, 0 where alpha is 0).
    """
    from gsplat import rasterization

    from ..cameras.geometry import normalize_quats

    sh = scene.sh[:, : (sh_degree + 1) ** 2]
    out, alpha, _ = rasterization(
        means=scene.means,
        quats=normalize_quats(scene.quats),  # gsplat's own normalisation over/underflows
        scales=torch.exp(scene.log_scales),
        opacities=torch.sigmoid(scene.opacity_logits),
        colors=sh,
        viewmats=world_to_cam,
        Ks=intrinsics,
        width=width,
        height=height,
        near_plane=near_plane,
        sh_degree=sh_degree,
        backgrounds=background,
        render_mode="RGB+ED" if return_depth else "RGB",
        eps2d=scene.blur_px2,
        rasterize_mode="antialiased" if scene.antialiased else "classic",
    )
    depth = torch.where(alpha > 0, out[..., 3:4], torch.zeros_like(alpha)) if return_depth else None
    return out[..., :3], alpha, depth
