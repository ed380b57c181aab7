"""Named presets and the command-line values that choose them."""

import dataclasses

import pytest
import torch

from artnvg_core.cli.main import build_parser
from artnvg_core.cli.options import parse_devices
from artnvg_core.diffusion.sampler import SCHEDULERS
from artnvg_core.diffusion.settings import SCHEDULER_NAMES, SamplerSettings
from artnvg_core.presets import PRESETS, get_preset


def _stylize_choices(dest: str) -> tuple:
    stylize = build_parser()._subparsers._group_actions[0].choices["stylize"]
    return tuple(next(action.choices for action in stylize._actions if action.dest == dest))


def test_cli_offers_every_preset_and_scheduler():
    assert _stylize_choices("preset") == tuple(PRESETS)
    assert _stylize_choices("scheduler") == tuple(SCHEDULERS) == SCHEDULER_NAMES


def test_only_paper_is_exact_and_paper_is_the_default_sampler():
    assert PRESETS["paper"].sampler == SamplerSettings() and not PRESETS["paper"].low_memory
    exact_fields = ("attention_backend", "sequential_cfg")
    for name, preset in PRESETS.items():
        if preset.sampler is None:  # diffusion-free (preview): nothing of the paper's diffusion stage
            continue
        changed = {f.name for f in dataclasses.fields(SamplerSettings)
                   if getattr(preset.sampler, f.name) != getattr(SamplerSettings(), f.name)}
        assert (name in ("paper", "low-memory")) == changed.issubset(exact_fields), name
    assert PRESETS["low-memory"].low_memory and PRESETS["low-memory"].sampler.sequential_cfg


def test_unknown_preset_and_device_raise():
    with pytest.raises(ValueError, match=r"preset must be one of \['balanced', 'fast', 'low-memory', 'paper', 'preview'\]"):
        get_preset("turbo")
    assert parse_devices("cuda:0, cuda:1") == [torch.device("cuda", 0), torch.device("cuda", 1)]
    assert parse_devices(None) is None
    with pytest.raises(ValueError, match="--devices: 'gpu0' is not a device"):
        parse_devices("cuda:0,gpu0")


def test_the_diffusion_presets_are_those_with_sampler_settings():
    from artnvg_core.presets import DIFFUSION_PRESETS

    assert DIFFUSION_PRESETS == ("paper", "balanced", "fast", "low-memory")


def test_preview_is_the_only_diffusion_free_preset_and_refuses_the_diffusion_stylizer(tmp_path, capsys):
    from artnvg_core.cli.main import main

    assert [name for name, preset in PRESETS.items() if preset.sampler is None] == ["preview"]
    preview = PRESETS["preview"]
    assert preview.finetune_iterations < PRESETS["paper"].finetune_iterations and not preview.low_memory
    assert main(["stylize", "--preset", "preview", "--stylizer", "diffusion", "--out", str(tmp_path / "s.ply")]) == 2
    assert "--preset preview runs without diffusion" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_preset_sets_the_finetunes_length_and_views_and_keeps_the_rest():
    from artnvg_core.finetune import FinetuneConfig

    fast, given = get_preset("fast"), FinetuneConfig(iterations=7, seed=3, views_per_step=5, color_transfer=False)
    assert fast.finetune_config(given) == dataclasses.replace(given, iterations=fast.finetune_iterations,
                                                              views_per_step=fast.views_per_step)
    assert (fast.finetune_iterations, fast.views_per_step) != (7, 5)  # the test shows a change


def test_a_preset_gives_its_sampler_settings_with_the_changes_and_refuses_unknown_ones():
    fast = get_preset("fast")
    settings = fast.sampler_settings("paper", {"steps": 9})
    assert settings == dataclasses.replace(fast.sampler, content_routing="paper", steps=9)
    assert fast.sampler_settings("released") == dataclasses.replace(fast.sampler, content_routing="released")
    with pytest.raises(ValueError, match=r"no SamplerSettings field: \['stpes'\]"):
        fast.sampler_settings("released", {"stpes": 9})
    with pytest.raises(ValueError, match="diffusion-free"):
        get_preset("preview").sampler_settings("released")


def test_a_presets_finetune_share_reads_as_words():
    """The Finetune node's tooltip quotes it: one view, not '1 views'; the views' own size, not '1 x' it."""
    preview = get_preset("preview")
    assert preview.finetune_words() == "100 iterations of 1 view each, at the views' own size"
    halved = dataclasses.replace(preview, finetune_iterations=1, views_per_step=4, scale=0.5)
    assert halved.finetune_words() == "1 iteration of 4 views each, at 0.5 x the views' size"
