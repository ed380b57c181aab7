"""SDXL 1.0 base without its weights: the diffusers-format folder (``model_index.json``, component
configs, both tokenizers) that ``from_single_file`` needs to build SDXL from
``sd_xl_base_1.0.safetensors``, written from what ships with the package, so that a single-file
checkpoint loads with no network and no Hugging Face cache.

* Configs: :mod:`artnvg_core.diffusion.architectures`; the scheduler is SDXL's Euler
  configuration (the sampler builds its own scheduler from it).
* Tokenizers: OpenAI CLIP's BPE (``clip_bpe/merges.txt.gz``, MIT, see ``clip_bpe/LICENSE``);
  ``vocab.json`` is derived from the merges as CLIP derives it (bytes, bytes + ``</w>``, one token
  per merge, then ``<|startoftext|>`` and ``<|endoftext|>``: 49,408 tokens). The first tokenizer
  pads with ``<|endoftext|>``, the second with ``!``, as in stabilityai/stable-diffusion-xl-base-1.0.
"""

from __future__ import annotations

import gzip
import json
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from .architectures import (
    BIGG_TEXT_CONFIG,
    CLIP_L_TEXT_CONFIG,
    SDXL_SCHEDULER_CONFIG,
    SDXL_UNET_CONFIG,
    SDXL_VAE_CONFIG,
)

CLIP_MERGES = Path(__file__).resolve().parent / "clip_bpe" / "merges.txt.gz"
START, END = "<|startoftext|>", "<|endoftext|>"

MODEL_INDEX = {
    "_class_name": "StableDiffusionXLPipeline",
    "force_zeros_for_empty_prompt": True,
    "scheduler": ["diffusers", "EulerDiscreteScheduler"],
    "text_encoder": ["transformers", "CLIPTextModel"],
    "text_encoder_2": ["transformers", "CLIPTextModelWithProjection"],
    "tokenizer": ["transformers", "CLIPTokenizer"],
    "tokenizer_2": ["transformers", "CLIPTokenizer"],
    "unet": ["diffusers", "UNet2DConditionModel"],
    "vae": ["diffusers", "AutoencoderKL"],
}


def _bytes_to_unicode() -> list[str]:
    """The 256 printable characters CLIP's (and GPT-2's) byte-level BPE uses for bytes 0..255, in CLIP's order."""
    printable = [*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1), *range(ord("®"), ord("ÿ") + 1)]
    others = [b for b in range(256) if b not in printable]
    return [chr(b) for b in printable] + [chr(256 + i) for i in range(len(others))]


def clip_vocabulary(merges_text: str) -> dict[str, int]:
    """CLIP's token -> id map from the text of its ``merges.txt`` (first line a ``#version`` header)."""
    merged = [line.replace(" ", "") for line in merges_text.splitlines()[1:] if line]  # "a b" merges into "ab"
    characters = _bytes_to_unicode()
    tokens = characters + [c + "</w>" for c in characters] + merged + [START, END]
    return {token: index for index, token in enumerate(tokens)}


def _write_json(path: Path, value: Mapping) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value))  # no indent: json's C encoder (the vocabulary's 49,408 entries)


def write_sdxl_config_dir(
    folder: str | Path,
    *,
    unet: Mapping = SDXL_UNET_CONFIG,
    vae: Mapping = SDXL_VAE_CONFIG,
    text_encoder: Mapping = CLIP_L_TEXT_CONFIG,
    text_encoder_2: Mapping = BIGG_TEXT_CONFIG,
) -> Path:
    """Write the weightless SDXL folder into ``folder`` (module docstring); returns it.

    The component configs default to SDXL's; other architectures (tests' tiny models) may be given.
    """
    folder = Path(folder)
    _write_json(folder / "model_index.json", MODEL_INDEX)
    _write_json(folder / "scheduler" / "scheduler_config.json", {
        "_class_name": "EulerDiscreteScheduler", **SDXL_SCHEDULER_CONFIG, "interpolation_type": "linear",
        "prediction_type": "epsilon", "use_karras_sigmas": False})
    _write_json(folder / "unet" / "config.json", {"_class_name": "UNet2DConditionModel", **unet})
    _write_json(folder / "vae" / "config.json", {"_class_name": "AutoencoderKL", **vae})
    for name, config, cls in (("text_encoder", text_encoder, "CLIPTextModel"),
                              ("text_encoder_2", text_encoder_2, "CLIPTextModelWithProjection")):
        _write_json(folder / name / "config.json", {"architectures": [cls], "model_type": "clip_text_model", **config})
    merges = gzip.decompress(CLIP_MERGES.read_bytes()).decode("utf-8")
    vocabulary = clip_vocabulary(merges)
    for name, pad in (("tokenizer", END), ("tokenizer_2", "!")):
        _write_json(folder / name / "vocab.json", vocabulary)
        (folder / name / "merges.txt").write_text(merges, encoding="utf-8")
        _write_json(folder / name / "tokenizer_config.json", {
            "tokenizer_class": "CLIPTokenizer", "model_max_length": 77, "do_lower_case": True, "errors": "replace",
            "bos_token": START, "eos_token": END, "unk_token": END, "pad_token": pad})
    return folder


@contextmanager
def built_in_sdxl_config() -> Iterator[Path]:
    """SDXL's weightless folder, written to a temporary directory removed when the block ends."""
    with tempfile.TemporaryDirectory(prefix="artnvg_sdxl_config_") as folder:
        yield write_sdxl_config_dir(folder)
