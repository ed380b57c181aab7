"""Finetune a Gaussian scene's appearance toward stylized views and a style image.

Loss per step, for one randomly chosen view (ArtNVG, Sec. 3.4):

    l1_weight * L1(render, stylized) + ssim_weight * (1 - SSIM(render, stylized))   [when stylized views are given]
  + nnfm_weight * NNFM(VGG(render), VGG(style image))
  + content_weight * relative feature MSE(VGG(render), VGG(original render))     [ARF's content term]
  + tv_weight * total variation(render)                                          [when not]

Renders are clamped to [0, 1] before every term, as splatfacto does. The VGG terms (NNFM,
content) see the render shrunk to at most ``nnfm_max_side`` pixels on its long side: at
1024x1024 this is ARF's factor 0.5 and a quarter of the VGG and matching work of full
resolution. ARF halves every render; we keep the measured 512 px cap instead: ARF's size at
1024 px, 4x cheaper than ARF's half at 2048 px, and more pixels than ARF's half below 1024 px
(a 128 px render is kept whole; halved, it would leave relu3 maps of 16x16), which we have not
measured against ARF's half. The style image is sized as ARF sizes it relative to
the render: its long side equal to the long side of the render the VGG sees (ARF: the style's
long side set to the render's, then both halved). L1/SSIM stay at full resolution.

With no stylized views this is ARF's diffusion-free stylizer, by default with ARF's colour
transfer (:mod:`artnvg_core.finetune.color_transfer`): the scene's colours are first matched to the
style image's mean and covariance, exactly in the SH, the content term compares against the
recoloured views (clamped to [0, 1]), and the match is estimated and applied again to the
result. The original Gaussians are the starting point (not a fresh fit); no densification.

With a ``selection`` (a region, :mod:`artnvg_core.selection`) only the selected Gaussians are trained (the
others render with them, unchanged, and come back bit for bit), every term is weighted by the pixels they
cover (their share of each pixel's colour in the original's renders, :func:`~artnvg_core.selection.coverage`),
the views where they cover less than one pixel are left out, and the colour transfer is estimated on the
pixels they cover at least half of and applied to them alone.
"""

from __future__ import annotations

import dataclasses
import logging

import torch

from ..cameras import CameraSet, scene_frame
from ..counted import counted
from ..images import check_image_values, resize_image, same_aspect
from ..losses import NNFMLoss, convolution_precision, load_vgg, resize_long_side, style_image_features
from ..progress import ProgressFn, StopFn, check_stop, staged
from ..raster import choose_backend, triton_warmups
from ..raster.step_renderer import StepRenderer
from ..raster.views import render_views
from ..scene import GaussianScene
from .color_transfer import match_colors
from .config import FinetuneConfig
from .finite_steps import FiniteAdam
from .region import placed, recolor, region_pixels, region_views
from .step_loss import GRAPH_MIN_ITERATIONS, StepLoss, can_graph, graphed, nchw, vgg_input

APPEARANCE = ("sh", "opacity_logits")
REPORT_EVERY = 50  # steps between the loss values handed to ``progress`` (reading them waits for the device)
_log = logging.getLogger(__name__)


def _parameters(scene: GaussianScene, config: FinetuneConfig) -> dict[str, torch.Tensor]:
    """Trainable leaf copies of the scene's tensors (the input scene is not modified).

    SH is split into ``sh_dc`` [N, 1, 3] and ``sh_rest`` [N, K-1, 3] so that each
    gets its own learning rate.
    """
    params = {name: value.detach().clone() for name, value in scene.tensors().items() if name != "sh"}
    sh = scene.sh.detach().clone()
    if config.from_scratch:
        sh.zero_()  # grey everywhere: colour = SH_C0 * 0 + 0.5
    params["sh_dc"], params["sh_rest"] = sh[:, :1].contiguous(), sh[:, 1:].contiguous()
    trainable = ("sh_dc", "sh_rest", "opacity_logits")
    if config.optimize == "all":
        trainable += ("means", "log_scales", "quats")
    for name in trainable:
        params[name].requires_grad_(True)
    return params


def _scene_of(params: dict[str, torch.Tensor], like: GaussianScene, frozen: GaussianScene | None = None) -> GaussianScene:
    """The scene of ``params`` with the render settings (blur, antialiasing) of ``like``, followed by the
    ``frozen`` Gaussians when given."""
    rest = {k: v for k, v in params.items() if not k.startswith("sh_")}
    scene = dataclasses.replace(like, **rest, sh=torch.cat([params["sh_dc"], params["sh_rest"]], 1))
    if frozen is None:
        return scene
    return dataclasses.replace(scene, **{k: torch.cat([v, getattr(frozen, k)]) for k, v in scene.tensors().items()})


def camera_extent(cameras: CameraSet, scene: GaussianScene) -> float:
    """The scale of the means' learning rate, in world units: gsplat's scene scale, 1.1 x the
    largest distance of a camera centre from the centres' mean. With fewer than two distinct
    centres, 1.1 x the scene's robust radius (:func:`~artnvg_core.cameras.scene_frame`).
    Far floaters never enter it."""
    centers = cameras.centers.detach().cpu().to(torch.float64)
    extent = float((centers - centers.mean(0)).norm(dim=-1).max())
    if not extent > 1e-9 * (1 + float(centers.abs().max())):
        extent = scene_frame(scene, up="+z").radius
    return 1.1 * extent


def _optimizer(params: dict[str, torch.Tensor], scene: GaussianScene, cameras: CameraSet, config: FinetuneConfig,
               has_targets: bool, triton: bool) -> FiniteAdam:
    """Adam with per-parameter learning rates (see :class:`FinetuneConfig`), finite steps only; its Triton
    step where the views render with Triton (``triton``): a finetune told to render with another backend
    (e.g. on a machine where Triton cannot compile) keeps Adam's PyTorch step too."""
    extent = camera_extent(cameras, scene) if config.optimize == "all" else 1.0
    default_dc, default_rest = (0.0025, 0.0025 / 20) if has_targets else (0.03, 0.003)
    rates = {
        "sh_dc": default_dc if config.lr_sh_dc is None else config.lr_sh_dc,
        "sh_rest": default_rest if config.lr_sh_rest is None else config.lr_sh_rest,
        "opacity_logits": config.lr_opacity,
        "means": config.lr_means * max(extent, 1e-6),
        "log_scales": config.lr_scales,
        "quats": config.lr_quats,
    }
    return FiniteAdam(params, rates, "finetune", eps=1e-15, fused=None if triton else False)


def _vgg_style(style_image: torch.Tensor, cameras: CameraSet, config: FinetuneConfig) -> torch.Tensor:
    """[H, W, 3] style image -> [1, 3, h, w] with its long side that of the renders the VGG sees
    (area-averaged when shrinking, as ARF's ``INTER_AREA``; bilinear when enlarging)."""
    side = max(cameras.width, cameras.height)
    if config.nnfm_max_side is not None:
        side = min(side, config.nnfm_max_side)
    return resize_long_side(nchw(style_image[None]), side)


def _check_blind_views(blind: torch.Tensor, warned: set[int], cameras: CameraSet) -> None:
    """Warn once about each view found to see no Gaussian (``blind [C]``, on the device: how many steps
    each view saw none); ValueError once every view is such."""
    found = blind.nonzero()[:, 0].tolist()
    for view in sorted(set(found) - warned):
        _log.warning("finetune: view %d (%s) sees no Gaussian; its steps are skipped", view, cameras.names[view])
    warned.update(found)
    if len(warned) == len(cameras):
        raise ValueError(f"finetune: none of the {counted(len(cameras), 'camera')} sees any Gaussian; check that the "
                         "cameras and the scene share one coordinate frame")


def _render_views(scene: GaussianScene, cameras: CameraSet, config: FinetuneConfig, stage: str,
                  report: ProgressFn | None, should_stop: StopFn | None) -> torch.Tensor:
    """Every view of ``cameras`` [C, H, W, 3] clamped to [0, 1], :data:`~artnvg_core.raster.views.RENDER_CHUNK`
    views a render call (a call launches the same kernels for one view as for several), reporting the views
    done after each."""
    return render_views(scene, cameras, backend=config.backend, progress=staged(report, stage),
                        should_stop=should_stop).rgb


def compile_kernels(scene: GaussianScene, cameras: CameraSet, config: FinetuneConfig, targets: bool) -> None:
    """Start compiling, in the background, the Triton kernels that :func:`finetune` launches for ``scene`` and
    ``cameras`` (the renders' forward and backward, Adam's step and, with stylized ``targets``, the SSIM's)
    where it renders with Triton; the first render waits for them (:mod:`~artnvg_core.triton_runtime`).
    Nothing on other backends."""
    if choose_backend(config.backend, scene.device, scene.means.dtype) != "triton":
        return
    from ..losses.ssim_triton import warmups as ssim_warmups
    from ..triton_runtime import compile_in_background
    from .finite_steps_triton import warmups as adam_warmups

    warmups = [*triton_warmups(scene, cameras, gradients=True), *adam_warmups(scene.device)]
    if targets:
        warmups += ssim_warmups(scene.device, 3, cameras.height, cameras.width)
    compile_in_background(warmups, scene.device)


def finetune(
    scene: GaussianScene,
    cameras: CameraSet,
    style_image: torch.Tensor,
    *,
    stylized: torch.Tensor | None = None,
    config: FinetuneConfig | None = None,
    progress: ProgressFn | None = None,
    should_stop: StopFn | None = None,
    render_progress: ProgressFn | None = None,
    selection: torch.Tensor | None = None,
) -> GaussianScene:
    """Finetune ``scene`` so its renders from ``cameras`` take on the style.

    scene: the original Gaussians (not modified; a new scene is returned, detached; a float16 or bfloat16
        scene's float32 copy is trained and returned).
    cameras: C views, rendered at their own resolution (scale them beforehand).
    style_image: [H, W, 3] RGB in [0, 1] (ComfyUI IMAGE layout, or [1, H, W, 3]).
    stylized: optional [C, H', W', 3] stylized views in camera order, floats in [0, 1] of the cameras' aspect,
        resized to the camera size when they differ; None runs the NNFM-only stylizer.
    progress(step, total, info): called with step 0 and ``info`` {} as the steps start (a step takes seconds
        at a capture's size on a CPU: a bar shows from the start), then after every step with the step's view
        (``view``, or ``views`` with several per step); at the first, every ``REPORT_EVERY``-th and the last step ``info`` also
        holds the loss terms as floats (reading them waits for the device, so not every step).
        should_stop(): checked before every step and within it (the render, the VGG's convolutions, NNFM's
        search and the backward pass through them); when it returns True,
        :class:`~artnvg_core.progress.Cancelled` is raised.
    render_progress(done, views, info): follows the work on every view before the steps (``info["stage"]``:
        ``"region"``, a selection's coverage; ``"setup"``: the renders for the colour transfer and the content
        term; ``"features"``: the content term's VGG features of those renders) and after them (``"final"``:
        the renders for the colour transfer), as each starts and after each render call (a few views) or
        view's features; ``should_stop`` can also end them.
    selection: optional [N] bool on the scene's device: finetune these Gaussians only, for the pixels they
        cover (module docstring).
    No step writes a non-finite value (:mod:`artnvg_core.finetune.finite_steps`): a step with a
    non-finite loss is skipped, Gaussians with non-finite gradients keep their last finite
    values, and both are logged with the step and the Gaussians' indices; so is a view that sees no
    Gaussian (a step none of whose views sees one is skipped). None of these checks waits for the
    device: they are read at the steps the loss values are.
    Deterministic for ``config.seed`` on CPU.
    """
    config = config or FinetuneConfig()
    with convolution_precision(config.vgg_precision, scene.device):
        return _finetune(scene, cameras, style_image, stylized, config, progress, should_stop, render_progress,
                         selection)


def check_stylized_views(stylized: torch.Tensor, count: int) -> None:
    """ValueError (naming the shape, not the input: the caller names it) unless ``stylized`` is [count, H, W, 3]:
    one view per camera of ``count``, in the cameras' order."""
    if stylized.ndim != 4 or stylized.shape[0] != count or stylized.shape[-1] != 3:
        raise ValueError(f"got {tuple(stylized.shape)} for {counted(count, 'camera')}; expected [{count}, H, W, 3], "
                         "one view per camera in the cameras' order (give the cameras the views were rendered from)")


def _finetune(scene: GaussianScene, cameras: CameraSet, style_image: torch.Tensor, stylized: torch.Tensor | None,
              config: FinetuneConfig, progress: ProgressFn | None, should_stop: StopFn | None,
              render_progress: ProgressFn | None, selection: torch.Tensor | None) -> GaussianScene:
    """:func:`finetune` with its config given, inside its convolutions' precision."""
    if style_image.ndim == 4 and style_image.shape[0] == 1:
        style_image = style_image[0]
    if style_image.ndim != 3 or style_image.shape[-1] != 3:
        raise ValueError(f"finetune: style_image must be [H, W, 3], got {tuple(style_image.shape)}")
    check_image_values(style_image, "finetune: style_image")
    if len(cameras) == 0:
        raise ValueError("finetune: cameras is empty")
    scene, device = scene.widened(), scene.device
    cameras = cameras.to(device)
    if stylized is not None:
        try:
            check_stylized_views(stylized, len(cameras))
        except ValueError as error:
            raise ValueError(f"finetune: stylized: {error}") from None
        check_image_values(stylized, "finetune: stylized")
        if not same_aspect(stylized.shape[2], stylized.shape[1], cameras.width, cameras.height):
            raise ValueError(f"finetune: stylized: views of {stylized.shape[2]}x{stylized.shape[1]} pixels, not the aspect "
                             f"of the cameras' {cameras.width}x{cameras.height} (they would be stretched)")
        stylized = resize_image(stylized.to(device, torch.float32), cameras.height, cameras.width).clamp(0, 1)
    weights = None
    if selection is not None:
        selection = selection.to(device)
        cameras, stylized, weights = region_views(scene, selection, cameras, stylized, config.backend,
                                                  staged(render_progress, "region"), should_stop)
    compile_kernels(scene, cameras, config, stylized is not None)  # beside the VGG and the style's features

    vgg = load_vgg(config.vgg, config.vgg_weights, device)
    layers = config.nnfm_layers
    style_image = style_image.to(device, torch.float32)
    style_feats = style_image_features(vgg, _vgg_style(style_image, cameras, config), layers, None)
    nnfm = NNFMLoss(style_feats, layer_groups=(layers,), precision=config.nnfm_search)

    color_transfer = stylized is None and config.color_transfer
    originals = None
    if color_transfer or (stylized is None and config.content_weight > 0):
        content = _render_views(scene, cameras, config, "setup", render_progress, should_stop)
        if color_transfer:
            transform = match_colors(region_pixels(content, weights), style_image)
            scene = recolor(scene, transform, selection)
            content = transform.apply(content).clamp(0, 1)  # ARF's recoloured training views
        if config.content_weight > 0:
            originals = vgg_input(content, config)
        del content
    step_loss = StepLoss(config, vgg, nnfm, stylized, originals, weights, staged(render_progress, "features"),
                         should_stop)
    names = step_loss.names
    worth_graphing = config.iterations >= GRAPH_MIN_ITERATIONS if config.cuda_graph is None else config.cuda_graph
    if worth_graphing and can_graph(device):
        step_loss = graphed(step_loss, (config.views_per_step, cameras.height, cameras.width, 3), device)
    # checks the inputs: a bad scene fails before any step
    renderer = StepRenderer(scene, cameras, config.backend, should_stop)
    frozen = None if selection is None else scene.select(~selection)
    params = _parameters(scene if selection is None else scene.select(selection), config)
    adam = _optimizer(params, scene, cameras, config, stylized is not None, renderer.backend == "triton")
    generator = torch.Generator().manual_seed(config.seed)
    # every step's views drawn up front and copied to the device once: a copy per step would wait for it
    schedule = torch.randint(len(cameras), (config.iterations, config.views_per_step), generator=generator)
    schedule_on_device = schedule.to(device)
    blind = torch.zeros(len(cameras), dtype=torch.int32, device=device)  # steps each view saw no Gaussian
    warned: set[int] = set()
    if progress is not None and config.iterations:
        progress(0, config.iterations, {})
    step = 1
    while step <= config.iterations:
        check_stop(should_stop)
        views, views_on_device = schedule[step - 1].tolist(), schedule_on_device[step - 1]
        out, incomplete = renderer.render(_scene_of(params, scene, frozen), views, views_on_device)
        sees = out.alpha.flatten(1).amax(1) > 0  # [B]: a view no Gaussian reaches teaches nothing
        skip = ~sees.any() if incomplete is None else ~sees.any() | incomplete
        loss, values = step_loss(out.rgb.clamp(0, 1), views_on_device)
        terms = dict(zip(names, values.unbind()))
        loss.backward()
        adam.step(step, loss, terms, skip=skip)
        if renderer.redo():
            continue  # the render was incomplete: the step was skipped on the device; again
        blind.index_add_(0, views_on_device, (~sees).int())
        info: dict = {"view": views[0]} if len(views) == 1 else {"views": tuple(views)}
        if step == 1 or step % REPORT_EVERY == 0 or step == config.iterations:
            adam.report()
            _check_blind_views(blind, warned, cameras)
            info.update(loss=loss.item(), **{k: v.item() for k, v in terms.items()})
        if progress is not None:
            progress(step, config.iterations, info)
        step += 1
    adam.summary()
    result = _scene_of({k: v.detach() for k, v in params.items()}, scene)
    if selection is not None:  # the trained Gaussians back in their places among the others
        result = dataclasses.replace(scene, **{k: placed(getattr(scene, k), v, selection)
                                               for k, v in result.tensors().items()})
    if color_transfer:  # ARF's post-transform: the stylized renders' colours matched to the style again
        renders = _render_views(result, cameras, config, "final", render_progress, should_stop)
        result = recolor(result, match_colors(region_pixels(renders, weights), style_image), selection)
    return result
