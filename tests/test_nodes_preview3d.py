"""Preview 3D's camera for a saved scene frames its bulk, in the axes the viewer draws the file in."""

import math

import torch

from artnvg_core.scene import GaussianScene
from nodes.preview3d import BULK_QUANTILE, PREVIEW_FOV_DEG, preview_camera


def _scene(means: torch.Tensor) -> GaussianScene:
    count = len(means)
    return GaussianScene(means=means, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(count, 1),
                         log_scales=torch.full((count, 3), -3.0), opacity_logits=torch.full((count,), 2.0),
                         sh=torch.zeros(count, 1, 3))


def _vector(point: dict) -> torch.Tensor:
    return torch.tensor([point["x"], point["y"], point["z"]], dtype=torch.float64)


def test_the_camera_frames_the_bulk_whatever_the_stray_gaussians():
    generator = torch.Generator().manual_seed(0)
    centre = torch.tensor([1.0, 2.0, 3.0])
    bulk = centre + torch.randn(4000, 3, generator=generator) * torch.tensor([1.0, 0.5, 0.3])
    strays = torch.randn(40, 3, generator=generator) * 500  # floaters hundreds of units out
    camera = preview_camera(_scene(torch.cat([bulk, strays])))
    assert camera["cameraType"] == "perspective" and camera["zoom"] == 1 and camera["fov"] == PREVIEW_FOV_DEG

    target, position = _vector(camera["target"]), _vector(camera["position"])
    viewer_centre = centre.double() * torch.tensor([1.0, -1.0, -1.0])  # the file's (x, y, z) drawn at (x, -y, -z)
    assert (target - viewer_centre).norm() < 0.1
    # the sphere holding half the Gaussians (all weigh alike here) just fills the field of view
    radius = float(torch.quantile((bulk.double() - bulk.double().median(0).values).norm(dim=1), BULK_QUANTILE))
    half_angle = math.degrees(math.asin(radius / float((position - target).norm())))
    assert abs(half_angle - PREVIEW_FOV_DEG / 2) < 1.0, half_angle
    alone = preview_camera(_scene(bulk))  # the strays move nothing that matters
    assert (_vector(alone["target"]) - target).norm() < 0.1
    assert abs(float((_vector(alone["position"]) - _vector(alone["target"])).norm())
               - float((position - target).norm())) < 0.1 * float((position - target).norm())


def test_aiming_at_a_scene_without_ground_asks_nothing_of_the_user(caplog):
    """Saving a scene computes Preview 3D's camera; an up direction guessed there (a scene without a ground:
    a standing blob) is the preview's business, so nothing is logged: "pass up=" is for nodes that place views
    (artnvg_core.orbit.orbit_cameras logs it), and Save Gaussian Scene has no such input."""
    standing = torch.randn(2000, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([0.5, 0.45, 1.0])
    with caplog.at_level("INFO"):
        preview_camera(_scene(standing))
    assert not caplog.records
