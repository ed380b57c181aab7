"""Where a Gaussian scene is and which way is up, from the Gaussians alone.

:func:`scene_frame` finds where the scene is and which way is up:

- weights: each Gaussian counts with its opacity times its footprint (the product of
  its two largest scales) relative to the median footprint, capped at 1, so
  transparent specks count little and huge background or sky-shell splats no more
  than an ordinary one; Gaussians with non-finite position, scale or opacity are ignored;
- ``center``: the weighted median of each coordinate (far floaters cannot move it);
- ``radius``: the weighted ``quantile`` (default 0.5) of the distances from the
  centre, the "subject": in an unbounded capture the dense middle, not the horizon;
- ``up``: the principal axes of the Gaussians within the weighted 90 % distance
  quantile. When the smallest extent is under 0.6 of the middle one the scene is
  ground-dominated: up is the ground's normal, pointing to the side where the mass reaches
  further (things rise from the ground, nothing hangs below it): the weighted 90 % height
  quantile lies further above the median than the 10 % one below it. Quantiles, not the
  third moment, which a few floaters under the ground outweigh (on the bundled demo bear,
  the bear capture's 40,000 best-seen Gaussians, it pointed down and the views came out
  upside down, from under the ground). Otherwise (objects, portraits) up is a
  guess (``up_source`` "long axis", which the callers that place views note): the longest
  axis of the dense core (the weighted 30 % nearest the centre), pointing to its narrower
  end (a head above shoulders). Pass ``up`` explicitly to override.

World units and axes are the scene's. All maths runs in float64 on the CPU. Views
placed around the frame are built in :mod:`artnvg_core.orbit`, which renders probe views.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..counted import counted
from ..scene import GaussianScene


UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
_BOUNDS_QUANTILE = 0.9  # the Gaussians whose principal axes give the up direction
_GROUND_FLATNESS = 0.6  # smallest / middle principal extent below this: a ground-dominated scene
_RISE_QUANTILE = 0.9  # up is the ground normal's side whose height quantile this far out lies further from the median
_CORE_QUANTILE = 0.3  # the dense core whose long axis is the up guess of a scene without a ground


@dataclass(frozen=True)
class SceneFrame:
    """Where a scene is: ``center`` [3] and ``up`` [3] (unit) float64 world vectors,
    ``radius`` (world units) of the subject sphere, and ``up_source`` saying how
    ``up`` was found ("given", "ground normal" or "long axis")."""

    center: torch.Tensor
    radius: float
    up: torch.Tensor
    up_source: str


def parse_up(up, what: str | None = None) -> torch.Tensor | None:
    """A unit float64 [3] vector from ``up``: None or "auto" (-> None: detect it), an axis name in
    :data:`UP_AXES` (the sign may be left out: "z" is "+z"), 3 finite numbers not all zero, or those
    numbers as comma-separated text ("0, -1, 0"), the command line's ``--up`` and the node's up input.

    Raises ValueError saying what was expected, after ``what:`` (a field's name) when given.
    """
    where = f"{what}: " if what else ""
    expected = f"expected 'auto', one of {', '.join(UP_AXES)} or 3 comma-separated numbers such as 0, -1, 0"
    if up is None or (isinstance(up, str) and up.strip().lower() == "auto"):
        return None
    numbers = up
    if isinstance(up, str) and "," in up:
        try:
            numbers = [float(part) for part in up.split(",")]
        except ValueError:
            raise ValueError(f"{where}{expected}, got {up!r}") from None
    elif isinstance(up, str):
        name = up.strip().lower()
        name = name if name[:1] in "+-" else "+" + name
        if name not in UP_AXES:
            raise ValueError(f"{where}{expected}, got {up!r}")
        vector = torch.zeros(3, dtype=torch.float64)
        vector["xyz".index(name[1])] = 1.0 if name[0] == "+" else -1.0
        return vector
    vector = torch.as_tensor(numbers, dtype=torch.float64).detach().cpu()
    if tuple(vector.shape) != (3,) or not torch.isfinite(vector).all() or vector.norm() == 0:
        raise ValueError(f"{where}expected 3 finite numbers, not all zero, got {up!r}")
    return vector / vector.norm()


def _weighted_quantile(values: torch.Tensor, weights: torch.Tensor, q: float) -> float:
    """The smallest value whose cumulative weight reaches fraction ``q`` of the total ([N], [N] float64)."""
    order = torch.argsort(values)
    cumulative = torch.cumsum(weights[order], 0)
    index = torch.searchsorted(cumulative, q * cumulative[-1]).clamp(max=len(values) - 1)
    return float(values[order][index])


def _gaussian_weights(scene: GaussianScene) -> tuple[torch.Tensor, torch.Tensor]:
    """(means [M, 3], weights [M]) in float64 of the Gaussians with finite position, scale and opacity."""
    means = scene.means.detach().cpu().to(torch.float64)
    log_scales = scene.log_scales.detach().cpu().to(torch.float64)
    logits = scene.opacity_logits.detach().cpu().to(torch.float64)
    finite = torch.isfinite(means).all(1) & torch.isfinite(log_scales).all(1) & torch.isfinite(logits)
    if not finite.any():
        raise ValueError(
            f"scene: none of its {counted(len(scene), 'Gaussian')} has a finite position, scale and opacity; "
            "cannot place cameras around it"
        )
    means, log_scales, logits = means[finite], log_scales[finite], logits[finite]
    log_footprint = log_scales.sort(1).values[:, 1:].sum(1)  # log of the two largest scales' product
    relative = torch.exp((log_footprint - log_footprint.median()).clamp(max=0))
    weights = torch.sigmoid(logits) * relative
    if not weights.sum() > 0:  # every Gaussian fully transparent: count them equally
        weights = torch.ones_like(weights)
    return means, weights


def _principal_axes(points: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(extents [3] ascending standard deviations, axes [3, 3] as columns, centred points [M, 3]) of weighted points."""
    total = weights.sum()
    centred = points - (weights[:, None] * points).sum(0) / total
    variances, axes = torch.linalg.eigh((centred.T * weights) @ centred / total)
    return variances.clamp_min(0).sqrt(), axes, centred


def _detect_up(means, weights, distances) -> tuple[torch.Tensor, str]:
    """Up direction [3] and how it was found (module docstring)."""
    bounds = distances <= _weighted_quantile(distances, weights, _BOUNDS_QUANTILE)
    extents, axes, centred = _principal_axes(means[bounds], weights[bounds])
    if extents[0] < _GROUND_FLATNESS * extents[1]:
        axis = axes[:, 0]
        heights, kept = centred @ axis, weights[bounds]
        low, middle, high = (_weighted_quantile(heights, kept, q) for q in (1 - _RISE_QUANTILE, 0.5, _RISE_QUANTILE))
        return (axis if high - middle >= middle - low else -axis), "ground normal"
    core = distances <= _weighted_quantile(distances, weights, _CORE_QUANTILE)
    _, axes, centred = _principal_axes(means[core], weights[core])
    axis = axes[:, 2]
    heights = centred @ axis
    spread = (centred - heights[:, None] * axis).pow(2).sum(1)  # squared distance from the axis
    narrowing = (weights[core] * heights * (spread - spread.mean())).sum()  # < 0 when narrower along +axis
    return (axis if narrowing <= 0 else -axis), "long axis"


def scene_frame(scene: GaussianScene, *, up=None, quantile: float = 0.5) -> SceneFrame:
    """Robust centre, subject radius and up direction of ``scene`` (module docstring).

    up: None / "auto" to detect it, else as :func:`parse_up` takes it.
    quantile: fraction (0, 1] of the Gaussians' weight inside the subject sphere.
    Raises ValueError for a scene with no finite Gaussian or with all of them at one point.
    """
    if not 0 < quantile <= 1:
        raise ValueError(f"scene_frame: quantile must be in (0, 1], got {quantile!r}")
    given_up = parse_up(up, "up")
    if len(scene) == 0:
        raise ValueError("scene: it contains no Gaussians; cannot place cameras around it")
    means, weights = _gaussian_weights(scene)
    center = torch.tensor([_weighted_quantile(means[:, i], weights, 0.5) for i in range(3)], dtype=torch.float64)
    distances = (means - center).norm(dim=1)
    scale = float(distances.max())
    negligible = 1e-9 * (1 + float(center.abs().max()))  # a distance from the centre that is float32's rounding
    if not scale > negligible:
        which = f"all {len(means):,} finite Gaussians sit" if len(means) > 1 else "its one finite Gaussian sits"
        raise ValueError(
            f"scene: {which} at one point {center.tolist()}; "
            "it has no extent to place cameras around"
        )
    radius = _weighted_quantile(distances, weights, quantile)
    if not radius > negligible:  # most of the weight at the centre itself (not: far from the farthest floater)
        radius = scale
    if given_up is not None:
        return SceneFrame(center, radius, given_up, "given")
    detected, source = _detect_up(means, weights, distances)
    return SceneFrame(center, radius, detected, source)


def horizontal_axes(up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors [3] orthogonal to unit ``up`` [3] and to each other: azimuth 0 and 90 degrees."""
    side = torch.linalg.cross(up, torch.eye(3, dtype=up.dtype)[up.abs().argmin()])
    side = side / side.norm()
    return side, torch.linalg.cross(up, side)
