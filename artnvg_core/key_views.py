"""Key views: K of a scene's views that cover it, for a diffusion stage that stylizes only those.

Each view is described by its pose: its camera centre ``c`` (world units) divided by the
cameras' spread ``s`` (root-mean-square distance of the centres to their mean; 1 when they all
coincide) and its viewing direction ``f`` (unit, the camera's +z axis in world coordinates).
The distance between two views is

    d(i, j) = sqrt(|c_i - c_j|^2 / s^2 + |f_i - f_j|^2)

(dimensionless: two cameras at one spot looking opposite ways are 2 apart, as are two parallel
cameras 2 s apart).

:func:`select_key_views` picks them by farthest-point traversal (Gonzalez): first the most
central view (the one nearest to the mean descriptor ``(c / s, f)``), then again and again the
view farthest from every view chosen so far (ties: the lower index). For every K the K views it
returns, with ``r`` the distance at which the K-th was added,

* lie pairwise at least ``r`` apart, and no K views lie pairwise more than ``2 r`` apart: at least
  half the best possible smallest pairwise distance (the maximin design);
* leave every view within the distance at which a (K+1)-th would be added, at most twice the
  smallest possible (the K-centre problem).

Both are the classical guarantees of the traversal. It is deterministic, the choice for K views
is contained in the choice for K + 1 views, and it costs O(K V) after the V x V distances.
"""

from __future__ import annotations

import numpy as np
import torch

from .cameras import CameraSet


def view_descriptors(cameras: CameraSet) -> np.ndarray:
    """Pose descriptors ``(c / s, f)`` [V, 6] (float64) of the views; distances between rows are the
    module's ``d(i, j)``."""
    world_to_cam = cameras.world_to_cam.detach().cpu().double()
    forward = world_to_cam[:, 2, :3]  # the camera's +z axis in world coordinates (rows of R are its axes)
    forward = forward / forward.norm(dim=1, keepdim=True)
    centers = cameras.centers.detach().cpu().double()
    spread = (centers - centers.mean(0)).square().sum(1).mean().sqrt()
    scale = spread if spread > 1e-12 * max(1.0, float(centers.abs().max())) else torch.tensor(1.0, dtype=torch.float64)
    return torch.cat([centers / scale, forward], 1).numpy()


def view_distances(cameras: CameraSet) -> np.ndarray:
    """The module's pose distance ``d(i, j)`` between every two views, [V, V] (float64)."""
    descriptors = view_descriptors(cameras)
    return np.linalg.norm(descriptors[:, None] - descriptors[None], axis=-1)


def select_key_views(cameras: CameraSet, count: int) -> list[int]:
    """Indices (ascending) of ``count`` views that cover the scene (farthest-point traversal, module
    docstring). ``count`` 0, or at least the number of views, gives every view."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise ValueError(f"select_key_views: count must be an integer >= 0 (0: every view), got {count!r}")
    total = len(cameras)
    if count == 0 or count >= total:
        return list(range(total))
    descriptors = view_descriptors(cameras)
    distances = np.linalg.norm(descriptors[:, None] - descriptors[None], axis=-1)
    first = int(np.argmin(np.linalg.norm(descriptors - descriptors.mean(0), axis=1)))
    chosen, nearest = [first], distances[first].copy()
    while len(chosen) < count:
        nearest[chosen] = -1.0  # never chosen twice (a duplicate view is 0 away)
        pick = int(np.argmax(nearest))  # the first maximum: ties go to the lower index
        chosen.append(pick)
        nearest = np.minimum(nearest, distances[pick])
    return sorted(chosen)


def covering_radius(cameras: CameraSet, chosen: list[int]) -> float:
    """The largest distance ``d`` from any view to its nearest chosen view (0 when every view is chosen)."""
    if not chosen:
        raise ValueError("covering_radius: chosen must hold at least one view")
    return float(view_distances(cameras)[:, chosen].min(axis=1).max())
