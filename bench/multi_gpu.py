"""What more GPUs buy, through Ray: one scene's groups (the executor) and a batch of scenes (``batch``).

* ``groups``: the bear's content views, rendered once, grouped as ``stylize --group-multiple M``
  groups them (``--views`` evenly spaced cameras, groups of at most 15, their number a multiple of
  ``--group-multiple``, default the least common multiple of the worker counts run, so every run has
  the same groups), stylized at each ``--presets`` preset's sampler settings by a :class:`GroupExecutor`
  of 1 worker, then of 2, 4 and ``--gpus`` workers (default: every visible GPU), each with random
  full-size models built from one seed. Wall time from every worker ready (models built) to the
  assembled result; the largest difference from the 1-GPU output. A GPU is busy while it samples a
  group (from the task's start, its inputs received, to its end); receiving inputs, returning views
  and waiting for the others count as idle. Each worker's groups and their times follow each row.
* ``batch``: ``--batch-scenes`` stylized whole (render, diffusion at ``--batch-preset``, finetune,
  contact sheet, save) as ``batch`` jobs on 1 worker, then on 2, 4 and ``--gpus`` workers, from random
  full-size model files in ``--models`` (``bench/model_files.py``'s released layout, SDXL as its single
  file; written where missing), the Triton kernels compiled before the first run
  (:func:`compile_job_kernels`). Wall time from start to the last job,
  including each worker's start and one model load (busy: inside a job, that load included); each
  output against the 1-GPU run's: the scene's largest parameter difference and the contact sheet's
  PSNR. The 1-GPU worker runs the first job a second time (not timed): the same comparison for one GPU
  twice (the rasterizer's backward adds gradients with atomics, in no fixed order, so two finetunes
  differ in the last bits and then drift). With ``--warm`` each worker count runs the batch twice on the same
  workers: the first round (cold, measured as without ``--warm``) and a second (warm: imports done, models
  loaded, as ``batch --keep-workers`` keeps its workers), each with its wall and its speed-up over the same
  round on 1 GPU, its outputs against the 1-GPU cold run's.

For each run: speed-up over 1 GPU; per GPU the busy fraction (seconds inside group or job tasks over
the wall: the rest is waiting for work, or loading) and the peak memory allocated. The runs of a
section go in one Ray session (a local instance with the GPUs given), one after the other.

    python bench/multi_gpu.py --sections groups --presets fast             # ~3 min on 2 H200s
    python bench/multi_gpu.py --sections groups --presets paper --views 30 # 2 groups of 15
    python bench/multi_gpu.py --sections batch                             # 4 scenes, fast
    python bench/multi_gpu.py --sections batch --batch-scenes bear face bear face bear face bear face --workers 1 4 2
    python bench/multi_gpu.py --sections batch --batch-scenes bear face bear face bear face bear face --workers 1 4 --warm
    python bench/multi_gpu.py --tiny --device cpu --views 8 --presets fast --batch-scenes bear face  # CPU smoke test
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from artnvg_core.cli.batch import BatchPool, BatchWorker  # noqa: E402
from artnvg_core.cli.batch_jobs import load_jobs, stylize_options  # noqa: E402
from artnvg_core.cameras import load_cameras  # noqa: E402
from artnvg_core.cluster import WorkerPool, Workers, ray_session  # noqa: E402
from artnvg_core.diffusion.executor import GroupExecutor  # noqa: E402
from artnvg_core.formats import load_scene  # noqa: E402
from artnvg_core.grouping import group_views  # noqa: E402
from artnvg_core.images import load_image  # noqa: E402
from artnvg_core.preview import evenly_spaced  # noqa: E402
from artnvg_core.presets import DIFFUSION_PRESETS, PRESETS  # noqa: E402
from artnvg_core.raster.views import render_views  # noqa: E402
from artnvg_core.stylize import sheet_path  # noqa: E402
from bench.diffusion import POOLED_DIM, TINY_POOLED_DIM, build_models, random_conditioning  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def seeded_models(tiny: bool, seed: int, device: torch.device):
    """Random models built from ``seed`` on ``device`` (bf16 on a GPU, float32 on the CPU)."""
    torch.manual_seed(seed)
    return build_models(tiny, device, torch.bfloat16 if device.type == "cuda" else torch.float32)


def content_views(scene_folder: Path, views: int | None, size: int | None,
                  multiple: int) -> tuple[torch.Tensor, object]:
    """The scene's content views [V, H, W, 3] (CPU; ``views`` evenly spaced cameras, long side ``size``)
    and their groups, as ``stylize --group-multiple MULTIPLE`` groups them."""
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    scene = load_scene(scene_folder / "scene.ply").to(device)
    cameras = load_cameras(scene_folder / "transforms.json")
    if views:
        cameras = cameras.subset(evenly_spaced(len(cameras), views))
    if size:
        cameras = cameras.scaled(size / max(cameras.width, cameras.height))
    return render_views(scene, cameras, cpu=True).rgb, group_views(cameras, 15, multiple=multiple)


def busy_row(label: str, workers: int, wall: float, reference_wall: float, stats: list[dict], equal: str) -> str:
    busy = " / ".join(f"{s['busy_s'] / wall:.2f}" for s in stats)
    peak = " / ".join("-" if s["peak_gib"] is None else f"{s['peak_gib']:.1f}" for s in stats)
    return f"| {label} | {workers} | {wall:.1f} | {reference_wall / wall:.2f}x | {busy} | {peak} | {equal} |"


def timeline(start: float, end: float, tasks: list[list[tuple[str, float, float]]]) -> str:
    """Per worker its tasks ``(name, start, end)`` (Unix seconds) relative to ``start``, and how long it
    waited before the first and after the last until ``end``."""
    lines = []
    for worker, own in enumerate(tasks):
        own = sorted(own, key=lambda task: task[1])
        spans = ", ".join(f"{name} {a - start:.1f}-{b - start:.1f}" for name, a, b in own)
        lead = own[0][1] - start if own else end - start
        tail = end - own[-1][2] if own else 0.0
        lines.append(f"    GPU {worker}: {spans} (waited {lead:.1f} s first, {tail:.1f} s at the end)")
    return "\n".join(lines)


def worker_counts(args, available: int) -> list[int]:
    """``--workers`` (the first run is the reference), else 1 GPU, then 2, 4 and every one available."""
    counts = args.workers or sorted({count for count in (1, 2, 4, available) if count <= available})
    if max(counts) > available:
        raise ValueError(f"--workers: {max(counts)} workers asked for, {available} devices given")
    return counts


def groups_section(args, devices: list[str], rows: list[str]) -> None:
    multiple = args.group_multiple or math.lcm(*worker_counts(args, len(devices)))
    images, groups = content_views(args.shared / "scenes" / "bear", args.views, args.size, multiple)
    print(f"bear: {len(images)} views at {images.shape[2]}x{images.shape[1]}, {len(groups)} groups of "
          f"{sorted({len(g.views) for g in groups})} views (--group-multiple {multiple})", flush=True)
    device = torch.device(devices[0].split(":")[0])  # the conditioning, once, from models built here
    models = seeded_models(args.tiny, args.seed, device)
    with torch.no_grad():
        conditioning = random_conditioning(models, device, models.base.unet.dtype,
                                           TINY_POOLED_DIM if args.tiny else POOLED_DIM)
    del models
    if device.type == "cuda":
        torch.cuda.empty_cache()
    with ray_session(devices) as available:
        load = functools.partial(seeded_models, args.tiny, args.seed)
        for name in args.presets:
            settings = PRESETS[name].sampler
            if args.tiny:
                settings = dataclasses.replace(settings, resolution=None)
            reference, reference_wall = None, None
            for count in worker_counts(args, available.count):
                with GroupExecutor(load, Workers(available.kind, count)) as executor:
                    executor.describe()  # every worker has built its models
                    start = time.time()
                    output = executor.stylize_groups(images, groups, conditioning, settings, seed=args.seed)
                    end = time.time()
                    stats = executor.stats()
                wall = end - start
                reference = output if reference is None else reference
                reference_wall = reference_wall or wall
                difference = (output - reference).abs().max().item()
                rows.append(busy_row(f"groups, {name}", count, wall, reference_wall, stats, f"max abs diff {difference:.3g}"))
                print(rows[-1], flush=True)
                print(timeline(start, end, [[(f"g{g}", a, b) for g, a, b in s["tasks"]] for s in stats]), flush=True)


# the parts of a stylize job timed in the batch's workers: (module, function, part)
JOB_PARTS = (("artnvg_core.cli.stylize", "load_scene_verbose", "scene"),
             *(("artnvg_core.stylize", name, part) for name, part in (
                 ("load_models_for", "models"), ("render_views", "render"), ("stylize_diffusion", "diffusion"),
                 ("finetune", "finetune"), ("save_result", "save"))))


class TimedBatchWorker(BatchWorker):
    """A batch worker that records when each part of its jobs (:data:`JOB_PARTS`) ran, Unix seconds: the
    models' load runs in a background thread beside the scene and the content render; ``render`` inside
    ``save`` is the contact sheet's."""

    def __init__(self, workers: Workers):
        super().__init__(workers)
        import importlib

        self.spans: list[tuple[str, float, float]] = []
        for module_name, name, part in JOB_PARTS:
            module = importlib.import_module(module_name)
            setattr(module, name, self._timed(getattr(module, name), part))

    def _timed(self, call, part: str):
        def timed(*args, **kwargs):
            start = time.time()
            try:
                return call(*args, **kwargs)
            finally:
                self.spans.append((part, start, time.time()))
        return timed

    def parts(self) -> list[tuple[str, float, float]]:
        return self.spans


class TimedBatchPool(BatchPool):
    """:class:`BatchPool` of :class:`TimedBatchWorker` actors."""

    def __init__(self, workers: Workers):
        WorkerPool.__init__(self, TimedBatchWorker, workers, workers)


def batch_section(args, devices: list[str], rows: list[str]) -> None:
    """With --tiny the tests' tiny model files are written and loaded once (a check of the loader), and the jobs
    use the NNFM stylizer at 1/8 scale (a preset's 768 or 1024 px working size takes minutes a view
    with tiny models on a CPU): it checks the plumbing, not the diffusion."""
    if args.tiny:
        from artnvg_core.diffusion.model_files import ModelFiles
        from artnvg_core.diffusion.loader import load_models_for

        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
        from diffusion_tiny import write_model_files as write_tiny_model_files

        args.models.mkdir(parents=True, exist_ok=True)
        load_models_for(ModelFiles(**write_tiny_model_files(args.models)), False, torch.device("cpu"))
        stylizer = {"stylizer": "nnfm", "scale": 0.125, "iters": 2}
    else:  # the released files as a user downloads them, SDXL as its single file
        from bench.model_files import write_model_files

        files = write_model_files(args.models, "cuda", sdxl_folder=False)
        stylizer = {"stylizer": "diffusion", "preset": args.batch_preset, "sdxl": str(files["sdxl"]),
                    "controlnet": str(files["controlnet"]), "image_encoder": str(files["image encoder"]),
                    "csgo": str(files["csgo"])}
    style = sorted((args.shared / "styles").glob("*.jpg"))[0]
    work = Path(tempfile.mkdtemp(prefix="artnvg-batch-bench-"))
    entries = []
    for number, name in enumerate(args.batch_scenes):
        folder = args.shared / "scenes" / name
        entries.append({"scene": str(folder / "scene.ply"), "cameras": str(folder / "transforms.json"),
                        "style": str(style), "seed": args.seed + number, "out": f"OUT/{number}-{name}.ply", **stylizer})

    if args.device == "cuda":
        compile_job_kernels(entries[0])

    def jobs_to(label: str, chosen: list[dict]):
        path = work / f"jobs-{label}.json"
        path.write_text(json.dumps(chosen).replace("OUT/", f"{label}/"))
        return load_jobs(path, stylize_options())

    import ray

    rounds = ("cold", "warm") if args.warm else ("cold",)
    with ray_session(devices) as available:
        reference, reference_walls = None, {}  # the first run's jobs (cold); per round, the first run's wall
        for count in worker_counts(args, available.count):
            first = reference is None
            with TimedBatchPool(Workers(available.kind, count)) as pool:
                for round in rounds:
                    jobs = jobs_to(f"out-{count}" + ("-warm" if round == "warm" else ""), entries)
                    start, end, results, spans, parts = timed_run(ray, pool, jobs)
                    per_worker = [{"busy_s": 0.0, "peak_gib": None} for _ in range(count)]
                    for result in results:
                        entry = per_worker[spans[result.job.number][0]]
                        entry["busy_s"] += result.seconds
                        if result.peak_gib is not None:
                            entry["peak_gib"] = max(entry["peak_gib"] or 0.0, result.peak_gib)
                    reference = reference or jobs
                    reference_walls.setdefault(round, end - start)
                    equal = "reference" if reference is jobs else compare_outputs(jobs, reference)
                    label = f"batch of {len(jobs)}, {args.batch_preset}" + (f", {round}" if args.warm else "")
                    rows.append(busy_row(label, count, end - start, reference_walls[round], per_worker, equal))
                    print(rows[-1], flush=True)
                    names = {r.job.number: f"job {r.job.number} ({args.batch_scenes[r.job.number - 1]}, "
                             f"{r.seconds:.1f} s in the worker)" for r in results}
                    print(timeline(start, end, [[(names[n], a, b) for n, (w, a, b) in spans.items() if w == worker]
                                                for worker in range(count)]), flush=True)
                    print("  parts of the jobs:\n" + timeline(start, end, parts), flush=True)
                if first and count == 1:  # the first job once more on the same GPU, its models loaded (not timed)
                    again = jobs_to("again", entries[:1])
                    timed_run(ray, pool, again)
                    rows.append(f"| batch, job 1 twice on 1 GPU | 1 | | | | | {compare_outputs(again, reference[:1])} |")
                    print(rows[-1], flush=True)


def timed_run(ray, pool: TimedBatchPool, jobs) -> tuple[float, float, list, dict, list]:
    """``jobs`` run on ``pool``: the run's start and end (Unix seconds), the results (RuntimeError unless every
    job is done), per job number its [worker, start, end] and per worker the parts of its jobs
    (:data:`JOB_PARTS`) that began in this run."""
    spans = {}

    def record(kind: str, job, detail) -> None:
        if kind == "started":
            spans[job.number] = [detail["worker"], time.time(), None]
        elif job.number in spans:
            spans[job.number][2] = time.time()

    start = time.time()
    results = pool.run(jobs, on_event=record)
    end = time.time()
    bad = [f"job {r.job.number}: {r.status} {r.message}" for r in results if r.status != "done"]
    if bad:
        raise RuntimeError("batch bench: " + "; ".join(bad))
    parts = [[part for part in own if part[1] >= start] for own in ray.get([actor.parts.remote() for actor in pool.actors])]
    return start, end, results, spans, parts


def compile_job_kernels(entry: dict) -> None:
    """A 2-view, 3-iteration finetune of ``entry``'s scene toward its own renders on this GPU: compiles the
    Triton kernels of every job's renders and finetune (rasterizer forward and backward, SSIM) into
    Triton's cache, so that the first run does not pay that one-off of a fresh install and the runs
    compare as they would on a used machine (BENCHMARKS.md, "First look")."""
    from artnvg_core.finetune import FinetuneConfig, finetune

    scene = load_scene(entry["scene"]).to("cuda")
    cameras = load_cameras(entry["cameras"]).subset([0, 1])
    style = load_image(entry["style"]).cuda()
    finetune(scene, cameras, style, stylized=render_views(scene, cameras, cpu=True).rgb,
             config=FinetuneConfig(iterations=3))
    torch.cuda.synchronize()


SCENE_TENSORS = ("means", "quats", "log_scales", "opacity_logits", "sh")


def compare_outputs(jobs, reference) -> str:
    """Over the jobs, the largest difference of an output scene's parameters from the reference job's
    and the lowest PSNR of a contact sheet against the reference's (inf: equal)."""
    largest, lowest = 0.0, math.inf
    for job, other in zip(jobs, reference):
        mine, theirs = load_scene(job.out), load_scene(other.out)
        largest = max(largest, *((getattr(mine, name) - getattr(theirs, name)).abs().max().item()
                                 for name in SCENE_TENSORS))
        error = (load_image(sheet_path(job.out)) - load_image(sheet_path(other.out))).square().mean().item()
        lowest = min(lowest, math.inf if error == 0 else -10 * math.log10(error))
    return f"params max abs diff {largest:.3g}, sheet PSNR {lowest:.1f} dB"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sections", nargs="+", choices=["groups", "batch"], default=["groups", "batch"])
    parser.add_argument("--presets", nargs="+", choices=DIFFUSION_PRESETS, default=["fast", "paper"])
    parser.add_argument("--views", type=int, help="groups: this many evenly spaced cameras of the bear (default all 96)")
    parser.add_argument("--group-multiple", type=int, help="groups: the number of groups a multiple of this (default: "
                        "the least common multiple of the worker counts run)")
    parser.add_argument("--size", type=int, help="groups: long side of the content views (default the cameras' 512)")
    parser.add_argument("--batch-scenes", nargs="+", default=["bear", "face", "bear", "face"])
    parser.add_argument("--batch-preset", choices=DIFFUSION_PRESETS, default="fast")
    parser.add_argument("--warm", action="store_true", help="batch: run the batch a second time on the same workers "
                        "(warm: imports done, models loaded, as --keep-workers keeps them) and report both rounds")
    parser.add_argument("--gpus", type=int, help="GPUs of the multi-GPU runs (default: every visible one)")
    parser.add_argument("--workers", type=int, nargs="+", help="worker counts to run, in this order, the first the "
                        "reference (default: 1, 2, 4 and --gpus)")
    parser.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    parser.add_argument("--tiny", action="store_true", help="tiny models, native view size (smoke test)")
    parser.add_argument("--models", type=Path, default=Path(tempfile.gettempdir()) / "artnvg-random-models",
                        help="batch: folder of the random model files (written once)")
    parser.add_argument("--shared", type=Path, default=SHARED)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.tiny:
        args.models = args.models.with_name(args.models.name + "-tiny")
    count = args.gpus or (torch.cuda.device_count() if args.device == "cuda" else 2)
    devices = [f"cuda:{i}" for i in range(count)] if args.device == "cuda" else ["cpu"] * count
    name = torch.cuda.get_device_name(0) if args.device == "cuda" else "CPU workers (1 thread each)"
    print(f"# {count} x {name}, {'tiny' if args.tiny else 'full-size'} random models, torch {torch.__version__}")
    print("# " + " ".join(["python", *sys.argv]), flush=True)
    rows = ["| run | GPUs | wall s | speed-up | busy fraction per GPU | peak GiB per GPU | output |",
            "|---|---:|---:|---:|---|---|---|"]
    if "groups" in args.sections:
        groups_section(args, devices, rows)
    if "batch" in args.sections:
        batch_section(args, devices, rows)
    print("\n" + "\n".join(rows))


if __name__ == "__main__":
    main()
