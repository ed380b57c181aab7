"""nerfstudio splatfacto checkpoints (``.ckpt``), read only.

nerfstudio keeps the training config beside the checkpoint
(``<run>/config.yml``, the checkpoint in ``<run>/nerfstudio_models/``); a run
trained with ``rasterize_mode: antialiased`` there is rendered with gsplat's
antialiased mode (``GaussianScene.antialiased``). Without a config the scene is
classic. Tensors saved sparse or expanded (stride 0) are made dense only when the dense
Gaussians take at most 4 times the file's size; larger ones are refused before they are made.
A checkpoint (a zip archive, as ``torch.save`` writes) is mapped rather than read
(``torch.load(mmap=True)``: its pickle alone is read), its Gaussian tensors' shapes checked, then
their values copied out of the file a chunk of Gaussians at a time, with progress and a stop between
chunks; the scene holds no page of the file, which may change or go once it is read.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import torch

from ..notes import NoteFn
from ..progress import ProgressFn, Stages, StopFn
from ..scene import SH_C0, GaussianScene, validate_scene
from ..tensor_files import load_failure
from .bounded import require_stored_zip
from .common import ChunkedWork, require_file

_log = logging.getLogger(__name__)
_SPLATFACTO_PREFIX = "_model.gauss_params."
_SPLATFACTO_REQUIRED = ("means", "scales", "quats", "features_dc", "opacities")
# Dense float32 Gaussian tensors may take at most this many times the checkpoint's bytes (float16
# files double; at least EXPANSION_FLOOR for small files).
MAX_EXPANSION = 4
EXPANSION_FLOOR = 1 << 24
# Seconds per million Gaussians of SH degree 3 (one thread of a 2-core CPU) in each stage of a read: the share of
# the progress bar each fills.
READ_STAGES = {"read": 0.12, "check": 0.18}
_RASTERIZE_MODE = re.compile(r"^\s*rasterize_mode:\s*['\"]?(\w+)", re.MULTILINE)


def trained_antialiased(path: Path) -> bool:
    """True when the run's ``config.yml`` (beside the checkpoint or one folder up) says
    ``rasterize_mode: antialiased``."""
    for config in (path.parent / "config.yml", path.parent.parent / "config.yml"):
        try:
            match = _RASTERIZE_MODE.search(config.read_text(encoding="utf-8", errors="replace"))
        except OSError:
            continue
        if match:
            _log.info("%s: rasterize_mode %s (from %s)", path, match.group(1), config)
            return match.group(1) == "antialiased"
    return False


def _splatfacto_params(path: Path) -> dict[str, torch.Tensor]:
    """The ``_model.gauss_params.*`` tensors of a checkpoint, by short name, dense, as stored otherwise: a zip
    archive's mapped from the file (nothing read yet), its records stored uncompressed
    (:func:`~.bounded.require_stored_zip`); an old-style pickle's read whole."""
    mapped = require_stored_zip(path)
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=mapped)
    except Exception as error:  # torch.load raises many types on corrupt or foreign files
        raise ValueError(f"{path}: not a loadable torch checkpoint ({load_failure(error)})") from error
    pipeline = checkpoint.get("pipeline") if isinstance(checkpoint, dict) else None
    if not isinstance(pipeline, dict):
        raise ValueError(f"{path}: expected a nerfstudio checkpoint, a dict with a 'pipeline' state dict")
    params = {
        key.removeprefix(_SPLATFACTO_PREFIX): value
        for key, value in pipeline.items()
        if isinstance(key, str) and key.startswith(_SPLATFACTO_PREFIX) and isinstance(value, torch.Tensor)
    }
    missing = [_SPLATFACTO_PREFIX + name for name in _SPLATFACTO_REQUIRED if name not in params]
    if missing:
        raise ValueError(f"{path}: not a splatfacto checkpoint, pipeline lacks tensors {', '.join(missing)}")
    _require_dense_within_cap(path, params)
    # to_dense: tensors saved in a sparse layout (COO, CSR, ...) read as the dense values they hold
    return {name: value.detach().to_dense() for name, value in params.items()}


def _in_memory(params: dict[str, torch.Tensor], work: ChunkedWork) -> dict[str, torch.Tensor]:
    """float32 copies of ``params`` (each of ``work.count`` rows, mapped from their file), a chunk of Gaussians at a
    time (``work``: one pass each)."""
    copies = {}
    for name, value in params.items():
        copies[name] = torch.empty(value.shape, dtype=torch.float32)
        for rows in work.chunks():
            copies[name][rows] = value[rows]
    return copies


def _require_dense_within_cap(path: Path, params: dict[str, torch.Tensor]) -> None:
    """ValueError naming ``path`` when the dense float32 Gaussian tensors would take more than
    :data:`MAX_EXPANSION` times the file's size (at least :data:`EXPANSION_FLOOR`): a sparse or
    stride-0 tensor holds a shape far larger than its stored values, so its shape is checked, before
    it is made dense."""
    needed = 4 * sum(value.numel() for value in params.values())
    file_size = path.stat().st_size
    cap = max(MAX_EXPANSION * file_size, EXPANSION_FLOOR)
    if needed > cap:
        shapes = ", ".join(f"{name} {tuple(value.shape)} ({_layout(value)})" for name, value in params.items())
        raise ValueError(f"{path}: {_SPLATFACTO_PREFIX}*: the Gaussian tensors take {needed:,} bytes as dense float32, "
                         f"more than the cap of {MAX_EXPANSION}x the {file_size:,}-byte file ({cap:,} bytes); "
                         f"sparse or stride-0 tensors that stand for far more values than the file holds ({shapes})")


def _layout(value: torch.Tensor) -> str:
    """``sparse_coo`` and the like, ``stride 0`` for an expanded tensor, else ``dense``."""
    if value.layout != torch.strided:
        return str(value.layout).removeprefix("torch.")
    return "stride 0" if 0 in value.stride() and value.numel() > 1 else "dense"


def _expect_shape(path: Path, name: str, value: torch.Tensor, shape: tuple[int, ...]) -> None:
    if tuple(value.shape) != shape:
        raise ValueError(f"{path}: {_SPLATFACTO_PREFIX}{name}: expected shape {shape}, got {tuple(value.shape)}")


def read_splatfacto_ckpt(path: str | os.PathLike, *, drop_invalid: bool = False, progress: ProgressFn | None = None,
                         should_stop: StopFn | None = None, notes: NoteFn | None = None) -> GaussianScene:
    """Read the Gaussians of a nerfstudio splatfacto ``.ckpt`` (loaded with ``weights_only=True``).

    Uses ``pipeline["_model.gauss_params.*"]``: means [N, 3], scales [N, 3] (log),
    quats [N, 4] (w x y z), opacities [N, 1] (logits), features_dc [N, 3] and
    features_rest [N, K-1, 3]. At SH degree 0 (features_rest empty or absent)
    splatfacto renders colour = sigmoid(features_dc), which is converted to the
    SH DC coefficient (sigmoid(f) - 0.5) / SH_C0. ``antialiased`` from the run's config
(module docstring). Validated with :func:`validate_scene`. ``progress`` follows the whole read in the file's bytes,
    filling once over its stages (:data:`READ_STAGES`: the Gaussians copied out of the file, then checked, a chunk at
    a time), ``should_stop`` ends it between chunks (:class:`~artnvg_core.progress.Cancelled`).
    ``notes`` is told of invalid Gaussians dropped (:func:`~artnvg_core.notes.tell`).
    """
    path = Path(path)
    require_file(path)
    stages = Stages(progress, path.stat().st_size, READ_STAGES)
    params = _splatfacto_params(path)
    n = params["means"].shape[0] if params["means"].ndim == 2 else -1
    shapes = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "features_dc": (n, 3), "opacities": (n, 1)}
    for name, shape in shapes.items():
        _expect_shape(path, name, params[name], shape)
    rest = params.get("features_rest", torch.zeros(n, 0, 3))
    if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3 or rest.shape[1] + 1 not in (1, 4, 9, 16):
        raise ValueError(
            f"{path}: {_SPLATFACTO_PREFIX}features_rest: expected shape ({n}, K-1, 3) with K-1 in "
            f"0, 3, 8, 15 (SH degree 0 to 3), got {tuple(rest.shape)}"
        )
    used = {name: params[name] for name in shapes} | {"features_rest": rest}
    params = _in_memory(used, ChunkedWork(n, len(used), stages["read"], should_stop))
    rest, dc = params["features_rest"], params["features_dc"]
    if rest.shape[1] == 0:
        dc = ((torch.sigmoid(dc.double()) - 0.5) / SH_C0).float()
    scene = GaussianScene(
        means=params["means"],
        quats=params["quats"],
        log_scales=params["scales"],
        opacity_logits=params["opacities"][:, 0].contiguous(),
        sh=torch.cat([dc[:, None, :], rest], dim=1),
        antialiased=trained_antialiased(path),
    )
    return validate_scene(scene, str(path), drop_invalid=drop_invalid, should_stop=should_stop,
                          progress=stages["check"], notes=notes)[0]
