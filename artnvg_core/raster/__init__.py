"""Differentiable Gaussian rasterization: :func:`render`, and :func:`prepare_backend` to load a backend
before the first render (announcing gsplat's first-use kernel build). :mod:`.views` renders every view
of a camera set in chunks (``render_views``); :mod:`.step_renderer` renders a loop's steps without waiting
for the device (``StepRenderer``, the finetune's).

``torch`` (the reference, any device and dtype) and ``gsplat`` share the projection
(:mod:`.projection`) and colours (:mod:`.sh`) and differ in the per-pixel compositing; ``triton``
(Triton kernels, float32 CUDA, the default there) computes both in one fused kernel
(:mod:`.triton_projection`) and composites with :mod:`.triton_backend` over :mod:`.triton_tiles`' lists; ``gsplat`` (gsplat's CUDA kernels,
optional: ``pip install ".[gsplat]"``; :mod:`.gsplat_backend`)."""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import torch
from torch.utils.weak import WeakIdKeyDictionary

from ..cameras import CameraSet
from ..counted import counted
from ..devices import available_memory, triton_available
from ..progress import StopFn, check_stop
from ..scene import GaussianScene
from .gsplat_backend import gsplat_available, load_kernels, rasterize_gsplat
from .projection import project
from .sh import sh_to_color
from .torch_backend import rasterize

if TYPE_CHECKING:
    from .triton_tiles import ListCapacity

BACKENDS = ("auto", "torch", "triton", "gsplat")


@dataclass
class RenderOutput:
    """Rendered views. rgb [C, H, W, 3] (not clamped to 1), alpha [C, H, W, 1],
    depth [C, H, W, 1] camera-space z (expected depth normalised by alpha,
    0 where nothing is hit) or None when not asked for."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor | None


def _triton_runs(device: torch.device, dtype: torch.dtype) -> bool:
    """Triton can composite float32 tensors on ``device``: CUDA, or the CPU in Triton's interpreter."""
    if dtype != torch.float32 or not triton_available():
        return False
    return device.type == "cuda" or (device.type == "cpu" and os.environ.get("TRITON_INTERPRET", "0") == "1")


def choose_backend(backend: str, device: torch.device, dtype: torch.dtype = torch.float32) -> str:
    """Resolve ``auto`` to ``triton`` for float32 CUDA tensors when Triton imports, else ``torch``."""
    if backend not in BACKENDS:
        raise ValueError(f"render: backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "gsplat" and (device.type != "cuda" or dtype != torch.float32 or not gsplat_available()):
        raise ValueError("render: backend 'gsplat' needs float32 CUDA tensors and the gsplat package "
                         '(pip install gsplat, or ".[gsplat]")')
    if backend == "triton" and not _triton_runs(device, dtype):
        raise ValueError("render: backend 'triton' needs float32 CUDA tensors (or TRITON_INTERPRET=1 on the CPU) "
                         "and the triton package (it comes with torch's CUDA builds)")
    if backend == "auto":
        return "triton" if device.type == "cuda" and _triton_runs(device, dtype) else "torch"
    return backend


def prepare_backend(device: torch.device | str, backend: str = "auto",
                    announce: Callable[[str], None] | None = None) -> str:
    """Resolve ``backend`` for float32 scenes on ``device`` and load what it needs before the first
    render, so that gsplat's first-use kernel build (minutes; BENCHMARKS.md, "First look") is
    announced through ``announce`` where the caller's user looks, before it starts. Returns the
    backend. Without this, the first gsplat render announces it as a logged warning. Triton
    compiles its kernels at their first launch in a process that finds no cached build (seconds,
    see docs/cuda_run.md), unless its caller has them compiled in the background first (:func:`triton_warmups`;
    the finetune does); here it is imported, and the hashing of its own files that its first kernel
    waits for begins in the background (:mod:`~artnvg_core.triton_runtime`)."""
    name = choose_backend(backend, torch.device(device))
    if name == "gsplat":
        load_kernels(announce)
    elif name == "triton":
        from . import triton_backend  # noqa: F401  (import errors surface before the first render)
        from ..triton_runtime import hash_triton_in_background

        hash_triton_in_background()
    return name


def triton_warmups(scene: GaussianScene, cameras: CameraSet, *, sh_degree: int | None = None,
                   return_depth: bool = False, gradients: bool = False) -> list:
    """The Triton kernels' launches :func:`render` makes on the Triton backend for ``scene`` seen by ``cameras``
    (``sh_degree``, ``return_depth`` as it takes them; with ``gradients``: its backward's too), as
    :class:`~artnvg_core.triton_runtime.Warmup` (for :func:`~artnvg_core.triton_runtime.compile_in_background`).
    Imports Triton."""
    from . import triton_backend, triton_projection

    degree = scene.sh_degree if sh_degree is None else sh_degree
    width, height = cameras.width, cameras.height
    return [*triton_projection.warmups(scene.device, scene.sh.shape[1], width, height, degree, bool(scene.antialiased),
                                       gradients),
            *triton_backend.warmups(scene.device, 4 if return_depth else 3, width, height, gradients)]


# Bytes a pixel takes: an image kept (float32 RGB, ComfyUI's IMAGE), and the view being rendered: its
# outputs, the compositing's buffers and the reference rasterizer's tile lists (measured: one 8192x8192 view
# of a 100,000-Gaussian capture, the test data's bear, peaked at 11.2 GB on the CPU, about 165 bytes a
# pixel; a scene whose Gaussians cover more tiles needs more).
KEPT_BYTES_PER_PIXEL = 12
RENDERING_BYTES_PER_PIXEL = 165


def check_render_plan(views: int, width: int, height: int, *, kept: int | None = None, what: str = "") -> None:
    """Before any work: a ValueError naming ``what`` (the inputs that chose the plan; '': none) when rendering ``views``
    views of ``width`` x ``height`` pixels, ``kept`` of whose images are held at once (default: all, as the render
    nodes return them; 1 where each is written as it is done), needs more than half the main memory available
    (:func:`~artnvg_core.devices.available_memory`; no check where the system does not say)."""
    kept = views if kept is None else min(kept, views)
    needed = width * height * (kept * KEPT_BYTES_PER_PIXEL + RENDERING_BYTES_PER_PIXEL)
    available = available_memory()
    if available is not None and needed > available // 2:
        held = "all their images held at once" if kept == views else f"{kept} of their images held at once"
        raise ValueError(f"{what + ': ' if what else ''}{counted(views, 'view')} of {width}x{height} pixels, {held}, "
                         f"need {needed / 2**30:.1f} GiB, "
                         f"more than half the {available / 2**30:.1f} GiB of memory available now; render fewer "
                         "views or at a smaller scale")


# tensors whose values passed render's checks -> their version then (``Tensor._version`` counts in-place changes)
_PASSED = WeakIdKeyDictionary()


def _positive_focals(intrinsics: torch.Tensor) -> torch.Tensor:
    return intrinsics[:, [0, 1], [0, 1]] > 0


_PINHOLE_ZEROS = torch.tensor([[0, 1, 0], [1, 0, 0], [1, 1, 0]], dtype=torch.bool)  # K's entries that must be 0


def _pinhole(intrinsics: torch.Tensor) -> torch.Tensor:
    """Whether each K has no skew and a last row [0, 0, 1] (the entries the projection does not read)."""
    zeros = _PINHOLE_ZEROS.to(intrinsics.device)
    return (intrinsics[:, zeros] == 0).all(1) & (intrinsics[:, 2, 2] == 1)


def check_render_inputs(scene: GaussianScene, cameras: CameraSet, sh_degree: int | None = None,
                        background: torch.Tensor | None = None, near_plane: float = 0.01) -> None:
    """What :func:`render` checks before it renders (ValueError otherwise): the SH degree, the near plane a
    finite number >= 0, the scene's tensors finite (their one dtype and device: :class:`~artnvg_core.scene.GaussianScene`'s
    own check), finite camera poses and pinhole intrinsics with positive focal lengths, the background's shape and
    finite values. The value checks are reduced on the device and read back together: one
    wait for the device (one per device where the cameras live elsewhere). A tensor that passed them is
    not checked again until it is changed in place (its version counter moves; writes that bypass it,
    through ``.data`` or shared memory, go unseen): a scene rendered view after view waits once. Inference
    tensors (made under ``torch.inference_mode``, as ComfyUI runs its nodes) keep no such counter and are
    checked at every render."""
    sh_degree = scene.sh_degree if sh_degree is None else sh_degree
    if isinstance(sh_degree, bool) or not (isinstance(sh_degree, int) and 0 <= sh_degree <= scene.sh_degree):
        raise ValueError(f"render: sh_degree must be an int in 0..{scene.sh_degree} for this scene, got {sh_degree!r}")
    if not (isinstance(near_plane, (int, float)) and math.isfinite(near_plane) and near_plane >= 0):
        raise ValueError(f"render: near_plane must be a finite number >= 0, got {near_plane!r}")
    if background is not None and tuple(background.shape) not in ((3,), (len(cameras), 3)):
        raise ValueError(f"render: background must have shape (3,) or ({len(cameras)}, 3), got {tuple(background.shape)}")
    tests = []  # (message if false, tensor, test), in the order they are reported
    for name, value in scene.tensors().items():
        tests.append((f"render: scene.{name} has non-finite values", value, torch.isfinite))
    tests += [("render: cameras have non-finite poses or intrinsics", cameras.world_to_cam, torch.isfinite),
              ("render: cameras have non-finite poses or intrinsics", cameras.intrinsics, torch.isfinite),
              ("render: cameras.intrinsics must have positive focal lengths fx, fy", cameras.intrinsics,
               _positive_focals),
              ("render: cameras.intrinsics must be pinhole matrices [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)",
               cameras.intrinsics, _pinhole)]
    if background is not None:
        tests.append(("render: background has non-finite values", background, torch.isfinite))
    checks = [(message, tensor, test(tensor).all()) for message, tensor, test in tests
              if tensor.is_inference() or _PASSED.get(tensor) != tensor._version]
    passed = [True] * len(checks)
    for device in {flag.device for _, _, flag in checks}:
        where = [i for i, (_, _, flag) in enumerate(checks) if flag.device == device]
        for i, ok in zip(where, torch.stack([checks[i][2] for i in where]).tolist()):
            passed[i] = ok
    for (message, _, _), ok in zip(checks, passed):
        if not ok:
            raise ValueError(message)
    for _, tensor, _ in checks:
        if not tensor.is_inference():  # made under torch.inference_mode (as ComfyUI runs nodes): no counter
            _PASSED[tensor] = tensor._version


def render(
    scene: GaussianScene,
    cameras: CameraSet,
    *,
    sh_degree: int | None = None,
    background: torch.Tensor | None = None,
    return_depth: bool = False,
    backend: str = "auto",
    near_plane: float = 0.01,
    checked: bool = False,
    list_capacity: ListCapacity | None = None,
    should_stop: StopFn | None = None,
) -> RenderOutput:
    """Render ``scene`` from every camera of ``cameras``.

    scene: GaussianScene (tensors may require grad; rendering is differentiable
        in means, quats, log_scales, opacity_logits and sh). A float16 or bfloat16 scene renders as
        its float32 copy (their ranges and precision cannot hold the projection's and compositing's values),
        to float32 images.
    cameras: CameraSet, OpenCV world-to-camera [C, 4, 4], K [C, 3, 3] in
        pixels, pixel centres at +0.5; taken to the scene's device and dtype (a float64 scene, the
        reference's oracle, renders from the float32 cameras a loader gives).
    sh_degree: SH degree to evaluate (default: the scene's); at most the scene's.
    background: [3] or [C, 3] colour composited behind the Gaussians (default black).
    return_depth: also return expected camera-space depth.
    backend: "torch" (reference, CPU/CUDA), "triton" (float32 CUDA), "gsplat" (float32 CUDA,
        optional package) or "auto" (triton for float32 CUDA tensors when Triton imports, else
        torch). All give the reference's projection and colours (triton from one fused kernel,
        :mod:`.triton_projection`) and differ in the per-pixel compositing (the reference's PyTorch
        tiles, :mod:`.triton_backend`'s kernels or gsplat's, see :mod:`.gsplat_backend`).
    near_plane: Gaussians with camera-space z <= near_plane (a finite number >= 0) are culled.
    checked: the caller has checked these inputs (:func:`check_render_inputs`) and keeps them valid, so
        the checks, which wait for the device where the inputs are new or changed, are skipped
        (:class:`.step_renderer.StepRenderer`, whose optimiser changes the scene at every step, does so), and so
        is the memory check of a CPU render (:func:`check_render_plan`: views that need more than half the
        memory available are a ValueError, where the process would be killed for memory).
    list_capacity: the Triton backend's :class:`.triton_tiles.ListCapacity` shared by renders made one
        after another, so that they do not wait for their tile intersection counts (ignored by the other
        backends); the caller checks it after each render for one that overflowed and must be redone
        (:class:`.step_renderer.StepRenderer` does so).
    should_stop: asked before each view and, on the reference backend, between its batches of tiles, in the
        backward pass of a render with gradients too; raises :class:`~artnvg_core.progress.Cancelled` when it says
        so (a huge view stops within a second or so).

    Semantics are gsplat's "classic" mode: EWA projection with a 0.3 px^2
    low-pass (``scene.blur_px2``; with ``scene.antialiased`` the opacity is
    compensated as gsplat's "antialiased" mode does), alpha = min(0.999, o * exp(-d^T Sigma^-1 d / 2)), samples with
    alpha < 1/255 skipped, front-to-back compositing in depth order stopping
    at transmittance 1e-4. Colour = max(SH(dir) + 0.5, 0), dir from the
    camera centre to the Gaussian. Any finite parameters give finite images and
    gradients, on every backend: unnormalised quaternions of any norm,
    log-scales up to the float32 limit, SH up to 3e38 (colours are capped where
    a pixel is already >= 1, see :mod:`.sh`). A render that shows nothing back-propagates
    zero gradients. Returns a :class:`RenderOutput`, of no views for cameras of none.
    """
    degree = scene.sh_degree if sh_degree is None else sh_degree
    if not checked:
        check_render_inputs(scene, cameras, degree, background, near_plane)
        if scene.device.type == "cpu":  # beyond main memory the process is killed; a device says so itself
            check_render_plan(len(cameras), cameras.width, cameras.height, what="render")
    scene = scene.widened()
    cameras = cameras.to(scene.device, scene.means.dtype)
    if background is not None:
        background = background.to(scene.means).expand(len(cameras), 3)
    composite = functools.partial(rasterize, should_stop=should_stop)
    name = choose_backend(backend, scene.device, scene.means.dtype)
    if name == "gsplat":
        load_kernels()
        composite = rasterize_gsplat
    elif name == "triton":
        from .triton_backend import rasterize_triton  # imports Triton: only when it renders
        from .triton_projection import project_color_triton
        from ..triton_runtime import wait_for_compilation

        wait_for_compilation()  # the kernels compiling in the background, if any: not compiled twice
        composite = functools.partial(rasterize_triton, capacity=list_capacity)
    width, height, centers = cameras.width, cameras.height, cameras.centers
    if len(cameras) == 0:
        empty = [scene.means.new_zeros(0, height, width, channels) for channels in (3, 1, 1)]
        return RenderOutput(*empty[:2], empty[2] if return_depth else None)
    rgbs, alphas, depths = [], [], []
    for c in range(len(cameras)):
        check_stop(should_stop)
        w2c, k, center = cameras.world_to_cam[c], cameras.intrinsics[c], centers[c]
        if name == "triton":  # one fused kernel; culled Gaussians stay, with no tiles
            proj, colors = project_color_triton(scene.means, scene.quats, scene.log_scales, scene.opacity_logits,
                                                scene.sh, w2c, k, center, width, height, degree, near_plane,
                                                scene.blur_px2, scene.antialiased)
        else:
            proj = project(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, w2c, k, width, height,
                           near_plane, scene.blur_px2, scene.antialiased)
            colors = sh_to_color(scene.sh.index_select(0, proj.index),
                                 scene.means.index_select(0, proj.index) - center, degree)
        features = torch.cat([colors, proj.depths[:, None]], -1) if return_depth else colors
        # nothing projected: the reference's empty image (kept in the autograd graph), for either backend
        blended, trans = (composite if len(proj.index) else rasterize)(proj, features, width, height)
        rgb = blended[..., :3]
        if background is not None:
            rgb = rgb + trans[..., None] * background[c]
        alpha = 1 - trans
        rgbs.append(rgb)
        alphas.append(alpha[..., None])
        if return_depth:
            depths.append(torch.where(alpha > 0, blended[..., 3] / alpha.clamp_min(1e-10), torch.zeros_like(alpha))[..., None])
    return RenderOutput(_batch(rgbs), _batch(alphas), _batch(depths) if return_depth else None)


def _batch(images: list[torch.Tensor]) -> torch.Tensor:
    """The views' images as one contiguous [C, ...] tensor (one view's without a copy where it is contiguous)."""
    return images[0].unsqueeze(0).contiguous() if len(images) == 1 else torch.stack(images)
