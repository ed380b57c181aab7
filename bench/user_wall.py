"""What the user waits for: whole ``stylize`` processes on full-size model files, cold and warm.

    cd bench && python user_wall.py --dir DIR --scene SCENE --cameras T.json --style S.jpg \
        [--runs fast:file,fast:file,fast:folder,balanced:file] [--device cuda] [--json OUT.json] \
        [--keep-caches | --bytecode installed|none] [--lora --more "--steps 4 --cfg-until 0"]

Writes the released model files with random weights into DIR where missing (``model_files.py``),
then runs each ``PRESET:SDXL`` of ``--runs`` in order as a new process, as a user types it:
``python -m artnvg_core stylize SCENE --cameras T --style S --preset PRESET --stylizer diffusion
--sdxl ... --controlnet ... --image-encoder ... --csgo ... --device DEVICE --out ...`` (SDXL ``file``:
the single ``sd_xl_base_1.0.safetensors``; ``folder``: the diffusers folder). ``--preset preview`` needs
no model file. The first process finds the caches as a fresh install leaves them, all in DIR/caches and
emptied when the bench starts: Triton's kernels, torch's compile cache, ArtNVG's and the checkout's Python
bytecode (``PYTHONPYCACHEPREFIX``) empty, the bytecode of the standard library and the installed packages
compiled before it, as installing them does (``--bytecode installed``, the default; ``none``: the first
process compiles every module); ``--keep-caches`` keeps them from an earlier invocation, the page cache
too, so every process is warm. The later processes find what the earlier ones left. ``--lora`` gives
every diffusion process a random LoRA of a few-step LoRA's shape (time only). The model files are
read from the page cache after the first process (the bench asks the kernel to drop it first; whether
it could is printed).

Each process's wall time (launch to exit, seen from here) is split into parts by timers a small
wrapper puts around the command's own calls before it runs the command (``artnvg_core`` is
unchanged): start (Python and the command's imports), scene (loading the scene file), content (rendering
the content views; a first run compiles the rasterizer's forward kernels there), imports (the diffusion
stage's modules: diffusers, transformers, after the content views; what is left of a background load's
imports), models (loading the model files, in a background thread beside the scene, the imports and the
content views: not part of the sum), wait (the rest of the diffusion stage: waiting for the models, grouping), sampling
(conditioning and the groups), finetune (a first run compiles the backward kernels there), save (scene
file and contact sheet) and the rest (argument checks, choosing views, exit). A second table splits
sampling, the GPU waited for at each end of a part: conditioning (text and style encoders), each group's
sampling (its decoding included) and the decoding of all groups. Prints both tables; ``--json`` keeps
them with each process's output.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

from common import print_table

from model_files import write_model_files, write_random_lora

REPO = Path(__file__).resolve().parents[1]
PARTS = ("start", "scene", "content", "imports", "models", "wait", "sampling", "finetune", "save")
OVERLAPPING = ("models",)  # read in the background beside the scene and the content views: not in the sum
SAMPLING = ("conditioning", "group", "decoding")  # parts of sampling, the GPU waited for at both ends

# Runs the command with timers around its calls; writes {part: seconds} to $USER_WALL_PARTS at exit.
WRAPPER = """
import atexit, json, os, runpy, sys, time
launched = float(os.environ["USER_WALL_LAUNCH"])
parts, active = {}, []
from artnvg_core.cli import main as cli, stylize as command
import artnvg_core.stylize as core

def synchronize():
    import torch
    if torch.cuda.is_initialized():
        torch.cuda.synchronize()

def timed(module, name, part, split=False):
    # module.name timed into parts[part]; split: a part of sampling, the GPU waited for at both ends,
    # each call's time also in parts["PART each"]
    call = getattr(module, name)
    def wrapper(*args, **kwargs):
        if split:
            synchronize()
        start, counted = time.time(), "save" not in active  # the contact sheet's renders are saving
        active.append(part)
        try:
            return call(*args, **kwargs)
        finally:
            active.pop()
            if split:
                synchronize()
            if counted:  # the models: the longest load (a prefetch's; the run's own then waits for it)
                elapsed = time.time() - start
                parts[part] = max(parts.get(part, 0.0), elapsed) if part == "models" else parts.get(part, 0.0) + elapsed
                if split:
                    parts.setdefault(part + " each", []).append(time.time() - start)
    setattr(module, name, wrapper)

timed(command, "load_scene_verbose", "scene")
def imports_after(render_views):
    # the content views, then the diffusion stage's modules, as stylize_diffusion imports them after the
    # content views (timed: what is left of a background load's imports), sampling's parts timed
    def wrapper(*args, **kwargs):
        views = render_views(*args, **kwargs)
        if "imports" not in parts:
            start = time.time()
            import artnvg_core.diffusion.conditioning as conditioning
            import artnvg_core.diffusion.sampler as sampler
            import artnvg_core.diffusion.stylize as groups
            parts["imports"] = time.time() - start
            timed(conditioning, "prepare_conditioning", "conditioning", split=True)
            timed(groups, "stylize_owned_views", "group", split=True)
            timed(sampler, "_decode", "decoding", split=True)
        return views
    return wrapper

timed(core, "stylize_diffusion", "diffusion")
timed(core, "load_models_for", "models")
timed(core, "render_views", "content")
core.render_views = imports_after(core.render_views)
timed(core, "finetune", "finetune")
timed(core, "save_result", "save")
parts["start"] = time.time() - launched
atexit.register(lambda: json.dump(parts, open(os.environ["USER_WALL_PARTS"], "w")))
sys.argv[0] = "artnvg_core"  # the command as `python -m artnvg_core` runs it, its exit included
runpy.run_module("artnvg_core", run_name="__main__", alter_sys=True)
"""


def drop_page_cache() -> bool:
    """Ask the kernel to drop its page cache (root on Linux); whether it could."""
    try:
        os.sync()
        Path("/proc/sys/vm/drop_caches").write_text("3\n")
        return True
    except OSError:
        return False


def process_env(caches: Path) -> dict:
    """This process's environment for a stylize process: the checkout on its path, Python's bytecode,
    Triton's, torch's compile and ArtNVG's caches in ``caches``."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env.update(PYTHONPATH=os.pathsep.join([str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])]),
               PYTHONPYCACHEPREFIX=str(caches / "pycache"), TRITON_CACHE_DIR=str(caches / "triton"),
               TORCHINDUCTOR_CACHE_DIR=str(caches / "inductor"), ARTNVG_CACHE_DIR=str(caches / "artnvg"))
    return env


def compile_installed_bytecode(env: dict) -> float:
    """Compile the bytecode of every module on the stylize process's path outside the checkout (the
    standard library and the installed packages) into ``env``'s bytecode cache (``PYTHONPYCACHEPREFIX``),
    as installing them leaves it; returns the seconds it took. Files that do not compile are skipped, as
    pip skips them."""
    start = time.time()
    path = json.loads(subprocess.run([sys.executable, "-c", "import json, sys; print(json.dumps(sys.path))"],
                                     env=env, capture_output=True, text=True, check=True).stdout)
    folders = {str(Path(entry).resolve()) for entry in path if entry and Path(entry).is_dir()}
    installed = sorted(f for f in folders if not Path(f).is_relative_to(REPO))
    subprocess.run([sys.executable, "-m", "compileall", "-q", "-j", "0", *installed], env=env,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.time() - start


def stylize_argv(scene, cameras, style, preset: str, device: str, out: Path, files: dict | None,
                 layout: str = "file", more: list[str] = ()) -> list[str]:
    """The arguments of ``stylize`` as a user types them: ``files`` (:func:`write_model_files`' paths; None for
    the diffusion-free ``preview``) with SDXL as the single ``file`` or the diffusers ``folder``."""
    argv = [str(scene), f"--cameras={cameras}", f"--style={style}", f"--preset={preset}", f"--device={device}",
            f"--out={out}", *more]
    if files is not None:
        argv += ["--stylizer=diffusion", f"--sdxl={files['sdxl' if layout == 'file' else 'sdxl folder']}",
                 f"--controlnet={files['controlnet']}", f"--image-encoder={files['image encoder']}",
                 f"--csgo={files['csgo']}"]
    return argv


def run_process(argv: list[str], env: dict, parts_path: Path, log: Path) -> dict:
    """One stylize process; its wall time, exit status and parts (sampling: what ``stylize_diffusion``
    spent between the content views and the finetune)."""
    launched = time.time()
    env = {**env, "USER_WALL_LAUNCH": repr(launched), "USER_WALL_PARTS": str(parts_path)}
    with open(log, "w") as stream:
        code = subprocess.run([sys.executable, "-c", WRAPPER, "stylize", *argv], stdout=stream, stderr=subprocess.STDOUT,
                              env=env).returncode
    wall = time.time() - launched
    parts = json.loads(parts_path.read_text()) if parts_path.exists() else {}
    if "diffusion" in parts:
        parts["sampling"] = parts.get("conditioning", 0.0) + sum(parts.get("group each", []))
        parts["wait"] = parts.pop("diffusion") - sum(parts.get(p, 0.0) for p in ("imports", "content", "sampling",
                                                                                   "finetune"))
    return {"wall": wall, "exit": code, **parts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dir", required=True, type=Path,
                        help="folder for the model files (kept) and the caches (emptied)")
    parser.add_argument("--scene", required=True)
    parser.add_argument("--cameras", required=True)
    parser.add_argument("--style", required=True)
    parser.add_argument("--runs", default="fast:file,fast:file,fast:folder,balanced:file",
                        help="PRESET:SDXL (file or folder) per process, in order")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--more", default="", help="more stylize options for every process, e.g. '--iters 20'")
    parser.add_argument("--keep-caches", action="store_true",
                        help="keep DIR's caches and the page cache from an earlier invocation: every process warm")
    parser.add_argument("--bytecode", choices=("installed", "none"), default="installed",
                        help="the first process's bytecode of the standard library and the installed packages: "
                        "compiled before it, as installing them leaves it, or none (it compiles every module)")
    parser.add_argument("--lora", action="store_true",
                        help="write a random few-step-sized LoRA (model_files.write_random_lora) and pass it to "
                        "every diffusion process; add its steps and guidance with --more (time only)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    runs = [tuple(item.split(":")) if ":" in item else (item, "file") for item in args.runs.split(",")]

    start = time.time()
    if any(preset != "preview" for preset, _ in runs):
        files = write_model_files(args.dir / "models", args.device,
                                  sdxl_folder=any(layout == "folder" for preset, layout in runs if preset != "preview"))
        print(f"model files ready in {time.time() - start:.0f} s", flush=True)
    if args.lora:
        args.more += f" --lora={write_random_lora(args.dir / 'models' / 'random_lora_rank64.safetensors')}"
    caches, work = args.dir / "caches", args.dir / "runs"
    if not args.keep_caches:
        shutil.rmtree(caches, ignore_errors=True)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    env = process_env(caches)
    if not args.keep_caches and args.bytecode == "installed":
        print(f"installed packages' bytecode compiled in {compile_installed_bytecode(env):.0f} s", flush=True)
    dropped = not args.keep_caches and drop_page_cache()
    print(f"page cache dropped before the first process: {dropped}", flush=True)

    rows, split, report = [], [], []
    for number, (preset, layout) in enumerate(runs, 1):
        argv = stylize_argv(args.scene, args.cameras, args.style, preset, args.device,
                            work / f"{number}_{preset}.ply", files if preset != "preview" else None, layout,
                            args.more.split())
        log = work / f"{number}_{preset}.log"
        result = run_process(argv, env, work / f"{number}.json", log)
        known = sum(result.get(part, 0.0) for part in PARTS if part not in OVERLAPPING)
        row = [number, preset, layout if preset != "preview" else "",
               "cold" if number == 1 and not args.keep_caches else "warm",
               result["wall"], *[result.get(part) for part in PARTS], result["wall"] - known, result["exit"]]
        rows.append(row)
        if "group each" in result:
            split.append([number, preset, row[3], result["conditioning"], *[f"{t:.1f}" for t in result["group each"]],
                          result["decoding"]])
        report.append({"preset": preset, "sdxl": layout, **result, "output": log.read_text()[-4000:]})
        print(row, flush=True)
        if result["exit"] != 0:
            print(log.read_text()[-3000:], flush=True)
        if args.json:
            args.json.write_text(json.dumps({"page_cache_dropped": dropped, "runs": report}, indent=1))
    print_table(f"Whole stylize processes on {args.device} (seconds)",
                ["#", "preset", "SDXL", "caches", "wall", *PARTS, "rest", "exit"], rows,
                "python " + shlex.join(sys.argv))
    if split:
        groups = max(len(row) for row in split) - 5
        print_table("Sampling split (seconds)", ["#", "preset", "caches", "conditioning",
                                                  *[f"group {g + 1}" for g in range(groups)], "decoding"],
                    [row[:-1] + [""] * (groups + 5 - len(row)) + row[-1:] for row in split], "(same run)")


if __name__ == "__main__":
    main()
