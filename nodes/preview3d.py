"""The camera ComfyUI's Preview 3D node starts from when it shows a saved scene.

Preview 3D (``Preview3D``: ``model_file``, a path inside the output folder, and ``camera_info``, a
LOAD3D_CAMERA) frames the whole bounding box of what it loads, so the stray Gaussians far out that most
captures hold make the subject a speck. :func:`preview_camera` aims at the scene's bulk instead: the
subject sphere of :func:`~artnvg_core.cameras.framing.scene_frame` (centre: the weighted median of the
Gaussians; radius: the weighted median of their distances, the subject of a capture rather than its
background), seen from 20 degrees above its horizon at the distance where that sphere fills the view.

Frontends that show Gaussian splat files in Preview 3D (the newer ones, e.g. 1.58.1) load them with
Spark, whose splat mesh turns the file's axes half a turn about x: a point (x, y, z) of the file is
drawn at (x, -y, -z). The camera is given in those drawn coordinates. (The frontend ComfyUI 0.3.64 pins,
1.27.10, has no splat loader: there Preview 3D stays empty.)
"""

from __future__ import annotations

import math

import torch

from artnvg_core.cameras.framing import horizontal_axes, scene_frame
from artnvg_core.scene import GaussianScene

PREVIEW_FOV_DEG = 35.0  # Preview 3D's perspective camera
BULK_QUANTILE = 0.5  # the share of the Gaussians' weight the framed sphere holds: the subject
ELEVATION_DEG = 20.0
FILE_TO_VIEWER = torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)  # Spark's half turn about x


def preview_camera(scene: GaussianScene) -> dict:
    """Preview 3D's ``camera_info`` framing the bulk of ``scene`` (module docstring): ``{"position": {x, y, z},
    "target": {x, y, z}, "zoom": 1, "fov": degrees, "cameraType": "perspective"}`` in the viewer's axes."""
    frame = scene_frame(scene, quantile=BULK_QUANTILE)
    side, _ = horizontal_axes(frame.up)
    elevation = math.radians(ELEVATION_DEG)
    direction = math.cos(elevation) * side + math.sin(elevation) * frame.up
    distance = frame.radius / math.sin(math.radians(PREVIEW_FOV_DEG) / 2)
    position, target = frame.center + distance * direction, frame.center

    def point(vector: torch.Tensor) -> dict:
        return dict(zip("xyz", (FILE_TO_VIEWER * vector).tolist()))

    return {"position": point(position), "target": point(target), "zoom": 1, "fov": PREVIEW_FOV_DEG,
            "cameraType": "perspective"}
