"""Finetune Gaussians: the scene's appearance toward stylized views (optional) and a style image."""

from __future__ import annotations

import time

from artnvg_core.counted import counted
from artnvg_core.finetune import NNFM_MIN_SIDE, OPTIMIZE_CHOICES, FinetuneConfig, check_stylized_views, finetune
from artnvg_core.losses import SEARCH_PRECISIONS
from artnvg_core.presets import PRESETS
from artnvg_core.style_image import check_style_size

from .comfy_bridge import (
    autograd_enabled,
    cancellable,
    interrupt_requested,
    progress_bar,
    progress_text,
    render_device,
    trainable_copy,
)
from .node_base import STYLE_IMAGE_INPUT, ArtNVGNode
from .node_errors import node_input
from .node_types import CAMERAS, IMAGE, SCENE, SELECTION

_DEFAULTS = FinetuneConfig()
_PREVIEW = PRESETS["preview"]
PRESET_CHOICES = ("custom", "preview")
STAGES = {"region": "measuring what the selection covers in the {views}",
          "setup": "rendering the {views} before finetuning",
          "features": "computing the VGG features of the {views} for the content term",
          "steps": "finetuning: {steps}",
          "final": "rendering the {finetuned} for the colour match"}


def staged_progress():
    """A core ``ProgressFn`` for the node's bar that also names each stage under the node at its first report
    (``info["stage"]``: region, setup, features, final, else the steps); None without ComfyUI."""
    report = progress_bar()
    if report is None:
        return None
    shown = None

    def staged(step: int, total: int, info: dict) -> None:
        nonlocal shown
        stage = info.get("stage", "steps")
        if stage != shown:
            shown = stage
            counts = {"views": counted(total, "view"), "steps": counted(total, "step"),
                      "finetuned": counted(total, "finetuned view")}
            progress_text(STAGES[stage].format(**counts), FinetuneGaussians.DISPLAY_NAME)
        report(step, total, info)

    return staged


def vgg_side(side: int) -> int | None:
    """The input ``nnfm_max_side`` (px; 0: full resolution) as FinetuneConfig takes it (None: full resolution);
    ValueError for a side too small for the VGG terms (1 to NNFM_MIN_SIDE - 1)."""
    if 0 < side < NNFM_MIN_SIDE:
        raise ValueError(f"expected 0 (full resolution) or at least {NNFM_MIN_SIDE} px, got {side}")
    return side or None


def _weight(default: float, tooltip: str) -> tuple:
    return ("FLOAT", {"default": default, "min": 0.0, "max": 1000.0, "step": 0.01, "tooltip": tooltip})


class FinetuneGaussians(ArtNVGNode):
    """Finetune the original Gaussians so their renders take on the style.

    With stylized views (in the cameras' order, e.g. from Sample Group) the loss is
    0.8 L1 + 0.2 (1 - SSIM) to them plus NNFM to the style image; without them it is the
    NNFM-only stylizer (plus a content term that keeps the scene recognisable).
    """

    DISPLAY_NAME = "Finetune Gaussians"
    FUNCTION = "finetune"
    RETURN_TYPES = (SCENE,)
    RETURN_NAMES = ("scene",)
    VALUE_CHECKS = {"nnfm_max_side": vgg_side}
    REQUIRED = {
        "scene": (SCENE,),
        "cameras": (CAMERAS, {"tooltip": (
            "Training views, rendered at their own size (e.g. from Render Views); with stylized_views, the cameras "
            "those views were made from (the Render Views that gave Sample Group its content views).")}),
        "style_image": STYLE_IMAGE_INPUT,
        "iterations": ("INT", {"default": _DEFAULTS.iterations, "min": 0, "max": 100000, "tooltip": (
            "Optimisation steps, one random view each (the paper uses 1,000).")}),
        "optimize": (OPTIMIZE_CHOICES, {"default": _DEFAULTS.optimize, "tooltip": (
            "appearance: colours and opacities only; all: geometry too.")}),
        "l1_weight": _weight(_DEFAULTS.l1_weight, "L1 to the stylized views (only with stylized_views)."),
        "ssim_weight": _weight(_DEFAULTS.ssim_weight, "1 - SSIM to the stylized views (only with stylized_views)."),
        "nnfm_weight": _weight(_DEFAULTS.nnfm_weight, "Nearest-neighbour VGG feature match to the style image."),
        "content_weight": _weight(_DEFAULTS.content_weight, (
            "VGG feature match to the original renders (only without stylized_views).")),
        "tv_weight": _weight(_DEFAULTS.tv_weight, "Total variation of the renders (smoothness)."),
        "seed": ("INT", {"default": _DEFAULTS.seed, "min": 0, "max": 2**31 - 1, "tooltip": "View order seed."}),
    }
    OPTIONAL = {
        "stylized_views": (IMAGE, {"tooltip": "Stylized views in the cameras' order; leave unconnected for NNFM only."}),
        "nnfm_max_side": ("INT", {"default": _DEFAULTS.nnfm_max_side, "min": 0, "max": 16384, "tooltip": (
            "Longest side (px) of the renders and style image the VGG terms see, shrunk to it as ARF does "
            "(512: ARF's half resolution for 1024 px views, a quarter of the features to match); 0: full resolution; "
            f"at least {NNFM_MIN_SIDE} otherwise.")}),
        "color_transfer": ("BOOLEAN", {"default": _DEFAULTS.color_transfer, "tooltip": (
            "Without stylized_views: match the scene's colours to the style image's mean and covariance "
            "before and after finetuning, as ARF does (exact, no extra iterations).")}),
        "preset": (PRESET_CHOICES, {"default": "custom", "tooltip": (
            f"preview: a first look in seconds (BENCHMARKS.md, First look): {_PREVIEW.finetune_words()}, in place of "
            "iterations, views_per_step and the views' size; custom: the inputs as set.")}),
        "views_per_step": ("INT", {"default": _DEFAULTS.views_per_step, "min": 1, "max": 64, "tooltip": (
            "Views rendered and compared per step, their losses averaged.")}),
        "nnfm_search": (SEARCH_PRECISIONS, {"default": _DEFAULTS.nnfm_search, "tooltip": (
            "Arithmetic of NNFM's nearest-neighbour search (the loss stays float32): bf16 is the fastest, "
            "fp32 the exact one (BENCHMARKS.md, NNFM search precision).")}),
        "selection": (SELECTION, {"tooltip": (
            "From Select Gaussians: finetune only these Gaussians, the loss weighted to the pixels they cover; "
            "the others stay exactly as they are.")}),
    }

    @cancellable
    def finetune(self, scene, cameras, style_image, iterations, optimize, l1_weight, ssim_weight, nnfm_weight,
                 content_weight, tv_weight, seed, stylized_views=None, nnfm_max_side=_DEFAULTS.nnfm_max_side,
                 color_transfer=_DEFAULTS.color_transfer, preset="custom", views_per_step=_DEFAULTS.views_per_step,
                 nnfm_search=_DEFAULTS.nnfm_search, selection=None, node_id=None):
        with node_input(self.DISPLAY_NAME, "style_image"):  # before any work
            check_style_size(style_image.shape[2], style_image.shape[1])
        if stylized_views is not None:
            with node_input(self.DISPLAY_NAME, "stylized_views"):
                check_stylized_views(stylized_views, len(cameras))
        with node_input(self.DISPLAY_NAME), autograd_enabled():
            config = FinetuneConfig(
                iterations=iterations, optimize=optimize, l1_weight=l1_weight, ssim_weight=ssim_weight,
                nnfm_weight=nnfm_weight, content_weight=content_weight, tv_weight=tv_weight, seed=seed,
                nnfm_max_side=vgg_side(nnfm_max_side), color_transfer=color_transfer, views_per_step=views_per_step,
                nnfm_search=nnfm_search,
            )
            if preset == "preview":
                chosen = PRESETS["preview"]
                cameras, config = cameras.scaled(chosen.scale), chosen.finetune_config(config)
            report, start = staged_progress(), time.monotonic()
            with render_device() as device:
                result = finetune(
                    trainable_copy(scene).to(device), trainable_copy(cameras), style_image[:1].clone(),
                    stylized=None if stylized_views is None else stylized_views.clone(), config=config,
                    progress=report, render_progress=report, should_stop=interrupt_requested,
                    selection=None if selection is None else selection.clone().to(device),
                )
        # in place of the last stage's name, which would stand under the node as if it were still at work
        progress_text(f"finished {counted(config.iterations, 'step')} in {time.monotonic() - start:.1f} s",
                      self.DISPLAY_NAME)
        return (result.to("cpu"),)
