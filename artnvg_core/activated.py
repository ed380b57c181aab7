"""Gaussians in activated (render-ready) form, as splat viewers and ComfyUI's core splat type hold them.

A :class:`~artnvg_core.scene.GaussianScene` stores the raw INRIA parameters (log-scales, opacity
logits, unnormalised quaternions). The activated form of N Gaussians is

- ``positions`` [N, 3]  world positions (the scene's ``means``)
- ``scales``    [N, 3]  per-axis standard deviations, ``exp(log_scales)``, > 0
- ``rotations`` [N, 4]  unit quaternions, w x y z
- ``opacities`` [N]     ``sigmoid(opacity_logits)``, in [0, 1]
- ``sh``        [N, K, 3] spherical-harmonic coefficients, unchanged (DC first, K = (d + 1)^2, d <= 3)

It has no place for a scene's rendering settings (``blur_px2``, ``antialiased``): viewers render it
as classic 3DGS, and :func:`deactivate` gives a scene with the defaults.

Both directions compute in float64 and round once to float32, so each value is the correctly
rounded image of its source; float32 ``exp``/``log`` and ``sigmoid``/``logit`` are not bijections,
so round trips are exact only up to that rounding. Activated -> scene -> activated gives positions
and SH back bit-identical, scales and rotations within 1 float32 step and an opacity within the
rounding of its logit (relative error at most about |logit| * 2^-24). Scene ->
activated -> scene moves a log-scale by the rounding of its scale (about 6e-8) and a logit by the
rounding of its opacity divided by o(1 - o) (1e-3 at a logit of 10). Opacities are first clamped to
[2^-126, 1 - 2^-24], the normal float32 range strictly inside (0, 1), so 0 and 1 get finite logits
(-87.3 and 16.6).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

from .cameras.geometry import normalize_quats
from .scene import GaussianScene, describe_invalid, logit, sh_degree_for

OPACITY_RANGE = (2.0**-126, 1 - 2.0**-24)  # float32 opacities with finite logits


@dataclass
class ActivatedGaussians:
    """N Gaussians in activated form (shapes and conventions in the module docstring)."""

    positions: torch.Tensor
    scales: torch.Tensor
    rotations: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor

    def map(self, fn) -> "ActivatedGaussians":
        """A new instance with ``fn`` applied to every tensor."""
        return ActivatedGaussians(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})


def activate(scene: GaussianScene) -> ActivatedGaussians:
    """The activated form of ``scene``: float32 on the CPU (the float64 maths runs there), quaternions normalised."""
    raw = scene.map(lambda t: t.detach().to("cpu", torch.float64))
    return ActivatedGaussians(
        positions=raw.means,
        scales=raw.log_scales.exp(),
        rotations=normalize_quats(raw.quats),
        opacities=torch.sigmoid(raw.opacity_logits),
        sh=raw.sh,
    ).map(lambda t: t.float())


def _check(source: str, name: str, bad: torch.Tensor, problem: str) -> None:
    """Raise naming ``source``, the field and the first offending Gaussian when ``bad`` [N] has any True."""
    if bad.any():
        raise ValueError(f"{source}: {describe_invalid(name, bad, problem)}")


def deactivate(gaussians: ActivatedGaussians, source: str) -> GaussianScene:
    """The float32 scene (on the CPU) of activated ``gaussians``; ``source`` names them in errors.

    Raises ValueError naming ``source`` and the field for wrong shapes, an SH degree above 3,
    non-finite values, scales that are not positive, opacities outside [0, 1] or zero quaternions.
    """
    n = gaussians.positions.shape[0] if gaussians.positions.ndim == 2 else -1
    shapes = {"positions": (n, 3), "scales": (n, 3), "rotations": (n, 4), "opacities": (n,)}
    for name, shape in shapes.items():
        got = tuple(getattr(gaussians, name).shape)
        if got != shape or n < 0:
            raise ValueError(f"{source}: {name}: expected shape {shape} (N Gaussians), got {got}")
    sh = gaussians.sh
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
        raise ValueError(f"{source}: sh: expected shape ({n}, K, 3), got {tuple(sh.shape)}")
    try:
        sh_degree_for(sh.shape[1])
    except ValueError as error:
        raise ValueError(f"{source}: {error} (SH degree above 3 is not supported)") from error
    for field in fields(gaussians):
        value = getattr(gaussians, field.name)
        _check(source, field.name, ~torch.isfinite(value).reshape(n, -1).all(dim=1), "have non-finite values")
    _check(source, "scales", (gaussians.scales <= 0).any(dim=1), "have a scale that is not positive")
    _check(source, "opacities", (gaussians.opacities < 0) | (gaussians.opacities > 1), "lie outside [0, 1]")
    _check(source, "rotations", torch.linalg.vector_norm(gaussians.rotations, dim=1) == 0, "have a zero quaternion")
    cpu = gaussians.map(lambda t: t.detach().to("cpu", torch.float32))
    opacities = cpu.opacities.clamp(*OPACITY_RANGE).double()
    return GaussianScene(
        means=cpu.positions.clone(),
        quats=cpu.rotations.clone(),
        log_scales=cpu.scales.double().log().float(),
        opacity_logits=logit(opacities).float(),
        sh=cpu.sh.clone(),
    )
