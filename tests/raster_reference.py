"""Brute-force float64 Gaussian splatting evaluator, independent of artnvg_core.raster.

Every pixel is tested against every Gaussian in global depth order; no tiles,
no bounding boxes, no culling except the near plane. Written from the
gsplat "classic" definition, with plain NumPy.
"""

import numpy as np

C0 = 0.28209479177387814


def _rotation(q):
    """Rotation matrix of quaternion w x y z of any norm; the zero quaternion is the identity."""
    norm = np.linalg.norm(q)
    w, x, y, z = q / norm if norm > 0 else (1.0, 0.0, 0.0, 0.0)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _sh_color(sh, d):
    """Colour for SH [K, 3] along unit direction d (degrees 0..3 by K)."""
    x, y, z = d
    basis = [C0]
    if len(sh) > 1:
        basis += [-0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x]
    if len(sh) > 4:
        basis += [
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.31539156525252005 * (2 * z * z - x * x - y * y),
            -1.0925484305920792 * x * z,
            0.5462742152960396 * (x * x - y * y),
        ]
    if len(sh) > 9:
        basis += [
            -0.5900435899266435 * y * (3 * x * x - y * y),
            2.890611442640554 * x * y * z,
            -0.4570457994644658 * y * (4 * z * z - x * x - y * y),
            0.3731763325901154 * z * (2 * z * z - 3 * x * x - 3 * y * y),
            -0.4570457994644658 * x * (4 * z * z - x * x - y * y),
            1.445305721320277 * z * (x * x - y * y),
            -0.5900435899266435 * x * (x * x - 3 * y * y),
        ]
    return np.maximum(np.asarray(basis) @ sh + 0.5, 0.0)


def brute_force_render(means, quats, log_scales, opacity_logits, sh, w2c, K, width, height, near=0.01, background=None,
                       blur=0.3, antialiased=False, filter_3d=None):
    """Render one view in float64. Returns rgb [H, W, 3], alpha [H, W], depth [H, W] (normalised).

    blur: the 2D low-pass variance (px^2); antialiased: opacity x sqrt(det(cov2) / det(cov2 + blur I))
    (gsplat "antialiased"); filter_3d: [N] Mip-Splatting 3D filter, covariance R (S^2 + f^2 I) R^T and
    opacity x sqrt(det(S^2) / det(S^2 + f^2 I)).
    """
    means, quats, log_scales, sh = (np.asarray(a, np.float64) for a in (means, quats, log_scales, sh))
    opac = 1 / (1 + np.exp(-np.asarray(opacity_logits, np.float64)))
    w2c, K = np.asarray(w2c, np.float64), np.asarray(K, np.float64)
    rot_w, t_w = w2c[:3, :3], w2c[:3, 3]
    cam_center = -rot_w.T @ t_w
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    splats = []
    for i in range(len(means)):
        p = rot_w @ means[i] + t_w
        if p[2] <= near:
            continue
        variances = np.exp(2 * log_scales[i])
        opacity = opac[i]
        if filter_3d is not None:
            opacity *= np.sqrt(np.prod(variances) / np.prod(variances + filter_3d[i] ** 2))
            variances = variances + filter_3d[i] ** 2
        tx = p[2] * min((width - cx) / fx + 0.3 * 0.5 * width / fx, max(-(cx / fx + 0.3 * 0.5 * width / fx), p[0] / p[2]))
        ty = p[2] * min((height - cy) / fy + 0.3 * 0.5 * height / fy, max(-(cy / fy + 0.3 * 0.5 * height / fy), p[1] / p[2]))
        J = np.array([[fx / p[2], 0, -fx * tx / p[2] ** 2], [0, fy / p[2], -fy * ty / p[2] ** 2]])
        # cov2 = A A^T + blur I with A = J W R S; its determinant from A's 2x2 minors (Cauchy-Binet) and
        # its inverse as adjugate / determinant: no cancellation for needles of any aspect ratio
        A = J @ rot_w @ _rotation(quats[i]) @ np.diag(np.sqrt(variances))
        cov2 = A @ A.T + blur * np.eye(2)
        det_a = float((np.cross(A[0], A[1]) ** 2).sum())
        det = det_a + blur * np.trace(A @ A.T) + blur * blur
        if antialiased:
            opacity *= np.sqrt(det_a / det)
        conic = np.array([[cov2[1, 1], -cov2[0, 1]], [-cov2[1, 0], cov2[0, 0]]]) / det
        color = _sh_color(sh[i], (means[i] - cam_center) / np.linalg.norm(means[i] - cam_center))
        mean2 = np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])
        splats.append((p[2], mean2, conic, opacity, color))
    splats.sort(key=lambda s: s[0])
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    rgb = np.zeros((height, width, 3))
    depth = np.zeros((height, width))
    trans = np.ones((height, width))
    done = np.zeros((height, width), bool)
    for z, mean2, conic, o, color in splats:
        dx, dy = xs - mean2[0], ys - mean2[1]
        sigma = 0.5 * (conic[0, 0] * dx * dx + conic[1, 1] * dy * dy) + conic[0, 1] * dx * dy
        alpha = np.minimum(0.999, o * np.exp(-sigma))
        use = (sigma >= 0) & (alpha >= 1 / 255) & ~done
        next_t = trans * (1 - alpha)
        done |= use & (next_t <= 1e-4)
        use &= ~done
        w = np.where(use, alpha * trans, 0.0)
        rgb += w[..., None] * color
        depth += w * z
        trans = np.where(use, next_t, trans)
    if background is not None:
        rgb += trans[..., None] * np.asarray(background, np.float64)
    alpha = 1 - trans
    depth = np.where(alpha > 0, depth / np.maximum(alpha, 1e-300), 0.0)
    return rgb, alpha, depth
