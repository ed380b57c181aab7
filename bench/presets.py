"""What each shortcut of the diffusion stage costs: speed beside numerical deviation, memory, end to end.

Full-size random-weight models (``bench/diffusion.py``'s ``build_models``, CSGO branches on)
and content views rendered from a real scene (default the bear, cameras scaled to ``--size``),
so neighbouring-view attention and the warp metric see real geometry. With random weights the
deviation columns measure NUMERICAL deviation from the reference configuration on identical
inputs, models and seeds, not stylization quality.

Sections (no flag = --accuracy, --memory and --end-to-end fast):

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
* ``--end-to-end ROW ...`` (``--sweep`` adds :data:`bench.end_to_end.SWEEP`): the whole job on a real
  scene (render the content views, stylize, finetune) for each row, a preset optionally changed
  (``paper+key_views=28``, ``paper+scheduler=dpmpp_2m+steps=20``), priced on the FINAL finetuned scene
  against the ``paper`` row's: PSNR at training and held-back views, warp consistency, per-group image
  deviation (``bench/end_to_end.py`` says what each number can show). Results accumulate in ``--parts``;
  ``--report`` prints the table of every finished row.

    python bench/presets.py --scene .devdata/scenes/bear --accuracy --json out/presets.json
    python bench/presets.py --tiny --device cpu --size 64 --end-to-end paper fast paper+key_views=12 \
        --parts /tmp/parts --iterations 3 --scene ../shared/data/scenes/bear   # smoke test
    # on a GPU, one preset split over runs of at most 10 minutes sharing .parts (git-ignored):
    python bench/presets.py --end-to-end paper --groups 0:3 --parts .parts      # ~6 min on an H100
    python bench/presets.py --end-to-end paper --groups 3: --parts .parts       # ~5.5 min, then the reference
    python bench/presets.py --end-to-end fast "paper+scheduler=dpmpp_2m+steps=20+cfg_until=0.8+key_views=28" \
        paper+key_views=14 paper+key_views=28 --parts .parts --json $OUT/e2e.json
    python bench/presets.py --report --parts .parts
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import end_to_end as e2e  # noqa: E402
from bench.diffusion import POOLED_DIM, TINY_POOLED_DIM, build_models, random_conditioning, write_json  # noqa: E402
from bench.common import synchronize, timed_call, warp_rmse  # noqa: E402
from bench.end_to_end import at_size, compare  # noqa: E402

from artnvg_core.cameras import load_cameras  # noqa: E402
from artnvg_core.diffusion.memory import enable_low_memory  # noqa: E402
from artnvg_core.diffusion.sampler import stylize_group  # noqa: E402
from artnvg_core.diffusion.speed import COMPILED_BLOCKS, apply_speedups  # noqa: E402
from artnvg_core.formats import read_ply  # noqa: E402
from artnvg_core.grouping import group_views  # noqa: E402
from artnvg_core.presets import PRESETS  # noqa: E402
from artnvg_core.raster.views import render_views  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def measured(device: torch.device, run) -> tuple[object, float, float]:
    """(result, seconds, peak GiB allocated) of one synchronised call of ``run``."""
    if device.type == "cuda":
        synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
    result, seconds = timed_call(device, run)
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else float("nan")
    return result, seconds, peak


def load_inputs(args, device: torch.device):
    """The scene, its cameras at --size (longer side), and the first group of --views views."""
    scene = read_ply(Path(args.scene) / "scene.ply").to(device)
    cameras = load_cameras(Path(args.scene) / "transforms.json")
    cameras = cameras.scaled(args.size / max(cameras.width, cameras.height))
    groups = group_views(cameras, args.views)
    return scene, cameras, groups


def accuracy_rows(args):
    """(name, settings, compared with, seed offset) of the accuracy table at ``args.size``, reference first.
    The paper configuration with another seed gives the scale of "a different sample"."""
    paper = PRESETS["paper"].sampler
    approx = dataclasses.replace(paper, steps=args.approx_steps)
    rows = [("paper (reference)", paper, None), ("paper, another seed: a different sample", paper, None, 1)]
    rows += [(f"{steps} DDIM steps", dataclasses.replace(paper, steps=steps), None) for steps in (30, 20, 10)]
    rows += [("20 DPM-Solver++(2M) steps", dataclasses.replace(paper, steps=20, scheduler="dpmpp_2m"), None)]
    rows += [("20 UniPC steps", dataclasses.replace(paper, steps=20, scheduler="unipc"), None)]
    rows += [(f"guidance for the first {until:.0%} of {paper.steps} steps", dataclasses.replace(paper, cfg_until=until),
              None) for until in (0.8, 0.5)]
    rows += [(f"768 px, {paper.steps} steps, noise of the 1024 px grid resampled",
              dataclasses.replace(paper, resolution=768, noise_resolution=1024), None)]
    if args.approx_steps not in (30, 20, 10):
        rows.append((f"{args.approx_steps} DDIM steps", approx, None))
    rows += [
        (f"NV lowest level only, {args.approx_steps} steps", dataclasses.replace(approx, nv_levels="lowest"), approx),
        (f"NV 4 nearest views, {args.approx_steps} steps", dataclasses.replace(approx, nv_nearest=4), approx),
        (f"NV keys/values pooled 2x2, {args.approx_steps} steps", dataclasses.replace(approx, nv_kv_downsample=2),
         approx),
        (f"no NV attention, {args.approx_steps} steps", dataclasses.replace(approx, neighbour_views=False), approx),
    ]
    rows += [(f"preset {name}", dataclasses.replace(PRESETS[name].sampler, noise_resolution=paper.resolution), None)
             for name in ("balanced", "fast")]
    return [(name, at_size(settings, args.size), baseline and at_size(baseline, args.size), seed_offset)
            for name, settings, baseline, *seed_offset in rows for seed_offset in [seed_offset[0] if seed_offset else 0]]


def accuracy_table(models, conditioning, args, device, report: dict) -> None:
    scene, cameras, groups = load_inputs(args, device)
    views = list(groups[0].views)
    group_cameras = cameras.subset(views)
    rendered = render_views(scene, group_cameras, depth=True, backend="torch", cpu=True)  # no gsplat build needed
    content, depth, alpha = rendered.rgb, rendered.depth, rendered.alpha
    centers = group_cameras.centers

    def warp(images):
        return warp_rmse(images, depth, alpha, group_cameras)

    print(f"\nOne group of {len(views)} views of {args.scene} at {group_cameras.width}x{group_cameras.height} "
          f"(content warp RMSE, the floor: {warp(content):.4f}); deviation from the paper configuration; random weights.")
    print("\n| variant | s / group | peak GiB | rel L2 vs paper | PSNR vs paper dB | rel L2 vs exact NV, same steps "
          "| warp RMSE step 1 |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    outputs, rows = {}, report.setdefault("accuracy", [])
    for name, settings, baseline, seed_offset in accuracy_rows(args):
        try:
            result, seconds, peak = measured(device, lambda: stylize_group(
                models, content, conditioning, settings, seed=args.seed + seed_offset, view_centers=centers))
        except Exception as error:  # out of memory, a missing kernel: record it, go on
            rows.append({"variant": name, "error": f"{type(error).__name__}: {str(error)[:200]}"})
            print(f"| {name} | {rows[-1]['error']} | | | | | |", flush=True)
            continue
        outputs[settings, seed_offset] = result
        reference = outputs[at_size(PRESETS["paper"].sampler, args.size), 0]
        row = {"variant": name, "settings": dataclasses.asdict(settings), "seconds": seconds, "peak_gib": peak,
               **compare(result, reference), "warp_rmse": warp(result)}
        own = "-"
        if baseline is not None and (baseline, 0) in outputs:
            row["rel_l2_vs_exact_nv"] = compare(result, outputs[baseline, 0])["rel_l2"]
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
    parser.add_argument("--end-to-end", nargs="+", default=[], metavar="ROW",
                        help="PRESET[+FIELD=VALUE...], e.g. paper+key_views=28 (bench/end_to_end.py)")
    parser.add_argument("--sweep", action="store_true", help="add bench/end_to_end.py's SWEEP rows to --end-to-end")
    parser.add_argument("--report", action="store_true", help="print the table of every finished row in --parts")
    parser.add_argument("--groups", help="START:STOP: the end-to-end rows stylize only these groups (see --parts)")
    parser.add_argument("--parts", type=Path, default=Path(".parts"),
                        help="folder keeping the end-to-end results between calls (default .parts)")
    parser.add_argument("--hold-every", type=int, default=8,
                        help="end to end: every n-th view is held back from every row (default 8)")
    parser.add_argument("--iterations", type=int, help="end to end: finetune iterations of every row (smoke tests)")
    parser.add_argument("--speed", choices=["eager", "compiled-blocks"], default="eager",
                        help="compiled-blocks: what --compile switches on (speed.COMPILED_BLOCKS: the repeated "
                             "blocks compiled with dynamic shapes, the hint embedding cached; exact speedups)")
    parser.add_argument("--json", type=Path, help="write the results as JSON here")
    args = parser.parse_args()
    if args.memory or any(row.startswith("low-memory") for row in args.end_to_end):
        # before the first CUDA allocation, as the command line's low-memory preset does: 12 GiB holds N=14
        # only without fragmentation (a run without it failed with 2.8 GiB reserved but unallocated)
        os.environ.setdefault("PYTORCH_CUDA_ALLOC_CONF", "expandable_segments:True")
    if args.report:
        e2e.report(args.parts)
        return
    args.end_to_end += list(e2e.SWEEP) if args.sweep else []
    for text in args.end_to_end:  # bad rows fail before the models are built
        e2e.parse_row(text)
    if not (args.accuracy or args.memory or args.end_to_end):
        args.accuracy, args.memory, args.end_to_end = True, True, ["paper", "fast"]
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
    if args.end_to_end:
        e2e.end_to_end_table(models, conditioning, args, device, report, write_json)
    if args.memory:  # last: it moves the idle models to the CPU
        memory_table(models, conditioning, args, device, report)


if __name__ == "__main__":
    main()
