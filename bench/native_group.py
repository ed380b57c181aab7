"""One group of views sampled on ComfyUI's native path and on the library's diffusers path, in one process:
where the native path's time per group goes, kernel by kernel.

Both paths load the same model files (``model_files.py``'s released layouts, random weights; written into
DIR where missing): the library with :func:`~artnvg_core.diffusion.loader.load_models_for` (float16 on CUDA),
ComfyUI with its own loaders (``comfy.sd.load_checkpoint_guess_config``, ``comfy.controlnet.load_controlnet``,
``comfy.clip_vision.load``) imported from COMFYUI's checkout, not through a server. The group is the scene's
first group as ``stylize`` groups its cameras (15 views a group). The native side runs the pack's nodes as
workflow 3 wires them (Apply CSGO, NV-Attention Patch Model, Sample Group) with the inputs that make the
preset (as ``comfyui_native.py`` sets them); the diffusers side runs
:func:`~artnvg_core.diffusion.sampler.stylize_group` at the preset's settings. Prompts are random tensors of
SDXL's shapes on both sides (the text encoders are not part of a group's time). The diffusers path runs
first and its models are dropped before ComfyUI is imported (its import sets PyTorch's global switches, which
would otherwise hold for both). Each path samples the group once to warm up, then ``--repeats`` times, the GPU waited for around each (decoding included); with
``--profile``, ``torch.profiler`` records the last of them and the operations whose self GPU time (then self
CPU time) differs most between the paths are listed.

    cd bench && python native_group.py --comfyui COMFYUI --dir DIR --scene SCENE --cameras T.json \\
        [--preset balanced] [--repeats 2] [--profile]
"""

from __future__ import annotations

import argparse
import gc
import sys
import time
from pathlib import Path

import torch

from comfyui_native import COMFY_SAMPLERS
from common import print_table, synchronize
from first_group import differences, profiled_totals
from model_files import write_model_files

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from artnvg_core.cameras import load_cameras  # noqa: E402
from artnvg_core.diffusion.model_cache import forget_models  # noqa: E402
from artnvg_core.diffusion.model_files import ModelFiles  # noqa: E402
from artnvg_core.diffusion.stylize import group_members  # noqa: E402
from artnvg_core.formats import load_scene  # noqa: E402
from artnvg_core.grouping import ViewGroup, ViewGroups, group_views  # noqa: E402
from artnvg_core.presets import DIFFUSION_PRESETS, PRESETS  # noqa: E402
from artnvg_core.raster.views import render_views  # noqa: E402
from bench.diffusion import POOLED_DIM, random_conditioning  # noqa: E402

TEXT_SHAPE, POOLED_SHAPE = (1, 77, 2048), (1, POOLED_DIM)  # SDXL's prompt embeddings


def native_models(comfy: Path, files: dict):
    """ComfyUI's MODEL, VAE, CONTROL_NET and CLIP_VISION of ``files``, by its own loaders, and the pack's
    nodes (imported as ComfyUI imports a custom node folder)."""
    sys.path.insert(0, str(comfy))
    sys.path.insert(0, str(REPO / "tests" / "integration"))
    import comfy.clip_vision
    import comfy.controlnet
    import comfy.sd
    from native_path import _pack

    patch_nodes, diffusion_nodes = _pack()
    model, _, vae = comfy.sd.load_checkpoint_guess_config(str(files["sdxl"]), output_vae=True, output_clip=False)[:3]
    control_net = comfy.controlnet.load_controlnet(str(files["controlnet"]))
    clip_vision = comfy.clip_vision.load(str(files["image encoder"] / "model.safetensors"))
    csgo = patch_nodes.read_csgo(files["csgo"])
    return model, vae, control_net, clip_vision, csgo, patch_nodes, diffusion_nodes


def native_sampler(comfy: Path, files: dict, preset: str, members: torch.Tensor, centers: torch.Tensor):
    """A call that samples the group on ComfyUI's native path (seed 0), its inputs as ``preset``'s."""
    model, vae, control_net, clip_vision, csgo, patch_nodes, diffusion_nodes = native_models(comfy, files)
    sampler = PRESETS[preset].sampler
    generator = torch.Generator().manual_seed(0)
    text, pooled = torch.randn(TEXT_SHAPE, generator=generator), torch.randn(POOLED_SHAPE, generator=generator)
    positive = [[text, {"pooled_output": pooled}]]
    negative = [[torch.zeros_like(text), {"pooled_output": torch.zeros_like(pooled)}]]
    style = torch.rand((1, 512, 512, 3), generator=generator)
    patched, control = patch_nodes.ApplyCSGO().apply(model, control_net, csgo, clip_vision, style, sampler.style_scale,
                                                      sampler.content_scale, sampler.content_routing)
    (patched,) = patch_nodes.NVAttentionPatch().patch(patched, sampler.neighbour_views, sampler.nv_levels)
    groups = ViewGroups((ViewGroup(tuple(range(len(members)))),), len(members), centers=tuple(map(tuple, centers.tolist())))
    sampler_name, scheduler = COMFY_SAMPLERS[sampler.scheduler]
    return lambda: diffusion_nodes.SampleGroup().sample(
        patched, positive, negative, vae, control, members, groups, 0, 0, sampler.steps, sampler.guidance_scale,
        sampler_name, scheduler, 1.0, sampler.control_scale, sampler.resolution, sampler.size_rule, sampler.cfg_until)


def diffusers_sampler(files: dict, preset: str, members: torch.Tensor, centers: torch.Tensor, device: torch.device):
    """A call that samples the group on the library's diffusers path (seed 0) at ``preset``'s settings."""
    from artnvg_core.diffusion.loader import load_models_for
    from artnvg_core.diffusion.sampler import stylize_group

    models = load_models_for(ModelFiles(files["sdxl"], files["controlnet"], files["image encoder"], files["csgo"]),
                             False, device)
    with torch.no_grad():
        conditioning = random_conditioning(models, device, models.base.unet.dtype, POOLED_DIM)
    settings = PRESETS[preset].sampler
    return lambda: stylize_group(models, members, conditioning, settings, seed=0, view_centers=centers)


def timed_runs(run, device: torch.device, repeats: int, profile: bool) -> tuple[list[float], dict | None]:
    """One warm-up call of ``run``, then ``repeats`` timed ones (seconds); the last one profiled if asked."""
    with torch.inference_mode():
        run()
        seconds, totals = [], None
        for repeat in range(repeats):
            profiled = profile and repeat == repeats - 1
            activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
            profiler = torch.profiler.profile(activities=activities) if profiled else None
            if profiler:
                profiler.__enter__()
            synchronize(device)
            start = time.perf_counter()
            run()
            synchronize(device)
            seconds.append(time.perf_counter() - start)
            if profiler:
                profiler.__exit__(None, None, None)
                totals = profiled_totals(profiler)
    return seconds, totals


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--comfyui", type=Path, required=True, help="a ComfyUI checkout (the folder of main.py)")
    parser.add_argument("--dir", type=Path, required=True, help="where the model files are (written where missing)")
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--cameras", type=Path, required=True)
    parser.add_argument("--preset", choices=DIFFUSION_PRESETS, default="balanced")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--paths", default="diffusers,native", help="which paths, in this order")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--top", type=int, default=15, help="operations listed per profile table")
    args = parser.parse_args()
    device = torch.device("cuda")
    command = "python " + " ".join(sys.argv)
    files = write_model_files(args.dir / "models", device, sdxl_folder=False)
    cameras = load_cameras(args.cameras)
    images = render_views(load_scene(args.scene).to(device), cameras, cpu=True).rgb
    members, centers = group_members(images, group_views(cameras, 15), 0)
    rows, totals = [], {}
    # the diffusers path first, done before ComfyUI is imported (its import sets PyTorch's global switches)
    samplers = {"diffusers": lambda: diffusers_sampler(files, args.preset, members, centers, device),
                "native": lambda: native_sampler(args.comfyui, files, args.preset, members, centers)}
    for name in args.paths.split(","):
        run = samplers[name]()
        seconds, totals[name] = timed_runs(run, device, args.repeats, args.profile)
        rows.append([name, *seconds])
        print(rows[-1], flush=True)
        del run
        forget_models()
        gc.collect()
        torch.cuda.empty_cache()
    title = (f"One group of {len(members)} views, {args.preset} ({torch.cuda.get_device_name(device)}; seconds, "
             "decoding included)")
    print_table(title, ["path", *(f"run {i + 1}" for i in range(args.repeats))], rows, command)
    if args.profile and len(totals) == 2:
        for column, what in ((1, "self GPU"), (0, "self CPU")):
            print_table(f"Where the native path spends more than the diffusers path: {what} ms",
                        ["operation", "native", "diffusers", "calls"],
                        differences(totals["native"], totals["diffusers"], column, args.top), command)
            print_table(f"Where the diffusers path spends more than the native path: {what} ms",
                        ["operation", "diffusers", "native", "calls"],
                        differences(totals["diffusers"], totals["native"], column, args.top), command)
    if args.profile:
        for name, total in totals.items():
            ranked = sorted(total.items(), key=lambda item: -item[1][1])[: args.top]
            print_table(f"{name}: the operations with the most self GPU time (ms)", ["operation", "self GPU", "calls"],
                        [[op[:90], gpu, calls] for op, (_, gpu, calls) in ranked], command)
            print(f"{name}: self GPU {sum(v[1] for v in total.values()):.0f} ms, "
                  f"self CPU {sum(v[0] for v in total.values()):.0f} ms")


if __name__ == "__main__":
    main()
