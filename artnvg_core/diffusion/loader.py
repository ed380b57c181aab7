"""The one loader of the diffusion models for a device (:func:`load_models_for`): the command line's and
the workers'; once per process, placed for the memory mode, compiled where asked. Finding the files is
:mod:`.model_files`'s."""

from __future__ import annotations

import functools
from pathlib import Path

import torch

from ..background import brief_switches
from ..progress import Cancelled, ProgressFn, StopFn
from .lora import LoRA, LoRAError
from .model_cache import file_key, load_once
from .model_files import ModelFiles


class DiffusionModelsUnavailable(ValueError):
    """The diffusion models could not be loaded (the message says why)."""


def load_models_for(files: ModelFiles, low_memory: bool, device: str | torch.device, compile_blocks: bool = False,
                    *, loras: tuple[LoRA, ...] = (), dtype: torch.dtype | None = None,
                    sdxl_config_dir: str | Path | None = None, on_cpu: bool = False, progress: ProgressFn | None = None,
                    should_stop: StopFn | None = None):
    """The diffusion models of ``files`` for ``device``: the one loader of the command line and the
    workers.

    loras: fused into SDXL (:func:`.lora.fuse_loras`).
    dtype: default float16 on CUDA, float32 elsewhere. Placement: on ``device``; with ``low_memory`` loaded
    on the CPU and placed by :func:`.memory.enable_low_memory`; with ``on_cpu`` left on the CPU whatever the
    memory mode (the caller places them when they run). ``compile_blocks`` applies
    :data:`.speed.COMPILED_BLOCKS` (full memory only: with ``low_memory`` a ValueError) and loads an earlier
    run's compile artifacts (:mod:`.compile_cache`). Loaded once per process: the same files (path, size and
    modification time), device and options return the same models (:mod:`.model_cache`). Any failure to
    load raises :class:`DiffusionModelsUnavailable` saying why; a stop (``should_stop``, checked before each
    model) raises :class:`~artnvg_core.progress.Cancelled`. While it runs, Python threads hand the interpreter
    lock over every 0.1 ms (:func:`~artnvg_core.background.brief_switches`: a load in a background thread
    beside a busy one). ``progress`` follows the bytes loaded
    (:func:`.models.load_diffusion_models`). A module-level function, so a ``functools.partial`` of it can
    be sent to worker processes."""
    if compile_blocks and low_memory:
        raise ValueError("compile: the compiled blocks run in the full-memory mode only, not with low memory")
    device = indexed_device(device)
    dtype = dtype or (torch.float16 if device.type == "cuda" else torch.float32)
    key = ("diffusion models", tuple(file_key(path) for _, path in files.items()),
           tuple((file_key(lora.path), lora.strength) for lora in loras), file_key(sdxl_config_dir),
           str(dtype), str(device), low_memory, compile_blocks, on_cpu)
    with brief_switches():  # loaded beside other threads' Python (background.py)
        return load_once(key, functools.partial(_load_models, files, tuple(loras), low_memory, device,
                                                compile_blocks, dtype, sdxl_config_dir, on_cpu, progress, should_stop))


def indexed_device(device: str | torch.device) -> torch.device:
    """``device`` as a tensor on it names it (the key of the loaded models): ``cuda`` is the current CUDA
    device, ``cuda:0`` say."""
    device = torch.device(device)
    return torch.device("cuda", torch.cuda.current_device()) if device.type == "cuda" and device.index is None \
        else device


def _load_models(files: ModelFiles, loras: tuple[LoRA, ...], low_memory: bool, device: torch.device,
                 compile_blocks: bool, dtype: torch.dtype, sdxl_config_dir: str | Path | None, on_cpu: bool,
                 progress: ProgressFn | None, should_stop: StopFn | None):
    """:func:`load_models_for` without the once-per-process cache."""
    from .compile_cache import load_compile_cache
    from .memory import enable_low_memory  # imports diffusers: only when loading
    from .models import load_diffusion_models
    from .speed import COMPILED_BLOCKS, apply_speedups

    try:
        models = load_diffusion_models(files, sdxl_config_dir=sdxl_config_dir, dtype=dtype, loras=loras,
                                       device="cpu" if low_memory or on_cpu else device, progress=progress,
                                       should_stop=should_stop)
    except (Cancelled, LoRAError):  # a stop, or the user's LoRA is wrong: no fallback to another stylizer
        raise
    except Exception as error:  # a loader can fail in many ways (missing or corrupt file, format, memory)
        raise DiffusionModelsUnavailable(f"diffusion models could not be loaded: {error}") from error
    if low_memory and not on_cpu:
        enable_low_memory(models, device)
    if compile_blocks:
        apply_speedups(models, COMPILED_BLOCKS)
        load_compile_cache(device)
    return models
