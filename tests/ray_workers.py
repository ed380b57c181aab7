"""What the test session's Ray workers share (see the ``ray_local`` fixture in conftest.py).

``TINY_FAST`` replaces the ``fast`` preset in every worker (and, through monkeypatch, in the tests
that compare with it): two DDIM steps at the views' own size, so a diffusion job on tiny models takes
a second, not minutes. Workers run one intra-op thread, as the tests do, so results match bit for bit.
"""

from artnvg_core.diffusion.sampler import SamplerSettings
from artnvg_core.presets import PRESETS, Preset

TINY_FAST = Preset(SamplerSettings(steps=2, guidance_scale=3.0, resolution=None), 2, False, "two steps (tests)")


def setup_worker() -> None:
    PRESETS["fast"] = TINY_FAST
