"""PlayCanvas / SuperSplat compressed PLY (``.ply``), read only.

Elements, as PlayCanvas's splat-transform reads them: ``chunk`` (one per 256
Gaussians, in order) with float min_/max_ x y z, min_/max_scale_ x y z and
optionally min_/max_ r g b; ``vertex`` with uint32 packed_position,
packed_scale (11-10-11 bits, x in the high bits, each a fraction of its
chunk's min..max; scales are log-scales), packed_color (8-8-8-8: r g b
opacity, r in the high byte; r g b are colours SH_C0 * f_dc + 0.5, scaled to
the chunk's min..max when given) and packed_rotation (2 bits: the index of
the largest component of w x y z, then the other three in order, 10 bits each,
in [-1/sqrt2, 1/sqrt2]); an optional ``sh`` element with uchar f_rest_0..M-1
(M in 9, 24, 45; value (b + 0.5) / 256 * 8 - 4, with 0 and 255 the ends -4 and 4).
Coordinates are stored as they are (the PLY's axes). Every column is read by its declared type:
packed_* codes declared as float or double are read as their (whole-number) values.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from ..counted import counted
from ..progress import ProgressFn, StopFn
from ..scene import SH_C0, GaussianScene
from .common import ChunkedWork, opacity_logits_from_bytes
from .ply_data import PlyData

CHUNK_SIZE = 256
ELEMENTS = ("chunk", "vertex", "sh")  # the elements a compressed PLY's reader reads
_CHUNK_BOUNDS = [f"{end}_{axis}" for end in ("min", "max") for axis in "xyz"]
_CHUNK_SCALES = [f"{end}_scale_{axis}" for end in ("min", "max") for axis in "xyz"]
_CHUNK_COLOURS = [f"{end}_{channel}" for end in ("min", "max") for channel in "rgb"]
_PACKED = ["packed_position", "packed_rotation", "packed_scale", "packed_color"]


def is_compressed_ply(ply: PlyData) -> bool:
    """True when ``ply`` has a ``chunk`` element and a ``vertex`` element with ``packed_position``."""
    names = [element.name for element in ply.elements]
    return "chunk" in names and "vertex" in names and "packed_position" in ply["vertex"].property_names


def _columns(path: Path, ply: PlyData, element: str, names: list[str], rows: slice = slice(None)) -> np.ndarray:
    """The named properties of ``element``'s ``rows`` as one array [rows, len(names)] (float64 or int64)."""
    data = ply[element].data
    if data is None:  # an element with list properties is never read
        raise ValueError(f"{path}: element '{element}' has list properties; expected numbers")
    missing = [name for name in names if name not in (data.dtype.names or ())]
    if missing:
        raise ValueError(f"{path}: element '{element}' lacks properties {', '.join(missing)}")
    kinds = {data.dtype[name].kind for name in names}
    if kinds - {"f"} and kinds - {"u", "i"}:
        raise ValueError(f"{path}: element '{element}': properties {', '.join(names)} have the wrong types")
    data = data[rows]
    return np.stack([data[name] for name in names], 1).astype(np.int64 if kinds <= {"u", "i"} else np.float64)


def _unorm(values: np.ndarray, shift: int, bits: int) -> np.ndarray:
    mask = (1 << bits) - 1
    return (values >> shift & mask) / mask


def _unpack_11_10_11(packed: np.ndarray) -> np.ndarray:
    return np.stack([_unorm(packed, 21, 11), _unorm(packed, 11, 10), _unorm(packed, 0, 11)], 1)


def _lerp(low: np.ndarray, high: np.ndarray, t: np.ndarray) -> np.ndarray:
    return low * (1 - t) + high * t


def _rotations(packed: np.ndarray) -> np.ndarray:
    """[N, 4] w x y z quaternions of packed_rotation codes."""
    others = np.stack([_unorm(packed, 20, 10), _unorm(packed, 10, 10), _unorm(packed, 0, 10)], 1)
    others = (others - 0.5) * np.sqrt(2)
    largest = packed >> 30 & 3
    rest = np.sqrt(np.maximum(0, 1 - (others**2).sum(1)))
    q = np.empty((len(packed), 4))
    for i in range(4):
        # the three stored components fill the slots other than ``largest``, in order
        slot = np.where(largest <= i, i - 1, i)
        q[:, i] = np.where(largest == i, rest, others[np.arange(len(packed)), np.clip(slot, 0, 2)])
    return q


def _packed_codes(path: Path, ply: PlyData, rows: slice) -> np.ndarray:
    """The packed_* codes [rows, 4] (int64) of ``rows`` of the vertex element, whole numbers from 0 to 2^32 - 1."""
    packed = _columns(path, ply, "vertex", _PACKED, rows)
    if (packed < 0).any() or (packed >= 1 << 32).any() or (packed != np.floor(packed)).any():
        raise ValueError(f"{path}: element 'vertex': packed_* values must be whole numbers from 0 to 2^32 - 1 "
                         f"(declared {', '.join(sorted({str(ply['vertex'].data.dtype[n]) for n in _PACKED}))})")
    return packed.astype(np.int64)  # codes declared as float (any exact whole number) read as their value


def scene_from_compressed_ply(path: Path, ply: PlyData, *, progress: ProgressFn | None = None,
                              should_stop: StopFn | None = None) -> GaussianScene:
    """The scene of a parsed compressed PLY (layout in the module docstring), not yet validated, decoded a chunk of
    Gaussians at a time: ``progress`` counts them, ``should_stop`` ends the work between chunks
    (:class:`~artnvg_core.progress.Cancelled`)."""
    _packed_codes(path, ply, slice(0))  # the vertex element's properties checked before any work
    n = len(ply["vertex"].data)
    chunks = (n + CHUNK_SIZE - 1) // CHUNK_SIZE
    if ply["chunk"].count != chunks:
        raise ValueError(f"{path}: element 'chunk': count {ply['chunk'].count}, expected {chunks} "
                         f"(one per {CHUNK_SIZE} of the {counted(n, 'vertex', 'vertices')})")
    if n == 0:
        raise ValueError(f"{path}: the scene contains no Gaussians")
    bounds = _columns(path, ply, "chunk", _CHUNK_BOUNDS)
    scales = _columns(path, ply, "chunk", _CHUNK_SCALES)
    colours = _columns(path, ply, "chunk", _CHUNK_COLOURS) if "min_r" in ply["chunk"].property_names else None
    rest = 0
    if "sh" in ply:
        names = ply["sh"].property_names
        if len(names) not in (9, 24, 45) or ply["sh"].count != n:
            raise ValueError(f"{path}: element 'sh': {counted(len(names), 'property', 'properties')} for "
                             f"{counted(ply['sh'].count, 'row')}, expected 9, 24 or 45 f_rest_* for "
                             f"{counted(n, 'row')}")
        rest = len(names)
    scene = GaussianScene(means=torch.empty(n, 3), quats=torch.empty(n, 4), log_scales=torch.empty(n, 3),
                          opacity_logits=torch.empty(n), sh=torch.empty(n, 1 + rest // 3, 3))
    for rows in ChunkedWork(n, 1, progress, should_stop).chunks():
        position, rotation, scale, colour = _packed_codes(path, ply, rows).T
        chunk_of = np.arange(rows.start, rows.stop) // CHUNK_SIZE
        rgba = np.stack([colour >> shift & 255 for shift in (24, 16, 8, 0)], 1)
        rgb = rgba[:, :3] / 255
        if colours is not None:
            rgb = _lerp(colours[chunk_of, :3], colours[chunk_of, 3:], rgb)
        sh = [(rgb - 0.5)[:, None, :] / SH_C0]
        if rest:
            coded = _columns(path, ply, "sh", [f"f_rest_{i}" for i in range(rest)], rows)
            value = np.where(coded == 0, 0.0, np.where(coded == 255, 1.0, (coded + 0.5) / 256))
            sh.append(((value - 0.5) * 8).reshape(len(coded), 3, -1).transpose(0, 2, 1))  # channel-major f_rest
        low, high = bounds[chunk_of, :3], bounds[chunk_of, 3:]
        scene.means[rows] = torch.from_numpy(_lerp(low, high, _unpack_11_10_11(position)))
        scene.quats[rows] = torch.from_numpy(_rotations(rotation))
        low, high = scales[chunk_of, :3], scales[chunk_of, 3:]
        scene.log_scales[rows] = torch.from_numpy(_lerp(low, high, _unpack_11_10_11(scale)))
        scene.opacity_logits[rows] = torch.from_numpy(opacity_logits_from_bytes(rgba[:, 3]))
        scene.sh[rows] = torch.from_numpy(np.concatenate(sh, 1))
    return scene
