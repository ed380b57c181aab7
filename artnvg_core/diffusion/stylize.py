"""Whole-scene diffusion stylization: group the views, stylize group by group, reassemble.

Views are grouped by camera-centre distance (:func:`artnvg_core.grouping.group_views`);
group ``g`` is sampled with seed ``seed + g``. A group's borrowed context views (if
``context_views > 0``) take part in its neighbouring-view attention and are then dropped:
every view's output comes from the one group that owns it.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from ..cameras import CameraSet
from ..counted import counted
from ..grouping import DEFAULT_GROUP_SIZE, ViewGroups, group_views
from ..progress import ProgressFn, StopFn
from .conditioning import StyleConditioning, prepare_conditioning
from .images import check_images
from .models import DiffusionModels
from .sampler import SamplerSettings, stylize_group

DEFAULT_PROMPT = "best quality, high quality"
DEFAULT_NEGATIVE_PROMPT = (
    "text, watermark, lowres, low quality, worst quality, deformed, glitch, low contrast, noisy, saturation, blurry"
)


def stylize_views(
    models: DiffusionModels,
    content_images: torch.Tensor,
    cameras: CameraSet,
    style_image: torch.Tensor | None,
    settings: SamplerSettings = SamplerSettings(),
    *,
    group_size: int = DEFAULT_GROUP_SIZE,
    context_views: int = 0,
    seed: int = 0,
    prompt: str = DEFAULT_PROMPT,
    negative_prompt: str | None = DEFAULT_NEGATIVE_PROMPT,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """Stylize all views; returns IMAGE [V, H, W, 3] in the order of ``content_images`` / ``cameras``.

    progress(step, total, info) counts denoising steps over all groups; info holds "group" and "groups".
    """
    images = check_images(content_images, "stylize_views: content_images")
    if len(images) != len(cameras.world_to_cam):
        raise ValueError(f"stylize_views: {counted(len(images), 'content image')} but "
                         f"{counted(len(cameras.world_to_cam), 'camera')}")
    groups = group_views(cameras, group_size, context=context_views)
    conditioning = prepare_conditioning(models, style_image, prompt, negative_prompt)
    return stylize_groups(models, images, groups, conditioning, settings, seed=seed, progress=progress,
                          should_stop=should_stop)


def stylize_groups(
    models: DiffusionModels,
    images: torch.Tensor,
    groups: ViewGroups,
    conditioning: StyleConditioning,
    settings: SamplerSettings = SamplerSettings(),
    *,
    seed: int = 0,
    noise_seeds: Sequence[int] | None = None,
    group_indices: Sequence[int] | None = None,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """Stylize the chosen groups (default: all) of ``images`` [V, H, W, 3], in view order.

    Returns a copy of ``images`` in which every view owned by a chosen group is replaced by its
    stylized version. Group ``g`` uses seed ``seed + g``; ``noise_seeds`` (one per view) give each
    view its own initial noise instead, whatever its group (see :func:`stylize_group`).
    ``groups.centers`` (when recorded) give the views' camera centres to ``settings.nv_nearest``.
    progress(step, total, info) counts
    denoising steps over the chosen groups; info holds "group" and "groups".
    """
    chosen = list(range(len(groups))) if group_indices is None else [int(g) for g in group_indices]
    total = len(chosen) * settings.steps
    output = images.clone()
    for done, index in enumerate(chosen):

        def report(step: int, steps: int, info: dict, done: int = done, index: int = index) -> None:
            if progress is not None:
                progress(done * steps + step, total, {**info, "group": index, "groups": len(groups)})

        output[list(groups[index].views)] = stylize_owned_views(models, images, groups, index, conditioning, settings,
                                                                seed=seed, noise_seeds=noise_seeds, progress=report,
                                                                should_stop=should_stop)
    return output


def stylize_owned_views(
    models: DiffusionModels,
    images: torch.Tensor,
    groups: ViewGroups,
    index: int,
    conditioning: StyleConditioning,
    settings: SamplerSettings = SamplerSettings(),
    *,
    seed: int = 0,
    noise_seeds: Sequence[int] | None = None,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
) -> torch.Tensor:
    """Group ``index`` of ``images`` [V, H, W, 3] sampled with seed ``seed + index`` (and the members' own
    ``noise_seeds`` when given, one per view of ``images``), its context views included; returns its owned
    views' stylized images [len(views), H, W, 3] in ``groups[index].views`` order."""
    if noise_seeds is not None and len(noise_seeds) != len(images):
        raise ValueError(f"stylize_owned_views: {len(noise_seeds)} noise_seeds for {counted(len(images), 'view')}")
    members, centers = group_members(images, groups, index)
    seeds = None if noise_seeds is None else [noise_seeds[v] for v in groups[index].all_views]
    result = stylize_group(models, members, conditioning, settings, seed=seed + index, noise_seeds=seeds,
                           view_centers=centers, progress=progress, should_stop=should_stop)
    return result[: len(groups[index].views)]


def group_members(images: torch.Tensor, groups: ViewGroups, index: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """What sampling group ``index`` of ``images`` [V, H, W, 3] reads: its members' images [M, H, W, 3]
    (owned views, then context views) and their camera centres [M, 3] float64 (None when ``groups``
    records none)."""
    members = list(groups[index].all_views)
    centers = None if groups.centers is None else torch.tensor([groups.centers[v] for v in members])
    return images[members], centers
