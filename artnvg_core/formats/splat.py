"""antimatter15 ``.splat``: a headerless array of 32-byte little-endian records.

Record: position x y z (3 x float32), linear scales (3 x float32), colour
r g b and opacity a (4 x uint8, value / 255), rotation w x y z (4 x uint8,
(byte - 128) / 128, normalised on read). Colour is SH_C0 * f_dc + 0.5: the
format holds SH degree 0 only. Coordinates are stored as they are (the PLY's
axes, as antimatter15's converter and PlayCanvas's reader do; no conversion).

Round trip ply -> splat -> ply (``write_splat`` then ``read_splat``):
means exact; log-scales within 1e-6 (float32 exp/log), log-scales outside
[-87, 88] are refused (float32 range of the linear scale); colour
SH_C0 * f_dc + 0.5 within 0.5/255 where it lies in [0, 1] (clamped outside);
opacity sigmoid(logit) within 0.5/255; unit quaternion components within
1.5/128 (up to the sign of q); SH above degree 0 dropped, and a scene's 2D filter (the format records
none: read back classic), each with a note for the user.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ..cameras.geometry import normalize_quats
from ..counted import counted
from ..fileio import write_atomically
from ..notes import NoteFn, tell
from ..progress import ProgressFn, Stages, StopFn
from ..scene import DEFAULT_BLUR_PX2, DROP_INVALID_HINT, SH_C0, GaussianScene, describe_invalid, validate_scene
from .common import (
    ChunkedWork,
    opacity_bytes,
    opacity_logits_from_bytes,
    require_file,
    scene_to_write,
    tell_filter_change,
    to_bytes,
)

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
LOG_SCALE_RANGE = (-87.0, 88.0)  # log-scales whose linear scale float32 holds
# Seconds per million Gaussians (one thread of a 2-core CPU) in each stage of a read: the share of the progress bar
# each fills.
READ_STAGES = {"read": 0.03, "decode": 0.05, "check": 0.05}


def colour_and_opacity(rgba: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """SH DC [N, 1, 3] and opacity logits [N] (float32) of RGBA bytes [N, 4] (colour SH_C0 * f_dc + 0.5)."""
    colour = rgba[:, :3].astype(np.float64) / 255
    return (torch.from_numpy((colour - 0.5) / SH_C0).float()[:, None, :],
            torch.from_numpy(opacity_logits_from_bytes(rgba[:, 3])).float())


def rgba_bytes(cpu: GaussianScene) -> np.ndarray:
    """[N, 4] uint8: colour SH_C0 * f_dc + 0.5 clamped to [0, 1], then sigmoid(opacity logit), x 255 rounded."""
    colour = SH_C0 * cpu.sh[:, 0].double().numpy() + 0.5
    return np.concatenate([to_bytes(np.clip(colour, 0, 1) * 255), opacity_bytes(cpu.opacity_logits)[:, None]], 1)


def linear_scales(cpu: GaussianScene, path: Path, kind: str) -> np.ndarray:
    """exp(log-scales) [N, 3] (float64) for a format ``kind`` storing float32 linear scales; a ValueError
    naming ``path`` when a log-scale lies outside LOG_SCALE_RANGE."""
    log_scales = cpu.log_scales.double().numpy()
    outside = ((log_scales < LOG_SCALE_RANGE[0]) | (log_scales > LOG_SCALE_RANGE[1])).any(1)
    if outside.any():
        problem = f"lie outside {list(LOG_SCALE_RANGE)}, beyond the float32 linear scales of {kind}"
        raise ValueError(f"{path}: not written: {describe_invalid('log_scales', outside, problem)}")
    return np.exp(log_scales)


def tell_dropped(cpu: GaussianScene, path: Path, kind: str, degree: int, notes: NoteFn | None) -> None:
    """Notes for the user (:func:`~artnvg_core.notes.tell`) on what a format ``kind`` that holds SH up to ``degree``
    and no 2D filter (read back classic) drops of ``cpu``."""
    if cpu.sh_degree > degree:
        dropped = f"degree {cpu.sh_degree}" if cpu.sh_degree == degree + 1 else f"degree {degree + 1}-{cpu.sh_degree}"
        tell(notes, path, f"{kind} holds SH up to degree {degree}; the {dropped} view-dependent terms are dropped")
    tell_filter_change(notes, path, cpu, kind, DEFAULT_BLUR_PX2, False)


def check_geometry(cpu: GaussianScene, path: Path) -> None:
    """What :func:`write_splat` refuses of the geometry alone (log-scales outside [-87, 88]), checked now."""
    linear_scales(cpu, path, ".splat")


def read_splat(path: str | os.PathLike, *, drop_invalid: bool = False, progress: ProgressFn | None = None,
               should_stop: StopFn | None = None, notes: NoteFn | None = None) -> GaussianScene:
    """Read a ``.splat`` file (layout in the module docstring) as an SH degree 0 scene, decoded a chunk of
    Gaussians at a time: ``progress`` follows the whole read in the file's bytes, filling once over its stages
    (:data:`READ_STAGES`), ``should_stop`` ends it between chunks (:class:`~artnvg_core.progress.Cancelled`).
    ``notes`` is told of invalid Gaussians dropped (:func:`~artnvg_core.notes.tell`)."""
    path = Path(path)
    require_file(path)
    size = path.stat().st_size
    if size == 0 or size % RECORD.itemsize:
        raise ValueError(
            f"{path}: file size {counted(size, 'byte')} is not a positive multiple of the {RECORD.itemsize}-byte "
            ".splat record (empty or truncated file)"
        )
    stages = Stages(progress, size, READ_STAGES)
    records = np.fromfile(path, dtype=RECORD)
    scales = records["scale"].astype(np.float64)
    bad = ~(np.isfinite(scales) & (scales > 0)).all(1)
    if bad.any() and not drop_invalid:
        problem = "have a scale that is not a positive finite number"
        raise ValueError(f"{path}: {describe_invalid('scale', bad, problem)}; {DROP_INVALID_HINT}")
    n = len(records)
    scene = GaussianScene(means=torch.empty(n, 3), quats=torch.empty(n, 4), log_scales=torch.empty(n, 3),
                          opacity_logits=torch.empty(n), sh=torch.empty(n, 1, 3))
    for rows in ChunkedWork(n, 1, stages["decode"], should_stop).chunks():
        rotation = records["rotation"][rows].astype(np.float64) - 128  # all 128: the zero quaternion, refused later
        with np.errstate(divide="ignore", invalid="ignore"):
            log_scales = np.log(scales[rows])
        scene.means[rows] = torch.from_numpy(records["position"][rows])
        scene.quats[rows] = torch.from_numpy(rotation / 128)
        scene.log_scales[rows] = torch.from_numpy(log_scales)
        scene.sh[rows], scene.opacity_logits[rows] = colour_and_opacity(records["rgba"][rows])
    return validate_scene(scene, str(path), drop_invalid=drop_invalid, should_stop=should_stop,
                          progress=stages["check"], notes=notes)[0]


def _records(cpu: GaussianScene, scales: np.ndarray, rows: slice) -> np.ndarray:
    """The .splat records of Gaussians ``rows`` of ``cpu``, whose linear scales [N, 3] are ``scales``."""
    part = cpu.select(rows)
    records = np.empty(len(part), dtype=RECORD)
    records["position"] = part.means.numpy()
    records["scale"] = scales[rows]
    records["rgba"] = rgba_bytes(part)
    records["rotation"] = to_bytes(normalize_quats(part.quats.double()).numpy() * 128 + 128)
    return records


def write_splat(scene: GaussianScene, path: str | os.PathLike, *, overwrite: bool = True,
                progress: ProgressFn | None = None, should_stop: StopFn | None = None,
                notes: NoteFn | None = None) -> None:
    """Write ``scene`` as a ``.splat`` file atomically (quantisation in the module docstring); with ``overwrite``
    False never over an existing file (:func:`~artnvg_core.fileio.write_atomically`). Records are written a chunk
    of Gaussians at a time: ``progress`` counts them, ``should_stop`` ends the write between chunks
    (:class:`~artnvg_core.progress.Cancelled`, no file left). ``notes`` is told what the format drops (SH above
    degree 0, a 2D filter other than classic; :func:`~artnvg_core.notes.tell`).

    Refused with a ValueError before writing: non-finite values, zero
    quaternions, log-scales outside [-87, 88].
    """
    path = Path(path)
    cpu = scene_to_write(scene, path, should_stop)
    scales = linear_scales(cpu, path, ".splat")
    tell_dropped(cpu, path, ".splat", 0, notes)
    work = ChunkedWork(len(cpu), 1, progress, should_stop)

    def write(stream) -> None:
        for rows in work.chunks():
            stream.write(_records(cpu, scales, rows).tobytes())

    write_atomically(path, write, overwrite=overwrite)
