"""Finetune Gaussians on the shared bear scene, called as ComfyUI calls it, against the core's finetune with
the same settings; bad stylized views and style images refused before any work."""

from unittest import mock

import pytest
import torch

from artnvg_core.cameras import CameraSet, load_cameras
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.presets import PRESETS
from artnvg_core.scene import GaussianScene
from artnvg_core.stylize import DemoInputs
from node_calls import SCALE, bear, call, same_scene, small_bear  # noqa: F401  (fixtures)
from nodes.finetune_nodes import FinetuneGaussians
from nodes.node_errors import NodeInputError

def test_finetune_node_matches_the_core_and_checks_stylized_views(small_bear, bear):
    cameras = bear["cameras"].subset([0, 48]).scaled(SCALE)
    style = torch.rand(1, 32, 40, 3, generator=torch.Generator().manual_seed(0))
    stylized = torch.rand(2, 64, 64, 3, generator=torch.Generator().manual_seed(1))
    weights = {"l1_weight": 0.8, "ssim_weight": 0.2, "nnfm_weight": 1.0, "content_weight": 0.5, "tv_weight": 0.1}
    (result,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=2,
                     optimize="appearance", seed=3, stylized_views=stylized, **weights)
    expected = finetune(small_bear, cameras, style[0], stylized=stylized,
                        config=FinetuneConfig(iterations=2, optimize="appearance", seed=3, **weights))
    assert same_scene(result, expected)
    assert not torch.equal(result.sh, small_bear.sh)
    (full,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=2,
                   optimize="appearance", seed=3, stylized_views=stylized, nnfm_max_side=0, **weights)
    expected = finetune(small_bear, cameras, style[0], stylized=stylized,
                        config=FinetuneConfig(iterations=2, optimize="appearance", seed=3, nnfm_max_side=None, **weights))
    assert same_scene(full, expected)
    (plain,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=1,
                    optimize="appearance", seed=3, color_transfer=False, **weights)
    expected = finetune(small_bear, cameras, style[0],
                        config=FinetuneConfig(iterations=1, optimize="appearance", seed=3, color_transfer=False, **weights))
    assert same_scene(plain, expected)


def test_finetune_node_names_stylized_views_of_other_cameras_before_any_work():
    """Stylized views made from other cameras than those connected (say Load Cameras' every view, where Sample
    Group was given a Render Views of some of them) are refused naming the input and the two counts; no scene
    is given (a mock): none is touched."""
    scene = mock.Mock(spec=GaussianScene)
    with pytest.raises(NodeInputError, match=r"^Finetune Gaussians: input 'stylized_views': got \(1, 64, 64, 3\) "
                                             r"for 2 cameras; expected \[2, H, W, 3\], one view per camera"):
        call(FinetuneGaussians, scene=scene, cameras=load_cameras(DemoInputs().cameras).subset([0, 12]),
             style_image=torch.rand(1, 8, 8, 3),
             iterations=1, optimize="appearance", l1_weight=0.8, ssim_weight=0.2, nnfm_weight=1.0,
             content_weight=0.5, tv_weight=0.1, seed=0, stylized_views=torch.rand(1, 64, 64, 3))
    assert not scene.mock_calls


def test_finetune_node_refuses_a_style_image_the_command_line_refuses_before_any_work():
    """The rule of artnvg_core.style_image, as stylize --style applies it; no scene is given (mocks): none is touched."""
    with pytest.raises(NodeInputError, match=r"^Finetune Gaussians: input 'style_image': image size: 2x20000 pixels; "
                                             "a style image may be at most 32 times as long as it is wide"):
        call(FinetuneGaussians, scene=mock.Mock(spec=GaussianScene), cameras=mock.Mock(spec=CameraSet), style_image=torch.rand(1, 20000, 2, 3), iterations=1,
             optimize="appearance", l1_weight=0.8, ssim_weight=0.2, nnfm_weight=1.0, content_weight=0.5,
             tv_weight=0.1, seed=0)


def test_finetune_node_preview_preset_is_the_cores_preview(small_bear, bear, monkeypatch):
    """preset "preview" replaces iterations, views per step and the cameras' size by the preview preset's
    (PRESETS["preview"], shortened here): the same scene as the core's finetune with those settings."""
    import dataclasses

    from artnvg_core.presets import PRESETS

    preview = dataclasses.replace(PRESETS["preview"], finetune_iterations=3)
    monkeypatch.setitem(PRESETS, "preview", preview)
    cameras = bear["cameras"].subset([0, 24, 48, 72]).scaled(SCALE)
    style = torch.rand(1, 32, 40, 3, generator=torch.Generator().manual_seed(0))
    weights = {"l1_weight": 0.8, "ssim_weight": 0.2, "nnfm_weight": 1.0, "content_weight": 0.5, "tv_weight": 0.1}
    (result,) = call(FinetuneGaussians, scene=small_bear, cameras=cameras, style_image=style, iterations=1,
                     optimize="appearance", seed=3, preset="preview", nnfm_search="fp32", **weights)
    config = FinetuneConfig(iterations=preview.finetune_iterations, views_per_step=preview.views_per_step,
                            optimize="appearance", seed=3, nnfm_search="fp32", **weights)
    expected = finetune(small_bear, cameras.scaled(preview.scale), style[0], config=config)
    assert same_scene(result, expected)


def test_finetune_node_preset_tooltip_says_what_preview_sets_in_words():
    tooltip = FinetuneGaussians.INPUT_TYPES()["optional"]["preset"][1]["tooltip"]
    assert f"preview: a first look in seconds (BENCHMARKS.md, First look): {PRESETS['preview'].finetune_words()}, " in tooltip
    assert "1 views" not in tooltip and "1 x" not in tooltip
