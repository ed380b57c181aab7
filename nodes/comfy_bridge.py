"""The pack's only contact with ComfyUI's own modules, each imported lazily and optionally.

Inside ComfyUI this uses ``folder_paths`` (input/output/model folders),
``comfy.utils.ProgressBar`` (the node's progress bar), ``server.PromptServer`` with
``comfy_execution.utils`` (text under the running node) and ``comfy.model_management``
(the user's interrupt, the compute device and the low-VRAM state), and ``comfy_api.latest.Types`` (the core's data
classes, where present); it also lifts the ``torch.inference_mode``
under which ComfyUI runs every node, for nodes that need gradients. Without ComfyUI
(tests, scripts) every function falls back: the input and output folders are ``./input``
and ``./output`` of the working directory (ComfyUI's own layout), model folders are empty,
no progress is shown, nothing is interrupted and the device is CUDA, else Apple's MPS, else the CPU.
"""

from __future__ import annotations

import functools
import importlib
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import torch

from artnvg_core.devices import best_device
from artnvg_core.progress import Cancelled, ProgressFn
from artnvg_core.raster import prepare_backend
from artnvg_core.tensor_tree import map_tensors

from .cpu_threads import cpu_threads

_log = logging.getLogger("artnvg")


def comfy_module(name: str) -> ModuleType | None:
    """ComfyUI's module ``name`` (e.g. ``folder_paths``), or None outside ComfyUI."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


# --------------------------------------------------------------------------- folders


def input_directory() -> Path:
    """ComfyUI's input folder (``./input`` without ComfyUI)."""
    folder_paths = comfy_module("folder_paths")
    return Path(folder_paths.get_input_directory()) if folder_paths else Path.cwd() / "input"


def output_directory() -> Path:
    """ComfyUI's output folder (``./output`` without ComfyUI)."""
    folder_paths = comfy_module("folder_paths")
    return Path(folder_paths.get_output_directory()) if folder_paths else Path.cwd() / "output"


def load_image_path(name: str) -> Path:
    """The file ComfyUI's Load Image reads for its value ``name`` ("sub/a.png", or one annotated as in
    "a.png [output]"); ``./input/name`` without ComfyUI."""
    folder_paths = comfy_module("folder_paths")
    return Path(folder_paths.get_annotated_filepath(name)) if folder_paths else input_directory() / name


def readable_folders() -> list[Path]:
    """The folders a node may read from: ComfyUI's input and output folders and every model folder
    (``models/`` and each registered folder, extra_model_paths.yaml's included); without ComfyUI, ``./input``
    and ``./output``."""
    folders = [input_directory(), output_directory()]
    folder_paths = comfy_module("folder_paths")
    if folder_paths is not None:
        folders.append(Path(folder_paths.models_dir))
        folders.extend(Path(folder) for paths, _ in folder_paths.folder_names_and_paths.values() for folder in paths)
    return folders


def register_model_folder(name: str, extensions: set[str]) -> None:
    """Make ``models/<name>`` a ComfyUI model folder listing files with ``extensions``, and create it, so
    that the folder a missing-file message names is there to put the file into.

    Keeps any paths the user already configured for ``name`` (extra_model_paths.yaml). A models folder
    that cannot be written is logged, not raised: the pack still loads.
    """
    folder_paths = comfy_module("folder_paths")
    if folder_paths is None:
        return
    default = os.path.join(folder_paths.models_dir, name)
    try:
        os.makedirs(default, exist_ok=True)
    except OSError as error:
        _log.warning("ArtNVG: could not create the model folder %s (%s)", default, error)
    if name in folder_paths.folder_names_and_paths:
        paths, known = folder_paths.folder_names_and_paths[name]
        if default not in paths:
            paths.append(default)
        folder_paths.folder_names_and_paths[name] = (paths, set(known) | extensions)
    else:
        folder_paths.folder_names_and_paths[name] = ([default], set(extensions))


def model_files(folder: str) -> list[str]:
    """File names in ComfyUI's model folder ``folder`` (``checkpoints``, ``csgo``...); [] without ComfyUI
    or when ``folder`` is not a registered model folder."""
    folder_paths = comfy_module("folder_paths")
    if folder_paths is None or folder not in folder_paths.folder_names_and_paths:
        return []
    return list(folder_paths.get_filename_list(folder))


def model_folder_paths(folder: str) -> list[str]:
    """The folders ComfyUI searches for model folder ``folder``; [] without ComfyUI or when it is not registered."""
    folder_paths = comfy_module("folder_paths")
    if folder_paths is None or folder not in folder_paths.folder_names_and_paths:
        return []
    return list(folder_paths.get_folder_paths(folder))


def model_file_path(folder: str, name: str) -> Path | None:
    """The full path of ``name`` in ComfyUI's model folder ``folder``, or None when it is not there."""
    folder_paths = comfy_module("folder_paths")
    path = folder_paths.get_full_path(folder, name) if folder_paths else None
    return Path(path) if path else None


def comfy_types():
    """ComfyUI's ``comfy_api.latest.Types`` (its data classes: 3D files, splats...); None outside ComfyUI
    or on a ComfyUI without that API."""
    latest = comfy_module("comfy_api.latest")
    return getattr(latest, "Types", None) if latest is not None else None


def comfy_io():
    """ComfyUI's ``comfy_api.latest.IO`` (its link types, each with an ``io_type`` name); None outside
    ComfyUI or on a ComfyUI without that API."""
    latest = comfy_module("comfy_api.latest")
    return getattr(latest, "IO", None) if latest is not None else None


# --------------------------------------------------------------------------- device


def compute_device() -> torch.device:
    """ComfyUI's torch device (honours ``--cpu``; MPS on a Mac); without ComfyUI, CUDA, else MPS, else the CPU."""
    model_management = comfy_module("comfy.model_management")
    if model_management is not None:
        return torch.device(model_management.get_torch_device())
    return best_device()


def low_vram_mode() -> bool:
    """Whether ComfyUI runs in its low-VRAM state (``--lowvram`` or ``--novram``); False without ComfyUI."""
    model_management = comfy_module("comfy.model_management")
    if model_management is None:
        return False
    return model_management.vram_state in (model_management.VRAMState.LOW_VRAM, model_management.VRAMState.NO_VRAM)


# --------------------------------------------------------------------------- autograd


@contextmanager
def autograd_enabled():
    """Gradients inside a node: ComfyUI runs every node under ``torch.inference_mode()``."""
    with torch.inference_mode(False), torch.enable_grad():
        yield


def trainable_copy(value):
    """A copy of dataclass ``value`` (a scene, a camera set) whose tensors autograd may use.

    Call inside :func:`autograd_enabled`: tensors made under inference mode (every node
    output in ComfyUI) cannot be saved for backward, their clones made outside it can.
    """
    return map_tensors(torch.Tensor.clone, value)


# --------------------------------------------------------------------------- progress and interrupt


def progress_bar() -> ProgressFn | None:
    """A core ``ProgressFn`` that drives the running node's progress bar; None without ComfyUI."""
    utils = comfy_module("comfy.utils")
    if utils is None:
        return None
    bar = None

    def report(step: int, total: int, info: dict) -> None:
        nonlocal bar
        if bar is None:
            bar = utils.ProgressBar(total)
        bar.update_absolute(step, total)

    return report


def progress_text(message: str, node: str = "") -> None:
    """Show ``message`` under the running node in ComfyUI's editor (its progress text) and in the console log,
    there after ``node: `` (the node's display name, which the editor shows above the text already); without
    ComfyUI, in the log alone."""
    _log.warning(f"{node}: {message}" if node else message)
    server, execution = comfy_module("server"), comfy_module("comfy_execution.utils")
    context = execution.get_executing_context() if hasattr(execution, "get_executing_context") else None
    if server is not None and context is not None:
        server.PromptServer.instance.send_progress_text(message, context.node_id)


def shown_notes(notes: list[str], node: str) -> list[str]:
    """The library's ``notes`` for the user (:mod:`artnvg_core.notes`: what a file's read or write did) as lines of
    ``node``'s UI text, ``note: ...``; any are also shown under the node in the editor and logged once on the console
    (:func:`progress_text`: ComfyUI's frontend 1.27.10 draws no node's UI text)."""
    noted = [f"note: {note}" for note in notes]
    if noted:
        progress_text("\n".join(noted), node)
    return noted


def prepare_rasterizer(device: torch.device) -> None:
    """Load the rasterizer that renders on ``device`` before a node's first render: gsplat's
    first-use kernel build (minutes; BENCHMARKS.md, "First look") is announced by :func:`progress_text` first."""
    prepare_backend(device, announce=progress_text)


@contextmanager
def render_device() -> Iterator[torch.device]:
    """ComfyUI's device (:func:`compute_device`) for a node that renders, as the block's value: its rasterizer
    loaded first (:func:`prepare_rasterizer`), and torch's CPU threads set for the machine's load within the
    block (:func:`~nodes.cpu_threads.cpu_threads`)."""
    device = compute_device()
    prepare_rasterizer(device)
    with cpu_threads(device):
        yield device


def interrupt_requested() -> bool:
    """Whether the user pressed Cancel (ComfyUI's interrupt); a core ``StopFn``. False without ComfyUI."""
    model_management = comfy_module("comfy.model_management")
    return bool(model_management and model_management.processing_interrupted())


def cancellable(function):
    """Decorate a node function so a core :class:`Cancelled` becomes ComfyUI's interrupt.

    ComfyUI then reports the run as interrupted (not failed) and clears the request.
    Without a pending ComfyUI interrupt the ``Cancelled`` propagates unchanged.
    """

    @functools.wraps(function)
    def run(*args, **kwargs):
        try:
            return function(*args, **kwargs)
        except Cancelled:
            model_management = comfy_module("comfy.model_management")
            if model_management is not None:
                model_management.throw_exception_if_processing_interrupted()
            raise

    return run
