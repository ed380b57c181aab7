"""What ``--compile`` costs and saves for one scene on a fresh machine, with and without the compile cache
artifacts of an earlier run (``artnvg_core.diffusion.compile_cache``).

Three child processes run one after the other, each a fresh process (nothing compiled in memory) with
the random full-size models of ``bench/diffusion.py`` and an EMPTY Inductor cache folder of its own
(``TORCHINDUCTOR_CACHE_DIR``), as on a machine that never compiled:

1. ``eager``: one group of ``--views`` views at ``--size`` px, ``--steps`` DDIM steps, NV attention and
   guidance: seconds per step (median of the gaps between steps);
2. ``cold``: the same with ``speed.COMPILED_BLOCKS`` (what ``--compile`` switches on) and no artifact
   file: the first step's extra seconds (compiling), the steady step; then ``save_compile_cache``;
3. ``artifacts``: the same with the file of run 2 loaded first (``load_compile_cache``): the first
   step's extra seconds when the compiled code comes from the file.

Then a group of one view fewer (``--views`` - 1) in runs 2 and 3: the dynamic-shape graphs serve it.
Pay-back: the first step's extra seconds divided by the seconds a compiled step saves, in steps and in
groups of 50.

    python bench/compile_payback.py --json $OUT/compile_payback.json          # H100: about 5 minutes
    python bench/compile_payback.py --tiny --device cpu --size 64 --views 3   # smoke test (Inductor on the CPU)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.diffusion import POOLED_DIM, TINY_POOLED_DIM, build_models, random_conditioning  # noqa: E402

from artnvg_core.diffusion.compile_cache import compile_cache_file, load_compile_cache, save_compile_cache  # noqa: E402
from artnvg_core.diffusion.sampler import SamplerSettings, stylize_group  # noqa: E402
from artnvg_core.diffusion.speed import COMPILED_BLOCKS, apply_speedups  # noqa: E402

MODES = ("eager", "cold", "artifacts")


def group_run(models, conditioning, views: int, args, device: torch.device) -> dict:
    """One group of ``views`` random views: first step, median later step and whole-call seconds."""
    images = torch.rand(views, args.size, args.size, 3, generator=torch.Generator().manual_seed(views))
    stamps = []

    def stamp(*_):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        stamps.append(time.perf_counter())

    settings = SamplerSettings(steps=args.steps, resolution=args.size)
    begin = time.perf_counter()
    stylize_group(models, images, conditioning, settings, progress=stamp)
    stamp()
    gaps = [b - a for a, b in zip(stamps, stamps[1:-1])]
    step = statistics.median(gaps)
    return {"views": views, "first_step_s": stamps[0] - begin, "step_s": step,
            "first_call_extra_s": stamps[0] - begin - step, "call_s": stamps[-1] - begin}


def child(args) -> None:
    """One fresh-process run of ``args.child`` (see the module docstring); writes its record to ``args.out``."""
    from torch._dynamo.utils import counters

    device = torch.device(args.device)
    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    torch.manual_seed(0)
    begin = time.perf_counter()
    models = build_models(args.tiny, device, dtype)
    conditioning = random_conditioning(models, device, dtype, TINY_POOLED_DIM if args.tiny else POOLED_DIM)
    record = {"mode": args.child, "build_s": time.perf_counter() - begin}
    if args.child != "eager":
        apply_speedups(models, COMPILED_BLOCKS)
        loaded = time.perf_counter()
        record["artifacts_loaded"] = load_compile_cache(device) if args.child == "artifacts" else 0
        record["load_s"] = time.perf_counter() - loaded
    record["groups"] = [group_run(models, conditioning, args.views, args, device)]
    if args.child != "eager":
        record["groups"].append(group_run(models, conditioning, args.views - 1, args, device))
        saved = time.perf_counter()
        path = save_compile_cache(device) if args.child == "cold" else None
        record["save_s"] = time.perf_counter() - saved
        record["artifact_bytes"] = path.stat().st_size if path else None
    record["inductor"] = dict(counters["inductor"])
    record["file"] = str(compile_cache_file(device))
    Path(args.out).write_text(json.dumps(record))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tiny", action="store_true", help="tiny models (CPU smoke test)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--size", type=int, default=1024)
    parser.add_argument("--views", type=int, default=14)
    parser.add_argument("--steps", type=int, default=6)
    parser.add_argument("--scene-steps", type=int, default=350, help="a scene's steps for the pay-back (bear: 7 x 50)")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--child", choices=MODES, help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args)
        return
    records = {}
    with tempfile.TemporaryDirectory() as work:
        for mode in MODES:
            env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=str(Path(work) / f"inductor_{mode}"),
                       ARTNVG_CACHE_DIR=str(Path(work) / "artnvg"))
            out = Path(work) / f"{mode}.json"
            command = [sys.executable, __file__, "--child", mode, "--out", str(out), "--device", args.device,
                       "--size", str(args.size), "--views", str(args.views), "--steps", str(args.steps)]
            begin = time.perf_counter()
            subprocess.run(command + (["--tiny"] if args.tiny else []), env=env, check=True)
            records[mode] = dict(json.loads(out.read_text()), process_s=time.perf_counter() - begin)
            print(f"{mode}: {json.dumps(records[mode])}", flush=True)
    eager_step = records["eager"]["groups"][0]["step_s"]
    gpu = torch.cuda.get_device_name(args.device) if torch.device(args.device).type == "cuda" else "CPU"
    print(f"\n{gpu}, {args.views} views at {args.size} px, {args.steps} steps a group, NV + guidance; each run a fresh "
          f"process with an empty Inductor cache. `python {' '.join(sys.argv)}`\n")
    print("| run | first step extra s | step s | group of one view fewer: first step extra s | pay-back steps "
          "| over a scene of {} steps s |".format(args.scene_steps))
    print("|---|---:|---:|---:|---:|---:|")
    for mode in MODES:
        groups = records[mode]["groups"]
        extra, step = groups[0]["first_call_extra_s"], groups[0]["step_s"]
        fewer = f"{groups[1]['first_call_extra_s']:.1f}" if len(groups) > 1 else "-"
        saved = eager_step - step
        payback = "-" if mode == "eager" else (f"{extra / saved:.0f}" if saved > 0 else "never")
        net = (extra + args.scene_steps * step) - args.scene_steps * eager_step
        print(f"| {mode} | {extra:.1f} | {step:.3f} | {fewer} | {payback} | {net:+.1f} |")
    print(f"\nartifacts: {records['cold'].get('artifact_bytes')} bytes, {records['artifacts'].get('artifacts_loaded')} "
          f"loaded in {records['artifacts'].get('load_s', 0):.1f} s; Inductor cache counters, cold: "
          f"{records['cold']['inductor']}, from artifacts: {records['artifacts']['inductor']}")
    if args.json:
        args.json.write_text(json.dumps(records, indent=1))


if __name__ == "__main__":
    main()
