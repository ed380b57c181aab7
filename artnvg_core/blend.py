"""The strength dial: a stylized scene mixed with its original, Gaussian by Gaussian, without a re-run.

``blend(original, stylized, s)`` gives Gaussian i the parameters ``lerp(original_i, stylized_i, w_i)`` with
``w_i = s`` (or 0 outside a ``selection``): every SH coefficient (all bands), the opacity logit, and the
geometry (means, log-scales, quaternions) where the finetune moved it; a field the two scenes share bit
for bit is kept as it is. ``torch.lerp`` is exact at its ends, so ``s = 0`` gives the original's tensors
and ``s = 1`` the stylized one's, bit for bit (quaternions: the stylized ``q`` or ``-q``, one rotation,
whichever lies on the original's side, so that a mix never turns through the long way). Colours, being
linear in the SH, move in a straight line from the original's to the stylized one's; opacities move
monotonically between the two.

Only scenes that come from one another through a finetune correspond (:func:`check_corresponding`):
the same count, SH degree and render settings, and Gaussian i in about the same place in both.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import torch

from .cameras import CameraSet
from .counted import counted
from .progress import ProgressFn, StopFn
from .raster import render
from .scene import GaussianScene
from .selection import check_selection

# A finetune moves means by a small fraction of the scene's size; reordered or unrelated Gaussians
# typically lie a sizeable part of it apart.
MAX_MEDIAN_SHIFT = 0.05  # largest median mean displacement, as a fraction of the scene's size
SAMPLE = 65536  # Gaussians (evenly spaced) whose medians the check reads: enough for a median, quick at 1M


def scene_size(means: torch.Tensor) -> float:
    """A robust size of a point cloud [N, 3]: the median distance of the points from their median."""
    return float((means - means.median(0).values).norm(dim=1).median())


def check_corresponding(original: GaussianScene, stylized: GaussianScene,
                        names: tuple[str, str] = ("original", "stylized")) -> None:
    """ValueError, naming the two scenes by ``names``, unless ``stylized`` can be a finetune of ``original``:
    the same number of Gaussians, SH degree and render settings (blur, antialiasing), and Gaussian i of
    one within :data:`MAX_MEDIAN_SHIFT` of the scene's size of Gaussian i of the other, in the median (over
    :data:`SAMPLE` evenly spaced Gaussians; not checked where that size is 0)."""
    first, second = names
    refusal = f"cannot blend {first} and {second}: "
    if len(original) != len(stylized):
        raise ValueError(refusal + f"{first} has {counted(len(original), 'Gaussian')}, {second} {len(stylized):,}; "
                         "a blend mixes Gaussian i of one with Gaussian i of the other, so they must come from one "
                         "finetune")
    if original.sh_degree != stylized.sh_degree:
        raise ValueError(refusal + f"SH degree {original.sh_degree} in {first}, {stylized.sh_degree} in {second} "
                         "(was one saved in a format that drops SH bands? use .ply or .spz)")
    settings = (original.blur_px2, original.antialiased), (stylized.blur_px2, stylized.antialiased)
    if settings[0] != settings[1]:
        raise ValueError(refusal + f"render settings (blur_px2, antialiased) {settings[0]} in {first}, "
                         f"{settings[1]} in {second}")
    if torch.equal(original.means, stylized.means):
        return
    sample = torch.linspace(0, len(original) - 1, min(SAMPLE, len(original)), device=original.device).long()
    before, after = original.means[sample], stylized.means[sample].to(original.means)
    shift = float((before - after).norm(dim=1).median())
    size = scene_size(before)
    if shift > MAX_MEDIAN_SHIFT * size and size > 0:  # size 0 (one Gaussian, or all at one point): nothing to measure by
        raise ValueError(refusal + f"Gaussian i lies {shift:.4g} apart in the two scenes in the median, "
                         f"{shift / size:.0%} of the scene's size {size:.4g}: they are not one scene before and "
                         "after a finetune (a different scene, or its Gaussians reordered, e.g. by a .splat or "
                         ".ksplat save)")


def _weights(strength: float, selection: torch.Tensor | None, count: int, device: torch.device):
    """The mix weight: ``strength``, or per Gaussian [N] ``strength`` inside ``selection`` and 0 outside."""
    if not (isinstance(strength, (int, float)) and 0 <= strength <= 1):
        raise ValueError(f"blend: strength must be a number from 0 to 1, got {strength!r}")
    if selection is None:
        return float(strength)
    check_selection(selection, count, "blend")
    return selection.to(device, torch.float32) * strength


def blend(original: GaussianScene, stylized: GaussianScene, strength: float,
          selection: torch.Tensor | None = None, names: tuple[str, str] = ("original", "stylized")) -> GaussianScene:
    """``original`` and ``stylized`` (a finetune of it) mixed at ``strength`` in [0, 1] (module docstring).

    selection: optional boolean [N]: only these Gaussians are mixed, the others keep the original's values.
    names: how errors call the two scenes (e.g. their files). Returns a new scene on ``original``'s device
    with its render settings; the inputs are not modified.
    """
    check_corresponding(original, stylized, names)
    weight = _weights(strength, selection, len(original), original.device)
    mixed = {}
    for name, before in original.tensors().items():
        after = getattr(stylized, name).to(before)
        if torch.equal(before, after):
            mixed[name] = before
            continue
        if name == "quats":  # q and -q are one rotation: mix toward the one on the original's side
            after = torch.where((before * after).sum(1, keepdim=True) < 0, -after, after)
        w = weight if isinstance(weight, float) else weight.reshape(-1, *[1] * (before.ndim - 1))
        mixed[name] = torch.lerp(before, after, w)
    return dataclasses.replace(original, **mixed)


def render_strengths(original: GaussianScene, stylized: GaussianScene, camera: CameraSet, strengths: Sequence[float],
                     selection: torch.Tensor | None = None, backend: str = "auto", progress: ProgressFn | None = None,
                     should_stop: StopFn | None = None) -> torch.Tensor:
    """[K, H, W, 3] in [0, 1]: the first view of ``camera`` rendered from the blend at each of the K ``strengths``
    (a preview of the dial). Calls ``progress(renders done, K, {})`` as they start (0) and after each (a render
    of a capture's view takes seconds on a CPU), and raises :class:`~artnvg_core.progress.Cancelled` as soon as
    ``should_stop()`` says so (checked within each render)."""
    view = camera.subset([0]).to(original.device)
    report = progress or (lambda *args: None)
    report(0, len(strengths), {})
    frames = []
    with torch.no_grad():
        for strength in strengths:
            frames.append(render(blend(original, stylized, strength, selection), view, backend=backend,
                                 should_stop=should_stop).rgb.clamp(0, 1))
            report(len(frames), len(strengths), {})
    return torch.cat(frames)
