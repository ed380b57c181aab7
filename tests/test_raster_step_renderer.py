"""StepRenderer: the steps' renders equal render()'s, the inputs are checked once when it is made, and a
backend that cannot render is refused there."""

import dataclasses

import pytest
import torch

from artnvg_core.raster import render
from artnvg_core.raster.step_renderer import StepRenderer
from raster_scenes import EYES, hard_scene, make_cameras


def test_the_steps_render_as_render_does_for_the_views_asked():
    scene = hard_scene(2, n=60, degree=1)
    cameras = make_cameras(EYES, width=24, height=16, focal=12.0)
    renderer = StepRenderer(scene, cameras, "torch")
    assert renderer.backend == "torch"
    out, incomplete = renderer.render(scene, [2, 0], torch.tensor([2, 0]))
    expected = render(scene, cameras.subset([2, 0]), backend="torch")
    assert incomplete is None and not renderer.redo()
    assert torch.equal(out.rgb, expected.rgb) and torch.equal(out.alpha, expected.alpha)


def test_a_bad_scene_or_backend_is_refused_when_it_is_made():
    scene = hard_scene(2, n=60, degree=1)
    cameras = make_cameras(EYES, width=24, height=16, focal=12.0)
    broken = dataclasses.replace(scene, means=scene.means.clone().index_fill_(0, torch.tensor([3]), float("nan")))
    with pytest.raises(ValueError, match="scene.means has non-finite"):
        StepRenderer(broken, cameras)
    with pytest.raises(ValueError, match="backend must be one of"):
        StepRenderer(scene, cameras, "vulkan")
