"""Sample Group's, Load CSGO's and Apply CSGO's checks of their inputs, made before any ComfyUI model is touched
(the sampling itself runs in the real ComfyUI: tests/integration/test_native_path.py)."""

import pytest
import torch

from artnvg_core.grouping import ViewGroup, ViewGroups
from nodes.diffusion_nodes import SampleGroup
from nodes.model_patch_nodes import ApplyCSGO, LoadCSGO
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


def test_load_csgo_says_where_the_file_belongs_and_where_to_get_it():
    with pytest.raises(NodeInputError, match=r"^Load CSGO: input 'csgo_name': 'csgo_4_32.bin' is not in the 'csgo' "
                                             r"model folder .*; get it from https://huggingface.co/InstantX/CSGO: "
                                             r"`hf download InstantX/CSGO csgo_4_32.bin`, saved as models/csgo/csgo_4_32.bin$"):
        LoadCSGO().load("csgo_4_32.bin")


def test_apply_csgo_refuses_a_style_image_the_command_line_refuses_before_touching_a_model():
    """The rule of artnvg_core.style_image, as stylize --style applies it; no model is given: none is read."""
    with pytest.raises(NodeInputError, match=r"^Apply CSGO: input 'style_image': image size: 20000x2 pixels; a style "
                                             "image may be at most 32 times as long as it is wide"):
        ApplyCSGO().apply(None, None, None, None, torch.rand(1, 2, 20000, 3), 0.6, 1.0)
