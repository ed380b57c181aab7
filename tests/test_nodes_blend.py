"""Blend Stylization called as ComfyUI calls it, against the library calls it adapts."""

import dataclasses

import pytest
import torch

from artnvg_core.blend import blend
from artnvg_core.cameras import load_cameras
from artnvg_core.formats import load_scene
from artnvg_core.raster import render
from artnvg_core.selection import Box, select_region
from artnvg_core.stylize import DemoInputs
from node_calls import call, same_scene
from nodes.blend_nodes import BlendStylization
from nodes.node_errors import NodeInputError
from tests.test_orbit import standing_blob


@pytest.fixture(scope="module")
def demo():
    original = load_scene(DemoInputs().scene).select(slice(0, None, 20))
    stylized = dataclasses.replace(original, sh=original.sh.flip(-1), opacity_logits=original.opacity_logits + 0.5)
    cameras = load_cameras(DemoInputs().cameras).scaled(0.125)
    return original, stylized, cameras


def test_blend_node_gives_the_library_blend_and_a_strip_of_previews(demo, monkeypatch):
    monkeypatch.setattr("nodes.comfy_bridge.compute_device", lambda: torch.device("cpu"))  # where the renders below run
    original, stylized, cameras = demo
    selection = select_region(original, Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)))
    scene, preview = call(BlendStylization, original=original, stylized=stylized, strength=0.3, selection=selection,
                          cameras=cameras, view=2, preview_strengths="0, 1")
    expected = blend(original, stylized, 0.3, selection)
    assert same_scene(scene, expected)
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
    ({"view": 99}, r"^Blend Stylization: input 'view': view index 99 is out of range for 24 cameras \(0\.\.23\)$"),
])
def test_blend_node_bad_inputs_name_the_input(demo, inputs, message):
    original, stylized, cameras = demo
    with pytest.raises(NodeInputError, match=message):
        call(BlendStylization, original=original, stylized=stylized, strength=0.5,
             cameras=load_cameras(DemoInputs().cameras), **inputs)


def test_blend_node_refuses_scenes_that_do_not_correspond(demo):
    original, stylized, _ = demo
    with pytest.raises(NodeInputError, match="^Blend Stylization: cannot blend original and stylized: original has"):
        call(BlendStylization, original=original, stylized=stylized.select(slice(1, None)), strength=0.5)


@pytest.mark.parametrize("inputs, message", [
    ({"strength": float("nan")}, "input 'strength': expected a finite number, got nan"),
    ({"strength": 1.5}, "input 'strength': 1.5 is outside 0.0 to 1.0"),
    ({"selection": torch.ones(3, dtype=torch.bool)}, "blend: selection must be a boolean mask of the scene's 2,000"),
])
def test_blend_node_called_directly_names_the_input_at_fault(demo, inputs, message):
    """Called from Python, or given a value through a link, which no prompt check sees: the message named input
    'stylized' whatever was wrong."""
    original, stylized, _ = demo
    with pytest.raises(NodeInputError, match=f"^Blend Stylization: {message}"):
        call(BlendStylization, **{"original": original, "stylized": stylized, "strength": 0.5, **inputs})


def test_blend_node_without_cameras_shows_a_guessed_up_in_its_terms(monkeypatch, caplog):
    """No cameras and a scene with no ground: the preview's guessed up is noted under the node, with what to connect."""
    monkeypatch.setattr("nodes.comfy_bridge.compute_device", lambda: torch.device("cpu"))
    original = standing_blob().select(slice(0, None, 10))
    with caplog.at_level("WARNING"):
        call(BlendStylization, original=original, stylized=original, strength=0.5, preview_strengths="0")
    (message,) = [record.getMessage() for record in caplog.records]
    assert message.startswith("Blend Stylization: note: the up direction is a guess")
    assert message.endswith("connect cameras, e.g. Cameras Around Scene's with its up input set to -y or another axis")
