"""Loading the released single weight files: seconds per loader, full-size random weights.

    python bench/model_loading.py --dir DIR [--device cpu|cuda] [--dtype bf16|fp16] [--repeats 2]

Writes, where DIR lacks them, full-size files with random weights in the released layouts: the Tile
ControlNet as one fp16 ``.safetensors`` with diffusers keys (the SDXL ControlNet architecture of
``TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors``), the IP-Adapter SDXL image encoder
(ViT-bigG/14) as one fp16 ``model.safetensors``, and the SDXL UNet as one fp16 file with the original
checkpoint's keys (``model.diffusion_model.*``, as in ``sd_xl_base_1.0.safetensors``). Then times
:func:`load_controlnet` and :func:`load_image_encoder` from them to ``--device`` in ``--dtype``, and
diffusers' ``UNet2DConditionModel.from_single_file`` (what :func:`load_sdxl` runs for the UNet of a
single file) with and without ``low_cpu_mem_usage`` (diffusers' building without random weights,
which needs the ``accelerate`` package), ``--repeats`` times each (the first read may come from disk,
later ones from the page cache). Prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch
from diffusers import ControlNetModel, UNet2DConditionModel

from common import print_table, synchronize

from artnvg_core.diffusion.architectures import VIT_BIGG_IMAGE_ENCODER_CONFIG, controlnet_config_from_unet
from artnvg_core.diffusion.models import load_controlnet, load_image_encoder
from artnvg_core.diffusion.sdxl_config import built_in_sdxl_config

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from diffusion_tiny import _ldm_unet_keys  # noqa: E402  (diffusers UNet keys -> the original checkpoint's)

DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def write_random_files(folder: Path, unet_config: dict) -> dict[str, Path]:
    """The three files (written once, fp16, random weights) by name."""
    from safetensors.torch import save_file
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    files = {"controlnet": folder / "TTPLANET_Controlnet_Tile_realistic_v2_fp16.safetensors",
             "image encoder": folder / "image_encoder" / "model.safetensors",
             "sdxl unet": folder / "sdxl_unet_original_keys.safetensors"}
    builders = {"controlnet": lambda: ControlNetModel.from_config(controlnet_config_from_unet(unet_config)),
                "image encoder": lambda: CLIPVisionModelWithProjection(CLIPVisionConfig(**{
                    k: v for k, v in VIT_BIGG_IMAGE_ENCODER_CONFIG.items()
                    if k not in ("architectures", "model_type", "torch_dtype", "dtype")})),
                "sdxl unet": lambda: UNet2DConditionModel.from_config(unet_config)}
    for name, path in files.items():
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            model = builders[name]()
            keys = _ldm_unet_keys(model) if name == "sdxl unet" else {}
            prefix = "model.diffusion_model." if name == "sdxl unet" else ""
            state = {prefix + keys.get(k, k): v.half().contiguous() for k, v in model.state_dict().items()}
            save_file(state, str(path))
            print(f"wrote {path} ({path.stat().st_size / 2**30:.2f} GiB)", flush=True)
    return files


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dir", required=True, help="folder for the random-weight files (kept between runs)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="bf16", choices=sorted(DTYPES))
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    device, dtype = torch.device(args.device), DTYPES[args.dtype]
    with built_in_sdxl_config() as folder:
        unet_config = json.loads((Path(folder) / "unet" / "config.json").read_text())
    files = write_random_files(Path(args.dir), unet_config)

    def unet(low_cpu_mem_usage: bool):
        with built_in_sdxl_config() as config:
            return UNet2DConditionModel.from_single_file(
                str(files["sdxl unet"]), config=str(config), subfolder="unet", torch_dtype=dtype,
                low_cpu_mem_usage=low_cpu_mem_usage, local_files_only=True).to(device)

    loaders = {"controlnet": lambda: load_controlnet(files["controlnet"], unet_config=unet_config, dtype=dtype,
                                                     device=device),
               "image encoder": lambda: load_image_encoder(files["image encoder"], dtype=dtype, device=device),
               "sdxl unet": lambda: unet(True),
               "sdxl unet, low_cpu_mem_usage=False (no accelerate)": lambda: unet(False)}
    rows = []
    for name, load in loaders.items():
        file = files[name.split(",")[0]]
        for run in range(1, args.repeats + 1):
            synchronize(device)
            start = time.perf_counter()
            model = load()
            synchronize(device)
            rows.append([name, file.name, f"{file.stat().st_size / 2**30:.2f}", run, time.perf_counter() - start])
            print(rows[-1], flush=True)
            del model
    print_table(f"Loading single weight files to {args.device} in {args.dtype} (torch threads: "
                f"{torch.get_num_threads()})", ["model", "file", "GiB", "run", "seconds"], rows,
                "python " + " ".join(sys.argv))


if __name__ == "__main__":
    main()
