"""Blend Stylization and Select Gaussians called as ComfyUI calls them, against the library calls they adapt."""

import dataclasses

import pytest
import torch

from artnvg_core.blend import blend
from artnvg_core.cameras import load_cameras
from artnvg_core.formats import load_scene
from artnvg_core.raster import render
from artnvg_core.selection import Box, select_by_masks, select_region
from artnvg_core.stylize import DemoInputs
from nodes.blend_nodes import BlendStylization
from nodes.node_errors import NodeInputError
from nodes.selection_nodes import SelectGaussians


def call(node_class, **inputs):
    with torch.inference_mode():
        return getattr(node_class(), node_class.FUNCTION)(**inputs)


@pytest.fixture(scope="module")
def demo():
    original = load_scene(DemoInputs().scene).select(slice(0, None, 20))
    stylized = dataclasses.replace(original, sh=original.sh.flip(-1), opacity_logits=original.opacity_logits + 0.5)
    cameras = load_cameras(DemoInputs().cameras).scaled(0.125)
    return original, stylized, cameras


def test_blend_node_gives_the_library_blend_and_a_strip_of_previews(demo):
    original, stylized, cameras = demo
    selection = select_region(original, Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)))
    scene, preview = call(BlendStylization, original=original, stylized=stylized, strength=0.3, selection=selection,
                          cameras=cameras, view=2, preview_strengths="0, 1")
    expected = blend(original, stylized, 0.3, selection)
    assert all(torch.equal(a, b) for a, b in zip(scene.tensors().values(), expected.tensors().values()))
    size = cameras.width
    assert preview.shape == (1, cameras.height, 2 * size + 4, 3)
    with torch.no_grad():
        left = render(original, cameras.subset([2])).rgb[0].clamp(0, 1)
        right = render(blend(original, stylized, 1.0, selection), cameras.subset([2])).rgb[0].clamp(0, 1)
    torch.testing.assert_close(preview[0, :, :size], left, rtol=0, atol=1e-6)
    torch.testing.assert_close(preview[0, :, -size:], right, rtol=0, atol=1e-6)
    assert not torch.allclose(left, right, atol=0.05)
    assert (preview[0, :, size:size + 4] == 1).all()  # the white gap


@pytest.mark.parametrize("inputs, message", [
    ({"preview_strengths": "0, 2"}, "Blend Stylization.*preview_strengths.*from 0 to 1"),
    ({"view": 99}, "Blend Stylization.*view.*24 views"),
])
def test_blend_node_bad_inputs_name_the_input(demo, inputs, message):
    original, stylized, cameras = demo
    with pytest.raises(NodeInputError, match=message):
        call(BlendStylization, original=original, stylized=stylized, strength=0.5,
             cameras=load_cameras(DemoInputs().cameras), **inputs)


def test_blend_node_refuses_scenes_that_do_not_correspond(demo):
    original, stylized, _ = demo
    with pytest.raises(NodeInputError, match="Blend Stylization.*stylized.*cannot blend"):
        call(BlendStylization, original=original, stylized=stylized.select(slice(1, None)), strength=0.5)


def test_select_node_box_sphere_and_mask_give_the_library_selections(demo):
    original, _, cameras = demo
    (box,) = call(SelectGaussians, scene=original, mode="box", bounds="-1, -1, -1, 1, 1, 1")
    assert torch.equal(box, select_region(original, Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))))
    (ball,) = call(SelectGaussians, scene=original, mode="sphere", bounds="0, 0, 0, 1")
    assert torch.equal(ball, (original.means.double().square().sum(1) <= 1))
    masks = torch.zeros(2, cameras.height, cameras.width)
    masks[:, :, : cameras.width // 2] = 1
    (painted,) = call(SelectGaussians, scene=original, mode="mask", bounds="", cameras=cameras, mask=masks, views="3, 7")
    assert torch.equal(painted, select_by_masks(original, cameras.subset([3, 7]), masks))
    assert 0 < painted.sum() < len(original)


@pytest.mark.parametrize("inputs, message", [
    ({"mode": "box", "bounds": "1, 2, 3"}, "Select Gaussians.*bounds.*expected box:XMIN"),
    ({"mode": "sphere", "bounds": "100, 100, 100, 1"}, "Select Gaussians.*bounds.*selects no Gaussian"),
    ({"mode": "mask", "bounds": ""}, "Select Gaussians.*mask.*needs cameras and mask"),
])
def test_select_node_bad_inputs_name_the_input(demo, inputs, message):
    with pytest.raises(NodeInputError, match=message):
        call(SelectGaussians, scene=demo[0], **inputs)


def test_select_node_needs_one_view_per_mask(demo):
    original, _, cameras = demo
    with pytest.raises(NodeInputError, match="Select Gaussians.*views.*2 masks but 1 views"):
        call(SelectGaussians, scene=original, mode="mask", bounds="", cameras=cameras,
             mask=torch.ones(2, cameras.height, cameras.width), views="0")
