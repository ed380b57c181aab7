"""Select Gaussians, and Finetune Gaussians given its selection, called as ComfyUI calls them, against the
library calls they adapt."""

import re

import pytest
import torch

from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.formats import load_scene
from artnvg_core.images import load_image
from artnvg_core.selection import Box, select_by_masks, select_region
from artnvg_core.stylize import DemoInputs
from node_calls import call
from nodes.finetune_nodes import FinetuneGaussians
from nodes.node_errors import NodeInputError
from nodes.selection_nodes import SelectGaussians


@pytest.fixture(scope="module")
def demo():
    return load_scene(DemoInputs().scene).select(slice(0, None, 20)), load_cameras(DemoInputs().cameras).scaled(0.125)


def test_select_node_box_sphere_and_mask_give_the_library_selections(demo):
    original, cameras = demo
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
    ({"mode": "box", "bounds": "1, 2, 3"}, "^Select Gaussians: input 'bounds': a box takes 6 finite numbers"),
    ({"mode": "sphere", "bounds": "100, 100, 100, 1"}, "Select Gaussians.*bounds.*selects no Gaussian"),
    ({"mode": "mask", "bounds": ""}, "^Select Gaussians: input 'cameras': mode mask needs cameras and mask connected"),
    ({"mode": "mask", "bounds": "", "cameras": None, "mask": torch.ones(1, 8, 8)}, "^Select Gaussians: input 'cameras'"),
])
def test_select_node_bad_inputs_name_the_input(demo, inputs, message):
    with pytest.raises(NodeInputError, match=message):
        call(SelectGaussians, scene=demo[0], **inputs)


def test_select_node_in_mask_mode_needs_cameras_and_mask_connected_before_the_graph_runs(demo):
    """Refused only as it ran, after the nodes before it had run; now by the prompt's links (ComfyUI leaves an
    unconnected optional input out of the prompt), naming the input missing."""
    assert SelectGaussians.check_links(["scene", "cameras"], mode="mask", bounds="") == (
        "Select Gaussians: input 'mask': mode mask needs cameras and mask connected")
    assert SelectGaussians.check_links(["scene", "mask"], mode={"__value__": "mask"}).startswith(
        "Select Gaussians: input 'cameras':")
    assert SelectGaussians.check_links(["scene", "cameras", "mask"], mode="mask") is None
    assert SelectGaussians.check_links(["scene", "mode"]) is None  # a mode through a link: known as it runs
    assert SelectGaussians.check_links(["scene"], mode="sphere") is None
    with pytest.raises(NodeInputError, match="^Select Gaussians: input 'mask': mode mask needs"):
        call(SelectGaussians, scene=demo[0], mode="mask", bounds="", cameras=demo[1], mask=None)


def test_select_node_bounds_are_checked_for_their_mode_before_the_graph_runs():
    """The prompt's values are checked before anything runs (the editor shows it before Render Views renders),
    saying what the node's mode takes in the node's own terms: the numbers alone, no 'sphere:' the artist never
    typed."""
    assert SelectGaussians.check_values(mode="sphere", bounds="0.8, 0.2, -1.1") == (
        "Select Gaussians: input 'bounds': a sphere takes 4 finite numbers, X, Y, Z, R, comma-separated in the "
        "scene's units; got '0.8, 0.2, -1.1'")
    assert SelectGaussians.unreported_value(mode="box", bounds="0, 0, 0, 1, 1") is not None  # ComfyUI shows ours
    assert "minimum corner" in SelectGaussians.check_values(mode="box", bounds="1, 0, 0, 0, 1, 1")
    assert "radius must be > 0" in SelectGaussians.check_values(mode={"__value__": "sphere"}, bounds="0, 0, 0, 0")
    for fine in ({"mode": "sphere", "bounds": " 0.8, 0.2, -1.1, 1"}, {"mode": "box", "bounds": "-1,-1,-1,1,1,1"},
                 {"mode": "mask", "bounds": ""}, {"bounds": "x"}):
        assert SelectGaussians.check_values(**fine) is None, fine


@pytest.mark.parametrize("mode, bounds", [("sphere", "100, 100, 100, 1"), ("box", "50, 50, 50, 60, 60, 60")])
def test_select_node_that_selects_nothing_says_where_the_scene_is(demo, mode, bounds):
    """An empty box or sphere names the sphere that holds the middle of the scene, and that sphere, typed in as
    bounds, selects the bulk of it."""
    expected = (r"^Select Gaussians: input 'bounds': selects no Gaussian of the scene; the middle of the scene "
                r"\(the bulk of its Gaussians\) is the sphere (.+) \(X, Y, Z, R\)$")
    with pytest.raises(NodeInputError, match=expected) as refused:
        call(SelectGaussians, scene=demo[0], mode=mode, bounds=bounds)
    sphere = re.match(expected, str(refused.value)).group(1)
    (selection,) = call(SelectGaussians, scene=demo[0], mode="sphere", bounds=sphere)
    assert selection.float().mean() > 0.3


def test_select_node_says_why_a_mask_selects_nothing(demo):
    """Load Image's MASK of an image without alpha (nothing painted) is told apart from paint that misses the scene."""
    original, cameras = demo
    for mask, why in [(torch.zeros(1, 64, 64), "the mask has no painted pixel: paint the region in Load Image's mask"),
                      (None, "its painted pixels see no Gaussian")]:
        if mask is None:  # paint on a view turned away from every Gaussian
            cameras = cameras.subset([0])
            cameras.world_to_cam[:, :3, 3] += torch.tensor([0.0, 0.0, -1e4])
            mask = torch.ones(1, cameras.height, cameras.width)
        with pytest.raises(NodeInputError, match=f"^Select Gaussians: input 'mask': selects no Gaussian of the scene; "
                                                 f"{why}"):
            call(SelectGaussians, scene=original, mode="mask", bounds="", cameras=cameras, mask=mask, views="0")


def test_select_node_needs_one_view_per_mask(demo):
    original, cameras = demo
    with pytest.raises(NodeInputError, match="Select Gaussians.*views.*2 masks but 1 view "):
        call(SelectGaussians, scene=original, mode="mask", bounds="", cameras=cameras,
             mask=torch.ones(2, cameras.height, cameras.width), views="0")
    for views, problem in [("0, 99", "mode mask: view index 99 is out of range for 24 cameras"),  # as it starts
                           ("0, -1", "view index -1 is out of range: views count from 0")]:
        with pytest.raises(NodeInputError, match=f"^Select Gaussians: input 'views': {problem}"):
            call(SelectGaussians, scene=original, mode="mask", bounds="", cameras=cameras,
                 mask=torch.ones(2, cameras.height, cameras.width), views=views)
    (box,) = call(SelectGaussians, scene=original, mode="box", bounds="-1, -1, -1, 1, 1, 1", cameras=cameras,
                  views="0, 99")  # views box ignores: never refused
    assert torch.equal(box, select_region(original, Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))))
    assert SelectGaussians.check_values(views="3, 3") is None  # a view may hold several masks
    assert SelectGaussians.check_values(views="3, x").startswith("Select Gaussians: input 'views': expected comma")


def test_select_node_refuses_a_mask_of_another_aspect_than_its_view(demo):
    """It was stretched to the view."""
    original, cameras = demo
    with pytest.raises(NodeInputError, match=r"^Select Gaussians: input 'mask': the masks: 64x32 pixels, "
                                             r"not the aspect of its view's 64x64 \(it would be stretched\)"):
        call(SelectGaussians, scene=original, mode="mask", bounds="", cameras=cameras, mask=torch.ones(1, 32, 64),
             views="0")


def test_finetune_node_trains_the_selection_alone(demo, monkeypatch):
    # on the library call's device: a GPU's sums differ in the last bits, which Adam's first steps magnify
    monkeypatch.setattr("nodes.comfy_bridge.compute_device", lambda: torch.device("cpu"))
    scene, cameras = demo
    (selection,) = call(SelectGaussians, scene=scene, mode="box", bounds="-1, -1, -1, 1, 1, 1")
    style = load_image(DemoInputs().style)[None]
    inputs = dict(scene=scene, cameras=cameras.subset([0, 8]), style_image=style, iterations=2, optimize="appearance",
                  l1_weight=0.8, ssim_weight=0.2, nnfm_weight=1.0, content_weight=0.15, tv_weight=0.01, seed=0)
    (result,) = call(FinetuneGaussians, selection=selection, **inputs)
    expected = finetune(scene, cameras.subset([0, 8]), style, config=FinetuneConfig(iterations=2), selection=selection)
    torch.testing.assert_close(result.sh, expected.sh, rtol=0, atol=1e-6)
    assert torch.equal(result.sh[~selection], scene.sh[~selection]) and not torch.equal(result.sh, scene.sh)
