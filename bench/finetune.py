"""Finetune benchmark: time per iteration of the Gaussian finetuning loop.

    cd bench && python finetune.py [--device cpu|cuda] [--iters N] [--shared ../../shared/data]
        [--cases demo,bear,random] [--searches fp32,tf32,bf16] [--adams fused,torch] [--vggs fp32,tf32,bf16]
        [--graphs on,off] [--profile]
    cd bench && python finetune.py --vgg-variants [--device cpu|cuda]
    cd bench && python finetune.py --parts [--device cpu|cuda]

Cases: the bundled demo scene (128x128); on CUDA also the bear scene at 512x512 and 1024x1024
(cameras scaled x2; when ``--shared`` holds it) and a random 1M-Gaussian scene at 1024x1024, with
each available backend (the reference torch backend on the CPU; triton and gsplat on CUDA), without
stylized views (NNFM + content term, the NNFM-only stylizer) and with random ones (L1 + SSIM + NNFM,
the ArtNVG finetune), the VGG terms at ARF's resolution (the default ``nnfm_max_side`` 512) and, at
1024, at full resolution; the first backend's rows with each ``--searches`` precision of the NNFM
match search, each ``--vggs`` precision of the VGG terms' convolutions (``FinetuneConfig.vgg_precision``),
with the step's loss replayed as CUDA graphs or run eagerly (``--graphs``, ``FinetuneConfig.cuda_graph``)
(the others with the defaults); and the NNFM term alone (VGG forward+backward +
matching) per size and search precision, its input a permuted [1, H, W, 3] image as the finetune's
renders come (channels-last activations; until ``--vgg-variants`` came, a contiguous [1, 3, H, W]
one). The first backend's rows at 512 with the default search also run with each ``--adams`` step
of :class:`~artnvg_core.finetune.finite_steps.FiniteAdam` (``fused``: its Triton kernels, the default where
the finetune renders with Triton; ``torch``: its PyTorch step).
The style image is the demo style resized (area / bilinear) to half the render's long side, as ARF sizes it. Time per
iteration: the wall time of the iterations after 3 warm-up steps, the device waited for once at each
end, divided by their number (the loop itself never waits for the device: the CPU queues step k+1
while the GPU runs step k).

``--vgg-variants``: instead, the NNFM term alone (VGG19 relu3 forward+backward + matching) with the
convolutions' arithmetic and memory layout varied (:data:`VGG_VARIANTS`), each timed and compared
with the float32 run (no TF32 anywhere, float32 search) on the same image and style: relative error of
the loss and relative L2 error of the image's gradient.

``--parts``: instead, two parts of a step alone, each fast path beside its reference on the same inputs:
SSIM (forward+backward of a [1, 3, H, W] render in the finetune's layout against a target) by
:func:`~artnvg_core.losses.ssim.separable_ssim` (PyTorch; cuDNN's grouped convolutions on CUDA) and by
the fused Triton kernels (CUDA; the default there), with the fused one's deviation (value, gradient's relative
L2); and NNFM's match search (:func:`~artnvg_core.losses.nearest_style_indices`, TF32, the VGG19 relu3
features of the demo style and a noisy copy at the size) with several ``max_chunk_elements``, the matches
compared with one chunk's.

``--profile`` (CUDA): instead, where an iteration of the first case goes, with and without stylized
targets: the GPU kernels' time per iteration against the wall time, the 25 costliest kernels and the
15 costliest host calls (torch.profiler over 20 iterations; its totals include the renders of every
view before and after the steps).
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import itertools
import sys
import time
from pathlib import Path

import torch

from common import orbit_cameras, print_table, random_scene, synchronize, timed

import artnvg_core.finetune.loop as finetune_module
from artnvg_core.cameras import load_cameras
from artnvg_core.finetune import FinetuneConfig, finetune
from artnvg_core.finetune.finite_steps import FiniteAdam
from artnvg_core.formats import read_ply
from artnvg_core.images import load_image, resize_image
from artnvg_core.losses import (
    SEARCH_PRECISIONS,
    VGG_PRECISIONS,
    NNFMLoss,
    convolution_precision,
    features_autocast,
    load_vgg,
    nearest_style_indices,
    normalize_features,
    style_image_features,
)
from artnvg_core.losses.ssim import C1, C2, separable_ssim, window_on
from artnvg_core.raster import triton_available
from artnvg_core.raster.gsplat_backend import gsplat_available
from artnvg_core.stylize import DemoInputs


def seconds_per_iteration(scene, cameras, style, config: FinetuneConfig, targets: bool, device) -> float:
    stamps = {}
    stylized = torch.rand(len(cameras), cameras.height, cameras.width, 3, device=device) if targets else None
    total = config.iterations + 3

    def stamp(step, *_):
        if step in (3, total):
            synchronize(device)
            stamps[step] = time.perf_counter()

    finetune(scene, cameras, style, stylized=stylized, config=dataclasses.replace(config, iterations=total),
             progress=stamp)
    return (stamps[total] - stamps[3]) / config.iterations


@contextlib.contextmanager
def adam_step(kind: str):
    """The finetune's FiniteAdam with its ``fused`` (Triton) or ``torch`` step within the block."""
    fused = kind == "fused"
    finetune_module.FiniteAdam = lambda *args, **kwargs: FiniteAdam(*args, **{**kwargs, "fused": fused})
    try:
        yield
    finally:
        finetune_module.FiniteAdam = FiniteAdam


def profile_rows(scene, cameras, style, device, iterations=20) -> None:
    """Print where a finetune iteration goes (see the module's ``--profile``)."""
    from torch.profiler import ProfilerActivity, profile

    for targets in (False, True):
        stylized = torch.rand(len(cameras), cameras.height, cameras.width, 3, device=device) if targets else None
        config = FinetuneConfig(iterations=iterations + 3)
        wall = seconds_per_iteration(scene, cameras, style, dataclasses.replace(config, iterations=iterations),
                                     targets, device)
        profiler = profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA])

        def steps_only(step, *_):  # the profile holds the last ``iterations`` steps, nothing before or after
            if step in (3, config.iterations):
                synchronize(device)
                profiler.start() if step == 3 else profiler.stop()

        finetune(scene, cameras, style, stylized=stylized, config=config, progress=steps_only)
        events = profiler.key_averages()
        kernels = sorted((e for e in events if e.device_type.name == "CUDA"), key=lambda e: -e.device_time_total)
        host = sorted((e for e in events if e.device_type.name == "CPU"), key=lambda e: -e.self_cpu_time_total)
        gpu_ms = sum(e.device_time_total for e in kernels) / iterations / 1e3
        print(f"\n## {'L1+SSIM+NNFM' if targets else 'NNFM+content'}: wall {wall * 1e3:.2f} ms/it; "
              f"GPU kernels {gpu_ms:.2f} ms/it")
        for e in kernels[:25]:
            ms = e.device_time_total / iterations / 1e3
            print(f"{ms:8.3f} ms/it {e.count / iterations:6.1f} calls/it  {e.key[:100]}")
        print("-- host, self time")
        for e in host[:15]:
            ms = e.self_cpu_time_total / iterations / 1e3
            print(f"{ms:8.3f} ms/it {e.count / iterations:6.1f} calls/it  {e.key[:100]}")


def resized_style(style: torch.Tensor, side: int) -> torch.Tensor:
    """``style [H, W, 3]`` resized so that its long side is ``side`` (ARF: half the render's long side)."""
    factor = side / max(style.shape[:2])
    return resize_image(style, round(style.shape[0] * factor), round(style.shape[1] * factor))


def nnfm_seconds(size: int, style, device, search: str) -> float:
    """Median seconds of the NNFM term alone at ``size`` (a random image in a render's layout, the finetune's
    default convolutions) with the match search in ``search``."""
    image = torch.rand(1, size, size, 3, device=device)
    return vgg_variant(image, resized_style(style, size)[None].to(device), device, "tf32", False, "renders", search)[2]


VGG_VARIANTS = {  # name: (FinetuneConfig.vgg_precision, cuDNN autotuning, layout); layouts: "renders": the input as
    # the finetune gives it (a permuted [B, H, W, 3] render: channels-last activations, NCHW weights), "nchw": a
    # contiguous [B, 3, H, W] input, "channels-last": the weights converted to channels-last too
    "fp32 (reference)": ("fp32", False, "renders"),
    "tf32 (the finetune's)": ("tf32", False, "renders"),
    "tf32, cudnn.benchmark": ("tf32", True, "renders"),
    "tf32, NCHW input": ("tf32", False, "nchw"),
    "tf32, channels-last weights": ("tf32", False, "channels-last"),
    "bf16 autocast": ("bf16", False, "renders"),
    "bf16 autocast, channels-last weights": ("bf16", False, "channels-last"),
}


@contextlib.contextmanager
def autotuning(enabled: bool):
    """cuDNN's autotuner on or off within the block (restored after)."""
    before, torch.backends.cudnn.benchmark = torch.backends.cudnn.benchmark, enabled
    try:
        yield
    finally:
        torch.backends.cudnn.benchmark = before


def vgg_variant(image, style, device, precision: str, benchmark: bool, layout: str, search: str | None = None):
    """(loss value, image gradient, median seconds) of the NNFM term alone with one :data:`VGG_VARIANTS` setting,
    forward and backward in ``precision`` as the finetune runs them; ``image`` and ``style`` [1, H, W, 3];
    ``search``: the match search's precision (None: fp32 with fp32 convolutions, else tf32)."""
    layers = ("relu3_1", "relu3_2", "relu3_3")
    vgg = load_vgg("vgg19", device=device)
    if layout == "channels-last":
        vgg = copy.deepcopy(vgg).to(memory_format=torch.channels_last)  # the shared one untouched
    x = image.permute(0, 3, 1, 2).detach()  # as finetune's _vgg_input gives it
    x = (x.contiguous() if layout == "nchw" else x).requires_grad_(True)
    with convolution_precision(precision, device):  # the style's features in float32 (TF32), as the finetune's
        style_feats = style_image_features(vgg, style.permute(0, 3, 1, 2), layers, None)
    search = search or ("fp32" if precision == "fp32" else "tf32")
    loss = NNFMLoss(style_feats, layer_groups=(layers,), precision=search)

    def step():
        with convolution_precision(precision, device), autotuning(benchmark):
            with features_autocast(precision, device):
                feats = vgg(x, layers)
            value = loss(feats)
            value.backward()
        return value

    value = step().detach().float()
    grad, x.grad = x.grad.detach().float(), None
    return value, grad, timed(step, device)


def vgg_variant_rows(size: int, style, device) -> list[list]:
    """[variant, ms, loss relative error, gradient relative L2 error] of the NNFM term alone at ``size``
    (see the module's ``--vgg-variants``)."""
    image = torch.rand(1, size, size, 3, device=device, generator=torch.Generator(device).manual_seed(0))
    style = resized_style(style, size)[None].to(device)
    results = {name: vgg_variant(image, style, device, *setting) for name, setting in VGG_VARIANTS.items()}
    reference_value, reference_grad, _ = results["fp32 (reference)"]
    return [[name, f"{seconds * 1e3:.2f}", f"{float((value - reference_value).abs() / reference_value.abs()):.1e}",
             f"{float((grad - reference_grad).norm() / reference_grad.norm()):.1e}"]
            for name, (value, grad, seconds) in results.items()]


def ssim_part_rows(size: int, device) -> list[list]:
    """[path, ms, value deviation, gradient relative L2 deviation] of SSIM forward+backward at ``size``
    (``--parts``)."""
    generator = torch.Generator(device).manual_seed(0)
    render = torch.rand(1, size, size, 3, device=device, generator=generator)
    target = (render + 0.1 * torch.randn(render.shape, device=device, generator=generator)).clamp(0, 1)
    window = window_on(11, 1.5, device)
    paths = {"separable (PyTorch)": lambda a, b: separable_ssim(a, b, window)}
    if device.type == "cuda":
        from artnvg_core.losses.ssim_triton import fused_ssim

        paths["fused (Triton)"] = lambda a, b: fused_ssim(a, b, window, C1, C2)
    results = {}
    for name, fn in paths.items():
        leaf = render.clone().requires_grad_(True)

        def step():
            leaf.grad = None
            value = fn(leaf.permute(0, 3, 1, 2), target.permute(0, 3, 1, 2))
            value.backward()
            return value

        value = step().detach()
        results[name] = (value, leaf.grad.clone(), timed(step, device, repeats=20))
    reference_value, reference_grad, _ = results["separable (PyTorch)"]
    return [[name, f"{seconds * 1e3:.3f}", f"{float((value - reference_value).abs()):.1e}",
             f"{float((grad - reference_grad).norm() / reference_grad.norm()):.1e}"]
            for name, (value, grad, seconds) in results.items()]


def search_part_rows(size: int, style, device) -> list[list]:
    """[max_chunk_elements, ms, matches equal to one chunk's] of NNFM's TF32 match search at ``size`` (``--parts``)."""
    layers = ("relu3_1", "relu3_2", "relu3_3")
    vgg = load_vgg("vgg19", device=device)
    image = resized_style(style, size).permute(2, 0, 1)[None].to(device)
    noisy = (image + 0.1 * torch.randn(image.shape, device=device, generator=torch.Generator(device).manual_seed(0)))

    def units(x):
        with torch.no_grad():
            feats = torch.cat(list(vgg(x.clamp(0, 1), layers).values()), 1)
        return normalize_features(feats.permute(0, 2, 3, 1).reshape(-1, feats.shape[1]))

    render_unit, style_unit = units(noisy), units(image)
    one_chunk = render_unit.shape[0] * style_unit.shape[0]
    reference = nearest_style_indices(render_unit, style_unit, one_chunk, "tf32")
    rows = []
    for chunk in (one_chunk, 2**26, 2**24, 2**23, 2**22, 2**21):
        matches = nearest_style_indices(render_unit, style_unit, chunk, "tf32")
        seconds = timed(lambda: nearest_style_indices(render_unit, style_unit, chunk, "tf32"), device, repeats=20)
        rows.append([f"{chunk:,}" + (" (one chunk)" if chunk == one_chunk else ""), f"{seconds * 1e3:.3f}",
                     f"{float((matches == reference).float().mean()):.4f}"])
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--iters", type=int, default=20)
    parser.add_argument("--shared", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--cases", default="demo,bear,random")
    parser.add_argument("--searches", default=",".join(SEARCH_PRECISIONS))
    parser.add_argument("--adams", default="fused,torch", help="FiniteAdam steps to compare (CUDA)")
    parser.add_argument("--vggs", default=",".join(VGG_PRECISIONS), help="the VGG terms' convolution precisions")
    parser.add_argument("--graphs", default="on,off", help="the step's loss as CUDA graphs (on) or eager (off)")
    parser.add_argument("--parts", action="store_true", help="SSIM and the NNFM search alone, fast beside reference")
    parser.add_argument("--profile", action="store_true", help="where an iteration goes (CUDA), no timing table")
    parser.add_argument("--vgg-variants", action="store_true", help="the NNFM term alone, convolution variants")
    args = parser.parse_args()
    device = torch.device(args.device)
    wanted, searches, vggs = args.cases.split(","), args.searches.split(","), args.vggs.split(",")
    graphs = [choice == "on" for choice in args.graphs.split(",")] if device.type == "cuda" else [False]
    adams = args.adams.split(",") if device.type == "cuda" else ["torch"]
    default = FinetuneConfig()
    demo = DemoInputs()
    style = load_image(demo.style).to(device)
    command = "python " + " ".join(sys.argv)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    if args.vgg_variants:
        for size in (512, 1024) if device.type == "cuda" else (128,):
            print_table(f"NNFM term alone at {size}x{size} ({gpu}): the convolutions' arithmetic and layout",
                        ["convolutions", "ms", "loss rel. error", "gradient rel. L2 error"],
                        vgg_variant_rows(size, style, device), command)
        return
    if args.parts:
        for size in (512, 1024) if device.type == "cuda" else (128,):
            print_table(f"SSIM alone at {size}x{size} ({gpu}): forward+backward, deviation from the separable one",
                        ["SSIM", "ms", "value deviation", "gradient rel. L2 deviation"],
                        ssim_part_rows(size, device), command)
            print_table(f"NNFM match search alone at {size}x{size} ({gpu}), TF32",
                        ["max_chunk_elements", "ms", "same matches as one chunk"],
                        search_part_rows(size, style, device), command)
        return
    backends = ["torch"]
    if device.type == "cuda":  # the reference backend's speed: BENCHMARKS.md, Rasterizer
        backends = [name for name, there in (("triton", triton_available()), ("gsplat", gsplat_available())) if there]
    cases = [("demo (40k)", read_ply(demo.scene), load_cameras(demo.cameras).scaled(0.25))] if "demo" in wanted else []
    if device.type == "cuda":
        bear = Path(args.shared) / "scenes" / "bear"
        if "bear" in wanted and bear.is_dir():
            scene, cams = read_ply(bear / "scene.ply"), load_cameras(bear / "transforms.json")
            cases += [("bear (100k)", scene, cams), ("bear (100k)", scene, cams.scaled(2.0))]
        elif "bear" in wanted:
            print(f"no bear scene at {bear}: its cases are left out", flush=True)
        if "random" in wanted:
            cases += [("random (1M)", random_scene(1_000_000), orbit_cameras(16, 1024))]
    if args.profile:
        name, scene, cams = cases[0]
        print(f"profile: {name}, {cams.width}x{cams.height}", flush=True)
        return profile_rows(scene.to(device), cams, resized_style(style, max(cams.width, cams.height) // 2), device)
    rows = []
    for name, scene, cams in cases:
        sides = [512, None] if cams.width >= 1024 else [512]
        combos = itertools.product(backends, (False, True), sides)
        for backend, targets, side in [c for c in combos if c[0] == backends[0] or c[1:] == (False, 512)]:
            first = (default.nnfm_search, adams[0], default.vgg_precision, graphs[0])  # (search, Adam, VGG, graph)
            variants = [first]
            if backend == backends[0] and side == 512:  # each choice varied alone, the others as in the first
                variants += [(search, *first[1:]) for search in searches if search != first[0]]
                variants += [(first[0], adam, *first[2:]) for adam in adams[1:]]
                variants += [(*first[:2], vgg, first[3]) for vgg in vggs if vgg != first[2]]
                variants += [(*first[:3], graph) for graph in graphs[1:]]
            for search, adam, vgg, graph in variants:
                config = FinetuneConfig(iterations=args.iters, backend=backend, nnfm_max_side=side, nnfm_search=search,
                                        vgg_precision=vgg, cuda_graph=graph)
                arf_style = resized_style(style, max(cams.width, cams.height) // 2)
                with adam_step(adam):
                    sec = seconds_per_iteration(scene.to(device), cams, arf_style, config, targets, device)
                loss = "L1+SSIM+NNFM" if targets else "NNFM+content"
                rows.append([name, backend, f"{cams.width}x{cams.height}", loss, side or "full", search, vgg, adam,
                             "on" if graph else "off", f"{sec * 1e3:.1f}"])
                print(rows[-1], flush=True)
    nnfm_rows = [[f"{size}x{size}", search, f"{nnfm_seconds(size, style, device, search) * 1e3:.2f}"]
                 for size in ((128, 512, 1024) if device.type == "cuda" else (128,)) for search in searches]
    print_table(f"Finetune speed ({gpu})", ["scene", "backend", "size", "loss", "VGG terms' max side", "NNFM search",
                                           "VGG convolutions", "Adam step", "CUDA graph", "ms / iteration"], rows,
                command)
    print_table(f"NNFM term alone ({gpu}: VGG19 relu3 forward+backward + matching, style of the same size)",
                ["size", "search", "ms"], nnfm_rows, command)


if __name__ == "__main__":
    main()
