"""GaussianScene: shapes, render settings, validation."""

import pytest
import torch

from artnvg_core.scene import GaussianScene, validate_scene
from tests.test_formats_ply import random_scene


def test_map_and_select_keep_the_render_settings():
    scene = GaussianScene(**random_scene(5, 1).tensors(), blur_px2=0.1, antialiased=True)
    for derived in (scene.map(lambda t: t * 1), scene.select(slice(0, 2)), scene.to(dtype=torch.float64)):
        assert (derived.blur_px2, derived.antialiased, derived.classic) == (0.1, True, False)
    assert random_scene(3, 0).classic
    assert set(scene.tensors()) == {"means", "quats", "log_scales", "opacity_logits", "sh"}


@pytest.mark.parametrize("blur", [-0.1, float("nan"), float("inf"), "0.3"])
def test_bad_blur_is_rejected(blur):
    with pytest.raises(ValueError, match="GaussianScene.blur_px2: expected a finite number >= 0"):
        GaussianScene(**random_scene(3, 0).tensors(), blur_px2=blur)


def test_validate_scene_passes_a_valid_scene_through():
    scene = random_scene(6, 3)
    checked, dropped = validate_scene(scene, "memory")
    assert dropped == 0 and checked is scene


def test_scene_with_no_valid_gaussians_is_an_error():
    scene = random_scene(3, 0)
    scene.opacity_logits[:] = float("nan")
    with pytest.raises(ValueError, match="memory: all 3 Gaussians are invalid"):
        validate_scene(scene, "memory", drop_invalid=True)
    with pytest.raises(ValueError, match="memory: the scene contains no Gaussians"):
        validate_scene(scene.select(torch.zeros(3, dtype=torch.bool)), "memory")
