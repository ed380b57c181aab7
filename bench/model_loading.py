"""Loading the released single weight files: seconds per loader, full-size random weights.

    python bench/model_loading.py --dir DIR [--device cpu|cuda] [--dtype bf16|fp16] [--repeats 2]

Writes, where DIR lacks them, full-size files with random weights in the released layouts
(``model_files.py``). Then times :func:`load_controlnet` (the Tile ControlNet's fp16 ``.safetensors``)
and :func:`load_image_encoder` (the image encoder's ``model.safetensors``) to ``--device`` in ``--dtype``,
and diffusers' ``UNet2DConditionModel.from_single_file`` on ``sd_xl_base_1.0.safetensors`` (what
:func:`load_sdxl` runs for the UNet of a single file) with and without ``low_cpu_mem_usage``
(diffusers' building without random weights, which needs the ``accelerate`` package), and
:func:`load_diffusion_models` on all four files (SDXL's single file, the ControlNet, the image
encoder's folder, ``csgo_4_32.bin``: what a stylize run loads), ``--repeats`` times each (the first
read may come from disk, later ones from the page cache). Prints a table.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from diffusers import UNet2DConditionModel

from common import print_table, synchronize
from model_files import write_model_files

from artnvg_core.diffusion.architectures import SDXL_UNET_CONFIG
from artnvg_core.diffusion.model_cache import file_key
from artnvg_core.diffusion.model_files import ModelFiles
from artnvg_core.diffusion.models import load_controlnet, load_diffusion_models, load_image_encoder
from artnvg_core.diffusion.sdxl_config import built_in_sdxl_config

DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dir", required=True, help="folder for the random-weight files (kept between runs)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="bf16", choices=sorted(DTYPES))
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    device, dtype = torch.device(args.device), DTYPES[args.dtype]
    files = write_model_files(Path(args.dir), device)
    four = ModelFiles(files["sdxl"], files["controlnet"], files["image encoder"], files["csgo"])
    files["image encoder"] = files["image encoder"] / "model.safetensors"

    def unet(low_cpu_mem_usage: bool):
        with built_in_sdxl_config() as config:
            return UNet2DConditionModel.from_single_file(
                str(files["sdxl"]), config=str(config), subfolder="unet", torch_dtype=dtype,
                low_cpu_mem_usage=low_cpu_mem_usage, local_files_only=True).to(device)

    loaders = {"controlnet": lambda: load_controlnet(files["controlnet"], unet_config=SDXL_UNET_CONFIG, dtype=dtype,
                                                     device=device),
               "image encoder": lambda: load_image_encoder(files["image encoder"], dtype=dtype, device=device),
               "sdxl": lambda: unet(True),
               "sdxl, low_cpu_mem_usage=False (no accelerate)": lambda: unet(False),
               "all four": lambda: load_diffusion_models(four, dtype=dtype, device=device)}
    rows = []
    for name, load in loaders.items():
        paths = [path for _, path in four.items()] if name == "all four" else [files[name.split(",")[0]]]
        size = sum(size for path in paths for _, size, _ in file_key(path)[1])
        for run in range(1, args.repeats + 1):
            synchronize(device)
            start = time.perf_counter()
            model = load()
            synchronize(device)
            rows.append([name, ", ".join(path.name for path in paths), f"{size / 2**30:.2f}", run,
                         time.perf_counter() - start])
            print(rows[-1], flush=True)
            del model
    print_table(f"Loading single weight files to {args.device} in {args.dtype} (torch threads: "
                f"{torch.get_num_threads()})", ["model", "file", "GiB", "run", "seconds"], rows,
                "python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
