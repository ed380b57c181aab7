"""LoRAs on SDXL: checked before any work, fused into the UNet's and text encoders' weights at load time.

A :class:`LoRA` is a ``.safetensors`` file in any layout diffusers reads for SDXL (kohya's
``lora_unet_*`` / ``lora_te1_*`` / ``lora_te2_*`` with ``lora_down``/``lora_up``/``alpha``, diffusers' or
PEFT's ``unet.*.lora_A``/``lora_B``, ...) and a strength. :func:`fuse_loras` loads each through
diffusers/PEFT and merges it into the weights: ``W += strength * (alpha / rank) * up @ down`` for every
layer the file names, summed over the LoRAs, then drops the adapter layers, so sampling runs the
plain models at the plain models' speed (and strength 0 leaves the weights as they were).
"""

from __future__ import annotations

import importlib.util
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

from .quiet_notices import lora_loading_notices_silenced, torchvision_fallback_notice_silenced

PEFT_REQUIREMENT = "peft>=0.21"  # the [lora] extra's (pyproject.toml), named in the message when PEFT is missing
LORA_COMPONENTS = ("unet", "text_encoder", "text_encoder_2")  # what an SDXL LoRA may change


class LoRAError(ValueError):
    """A LoRA file or strength that cannot be used (the message names the file)."""


@dataclass(frozen=True)
class LoRA:
    """A LoRA file (``.safetensors``) and its ``strength`` (a finite number: 1 as trained, 0 no change,
    negative the opposite direction)."""

    path: Path
    strength: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path).expanduser())
        if isinstance(self.strength, bool) or not isinstance(self.strength, (int, float)) or not math.isfinite(
                self.strength):
            raise LoRAError(f"LoRA '{self.path}': strength must be a finite number, got {self.strength!r}")


def parse_lora(text: str) -> LoRA:
    """``FILE`` or ``FILE:STRENGTH`` (the command line's ``--lora``); LoRAError naming the text when the
    strength is not a finite number. A tail holding a path separator is part of the file (``C:\\x``)."""
    path, colon, tail = text.rpartition(":")
    if not colon or not tail or "/" in tail or "\\" in tail:
        return LoRA(Path(text))
    try:
        strength = float(tail)
    except ValueError:
        raise LoRAError(f"--lora '{text}': strength '{tail}' is not a number (FILE or FILE:STRENGTH)") from None
    if not math.isfinite(strength):
        raise LoRAError(f"--lora '{text}': strength must be a finite number, got '{tail}'")
    return LoRA(Path(path), strength)


def check_lora(lora: LoRA) -> None:
    """LoRAError naming the file unless it is a readable ``.safetensors`` whose every tensor is a LoRA's
    (its name holds 'lora' or is an alpha) and finite (a NaN fused into the weights makes every image NaN),
    and unless PEFT, which applies it, is installed (the optional ``lora`` extra); reads each tensor once,
    one at a time."""
    from safetensors import SafetensorError, safe_open

    where = f"LoRA '{lora.path}'"
    if importlib.util.find_spec("peft") is None:
        raise LoRAError(f"{where}: LoRAs are applied through the peft package, which is not installed: "
                        f'pip install "{PEFT_REQUIREMENT}" in the Python that runs ArtNVG (ComfyUI\'s, for the nodes)')
    if not lora.path.is_file():
        raise LoRAError(f"{where}: {'a folder, not a file' if lora.path.is_dir() else 'no such file'}")
    if lora.path.suffix.lower() != ".safetensors":
        raise LoRAError(f"{where}: expected a .safetensors file")
    try:
        with safe_open(os.fspath(lora.path), framework="pt") as file:
            names = list(file.keys())
            foreign = [name for name in names if "lora" not in name.lower() and not name.endswith("alpha")]
            if not names or foreign:
                raise LoRAError(f"{where}: not a LoRA (tensors without 'lora' in their names, e.g. "
                                f"{foreign[:3] if foreign else 'none at all'})")
            not_finite = next((name for name in names if not _finite(file.get_tensor(name))), None)
    except (SafetensorError, OSError) as error:
        raise LoRAError(f"{where}: not a readable .safetensors file ({error})") from None
    if not_finite is not None:
        raise LoRAError(f"{where}: tensor '{not_finite}' holds NaN or infinite values")


def _finite(tensor) -> bool:
    """False for a floating-point tensor holding NaN or an infinity."""
    return not tensor.is_floating_point() or bool(tensor.isfinite().all())


def keep_peft_out() -> None:
    """Make PEFT unimportable in this process (``import peft`` fails, ``find_spec`` finds nothing), for a process
    that fuses no LoRA: diffusers imports PEFT at start-up whenever it is installed (with the transformers
    auto classes PEFT imports: about 0.4 s of CPU), though only :func:`fuse_loras` uses it. Call it before
    diffusers is first imported; afterwards it changes nothing."""
    if "diffusers" not in sys.modules:
        sys.modules.setdefault("peft", None)


def fuse_loras(base, loras: tuple[LoRA, ...]) -> None:
    """Merge ``loras`` into the UNet and text encoders of ``base`` (an
    :class:`~artnvg_core.diffusion.models.SDXLBase`) in place, through a diffusers SDXL pipeline over its
    models (module docstring). LoRAError naming the file for one that diffusers cannot read as an SDXL LoRA
    or that matches no layer of these models."""
    if not loras:
        return
    with torchvision_fallback_notice_silenced():  # the pipeline's module imports transformers' image processors
        from diffusers import EulerDiscreteScheduler, StableDiffusionXLPipeline

    pipe = StableDiffusionXLPipeline(
        vae=base.vae, text_encoder=base.text_encoder, text_encoder_2=base.text_encoder_2, tokenizer=base.tokenizer,
        tokenizer_2=base.tokenizer_2, unet=base.unet,
        scheduler=EulerDiscreteScheduler.from_config(base.scheduler_config), add_watermarker=False)
    names = []
    for index, lora in enumerate(loras):
        check_lora(lora)
        name = f"lora_{index}"
        try:
            with lora_loading_notices_silenced():
                pipe.load_lora_weights(os.fspath(lora.path), adapter_name=name)
        except (ValueError, RuntimeError, KeyError) as error:  # diffusers' and PEFT's for a foreign layout
            raise LoRAError(f"LoRA '{lora.path}': cannot be applied to SDXL ({error})") from None
        if not any(name in adapters for adapters in pipe.get_list_adapters().values()):
            raise LoRAError(f"LoRA '{lora.path}': matches no layer of SDXL's UNet or text encoders "
                             "(a LoRA for another model?)")
        names.append(name)
    pipe.set_adapters(names, adapter_weights=[lora.strength for lora in loras])
    pipe.fuse_lora(components=list(LORA_COMPONENTS), adapter_names=names)
    pipe.unload_lora_weights()
