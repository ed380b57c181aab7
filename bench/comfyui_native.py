"""The bear's job on ComfyUI's own models (the native path) against the library's diffusers path: time per
group, whole run and peak GPU memory, per preset; and the native path in ComfyUI's low-VRAM mode under a
hard memory cap.

    cd bench && python comfyui_native.py --comfyui COMFYUI --dir DIR --scene SCENE --cameras T.json \
        --style S.jpg [--diffusers fast,balanced] [--native fast:2,balanced:1] [--lowvram fast:1] \
        [--cap-gib 12] [--key-views PRESET=K ...] [--device cuda] [--json OUT.json]

COMFYUI is a ComfyUI checkout (the folder of ``main.py``) whose Python (``--comfyui-python``, else this one)
has its requirements; the bench links this pack into its ``custom_nodes``, the model files into its model
folders and the inputs into ``input/``. The model files are the released ones with random weights
(``model_files.py``, written into DIR/models where missing; ComfyUI reads the same files).

- **diffusers**: ``python -m artnvg_core stylize SCENE --preset PRESET --stylizer diffusion ...`` as a whole
  process, each group's time from ``user_wall.py``'s timers (the GPU waited for; its decoding included).
- **native**: a ComfyUI server started fresh (``python main.py``), queued with workflow 3's API twin
  (``workflows_api/``) without its orbit render and previews, its inputs set from the preset
  (:data:`artnvg_core.presets.PRESETS`: key views, steps, guidance and its ``cfg_until``, DDIM as
  ``ddim``/``ddim_uniform``, resolution, NV levels, finetune iterations). Each preset runs ``N`` times on the
  same server, as ``comfyui_wall.py`` runs them: run ``i`` sets Sample Group's seed to ``i - 1``, so later
  runs execute only the sampling and what follows it. Presets after the first find the models loaded.
- **lowvram**: the same on a server started with ``--lowvram --reserve-vram R`` (R: the card's memory
  less the cap, so ComfyUI plans for a card of ``--cap-gib``) through a wrapper that caps PyTorch's
  allocations at ``--cap-gib`` (``torch.cuda.set_per_process_memory_fraction``, after ComfyUI has chosen
  its allocator, checked by an allocation over the cap that must fail) before ComfyUI's ``main.py`` runs.
  The cap bounds what PyTorch allocates (under ComfyUI's default cudaMallocAsync allocator not what its pool
  reserves, which may pass the cap); when the server stops, PyTorch's own peaks (allocated, reserved) over its
  life are printed under the table (nvidia-smi's figure adds the CUDA context and what the pool keeps).

Whole run: a process from launch to exit; a queued workflow from queueing to the end of its execution.
Groups (native): from the websocket's progress messages of Sample Group: group 1 from the node's start
to its last step, group g from group g-1's last step to its own (so it holds group g-1's decoding);
"per group" is the median over groups. Peak memory, the same for every row: the GPU's used memory as
``nvidia-smi`` reports it every 100 ms, during the row's run, less its value before anything started
(CUDA contexts included; none on the CPU). The stylize processes keep their caches (Python's bytecode,
Triton's kernels...) in DIR/caches, the servers in DIR/caches_comfyui, so each path's first run meets
what it left, not what the other compiled. Prints a table; ``--json`` keeps every run.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

from common import print_table
from comfyui_wall import REPO, queue, run_once
from model_files import write_model_files
from user_wall import process_env, run_process, stylize_argv

from artnvg_core.presets import get_preset

WORKFLOW = REPO / "workflows_api" / "ArtNVG_3_full_method_CSGO_SDXL_needs_4_model_files_api.json"
LEFT_OUT = ("Render Camera Path", "Stylized orbit", "Content views")  # nodes the command line has no part of
MODEL_FOLDERS = {"CheckpointLoaderSimple": ("ckpt_name", "checkpoints", "sdxl"),
                 "ControlNetLoader": ("control_net_name", "controlnet", "controlnet"),
                 "CLIPVisionLoader": ("clip_name", "clip_vision", "image encoder"),
                 "ArtNVGLoadCSGO": ("csgo_name", "csgo", "csgo")}
COMFY_SAMPLERS = {"ddim": ("ddim", "ddim_uniform")}  # the library's scheduler -> ComfyUI's sampler, scheduler
INPUTS = "bench_native"  # under ComfyUI's input folder

# Runs ComfyUI's main.py (argv[1:]) with PyTorch's allocations capped at $COMFYUI_NATIVE_CAP_GIB on device 0.
CAPPED = """
import os, runpy, sys
sys.argv = sys.argv[1:]
sys.path.insert(0, os.getcwd())
import comfy.options
comfy.options.enable_args_parsing()
import cuda_malloc  # ComfyUI's choice of allocator, made before torch loads, as main.py makes it
import torch
cap = float(os.environ["COMFYUI_NATIVE_CAP_GIB"]) * 2**30
torch.cuda.set_per_process_memory_fraction(cap / torch.cuda.get_device_properties(0).total_memory, 0)
try:
    probe = torch.empty(int(cap) + 2**28, dtype=torch.uint8, device="cuda")
except RuntimeError as error:  # torch.cuda.OutOfMemoryError
    print(f"memory cap: {cap / 2**30:g} GiB holds (an allocation over it failed: {type(error).__name__})", flush=True)
else:
    sys.exit(f"memory cap: {cap / 2**30:g} GiB does not hold (an allocation over it succeeded)")
torch.cuda.empty_cache()

def peaks(*_):  # at SIGTERM (stop_server): PyTorch's own peaks over the server's life, then exit at once
    try:
        print(f"memory cap: PyTorch's peak allocated {torch.cuda.max_memory_allocated() / 2**30:.2f} GiB, "
              f"peak reserved {torch.cuda.max_memory_reserved() / 2**30:.2f} GiB", flush=True)
    finally:
        os._exit(0)

import signal
signal.signal(signal.SIGTERM, peaks)
runpy.run_path("main.py", run_name="__main__")
"""


class MemoryWatch:
    """The GPU's used memory (nvidia-smi, every 100 ms) in the background; :meth:`peak` in GiB above the
    first second's median. Inactive without nvidia-smi or ``active`` False."""

    def __init__(self, active: bool):
        self.samples: list[tuple[float, float]] = []
        self.process, self.baseline = None, None
        if active and shutil.which("nvidia-smi"):
            index = (os.environ.get("CUDA_VISIBLE_DEVICES") or "0").split(",")[0]  # the GPU CUDA sees first
            self.process = subprocess.Popen(["nvidia-smi", "-i", index, "--query-gpu=memory.used",
                                             "--format=csv,noheader,nounits", "-lms", "100"],
                                            stdout=subprocess.PIPE, text=True)
            threading.Thread(target=self._read, daemon=True).start()
            time.sleep(1.5)
            self.baseline = statistics.median(used for _, used in self.samples) if self.samples else 0.0

    def _read(self) -> None:
        for line in self.process.stdout:
            if line.strip().isdigit():
                self.samples.append((time.perf_counter(), int(line) / 1024))

    def peak(self, since: float, until: float) -> float | None:
        window = [used for moment, used in self.samples if since <= moment <= until]
        return max(window) - self.baseline if self.process and window else None

    def stop(self) -> None:
        if self.process:
            self.process.terminate()


def native_workflow(preset_name: str, key_views: int | None) -> dict:
    """Workflow 3's API twin less :data:`LEFT_OUT`, its inputs set to do what ``stylize --preset`` does."""
    preset = get_preset(preset_name)
    sampler = preset.sampler
    if sampler.scheduler not in COMFY_SAMPLERS:
        raise ValueError(f"preset {preset_name}: scheduler {sampler.scheduler!r} has no ComfyUI twin here")
    workflow = queue.load_api_workflow(WORKFLOW)
    for title in LEFT_OUT:
        del workflow[queue.find_node(workflow, title)]
    sampler_name, scheduler = COMFY_SAMPLERS[sampler.scheduler]
    settings = {
        "Load Gaussian Scene.scene_file": f"{INPUTS}/scene.ply", "Load Cameras.camera_source": f"{INPUTS}/transforms.json",
        "Style image.image": f"{INPUTS}_style.jpg",
        "Render Views.key_views": preset.key_views if key_views is None else key_views,
        "NV-Attention Patch Model.enabled": sampler.neighbour_views, "NV-Attention Patch Model.levels": sampler.nv_levels,
        "Apply CSGO.style_scale": sampler.style_scale, "Apply CSGO.content_scale": sampler.content_scale,
        "Apply CSGO.content_routing": sampler.content_routing,
        "Sample Group.steps": sampler.steps, "Sample Group.cfg": sampler.guidance_scale,
        "Sample Group.cfg_until": sampler.cfg_until,
        "Sample Group.sampler_name": sampler_name, "Sample Group.scheduler": scheduler,
        "Sample Group.resolution": sampler.resolution, "Sample Group.size_rule": sampler.size_rule,
        "Sample Group.control_scale": sampler.control_scale, "Sample Group.seed": 0,
        "Finetune Gaussians.iterations": preset.finetune_iterations,
        "Finetune Gaussians.views_per_step": preset.views_per_step, "Finetune Gaussians.seed": 0,
    }
    for assignment, value in settings.items():
        queue.apply_override(workflow, f"{assignment}={json.dumps(value)}")
    return workflow


def prepare_comfyui(comfy: Path, files: dict, scene: Path, cameras: Path, style: Path) -> None:
    """This pack in custom_nodes (unless linked there), the model files linked into the model folders under the
    workflow's names, and the inputs copied into input/."""
    nodes = comfy / "custom_nodes"
    if not any(entry.is_symlink() and entry.resolve() == REPO for entry in nodes.iterdir()):
        (nodes / "artnvg-comfyui").symlink_to(REPO, target_is_directory=True)
    for spec in queue.load_api_workflow(WORKFLOW).values():
        if spec["class_type"] in MODEL_FOLDERS:
            field, folder, role = MODEL_FOLDERS[spec["class_type"]]
            source = files[role] / "model.safetensors" if files[role].is_dir() else files[role]
            link = comfy / "models" / folder / spec["inputs"][field]
            link.parent.mkdir(parents=True, exist_ok=True)
            link.unlink(missing_ok=True)
            link.symlink_to(source.resolve())
    inputs = comfy / "input" / INPUTS
    inputs.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(scene, inputs / "scene.ply")
    shutil.copyfile(cameras, inputs / "transforms.json")
    shutil.copyfile(style, comfy / "input" / f"{INPUTS}_style.jpg")


def start_server(python: str, comfy: Path, port: int, log: Path, frontend: Path, extra: list[str],
                 cap_gib: float | None, caches: Path) -> tuple[subprocess.Popen, float]:
    """A ComfyUI server (capped: through :data:`CAPPED`), its caches in ``caches`` (as
    :func:`user_wall.process_env`'s, the checkout left off its path), and the seconds until it answered."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/system_stats", timeout=5):
            raise RuntimeError(f"a server answers on port {port} already; stop it or pass another --port")
    except OSError:
        pass
    entry = ["-c", CAPPED, "main.py"] if cap_gib else ["main.py"]
    env = {**process_env(caches), "PYTHONPATH": os.environ.get("PYTHONPATH", ""),
           **({"COMFYUI_NATIVE_CAP_GIB": str(cap_gib)} if cap_gib else {})}
    launched = time.perf_counter()
    with log.open("w") as output:
        server = subprocess.Popen([python, *entry, "--listen", "127.0.0.1", "--port", str(port), "--front-end-root",
                                   str(frontend), *extra], cwd=comfy, stdout=output, stderr=subprocess.STDOUT, env=env)
    while time.perf_counter() - launched < 600:
        if server.poll() is not None:
            raise RuntimeError(f"ComfyUI exited with status {server.returncode}:\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/system_stats", timeout=5):
                return server, time.perf_counter() - launched
        except OSError:
            time.sleep(0.5)
    server.terminate()
    raise RuntimeError(f"ComfyUI did not answer within 600 s; see {log}")


def stop_server(server: subprocess.Popen) -> None:
    server.terminate()
    try:
        server.wait(timeout=60)
    except subprocess.TimeoutExpired:
        server.kill()


def native_groups(run: dict, node: str, steps: int) -> list[float]:
    """Seconds per group of Sample Group (``node``) from its progress messages (see the module docstring): its
    bar is the first one the node started of those it completed whose length is a multiple of ``steps`` (a
    node may show other bars, e.g. a tiled decoding's fallback after the first group)."""
    bars: dict[int, dict[int, float]] = {}
    for name, value, total, moment in run["progress"]:
        if name == node and total % steps == 0:
            bars.setdefault(total, {}).setdefault(value, moment)
    complete = [total for total, seen in bars.items() if len(seen) == total]
    start = run["spans"].get(node, [None])[0]
    if start is None or not complete:
        return []
    total = min(complete, key=lambda length: bars[length][1])
    marks = [start] + [bars[total][value] for value in range(steps, total + 1, steps)]
    return [b - a for a, b in zip(marks, marks[1:])]


def runs_per_preset(text: str) -> list[tuple[str, int]]:
    """``fast:2,balanced:1`` -> [("fast", 2), ("balanced", 1)]; a preset without a count runs once."""
    pairs = [item.partition(":") for item in text.split(",") if item]
    return [(name, int(count or 1)) for name, _, count in pairs]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--comfyui", required=True, type=Path, help="a ComfyUI checkout (the folder of main.py)")
    parser.add_argument("--comfyui-python", default=sys.executable)
    parser.add_argument("--dir", required=True, type=Path, help="model files (kept), caches and logs")
    parser.add_argument("--scene", required=True, type=Path)
    parser.add_argument("--cameras", required=True, type=Path)
    parser.add_argument("--style", required=True, type=Path)
    parser.add_argument("--diffusers", default="fast,balanced", help="presets run as stylize processes")
    parser.add_argument("--native", default="fast:2,balanced:1", help="PRESET:RUNS queued on one fresh server")
    parser.add_argument("--lowvram", default="fast:1", help="PRESET:RUNS on one fresh low-VRAM, capped server")
    parser.add_argument("--cap-gib", type=float, default=12.0)
    parser.add_argument("--key-views", action="append", default=[], metavar="PRESET=K",
                        help="stylize that preset on K key views instead of its own number (0: every view)")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--port", type=int, default=8189)
    parser.add_argument("--timeout", type=float, default=1200, help="seconds a queued run may take")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    key_views = {name: int(k) for name, _, k in (item.partition("=") for item in args.key_views)}
    gpu = args.device != "cpu"
    begin = time.perf_counter()

    def say(text: str) -> None:
        print(f"[{time.perf_counter() - begin:.0f} s] {text}", flush=True)

    files = write_model_files(args.dir / "models", args.device)
    if gpu:
        import torch
        torch.cuda.empty_cache()  # the baseline below then holds this process's CUDA context alone
    say("model files ready")
    prepare_comfyui(args.comfyui, files, args.scene, args.cameras, args.style)
    frontend, logs = args.dir / "frontend", args.dir / "logs"
    for folder in (frontend, logs, args.dir / "out"):
        folder.mkdir(parents=True, exist_ok=True)
    (frontend / "index.html").write_text("<!doctype html><title>no frontend: a benchmark server</title>\n")
    watch = MemoryWatch(gpu)
    rows, report, notes = [], [], []

    def record(preset: str, path: str, groups: list[float], wall: float, peak: float | None, end: str, **more) -> None:
        rows.append([preset, path, statistics.median(groups) if groups else None,
                     " ".join(f"{g:.1f}" for g in groups), wall, peak, end])
        report.append({"preset": preset, "path": path, "groups": groups, "wall": wall, "peak_gib": peak, "end": end,
                       **more})
        say(f"{preset}, {path}: {end}, wall {wall:.1f} s, groups {rows[-1][3]}, peak {peak} GiB")
        if args.json:
            args.json.write_text(json.dumps({"baseline_gib": watch.baseline, "runs": report}, indent=1))

    for preset in filter(None, args.diffusers.split(",")):
        more = [f"--key-views={key_views[preset]}"] if preset in key_views else []
        log = logs / f"diffusers_{preset}.log"
        argv = stylize_argv(args.scene, args.cameras, args.style, preset, args.device,
                            args.dir / "out" / f"{preset}.ply", files, more=more)
        since = time.perf_counter()
        result = run_process(argv, process_env(args.dir / "caches"), logs / f"diffusers_{preset}.json", log)
        record(preset, "diffusers: stylize process", result.get("group each", []), result["wall"],
               watch.peak(since, time.perf_counter()), "success" if result["exit"] == 0 else f"exit {result['exit']}",
               parts=result, output=log.read_text()[-3000:])

    if gpu:  # ComfyUI plans with torch's view of the card, less what --reserve-vram keeps back
        import torch
        total = torch.cuda.get_device_properties(0).total_memory / 2**30
    low = ["--lowvram", "--reserve-vram", f"{total - args.cap_gib:.2f}"] if gpu else ["--cpu"]
    for label, plan, extra, cap in (("native", args.native, [] if gpu else ["--cpu"], None),
                                    (f"native --lowvram, {args.cap_gib:g} GiB cap", args.lowvram, low, args.cap_gib)):
        plan = runs_per_preset(plan)
        if not plan:
            continue
        log = logs / f"comfyui_{'lowvram' if cap else 'native'}_{args.port}.log"  # one per invocation
        since = time.perf_counter()
        try:
            server, started = start_server(args.comfyui_python, args.comfyui, args.port, log, frontend, extra,
                                           cap if gpu else None, args.dir / "caches_comfyui")
        except RuntimeError as error:
            record(plan[0][0], label, [], time.perf_counter() - since, None, "server failed", error=str(error))
            continue
        say(f"{label}: server answered in {started:.1f} s")
        fresh = True
        try:
            for preset, count in plan:
                workflow = native_workflow(preset, key_views.get(preset))
                node = queue.find_node(workflow, "Sample Group")
                for number in range(1, count + 1):
                    queue.apply_override(workflow, f"Sample Group.seed={number - 1}")
                    since = time.perf_counter()
                    try:
                        run = run_once(f"http://127.0.0.1:{args.port}", workflow, args.timeout)
                    except (queue.RejectedError, ConnectionError, OSError) as error:
                        record(preset, f"{label}, run {number}", [], time.perf_counter() - since, None, "failed",
                               error=str(getattr(error, "details", error)), log=log.read_text()[-3000:])
                        break
                    where = (f"fresh server, up in {started:.1f} s" if fresh else
                             "sampling on" if number > 1 else "models loaded")
                    record(preset, f"{label}, run {number} ({where})",
                           native_groups(run, node, get_preset(preset).sampler.steps), run["wall"],
                           watch.peak(since, time.perf_counter()), run["end"], nodes=run["nodes"], log=log.read_text()[-3000:] if run["end"] != "success" else "")
                    fresh = False
        finally:
            stop_server(server)
        notes += [f"{label}: {line}" for line in log.read_text().splitlines() if line.startswith("memory cap:")]
    watch.stop()
    print_table("The bear's job: ComfyUI's native path against the diffusers path (seconds, GiB)",
                ["preset", "path", "per group (median)", "groups", "whole run", "peak GiB", "end"], rows,
                "python " + shlex.join(sys.argv))
    print("\n".join(["", *notes]))
    if args.json:
        args.json.write_text(json.dumps({"baseline_gib": watch.baseline, "runs": report,
                                         "notes": notes}, indent=1))


if __name__ == "__main__":
    main()
