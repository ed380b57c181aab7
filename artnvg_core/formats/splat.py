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
1.5/128 (up to the sign of q); SH above degree 0 dropped (with a warning).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import torch

from ..cameras.geometry import normalize_quats
from ..counted import counted
from ..fileio import write_atomically
from ..scene import DROP_INVALID_HINT, SH_C0, GaussianScene, describe_invalid, validate_scene
from .common import opacity_bytes, opacity_logits_from_bytes, require_file, scene_to_write, to_bytes

_log = logging.getLogger(__name__)

RECORD = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
LOG_SCALE_RANGE = (-87.0, 88.0)  # log-scales whose linear scale float32 holds


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


def check_geometry(cpu: GaussianScene, path: Path) -> None:
    """What :func:`write_splat` refuses of the geometry alone (log-scales outside [-87, 88]), checked now."""
    linear_scales(cpu, path, ".splat")


def read_splat(path: str | os.PathLike, *, drop_invalid: bool = False) -> GaussianScene:
    """Read a ``.splat`` file (layout in the module docstring) as an SH degree 0 scene."""
    path = Path(path)
    require_file(path)
    size = path.stat().st_size
    if size == 0 or size % RECORD.itemsize:
        raise ValueError(
            f"{path}: file size {counted(size, 'byte')} is not a positive multiple of the {RECORD.itemsize}-byte "
            ".splat record (empty or truncated file)"
        )
    records = np.fromfile(path, dtype=RECORD)
    scales = records["scale"].astype(np.float64)
    bad = ~(np.isfinite(scales) & (scales > 0)).all(1)
    if bad.any() and not drop_invalid:
        problem = "have a scale that is not a positive finite number"
        raise ValueError(f"{path}: {describe_invalid('scale', bad, problem)}; {DROP_INVALID_HINT}")
    rotation = records["rotation"].astype(np.float64) - 128  # all 128: the zero quaternion, refused by validation
    with np.errstate(divide="ignore", invalid="ignore"):
        log_scales = np.log(scales)
    sh, opacity_logits = colour_and_opacity(records["rgba"])
    scene = GaussianScene(
        means=torch.from_numpy(records["position"].copy()),
        quats=torch.from_numpy(rotation / 128).float(),
        log_scales=torch.from_numpy(log_scales).float(),
        opacity_logits=opacity_logits,
        sh=sh,
    )
    return validate_scene(scene, str(path), drop_invalid=drop_invalid)[0]


def write_splat(scene: GaussianScene, path: str | os.PathLike, *, overwrite: bool = True) -> None:
    """Write ``scene`` as a ``.splat`` file atomically (quantisation in the module docstring); with ``overwrite``
    False never over an existing file (:func:`~artnvg_core.fileio.write_atomically`).

    Refused with a ValueError before writing: non-finite values, zero
    quaternions, log-scales outside [-87, 88].
    """
    path = Path(path)
    cpu = scene_to_write(scene, path)
    scales = linear_scales(cpu, path, ".splat")
    if cpu.sh_degree > 0:
        _log.warning("%s: .splat holds SH degree 0 only; the degree %d view-dependent terms are dropped",
                     path, cpu.sh_degree)
    records = np.empty(len(cpu), dtype=RECORD)
    records["position"] = cpu.means.numpy()
    records["scale"] = scales
    records["rgba"] = rgba_bytes(cpu)
    records["rotation"] = to_bytes(normalize_quats(cpu.quats.double()).numpy() * 128 + 128)
    write_atomically(path, lambda stream: stream.write(records.tobytes()), overwrite=overwrite)
