"""Compile work kept across runs: PyTorch's compile cache artifacts in one file per machine kind.

``torch.compile`` spends its first call on tracing and generating kernels (for the UNet's and the
ControlNet's repeated blocks, over a minute: BENCHMARKS.md, "Diffusion step") and keeps Inductor's results in the
system's temporary folder, which a reboot or a fresh container empties. PyTorch can export what a
process compiled or found in that cache (``torch.compiler.save_cache_artifacts``: generated code,
AOTAutograd graphs, autotuning results) and load it into another process before it compiles
(``torch.compiler.load_cache_artifacts``), which then finds those results instead of generating them.

:func:`load_compile_cache` loads the file, if any, before the first compiled call;
:func:`save_compile_cache` writes this process's artifacts after the compiled models have run (the
latest run's set replaces the file's). The file is ``compile/torch-<version>-<device name>.bin``
under ``$ARTNVG_CACHE_DIR`` (default ``~/.cache/artnvg``), written atomically. PyTorch checks its
own versions and the code before using an artifact, so a stale file costs nothing but its loading.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import torch

from ..fileio import write_atomically

CACHE_DIR_VARIABLE = "ARTNVG_CACHE_DIR"


def cache_root() -> Path:
    """``$ARTNVG_CACHE_DIR``, else ``~/.cache/artnvg``."""
    return Path(os.environ.get(CACHE_DIR_VARIABLE) or Path.home() / ".cache" / "artnvg")


def compile_cache_file(device: str | torch.device) -> Path:
    """The artifact file for this PyTorch version and ``device``'s kind (its CUDA device name, or its type)."""
    device = torch.device(device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else device.type
    label = re.sub(r"[^A-Za-z0-9.+-]+", "_", f"torch-{torch.__version__}-{name}")
    return cache_root() / "compile" / f"{label}.bin"


def load_compile_cache(device: str | torch.device) -> int:
    """Load the artifact file of ``device`` into this process's compile caches; returns how many artifacts
    it held (0: no file, or one PyTorch could not read)."""
    path = compile_cache_file(device)
    if not path.is_file():
        return 0
    info = torch.compiler.load_cache_artifacts(path.read_bytes())
    return 0 if info is None else sum(len(keys) for keys in info.artifacts.values())


def save_compile_cache(device: str | torch.device) -> Path | None:
    """Write the artifacts this process compiled or found since it started to ``device``'s file (replacing
    it); returns the path, or None when there was nothing to save."""
    saved = torch.compiler.save_cache_artifacts()
    if saved is None:
        return None
    path = compile_cache_file(device)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda file: file.write(saved[0]))
    return path
