"""The group sampler's settings (:class:`SamplerSettings`) and the names they choose from.

Kept apart from :mod:`.sampler` so that presets, the command line and the nodes read them without
importing diffusers or transformers (seconds of start-up a diffusion-free run does not need).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .csgo import CONTENT_ROUTINGS
from .speed import check_sdpa_backend

SCHEDULER_NAMES = ("ddim", "euler", "euler_ancestral", "dpmpp_2m", "unipc")  # :data:`.sampler.SCHEDULERS`' keys
NV_LEVELS = ("all", "lowest")
SIZE_RULES = ("long_side", "area")


@dataclass(frozen=True)
class SamplerSettings:
    """How one neighbouring-view group is sampled. Defaults: the paper's scales (content 1.0, style 0.6,
    control 1.0) and DDIM; guidance 10 and 50 steps as in CSGO's inference script. The approximations
    (``nv_levels``, ``nv_nearest``, ``nv_kv_downsample``) are off by default; every other field is exact
    up to floating-point rounding or changes the method itself.

    Args:
        steps (`int`, defaults to 50): denoising steps, >= 1.
        guidance_scale (`float`, defaults to 10.0): classifier-free guidance scale (unitless); <= 1 runs
            the conditional half alone.
        content_scale (`float`, defaults to 1.0): weight of the CSGO content tokens' attention (unitless);
            no effect with ``content_routing="released"``.
        style_scale (`float`, defaults to 0.6): weight of the CSGO style tokens' attention (unitless).
        control_scale (`float`, defaults to 1.0): Tile ControlNet conditioning scale (unitless).
        content_routing (`str`, defaults to ``"released"``): ``"released"`` (CSGO's released inference: UNet
            down blocks read text only, content comes through the Tile ControlNet) or ``"paper"`` (content
            tokens into every UNet down-block attn2; needs the CSGO file's content entries).
        neighbour_views (`bool`, defaults to True): neighbouring-view attention on (False: the paper's
            "w/o NV" ablation).
        resolution (`int` or None, defaults to 1024): working size of a view in pixels, >= 64, read by
            ``size_rule`` (None: keep the content size, rounded to 64).
        size_rule (`str`, defaults to ``"long_side"``): ``"long_side"``, CSGO's ``resize_content``: the long
            side becomes ``resolution`` (a 16:9 view samples at 1024x576), sides floored to what the UNet
            halves exactly (multiples of 32 on SDXL); ``"area"``: about ``resolution``² pixels, multiples of
            64 (SDXL's training sizes; 1344x768 for 16:9, 1.75x the tokens). Outputs come back at each
            view's own size either way.
        scheduler (`str`, defaults to ``"ddim"``): one of :data:`SCHEDULER_NAMES` (``ddim``, ``euler``,
            ``euler_ancestral``, ``dpmpp_2m``, ``unipc``).
        attention_backend (`str`, defaults to ``"auto"``): scaled-dot-product attention backend of the
            denoising loop, one of ``speed.SDPA_BACKENDS`` ("auto" = PyTorch's choice).
        sequential_cfg (`bool`, defaults to False): run the two guidance halves one after the other
            (less memory).
        cfg_until (`float`, defaults to 1.0): fraction in [0, 1] of the steps that use classifier-free
            guidance (the first ``ceil(cfg_until * steps)``, :func:`guided_steps`); after them the
            conditional half alone, a batch of N views instead of 2N (1.0: every step; 0: never).
        noise_resolution (`int` or None, defaults to None): draw the initial noise on the latent grid this
            resolution (pixels, >= 64) would give and resample it to the working grid
            (:func:`resample_noise`), so runs at different resolutions start from the same noise field
            (None: drawn on the working grid).
        nv_levels (`str`, defaults to ``"all"``): approximation: ``"lowest"`` keeps NV attention in the
            lowest-resolution attention level only, per-view attention elsewhere.
        nv_nearest (`int` or None, defaults to None): approximation: each view attends to itself and its k
            nearest views of the group by camera centre, k >= 1 (None: all views; needs the camera centres).
        nv_kv_downsample (`int`, defaults to 1): approximation: the other views' keys and values
            average-pooled by this factor per side, >= 1 (1: exact).
    """

    steps: int = 50
    guidance_scale: float = 10.0
    content_scale: float = 1.0
    style_scale: float = 0.6
    control_scale: float = 1.0
    content_routing: str = "released"
    neighbour_views: bool = True
    resolution: int | None = 1024
    size_rule: str = "long_side"
    scheduler: str = "ddim"
    attention_backend: str = "auto"
    sequential_cfg: bool = False
    cfg_until: float = 1.0
    noise_resolution: int | None = None
    nv_levels: str = "all"
    nv_nearest: int | None = None
    nv_kv_downsample: int = 1

    def __post_init__(self) -> None:
        check_sdpa_backend(self.attention_backend, "SamplerSettings.attention_backend")
        if self.nv_levels not in NV_LEVELS:
            raise ValueError(f"SamplerSettings.nv_levels must be one of {NV_LEVELS}, got {self.nv_levels!r}")
        if self.nv_nearest is not None and self.nv_nearest < 1:
            raise ValueError(f"SamplerSettings.nv_nearest must be None or >= 1, got {self.nv_nearest}")
        if self.nv_kv_downsample < 1:
            raise ValueError(f"SamplerSettings.nv_kv_downsample must be >= 1, got {self.nv_kv_downsample}")
        if self.steps < 1:
            raise ValueError(f"SamplerSettings.steps must be >= 1, got {self.steps}")
        if not 0 <= self.cfg_until <= 1:
            raise ValueError(f"SamplerSettings.cfg_until must be in [0, 1], got {self.cfg_until}")
        if self.scheduler not in SCHEDULER_NAMES:
            raise ValueError(f"SamplerSettings.scheduler must be one of {sorted(SCHEDULER_NAMES)}, got {self.scheduler!r}")
        if self.content_routing not in CONTENT_ROUTINGS:
            raise ValueError(
                f"SamplerSettings.content_routing must be one of {CONTENT_ROUTINGS}, got {self.content_routing!r}"
            )
        if self.size_rule not in SIZE_RULES:
            raise ValueError(f"SamplerSettings.size_rule must be one of {SIZE_RULES}, got {self.size_rule!r}")
        if self.resolution is not None and self.resolution < 64:
            raise ValueError(f"SamplerSettings.resolution must be >= 64 or None, got {self.resolution}")
        if self.noise_resolution is not None and self.noise_resolution < 64:
            raise ValueError(f"SamplerSettings.noise_resolution must be >= 64 or None, got {self.noise_resolution}")


def guided_steps(steps: int, cfg_until: float, guidance_scale: float) -> int:
    """How many of the first ``steps`` denoising steps use classifier-free guidance: ``ceil(cfg_until * steps)``
    (rounded to 1e-6 first, so 0.8 x 50 is 40), or 0 when ``guidance_scale <= 1`` (no unconditional half)."""
    if guidance_scale <= 1:
        return 0
    return min(steps, math.ceil(round(cfg_until * steps, 6)))
