"""Loading the released single weight files: seconds per loader, full-size random weights.

    python bench/model_loading.py --dir DIR [--device cpu|cuda] [--dtype bf16|fp16] [--repeats 2] [--loads NAME ...]

Writes, where DIR lacks them, full-size files with random weights in the released layouts
(``model_files.py``). Then times reading ``sd_xl_base_1.0.safetensors``'s tensors alone
(:func:`~artnvg_core.tensor_files.read_tensors`), :func:`load_controlnet` (the Tile ControlNet's fp16 ``.safetensors``)
and :func:`load_image_encoder` (the image encoder's ``model.safetensors``) to ``--device`` in ``--dtype``,
:func:`load_sdxl` on ``sd_xl_base_1.0.safetensors`` (read straight to the device, converted there) and,
for comparison, diffusers' ``StableDiffusionXLPipeline.from_single_file`` on it then moved to the device
(how :func:`load_sdxl` loaded it before), and :func:`load_diffusion_models` on all four files (SDXL's
single file, the ControlNet, the image encoder's folder, ``csgo_4_32.bin``: what a stylize run loads),
``--repeats`` times each (the first read may come from disk, later ones from the page cache); ``--loads`` picks
rows by name (``sdxl``, ``all four`` ...).

Each load runs alone, then again beside a thread that counts in Python (as the command's main thread
renders beside the background load), within :func:`~artnvg_core.background.brief_switches` as the
command's background load runs (with the interpreter's default 5 ms switch interval, each of a loader's
thousands of calls into C waits for the counting thread's turn to end: minutes): "beside s" is that load's
time, "others' GIL share" the thread's count per second during it over its count alone, so 1 means the
loading left the interpreter lock to the rest of the process (it waited in system calls and device
copies), 0 that it held it throughout. "thread CPU s" is the CPU time of the thread that called the load
(alone): its own work, Python and the calls it waits in, whatever other processes take of a shared CPU
(the readers' threads of a CUDA load are not in it). Prints a table.
"""

from __future__ import annotations

import argparse
import gc
import sys
import threading
import time
from pathlib import Path

import torch

from common import print_table, synchronize
from model_files import write_model_files

from artnvg_core.background import brief_switches
from artnvg_core.diffusion.architectures import SDXL_UNET_CONFIG
from artnvg_core.diffusion.model_cache import file_key
from artnvg_core.diffusion.model_files import ModelFiles
from artnvg_core.diffusion.models import load_controlnet, load_diffusion_models, load_image_encoder, load_sdxl
from artnvg_core.diffusion.sdxl_config import built_in_sdxl_config
from artnvg_core.tensor_files import read_tensors

DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dir", required=True, help="folder for the random-weight files (kept between runs)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="bf16", choices=sorted(DTYPES))
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--loads", nargs="+", help="the rows to time, by name (default: every row)")
    args = parser.parse_args()
    device, dtype = torch.device(args.device), DTYPES[args.dtype]
    files = write_model_files(Path(args.dir), device, sdxl_folder=False)
    four = ModelFiles(files["sdxl"], files["controlnet"], files["image encoder"], files["csgo"])
    files["image encoder"] = files["image encoder"] / "model.safetensors"

    def pipeline():  # SDXL as load_sdxl read it before: diffusers' pipeline on the CPU, then moved
        from diffusers import StableDiffusionXLPipeline

        with built_in_sdxl_config() as config:
            pipe = StableDiffusionXLPipeline.from_single_file(str(files["sdxl"]), config=str(config), torch_dtype=dtype,
                                                              local_files_only=True, add_watermarker=False)
        return [part.to(device) for part in (pipe.unet, pipe.vae, pipe.text_encoder, pipe.text_encoder_2)]

    loaders = {"sdxl, read only": lambda: read_tensors(files["sdxl"], device),
               "controlnet": lambda: load_controlnet(files["controlnet"], unet_config=SDXL_UNET_CONFIG, dtype=dtype,
                                                     device=device),
               "image encoder": lambda: load_image_encoder(files["image encoder"], dtype=dtype, device=device),
               "sdxl": lambda: load_sdxl(files["sdxl"], dtype=dtype, device=device),
               "all four": lambda: load_diffusion_models(four, dtype=dtype, device=device),
               "sdxl, diffusers from_single_file then moved (before)": pipeline}
    if args.loads:
        unknown = set(args.loads) - set(loaders)
        if unknown:
            parser.error(f"--loads: unknown {sorted(unknown)}; the rows are {list(loaders)}")
        loaders = {name: load for name, load in loaders.items() if name in args.loads}
    idle = Ticker().rate(1.0)
    rows = []
    for name, load in loaders.items():
        paths = [path for _, path in four.items()] if name == "all four" else [files[name.split(",")[0]]]
        size = sum(size for path in paths for _, size, _ in file_key(path)[1])
        for run in range(1, args.repeats + 1):
            seconds, cpu = timed_load(load, device)
            with Ticker() as ticker, brief_switches():
                beside, _ = timed_load(load, device)
            rows.append([name, ", ".join(path.name for path in paths), f"{size / 2**30:.2f}", run, seconds, cpu, beside,
                         f"{ticker.count / beside / idle:.2f}"])
            print(rows[-1], flush=True)
    print_table(f"Loading single weight files to {args.device} in {args.dtype} (torch threads: "
                f"{torch.get_num_threads()})",
                ["model", "file", "GiB", "run", "seconds", "thread CPU s", "beside s", "others' GIL share"], rows,
                "python " + " ".join(sys.argv))


def timed_load(load, device: torch.device) -> tuple[float, float]:
    """(seconds, the calling thread's CPU seconds) of ``load()``, the device waited for at both ends and the
    interpreter's garbage collected before (a full collection takes 0.25-0.4 s on a 2-core CPU: one that the
    objects of earlier loads set off would fall in this load's figures, in some rows and not others); what it
    loaded is dropped."""
    synchronize(device)
    gc.collect()
    start, cpu = time.perf_counter(), time.thread_time()
    model = load()
    synchronize(device)
    seconds, cpu = time.perf_counter() - start, time.thread_time() - cpu
    del model
    return seconds, cpu


class Ticker:
    """A thread counting in Python while the block runs (``count``); :meth:`rate`: counts per second alone."""

    def __init__(self) -> None:
        self.count, self._running = 0, False

    def _tick(self) -> None:
        while self._running:
            self.count += 1

    def __enter__(self) -> "Ticker":
        self._running, self._thread = True, threading.Thread(target=self._tick, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *_) -> None:
        self._running = False
        self._thread.join()

    def rate(self, seconds: float) -> float:
        with self:
            time.sleep(seconds)
        return self.count / seconds


if __name__ == "__main__":
    main()
