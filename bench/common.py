"""Shared helpers for the benchmarks: timing, memory, warp error, random scenes and cameras."""

from __future__ import annotations

import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from artnvg_core.cameras import CameraSet, look_at  # noqa: E402
from artnvg_core.metrics.warp import warp_consistency  # noqa: E402
from artnvg_core.scene import GaussianScene  # noqa: E402


def synchronize(device: torch.device) -> None:
    """Wait for ``device``'s queued work (CUDA); nothing elsewhere."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed_call(device: torch.device, run):
    """(result, seconds) of one synchronised call of ``run``."""
    synchronize(device)
    begin = time.perf_counter()
    result = run()
    synchronize(device)
    return result, time.perf_counter() - begin


def warp_rmse(images: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, cameras: CameraSet,
              step: int = 1) -> float:
    """Warp RMSE (:func:`~artnvg_core.metrics.warp.warp_consistency`) of IMAGE ``images`` [C, H, W, 3]
    between views ``step`` apart, with the original scene's ``depth`` and ``alpha`` [C, H, W, 1]
    (moved to the images' device)."""
    return warp_consistency(images, depth.to(images.device), alpha.to(images.device), cameras, step=step).rmse


def finetune_render(scene: GaussianScene, camera: CameraSet):
    """A render closure (a scene of ``scene``'s size -> rgb) on the Triton backend as the finetune's steps
    call it (:class:`~artnvg_core.raster.step_renderer.StepRenderer`): the inputs checked once, here, and the
    tile lists given room from earlier counts instead of waiting for their own: nothing waits for the GPU."""
    from artnvg_core.raster.step_renderer import StepRenderer

    renderer = StepRenderer(scene, camera, "triton")
    return lambda scene: renderer.render(scene, [0])[0].rgb


def timed(fn, device: torch.device, repeats: int = 5, warmup: int = 2) -> float:
    """Median seconds of ``fn()`` after ``warmup`` untimed calls: CUDA events on a GPU, perf_counter on the CPU."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            torch.cuda.synchronize(device)
            times.append(start.elapsed_time(end) / 1000)
        else:
            begin = time.perf_counter()
            fn()
            times.append(time.perf_counter() - begin)
    return statistics.median(times)


def peak_memory(fn, device: torch.device, *, absolute: bool = False) -> float:
    """Peak CUDA memory in GiB while ``fn()`` runs: above what was allocated before it, or the
    whole allocation with ``absolute`` (nan on the CPU, where ``fn`` still runs)."""
    if device.type != "cuda":
        fn()
        return float("nan")
    torch.cuda.synchronize(device)
    torch.cuda.reset_peak_memory_stats(device)
    base = 0 if absolute else torch.cuda.memory_allocated(device)
    fn()
    torch.cuda.synchronize(device)
    return (torch.cuda.max_memory_allocated(device) - base) / 2**30


def random_scene(n: int, *, seed: int = 0, degree: int = 3, device="cpu") -> GaussianScene:
    """``n`` random Gaussians in a unit-radius ball, sized so that the ball is about covered."""
    g = torch.Generator().manual_seed(seed)
    radius = torch.rand(n, 1, generator=g) ** (1 / 3)
    means = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * radius
    mean_scale = 1.5 / n ** (1 / 3)
    return GaussianScene(
        means=means,
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.log(mean_scale * torch.exp(0.5 * torch.randn(n, 3, generator=g))),
        opacity_logits=torch.randn(n, generator=g),
        sh=0.3 * torch.randn(n, (degree + 1) ** 2, 3, generator=g),
    ).to(device)


def orbit_cameras(count: int, size: int, distance: float = 3.0, fov_deg: float = 50.0) -> CameraSet:
    """``count`` cameras on a circle of radius ``distance`` looking at the origin, ``size`` x ``size`` px."""
    angles = torch.arange(count, dtype=torch.float64) * (2 * math.pi / max(count, 1))
    eyes = torch.stack([distance * torch.sin(angles), -0.5 * torch.ones_like(angles), -distance * torch.cos(angles)], -1)
    w2c = look_at(eyes, torch.zeros(count, 3, dtype=torch.float64), torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
    focal = 0.5 * size / math.tan(math.radians(fov_deg) / 2)
    k = torch.tensor([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1]], dtype=torch.float32).expand(count, 3, 3)
    return CameraSet(w2c.float(), k.clone(), size, size, [f"orbit_{i:03d}" for i in range(count)])


def psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    """PSNR in dB between images ``a`` and ``b`` of values in [0, 1] (float64 mean; equal images: 300 dB)."""
    return float(-10 * torch.log10((a - b).double().square().mean().clamp_min(1e-30)))


def print_table(title: str, header: list[str], rows: list[list], command: str) -> None:
    """A Markdown table with the command that produced it."""
    print(f"\n### {title}\n\n`{command}`\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        print("| " + " | ".join("" if v is None else (f"{v:.4g}" if isinstance(v, float) else str(v)) for v in row) + " |")
