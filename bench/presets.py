"""What each shortcut of the diffusion stage costs: speed beside numerical deviation, memory, end to end.

Full-size random-weight models (``bench/diffusion.py``'s ``build_models``, CSGO branches on)
and content views rendered from a real scene (default the bear, cameras scaled to ``--size``),
so neighbouring-view attention and the warp metric see real geometry. With random weights the
deviation columns measure NUMERICAL deviation from the reference configuration on identical
inputs, models and seeds, not stylization quality.

Sections (no flag = all three):

* ``--accuracy``: one group (the first of ``group_views(cameras, 15)``). Reference: the paper
  configuration (50 DDIM steps, NV attention everywhere, 1024 px). Each row is one whole-group run
  (sampling + VAE decoding, one synchronised run): seconds, peak GiB, relative L2 and PSNR of the
  final images against the reference, and the warp error (RMSE, step 1) of the stylized views
  (content renders: the floor). NV approximations run at ``--approx-steps`` steps and are also
  compared with the exact NV run at the same steps (their own error, without the step count's).
* ``--memory``: the low-memory mode (idle models on the CPU, chunked feed-forward, sequential
  guidance halves) for one group under a ``--memory-cap`` GiB cap
  (``torch.cuda.set_per_process_memory_fraction``), beside the full-memory mode: seconds per step
  (median of the steps), peak allocated and reserved GiB, deviation after ``--memory-steps`` steps.
* ``--end-to-end PRESET ...``: every view of the scene: render the content views, stylize all
  groups with the preset, finetune the preset's iterations (gsplat when available); phase times.

    python bench/presets.py --scene .devdata/scenes/bear --json out/presets.json
    python bench/presets.py --tiny --device cpu --size 64 --views 6   # smoke test
    # the paper configuration end to end, split over two calls of at most 10 minutes on one
    # machine (.parts is git-ignored and not carried, so it survives between calls):
    python bench/presets.py --end-to-end paper --groups 0:4 --parts .parts
    python bench/presets.py --end-to-end paper --groups 4: --parts .parts
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.diffusion import POOLED_DIM, TINY_POOLED_DIM, build_models, random_conditioning, write_json  # noqa: E402

from artnvg_core.cameras import load_cameras  # noqa: E402
from artnvg_core.diffusion.memory import enable_low_memory  # noqa: E402
from artnvg_core.diffusion.sampler import SamplerSettings, stylize_group  # noqa: E402
from artnvg_core.diffusion.speed import COMPILED_BLOCKS, apply_speedups  # noqa: E402
from artnvg_core.diffusion.stylize import stylize_groups  # noqa: E402
from artnvg_core.finetune import FinetuneConfig, finetune  # noqa: E402
from artnvg_core.formats import read_ply  # noqa: E402
from artnvg_core.grouping import group_views  # noqa: E402
from artnvg_core.metrics.warp import warp_consistency  # noqa: E402
from artnvg_core.presets import PRESETS  # noqa: E402
from artnvg_core.raster import render  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measured(device: torch.device, run) -> tuple[object, float, float]:
    """(result, seconds, peak GiB allocated) of one synchronised call of ``run``."""
    synchronize(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    begin = time.perf_counter()
    result = run()
    synchronize(device)
    seconds = time.perf_counter() - begin
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")
    return result, seconds, peak


def compare(images: torch.Tensor, reference: torch.Tensor) -> dict:
    """Relative L2 and PSNR (dB, peak 1) of IMAGE batches on the same views."""
    difference = (images.double() - reference.double())
    mse = difference.square().mean().item()
    return {"rel_l2": (difference.norm() / reference.double().norm()).item(),
            "psnr_db": math.inf if mse == 0 else 10 * math.log10(1 / mse)}


def load_inputs(args, device: torch.device):
    """The scene, its cameras at --size (longer side), and the first group of --views views."""
    scene = read_ply(Path(args.scene) / "scene.ply").to(device)
    cameras = load_cameras(Path(args.scene) / "transforms.json")
    cameras = cameras.scaled(args.size / max(cameras.width, cameras.height))
    groups = group_views(cameras, args.views)
    return scene, cameras, groups


def render_views(scene, cameras, backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Content IMAGE [C, H, W, 3] on the CPU, depth and alpha [C, H, W, 1], rendered 8 views at a time."""
    parts = []
    with torch.no_grad():
        for start in range(0, len(cameras), 8):
            views = cameras.subset(range(start, min(start + 8, len(cameras))))
            out = render(scene, views, return_depth=True, backend=backend)
            parts.append((out.rgb.clamp(0, 1).cpu(), out.depth.cpu(), out.alpha.cpu()))
    return tuple(torch.cat(p) for p in zip(*parts))


def at_size(settings: SamplerSettings, size: int) -> SamplerSettings:
    """``settings`` with its resolution scaled from 1024 to ``size`` (the presets are written for 1024),
    at least SDXL's 64 px."""
    return dataclasses.replace(settings, resolution=max(64, settings.resolution * size // 1024))


def accuracy_rows(args):
    """(name, settings, compared with) of the accuracy table at ``args.size``, reference first."""
    paper = PRESETS["paper"].sampler
    approx = dataclasses.replace(paper, steps=args.approx_steps)
    rows = [("paper (reference)", paper, None)]
    rows += [(f"{steps} DDIM steps", dataclasses.replace(paper, steps=steps), None) for steps in (30, 20, 10)]
    rows += [("20 DPM-Solver++(2M) steps", dataclasses.replace(paper, steps=20, scheduler="dpmpp_2m"), None)]
    rows += [(f"768 px, {paper.steps} steps", dataclasses.replace(paper, resolution=768), None)]
    if args.approx_steps not in (30, 20, 10):
        rows.append((f"{args.approx_steps} DDIM steps", approx, None))
    rows += [
        (f"NV lowest level only, {args.approx_steps} steps", dataclasses.replace(approx, nv_levels="lowest"), approx),
        (f"NV 4 nearest views, {args.approx_steps} steps", dataclasses.replace(approx, nv_nearest=4), approx),
        (f"NV keys/values pooled 2x2, {args.approx_steps} steps", dataclasses.replace(approx, nv_kv_downsample=2),
         approx),
        (f"no NV attention, {args.approx_steps} steps", dataclasses.replace(approx, neighbour_views=False), approx),
    ]
    rows += [(f"preset {name}", PRESETS[name].sampler, None) for name in ("balanced", "fast")]
    return [(name, at_size(settings, args.size), baseline and at_size(baseline, args.size))
            for name, settings, baseline in rows]


def accuracy_table(models, conditioning, args, device, report: dict) -> None:
    scene, cameras, groups = load_inputs(args, device)
    views = list(groups[0].views)
    group_cameras = cameras.subset(views)
    content, depth, alpha = render_views(scene, group_cameras, backend="torch")  # no gsplat build needed
    centers = group_cameras.centers

    def warp(images):
        return warp_consistency(images, depth, alpha, group_cameras, step=1).rmse

    print(f"\nOne group of {len(views)} views of {args.scene} at {group_cameras.width}x{group_cameras.height} "
          f"(content warp RMSE, the floor: {warp(content):.4f}); deviation from the paper configuration; random weights.")
    print("\n| variant | s / group | peak GiB | rel L2 vs paper | PSNR vs paper dB | rel L2 vs exact NV, same steps "
          "| warp RMSE step 1 |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    outputs, rows = {}, report.setdefault("accuracy", [])
    for name, settings, baseline in accuracy_rows(args):
        try:
            result, seconds, peak = measured(device, lambda: stylize_group(
                models, content, conditioning, settings, seed=args.seed, view_centers=centers))
        except Exception as error:  # out of memory, a missing kernel: record it, go on
            rows.append({"variant": name, "error": f"{type(error).__name__}: {str(error)[:200]}"})
            print(f"| {name} | {rows[-1]['error']} | | | | | |", flush=True)
            continue
        outputs[settings] = result
        reference = outputs[at_size(PRESETS["paper"].sampler, args.size)]
        row = {"variant": name, "settings": dataclasses.asdict(settings), "seconds": seconds, "peak_gib": peak,
               **compare(result, reference), "warp_rmse": warp(result)}
        own = "-"
        if baseline is not None and baseline in outputs:
            row["rel_l2_vs_exact_nv"] = compare(result, outputs[baseline])["rel_l2"]
            own = f"{row['rel_l2_vs_exact_nv']:.4f}"
        rows.append(row)
        write_json(args.json, report)
        print(f"| {name} | {seconds:.1f} | {peak:.1f} | {row['rel_l2']:.4f} | {row['psnr_db']:.1f} | {own} | "
              f"{row['warp_rmse']:.4f} |", flush=True)


def memory_table(models, conditioning, args, device, report: dict) -> None:
    """Low-memory mode under the cap, beside the full-memory mode (without the cap)."""
    images = torch.rand(args.views, args.size, args.size, 3, generator=torch.Generator().manual_seed(1))
    full = at_size(dataclasses.replace(PRESETS["paper"].sampler, steps=args.memory_steps), args.size)
    low = at_size(dataclasses.replace(PRESETS["low-memory"].sampler, steps=args.memory_steps), args.size)

    def run(settings):
        stamps = []

        def stamp(*_):
            synchronize(device)
            stamps.append(time.perf_counter())

        result, seconds, peak = measured(device, lambda: stylize_group(
            models, images, conditioning, settings, seed=args.seed, progress=stamp))
        reserved = torch.cuda.max_memory_reserved(device) / 2**30 if device.type == "cuda" else float("nan")
        step = statistics.median(b - a for a, b in zip(stamps, stamps[1:])) if len(stamps) > 1 else seconds
        return result, {"seconds": seconds, "s_per_step": step, "peak_gib": peak, "reserved_gib": reserved}

    print(f"\nMemory: N={args.views} at {args.size}x{args.size}, {args.memory_steps} steps, NV on, CFG; "
          f"cap {args.memory_cap} GiB via torch.cuda.set_per_process_memory_fraction.")
    print("\n| mode | cap | s / step | whole run s | peak allocated GiB | peak reserved GiB | rel L2 vs full |")
    print("|---|---|---:|---:|---:|---:|---:|")
    rows, reference = report.setdefault("memory", []), None
    plan = [("full memory", full, None), ("low memory", low, None), ("low memory", low, args.memory_cap),
            ("full memory, idle models on the CPU", full, args.memory_cap)]
    for mode, settings, cap in plan:
        if mode == "low memory" and cap is None:
            enable_low_memory(models)
        if device.type == "cuda":
            torch.cuda.empty_cache()
            total = torch.cuda.get_device_properties(device).total_memory
            torch.cuda.set_per_process_memory_fraction(1.0 if cap is None else cap * 2**30 / total)
            torch.cuda.reset_peak_memory_stats(device)
            resident = torch.cuda.memory_allocated(device) / 2**30
        try:
            result, row = run(settings)
            reference = result if reference is None else reference
            row["rel_l2"] = compare(result, reference)["rel_l2"]
            line = (f"| {row['s_per_step']:.3f} | {row['seconds']:.1f} | {row['peak_gib']:.2f} | "
                    f"{row['reserved_gib']:.2f} | {row['rel_l2']:.2g} |")
        except torch.OutOfMemoryError as error:
            row = {"error": f"out of memory: {str(error).splitlines()[0][:160]}"}
            line = f"| {row['error']} | | | | |"
        rows.append({"mode": mode, "cap_gib": cap, "resident_gib": resident if device.type == "cuda" else None, **row})
        write_json(args.json, report)
        print(f"| {mode} (resident before: {rows[-1]['resident_gib'] or 0:.2f} GiB) | "
              f"{'none' if cap is None else f'{cap} GiB'} {line}", flush=True)
    if device.type == "cuda":
        torch.cuda.set_per_process_memory_fraction(1.0)


def _group_range(text: str | None, count: int) -> range:
    """``START:STOP`` (Python slice of the scene's groups) as a range; all groups when None."""
    if text is None:
        return range(count)
    start, _, stop = text.partition(":")
    return range(count)[slice(int(start) if start else None, int(stop) if stop else None)]


def end_to_end(models, conditioning, args, device, name: str, report: dict) -> None:
    """Render, stylize every group and finetune with preset ``name``; prints and records phase times.

    With ``--groups START:STOP`` and ``--parts DIR`` (a run split over several calls), this call renders
    and stylizes only those groups and saves each group's views, images and times to DIR; once DIR holds
    every group, it finetunes on all of them and prints the phases summed over the parts.
    """
    preset = PRESETS[name]
    scene, cameras, groups = load_inputs(args, device)
    chosen = _group_range(args.groups, len(groups))
    settings = at_size(preset.sampler, args.size)
    times, parts = {"render content": 0.0, "stylize": 0.0}, []
    peak = 0.0
    for index in chosen:
        views = list(groups[index].views)
        needed = sorted(set(views) | set(groups[index].context))
        content = torch.zeros(len(cameras), cameras.height, cameras.width, 3)
        (content[needed], _, _), render_s, _ = measured(
            device, lambda: render_views(scene, cameras.subset(needed), "torch"))
        stylized_all, stylize_s, group_peak = measured(device, lambda: stylize_groups(
            models, content, groups, conditioning, settings, seed=args.seed, group_indices=[index]))
        images = stylized_all[views]
        part = {"group": index, "views": views, "images": images.cpu(), "render_s": render_s,
                "stylize_s": stylize_s, "peak_gib": group_peak}
        times["render content"] += render_s
        times["stylize"] += stylize_s
        peak = max(peak, group_peak)
        print(f"group {index}: {len(views)} views, rendered in {render_s:.1f} s (reference rasterizer), "
              f"stylized in {stylize_s:.1f} s, peak {group_peak:.1f} GiB", flush=True)
        if args.parts is not None:
            args.parts.mkdir(parents=True, exist_ok=True)
            torch.save(part, args.parts / f"group_{index:03d}.pt")
        parts.append(part)
    if args.parts is not None:
        saved = {int(f.stem.split("_")[1]): f for f in args.parts.glob("group_*.pt")}
        missing = sorted(set(range(len(groups))) - set(saved))
        if missing:
            print(f"\nparts saved in {args.parts}; groups {missing} still to stylize before the finetune")
            return
        parts = [torch.load(saved[i]) for i in range(len(groups))]
        times = {"render content": sum(p["render_s"] for p in parts), "stylize": sum(p["stylize_s"] for p in parts)}
        peak = max(p["peak_gib"] for p in parts)
    stylized = torch.empty(len(cameras), cameras.height, cameras.width, 3)
    for part in parts:
        stylized[part["views"]] = part["images"]
    _, build, _ = measured(device, lambda: render(scene, cameras.subset([0])))  # builds gsplat's kernels once
    print(f"\n(first render with the default backend, building the rasterizer's kernels once: {build:.1f} s, "
          "not counted)")
    style = torch.rand(512, 512, 3, generator=torch.Generator().manual_seed(2)).to(device)
    config = FinetuneConfig(iterations=preset.finetune_iterations)
    _, times["finetune"], _ = measured(device, lambda: finetune(scene, cameras, style, stylized=stylized.to(device),
                                                                config=config))
    times["total"] = sum(times.values())
    report.setdefault("end_to_end", []).append({"preset": name, "views": len(cameras), "groups": len(groups),
                                                "group_sizes": [len(g.views) for g in groups],
                                                "size": [cameras.width, cameras.height], "seconds": times,
                                                "stylize_peak_gib": peak, "speed": args.speed})
    write_json(args.json, report)
    print(f"\nEnd to end, preset {name} ({preset.summary}): {len(cameras)} views in {len(groups)} groups of "
          f"{sorted({len(g.views) for g in groups})} views at {cameras.width}x{cameras.height}, "
          f"{preset.finetune_iterations} finetune iterations, speedups: {args.speed}; stylize peak {peak:.1f} GiB")
    print("\n| phase | seconds |\n|---|---:|")
    for phase, seconds in times.items():
        print(f"| {phase} | {seconds:.1f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tiny", action="store_true", help="tiny models (CPU smoke test)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--scene", default=str(REPO / ".devdata" / "scenes" / "bear"),
                        help="folder with scene.ply and transforms.json")
    parser.add_argument("--size", type=int, default=1024, help="longer image side of the views")
    parser.add_argument("--views", type=int, default=15, help="views per group")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--accuracy", action="store_true")
    parser.add_argument("--approx-steps", type=int, default=20)
    parser.add_argument("--memory", action="store_true")
    parser.add_argument("--memory-cap", type=float, default=12.0, help="GiB")
    parser.add_argument("--memory-steps", type=int, default=4)
    parser.add_argument("--end-to-end", nargs="+", choices=sorted(PRESETS), default=[])
    parser.add_argument("--groups", help="START:STOP: the end-to-end run stylizes only these groups (see --parts)")
    parser.add_argument("--parts", type=Path, help="folder of a split end-to-end run's per-group results")
    parser.add_argument("--speed", choices=["eager", "compiled-blocks"], default="eager",
                        help="compiled-blocks: what --compile switches on (speed.COMPILED_BLOCKS: the repeated "
                             "blocks compiled with dynamic shapes, the hint embedding cached; exact speedups)")
    parser.add_argument("--json", type=Path, help="write the results as JSON here")
    args = parser.parse_args()
    if not (args.accuracy or args.memory or args.end_to_end):
        args.accuracy, args.memory, args.end_to_end = True, True, ["fast"]
    device = torch.device(args.device)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    begin = time.perf_counter()
    torch.manual_seed(0)
    models = build_models(args.tiny, device, dtype)
    conditioning = random_conditioning(models, device, dtype, TINY_POOLED_DIM if args.tiny else POOLED_DIM)
    if args.speed == "compiled-blocks":
        apply_speedups(models, COMPILED_BLOCKS)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"# ArtNVG presets benchmark: {gpu}, {dtype}, {'tiny' if args.tiny else 'full-size'} random models "
          f"(built in {time.perf_counter() - begin:.0f} s), torch {torch.__version__}\n\n`python {' '.join(sys.argv)}`")
    report = {"setup": {"device": gpu, "command": " ".join(sys.argv), "torch": torch.__version__}}
    if args.accuracy:
        accuracy_table(models, conditioning, args, device, report)
    for name in args.end_to_end:
        end_to_end(models, conditioning, args, device, name, report)
    if args.memory:  # last: it moves the idle models to the CPU
        memory_table(models, conditioning, args, device, report)


if __name__ == "__main__":
    main()
