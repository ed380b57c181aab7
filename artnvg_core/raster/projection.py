"""EWA projection of 3D Gaussians into one pinhole camera (gsplat "classic").

Conventions: OpenCV camera (x right, y down, z forward), pixel centres at
+0.5, a low-pass (0.3 px^2 unless the scene says otherwise) added to every
2D covariance, Gaussians whose centre lies before the near plane culled. The perspective Jacobian clamps
x/z and y/z to 1.3x the field of view, as 3DGS and gsplat do.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..cameras.geometry import quat_to_rotmat

BLUR_PX2 = 0.3
ALPHA_MIN = 1.0 / 255.0
MAX_EXTENT = 3.33  # sigma multiple bounding the footprint, as in gsplat
MAX_RADIUS_PX = 2.0**31  # footprints are cut to the image, then to this (centres this far off the image)


@dataclass
class Projection:
    """Projected Gaussians of one camera, for the M kept ones only.

    index: [M] long, indices into the scene's N Gaussians.
    means2d: [M, 2] pixel coordinates (x right, y down).
    conics: [M, 3] inverse 2D covariance (a, b, c) of [[a, b], [b, c]], 1/px^2.
    depths: [M] camera-space z.
    opacities: [M] sigmoid(opacity logit).
    radii: [M, 2] integer half extents (x, y) of the footprint in pixels, cut to the image.
    """

    index: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    radii: torch.Tensor


def project(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    world_to_cam: torch.Tensor,
    intrinsics: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    blur_px2: float = BLUR_PX2,
    antialiased: bool = False,
) -> Projection:
    """Project N Gaussians into one camera ([4, 4] world-to-camera, [3, 3] K).

    ``blur_px2`` is the low-pass variance added to every 2D covariance S;
    ``antialiased`` scales each opacity by sqrt(det(S) / det(S + blur I)) (gsplat's
    "antialiased" mode), computed only when set.

    Keeps the Gaussians in front of ``near_plane``, with opacity >= 1/255,
    whose footprint overlaps the image; the footprint is the box where the
    Gaussian's alpha can reach 1/255. Differentiable in all parameters.
    """
    rot_w2c = world_to_cam[:3, :3]
    mean_c = means @ rot_w2c.T + world_to_cam[:3, 3]
    opacities = torch.sigmoid(opacity_logits)
    keep = (mean_c[:, 2] > near_plane) & (opacities >= ALPHA_MIN)
    index = keep.nonzero()[:, 0]
    # index_select, not x[index]: its backward adds with atomics where indexing's sorts the indices
    mean_c, opacities = mean_c.index_select(0, index), opacities.index_select(0, index)

    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    x, y, z = mean_c.unbind(-1)
    lim_x_pos = (width - cx) / fx + 0.15 * width / fx
    lim_x_neg = cx / fx + 0.15 * width / fx
    lim_y_pos = (height - cy) / fy + 0.15 * height / fy
    lim_y_neg = cy / fy + 0.15 * height / fy
    tx = z * torch.minimum(torch.maximum(x / z, -lim_x_neg), lim_x_pos)
    ty = z * torch.minimum(torch.maximum(y / z, -lim_y_neg), lim_y_pos)

    # Sigma_2d = A A^T with A = J W R S, so det(Sigma_2d) is a sum of squared
    # 2x2 minors (Cauchy-Binet): exact and non-negative even for needle-thin
    # Gaussians, where a*c - b^2 would cancel catastrophically in float32.
    # Any finite log-scale is valid: the largest scale k = exp(top) (top >= 0) is
    # factored out, A = k A', so no square or minor overflows, and
    # conic = inverse(A'A'^T + u blur I) * u with u = 1/k^2, which underflows
    # to 0 (alpha = opacity everywhere) for a Gaussian far larger than any view.
    # In float64 where the device has it (all but Apple's MPS): factored by k, a needle's thin axes
    # (scale ratios past e^40) fall below float32's normal range and lose its precision (the "needle
    # 45 x 1e-2" hard case: 56 dB in float32 against 123 dB). A = J (W R S') is formed from the
    # rows of J (whose zeros are known) rather than as a batched matrix product: batched float64
    # 3x3 products are slow GEMMs on GPUs.
    work = torch.float32 if means.device.type == "mps" else torch.float64
    log_s = log_scales.index_select(0, index).to(work)
    top = log_s.detach().amax(-1).clamp_min(0)
    scaled_rot = quat_to_rotmat(quats.index_select(0, index)).to(work) * torch.exp(log_s - top[:, None])[:, None, :]
    cam_rot = (rot_w2c.to(work) @ scaled_rot.transpose(1, 2).reshape(-1, 3).T).T.reshape(-1, 3, 3)  # rows: W R S' columns
    j_x, j_xz = (fx / z).to(work)[:, None], (-fx * tx / (z * z)).to(work)[:, None]  # J's non-zero entries
    j_y, j_yz = (fy / z).to(work)[:, None], (-fy * ty / (z * z)).to(work)[:, None]
    r0 = j_x * cam_rot[:, :, 0] + j_xz * cam_rot[:, :, 2]
    r1 = j_y * cam_rot[:, :, 1] + j_yz * cam_rot[:, :, 2]
    inv_k2 = torch.exp(-2 * top)
    blur = blur_px2 * inv_k2
    cov_a = (r0 * r0).sum(-1) + blur
    cov_b = (r0 * r1).sum(-1)
    cov_c = (r1 * r1).sum(-1) + blur
    minors = torch.linalg.cross(r0, r1, dim=-1)
    det_unblurred = (minors * minors).sum(-1)
    det = det_unblurred + blur * (cov_a + cov_c - blur)
    if antialiased:  # both determinants carry the same 1/k^4, so their ratio is exact
        opacities = opacities * torch.sqrt(det_unblurred / det.clamp_min(torch.finfo(work).tiny)).to(opacities.dtype)
    conics = torch.stack([cov_c, -cov_b, cov_a], -1) * (inv_k2 / det.clamp_min(torch.finfo(work).tiny))[:, None]
    conics = conics.to(means.dtype)
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], -1)

    with torch.no_grad():
        extent = torch.sqrt(2.0 * torch.log(opacities / ALPHA_MIN).clamp_min(0)).clamp_max(MAX_EXTENT)
        sigmas = torch.exp(top[:, None] + 0.5 * torch.log(torch.stack([cov_a, cov_c], -1)))  # may be inf
        radii = torch.ceil(extent[:, None] * sigmas).to(means2d.dtype)
        on_screen = (
            (means2d[:, 0] + radii[:, 0] > 0)
            & (means2d[:, 0] - radii[:, 0] < width)
            & (means2d[:, 1] + radii[:, 1] > 0)
            & (means2d[:, 1] - radii[:, 1] < height)
        )
        sel = on_screen.nonzero()[:, 0]
        # A footprint reaching past the whole image is cut to the image: same tiles, integer-sized.
        size = torch.tensor([width, height], dtype=means2d.dtype, device=means2d.device)
        reach = torch.maximum(means2d.abs(), (means2d - size).abs()).ceil()
        radii = torch.minimum(radii, reach).clamp_max(MAX_RADIUS_PX)
    return Projection(
        index=index[sel],
        means2d=means2d.index_select(0, sel),
        conics=conics.index_select(0, sel),
        depths=z.index_select(0, sel),
        opacities=opacities.index_select(0, sel),
        radii=radii[sel].to(torch.long),
    )
