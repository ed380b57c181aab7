"""Scenes and cameras for the rasterizer tests: small random scenes with hard cases mixed in, the
extreme-but-finite Gaussians of :func:`hard_cases` (one scene each), and how agreement with the
float64 references is measured (:func:`parity`), shared by tests/test_raster*.py and
bench/gsplat_parity.py."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from artnvg_core.cameras import CameraSet
from artnvg_core.raster import render
from artnvg_core.scene import GaussianScene

from raster_reference import brute_force_render


def look_at_camera(eye, target, width=40, height=32, focal=36.0):
    """OpenCV world-to-camera for a camera at ``eye`` looking at ``target`` (world up = -y)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([x, y, z])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    k = np.array([[focal, 0, width / 2 + 0.7], [0, focal * 1.1, height / 2 - 0.4], [0, 0, 1]])
    return w2c, k


def make_cameras(eyes, width=40, height=32, dtype=torch.float32, focal=36.0):
    """Cameras at ``eyes`` looking at the origin, ``focal`` pixels (x; y 1.1 x that)."""
    mats = [look_at_camera(e, [0, 0, 0], width, height, focal) for e in eyes]
    return CameraSet(
        torch.tensor(np.stack([m[0] for m in mats]), dtype=dtype),
        torch.tensor(np.stack([m[1] for m in mats]), dtype=dtype),
        width,
        height,
        [f"v{i}" for i in range(len(eyes))],
    )


def hard_scene(seed=0, n=60, degree=3, dtype=torch.float32):
    """Random Gaussians plus the hard cases: near-plane crossers, off-screen, tiny, huge,
    opacity near 0 and 1, needle-thin."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.8
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    log_scales = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.5 - 2.5
    logits = torch.randn(n, generator=g, dtype=torch.float64) * 2
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.4
    special = [
        ([0.0, 0.0, -3.95], [-1.0, -1.0, -1.0], 2.0),  # centre just past the near plane, crosses it
        ([0.0, 0.0, -4.2], [-1.0, -1.0, -1.0], 2.0),  # behind the camera
        ([9.0, 0.0, 0.0], [0.0, 0.0, 0.0], 3.0),  # far off-screen, big
        ([0.1, 0.05, 0.0], [math.log(1e-6)] * 3, 3.0),  # tiny
        ([0.0, 0.0, 3.0], [2.5, 2.5, 2.5], -1.0),  # huge, behind the others
        ([0.2, -0.1, 0.1], [-2.0, -2.0, -2.0], -5.5),  # opacity just above 1/255
        ([-0.2, 0.1, 0.1], [-2.0, -2.0, -2.0], -8.0),  # opacity below 1/255
        ([0.0, 0.3, -0.5], [-1.5, -1.5, -1.5], 9.0),  # opacity ~1 (clamped to 0.999)
        ([0.3, 0.3, 0.2], [0.5, -7.0, -7.0], 2.0),  # needle-thin, long
        ([-0.3, 0.2, 0.2], [0.2, 0.1, -9.0], 2.0),  # flat disc
    ]
    extra_means = torch.tensor([s[0] for s in special], dtype=torch.float64)
    extra_scales = torch.tensor([s[1] for s in special], dtype=torch.float64)
    extra_logits = torch.tensor([s[2] for s in special], dtype=torch.float64)
    k = len(special)
    return GaussianScene(
        torch.cat([means, extra_means]).to(dtype),
        torch.cat([quats, torch.randn(k, 4, generator=g, dtype=torch.float64)]).to(dtype),
        torch.cat([log_scales, extra_scales]).to(dtype),
        torch.cat([logits, extra_logits]).to(dtype),
        torch.cat([sh, torch.randn(k, (degree + 1) ** 2, 3, generator=g, dtype=torch.float64) * 0.4]).to(dtype),
    )


EYES = [[0.0, 0.0, -4.0], [3.0, -1.0, -2.5], [-2.0, 2.5, 2.0]]


@dataclass
class HardCase:
    """One hard case: a scene (float32, CPU) and the cameras that see it."""

    name: str
    scene: GaussianScene
    cameras: CameraSet


def _with(base: GaussianScene, rows: dict[str, list], **settings) -> GaussianScene:
    """``base`` with Gaussians appended: ``rows`` maps each field to one value per new Gaussian (SH as
    its DC colour coefficient, the rest zero)."""
    k = len(rows["means"])
    extra = {
        "means": torch.tensor(rows["means"], dtype=torch.float32),
        "quats": torch.tensor(rows.get("quats", [[1.0, 0, 0, 0]] * k), dtype=torch.float32),
        "log_scales": torch.tensor(rows["log_scales"], dtype=torch.float32),
        "opacity_logits": torch.tensor(rows.get("opacity_logits", [0.0] * k), dtype=torch.float32),
    }
    sh = torch.zeros(k, base.sh.shape[1], 3)
    sh[:, 0] = torch.tensor(rows.get("dc", [[0.8, -0.3, 0.2]] * k), dtype=torch.float32)
    extra["sh"] = sh
    joined = {name: torch.cat([value, extra[name]]) for name, value in base.tensors().items()}
    return dataclasses.replace(base, **joined, **settings)


def hard_cases(width: int = 64, height: int = 48) -> list[HardCase]:
    """Extreme but finite Gaussians, each case in front of (or around) a random cloud of 40 ordinary
    ones, seen by two cameras of ``width`` x ``height`` pixels at 4-5 units from the origin."""
    cloud = hard_scene(0, n=40).select(torch.arange(40))
    cams = make_cameras(EYES[:2], width, height)
    logit_044 = math.log(0.44 / 0.56)
    g = torch.Generator().manual_seed(11)
    quats = torch.randn(40, 4, generator=g)
    cases = [
        ("log-scale 45", _with(cloud, {"means": [[0, 0, 1.0]], "log_scales": [[45.0] * 3],
                                       "opacity_logits": [logit_044]})),
        ("log-scale 88", _with(cloud, {"means": [[0, 0, 1.0]], "log_scales": [[88.0] * 3],
                                       "opacity_logits": [logit_044]})),
        ("needle 45 x 1e-2", _with(cloud, {"means": [[0.2, 0.1, 0.0]], "log_scales": [[45.0, -4.6, -4.6]],
                                          "quats": [[0.9, 0.3, 0.2, 0.1]], "opacity_logits": [1.0]})),
        ("anisotropy 1e6", _with(cloud, {"means": [[0.3, -0.2, 0.1], [-0.3, 0.2, -0.1]],
                                        "log_scales": [[0.0, -13.8, -6.9], [-0.5, -14.3, -0.5]],
                                        "quats": [[0.8, 0.1, 0.5, 0.3], [0.2, 0.9, 0.1, 0.4]],
                                        "opacity_logits": [2.0, 2.0]})),
        ("zero quaternions", dataclasses.replace(cloud, quats=cloud.quats * torch.tensor([0.0] * 20 + [1.0] * 20)[:, None])),
        ("tiny quaternions", dataclasses.replace(cloud, quats=quats * 1e-30)),
        ("huge SH 3e38", dataclasses.replace(cloud, sh=torch.where(torch.arange(40)[:, None, None] < 6,
                                                                   torch.full_like(cloud.sh, 3e38), cloud.sh))),
        ("camera inside", _with(cloud, {"means": [[0.0, 0.0, -3.5]], "log_scales": [[1.0, 1.5, 1.2]],
                                        "opacity_logits": [-0.5]})),
        ("near-plane straddlers", _with(cloud, {"means": [[0.0, 0.0, -3.98], [0.02, -0.01, -3.985], [-0.1, 0.05, -3.97]],
                                                "log_scales": [[-1.0] * 3, [-2.0, -0.5, -1.0], [-0.7] * 3],
                                                "opacity_logits": [1.0, 2.0, 0.5]})),
        ("far floaters 1e6", _with(cloud, {"means": [[1e6, 2e5, 3e6], [-2e6, 1e6, 5e6], [0.0, 0.0, 1e6]],
                                           "log_scales": [[12.0] * 3, [13.5] * 3, [11.0] * 3],
                                           "opacity_logits": [3.0, 3.0, 3.0]})),
        ("antialiased", dataclasses.replace(hard_scene(6), antialiased=True)),
        ("blur 0.1 antialiased", dataclasses.replace(hard_scene(6), blur_px2=0.1, antialiased=True)),
        ("blur 0.1 classic", dataclasses.replace(hard_scene(6), blur_px2=0.1)),
    ]
    return [HardCase(name, scene, cams) for name, scene in cases]


def many_gaussians(count: int, size: int = 512, seed: int = 0) -> HardCase:
    """``count`` random Gaussians in a ball of radius 1 seen from 3 units away: the scale case."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(count, 3, generator=g)
    means = means / means.norm(dim=1, keepdim=True) * torch.rand(count, 1, generator=g) ** (1 / 3)
    scene = GaussianScene(means, torch.randn(count, 4, generator=g),
                          torch.randn(count, 3, generator=g) * 0.3 - 5.0 - math.log(count / 1e5) / 3,
                          torch.randn(count, generator=g) - 1.0, torch.randn(count, 16, 3, generator=g) * 0.3)
    return HardCase(f"{count:,} Gaussians", scene, make_cameras([[0.0, -0.5, -3.0]], size, size, focal=size))


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR in dB of ``image`` against ``reference``, both clamped to [0, 1] (infinite when equal)."""
    mse = float(((np.clip(image, 0, 1) - np.clip(reference, 0, 1)) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


def loss_weights(cameras: CameraSet, seed: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed random weights [C, H, W, 3] and [C, H, W, 1] of the test loss sum(w * rgb) + sum(v * alpha)."""
    g = torch.Generator().manual_seed(seed)
    shape = (len(cameras), cameras.height, cameras.width)
    return torch.randn(*shape, 3, generator=g, dtype=torch.float64), torch.randn(*shape, 1, generator=g, dtype=torch.float64)


def gradients(scene: GaussianScene, cameras: CameraSet, backend: str, device, dtype=torch.float32):
    """(rgb [C, H, W, 3] float64 numpy, gradient of the test loss by field) of ``scene`` rendered with
    ``backend`` on ``device`` in ``dtype``; RGB clamped to [0, 1] in the loss, as the finetune does."""
    params = {k: v.to(device, dtype).detach().clone().requires_grad_(True) for k, v in scene.tensors().items()}
    cams = cameras.to(device)
    cams = dataclasses.replace(cams, world_to_cam=cams.world_to_cam.to(dtype), intrinsics=cams.intrinsics.to(dtype))
    out = render(dataclasses.replace(scene, **params), cams, backend=backend)
    w_rgb, w_alpha = (w.to(device, dtype) for w in loss_weights(cameras))
    ((out.rgb.clamp(0, 1) * w_rgb).sum() + (out.alpha * w_alpha).sum()).backward()
    return out.rgb.detach().double().cpu().numpy(), {k: p.grad.double().cpu() for k, p in params.items()}


def relative_error(grad: torch.Tensor, reference: torch.Tensor) -> float:
    """||grad - reference|| / ||reference|| (absolute when the reference is 0)."""
    scale = float(reference.norm())
    return float((grad - reference).norm()) / (scale if scale > 0 else 1.0)


def parity(case: HardCase, backend: str, device) -> dict:
    """How ``backend`` (float32, on ``device``) agrees with the float64 references on ``case``:
    ``psnr`` of its renders against the brute-force evaluator (tests/raster_reference.py; the float32
    reference rasterizer when there are over 10,000 Gaussians), ``grad_error`` the largest relative
    gradient error over the five fields against the reference rasterizer in float64 (float32 past
    10,000 Gaussians) and ``finite`` whether every gradient is finite."""
    small = len(case.scene) <= 10_000
    rgb, grads = gradients(case.scene, case.cameras, backend, device)
    if small:
        s = case.scene.to(dtype=torch.float64)
        references = [brute_force_render(s.means, s.quats, s.log_scales, s.opacity_logits, s.sh,
                                         case.cameras.world_to_cam[c].double(), case.cameras.intrinsics[c].double(),
                                         case.cameras.width, case.cameras.height,
                                         blur=s.blur_px2, antialiased=s.antialiased)[0]
                      for c in range(len(case.cameras))]
        ref_rgb = np.stack(references)
        _, ref_grads = gradients(case.scene, case.cameras, "torch", device, torch.float64)
    else:
        ref_rgb, ref_grads = gradients(case.scene, case.cameras, "torch", device)
    return {
        "psnr": psnr(rgb, ref_rgb),
        "grad_error": max(relative_error(grads[k], ref_grads[k]) for k in grads),
        "finite": all(bool(torch.isfinite(g).all()) for g in grads.values()),
    }
