"""Named speed/accuracy presets (sampler settings, memory mode, finetune length, resolution).

Only ``paper`` (and ``low-memory``, up to rounding) give the paper's result; ``balanced`` and ``fast``
trade accuracy for speed. What each costs in time and in the final scene: BENCHMARKS.md, "Presets on
the final scene" (docs/presets.md explains them). ``preview`` is diffusion-free: the NNFM stylizer,
short and at reduced resolution, a first look in seconds (BENCHMARKS.md, "First look").
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING

from .counted import counted
from .diffusion.settings import SamplerSettings

if TYPE_CHECKING:
    from .finetune import FinetuneConfig  # only a type here: importing the presets loads no finetune


@dataclass(frozen=True)
class Preset:
    """sampler: the group sampler's settings (None: diffusion-free, the NNFM stylizer); low_memory:
    :func:`artnvg_core.diffusion.memory.enable_low_memory` and sequential guidance halves; finetune_iterations:
    length of the Gaussian finetune; key_views: stylize and finetune on only that many views covering the scene
    (:mod:`artnvg_core.key_views`; 0: every view); scale: the views' resolution factor (1: as given);
    views_per_step: ``FinetuneConfig.views_per_step``."""

    sampler: SamplerSettings | None
    finetune_iterations: int
    low_memory: bool
    summary: str
    key_views: int = 0
    scale: float = 1.0
    views_per_step: int = 1

    def finetune_config(self, config: FinetuneConfig) -> FinetuneConfig:
        """The finetune's share: ``config`` with this preset's length and views per step (the views' scale,
        :attr:`scale`, is the caller's to apply where it makes its views)."""
        return replace(config, iterations=self.finetune_iterations, views_per_step=self.views_per_step)

    def finetune_words(self) -> str:
        """The finetune's share in words, e.g. '100 iterations of 1 view each, at the views' own size'."""
        size = "the views' own size" if self.scale == 1 else f"{self.scale:g} x the views' size"
        return f"{counted(self.finetune_iterations, 'iteration')} of {counted(self.views_per_step, 'view')} each, at {size}"

    def sampler_settings(self, content_routing: str, changes: Mapping[str, object] | None = None) -> SamplerSettings:
        """The diffusion stage's share: this preset's sampler settings with ``content_routing`` and the fields of
        ``changes`` replaced (ValueError for a diffusion-free preset or a name that is no field)."""
        if self.sampler is None:
            raise ValueError("diffusion-free (run stylize_nnfm)")
        changes = dict(changes or {})
        unknown = sorted(set(changes) - {f.name for f in fields(self.sampler)})
        if unknown:
            raise ValueError(f"sampler_changes names no SamplerSettings field: {unknown}")
        return replace(self.sampler, content_routing=content_routing, **changes)


PRESETS = {
    "paper": Preset(SamplerSettings(), 1000, False,
                    "the paper: 50 DDIM steps, NV attention in every layer, 1024 px; exact"),
    # chosen from the measured curve of final-scene deviation against time (BENCHMARKS.md, "Presets on the
    # final scene")
    "balanced": Preset(SamplerSettings(steps=16, cfg_until=0.5), 1000, False,
                       "16 DDIM steps, guidance in the first half only (its cost: BENCHMARKS.md, Presets)"),
    "fast": Preset(SamplerSettings(steps=5, cfg_until=0.5, resolution=768, nv_levels="lowest"), 300, False,
                   "a first look: 42 key views, 5 DDIM steps at 768 px, guidance in the first 3, NV attention "
                   "in the lowest level, 300 finetune iterations (its cost: BENCHMARKS.md, Presets)",
                   key_views=42),
    "low-memory": Preset(SamplerSettings(sequential_cfg=True), 1000, True,
                         "the paper's result within 12 GiB: idle models on the CPU, guidance halves one at a time"),
    # chosen from the measured curve of time against the final scene's distance from the 1,000-iteration NNFM
    # result (BENCHMARKS.md, "First look")
    "preview": Preset(None, 100, False,
                      "a first look without diffusion: the NNFM stylizer, 100 iterations at the views' own size "
                      "(its cost: BENCHMARKS.md, First look)"),
}
DIFFUSION_PRESETS = tuple(name for name, preset in PRESETS.items() if preset.sampler is not None)


def get_preset(name: str) -> Preset:
    """The preset called ``name`` (ValueError listing the names otherwise)."""
    if name not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
    return PRESETS[name]
