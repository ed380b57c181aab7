"""Sample Group's and Apply CSGO's checks of their inputs, made before any ComfyUI model is touched
(the sampling itself runs in the real ComfyUI: tests/integration/test_native_path.py)."""

from types import SimpleNamespace
from unittest import mock

import pytest
import torch

from artnvg_core.diffusion.csgo_weights import CSGOFile
from artnvg_core.grouping import ViewGroup, ViewGroups
from nodes.diffusion_nodes import SampleGroup
from nodes.model_patch_nodes import ApplyCSGO
from nodes.node_errors import NodeInputError

GROUPS = ViewGroups((ViewGroup((0, 1)), ViewGroup((2,))), 3)


def _sample(views: torch.Tensor, group_index: int = -1):
    return SampleGroup().sample(None, [], [], None, None, views, GROUPS, group_index, 0, 1, 1.0, "ddim",
                                "ddim_uniform", 1.0, 1.0, 64, "long_side")


@pytest.mark.parametrize("views, group_index, message", [
    (torch.rand(2, 8, 8, 3), -1, "input 'content_views': 2 views but the groups cover 3 cameras"),
    (torch.rand(3, 8, 8, 3), 2, "input 'group_index': 2 is out of range for 2 groups"),
    (torch.rand(3, 8, 8, 3) * 2, -1, r"input 'content_views': the views: values must lie in \[0, 1\]"),
])
def test_sample_group_names_the_bad_input(views, group_index, message):
    with pytest.raises(NodeInputError, match=f"^Sample Group: {message}"):
        _sample(views, group_index)


def test_apply_csgo_refuses_a_style_image_the_command_line_refuses_before_touching_a_model():
    """The rule of artnvg_core.style_image, as stylize --style applies it; no model is given (a mock CSGO file): none
    is read."""
    with pytest.raises(NodeInputError, match=r"^Apply CSGO: input 'style_image': image size: 20000x2 pixels; a style "
                                             "image may be at most 32 times as long as it is wide"):
        ApplyCSGO().apply(None, None, mock.Mock(spec=CSGOFile), None, torch.rand(1, 2, 20000, 3), 0.6, 1.0)


def test_sample_group_seeds_past_the_largest_count_on_from_zero(monkeypatch):
    """Group g uses seed + g, which ComfyUI's noise (torch.manual_seed) takes only below 2^64: at the largest seed
    the second group failed after the first had been sampled."""
    seeds = []

    def sample_views(*args):  # as SampleGroup._sample_views, its noise as ComfyUI's prepare_noise seeds it
        views, size, seed = args[5], args[7], args[8]
        torch.manual_seed(seed)
        seeds.append(seed)
        return torch.zeros(len(views), *size, 3)

    monkeypatch.setattr("nodes.diffusion_nodes.diffusion_unet", lambda node, model: SimpleNamespace(channel_mult=(1,)))
    monkeypatch.setattr("nodes.diffusion_nodes.controlnet_model", lambda node, control_net: None)
    monkeypatch.setattr("nodes.diffusion_nodes._nv_patch", lambda model: None)
    monkeypatch.setattr(SampleGroup, "_sample_views", staticmethod(sample_views))
    largest = SampleGroup.INPUT_TYPES()["required"]["seed"][1]["max"]
    (images,) = SampleGroup().sample(None, [], [], SimpleNamespace(downscale_ratio=8), None, torch.rand(3, 8, 8, 3),
                                     GROUPS, -1, largest, 1, 1.0, "ddim", "ddim_uniform", 1.0, 1.0, 64, "long_side")
    assert seeds == [2**64 - 1, 0] and images.shape == (3, 8, 8, 3)
