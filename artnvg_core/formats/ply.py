"""INRIA 3DGS PLY: read (ASCII or binary, Mip-Splatting's ``filter_3D`` folded in) and write.

Layout (``vertex`` element, float properties in any order): x y z, f_dc_0..2,
f_rest_0..M-1 with M in {0, 9, 24, 45} (SH degree 0..3, channel-major:
``f_rest[c * (K-1) + j]`` is ``sh[:, 1 + j, c]``), opacity (logit),
scale_0..2 (log), rot_0..3 (w x y z). Normals and other properties are ignored.
Coordinates are stored as they are (the PLY's own axes; no conversion).

Mip-Splatting: a ``filter_3D`` property f [N] (its 3D smoothing filter) is
folded in at load, exactly as Mip-Splatting renders it: scales
s' = sqrt(s^2 + f^2), opacity o' = o * sqrt(prod(s^2) / prod(s^2 + f^2)); the
scene is then rendered with Mip-Splatting's 2D Mip filter (``blur_px2`` 0.1,
``antialiased``). A scene with ``antialiased`` set is written with a zero
``filter_3D`` column, so that it reads back (and opens in Mip-Splatting tools)
as antialiased; its ``blur_px2`` is then Mip-Splatting's 0.1.

A PLY with a ``chunk`` element and ``packed_*`` vertex properties is a
PlayCanvas/SuperSplat compressed PLY (:mod:`.compressed_ply`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from ..counted import counted
from ..fileio import write_atomically
from ..notes import NoteFn
from ..progress import ProgressFn, Stages, StopFn
from ..scene import DEFAULT_BLUR_PX2, GaussianScene, logit, validate_scene
from . import compressed_ply
from .common import ChunkedWork, require_file, scene_to_write, tell_filter_change
from .ply_data import PlyData, read_ply_elements, read_ply_header

_PLY_ELEMENT = "vertex"
_SH_DEGREE_FOR_REST_COUNT = {3 * ((d + 1) ** 2 - 1): d for d in range(4)}  # 0, 9, 24, 45
_REST_PROPERTY = re.compile(r"f_rest_\d+")
_FILTER_3D = "filter_3D"
MIP_SPLATTING_BLUR_PX2 = 0.1  # Mip-Splatting's 2D Mip filter (its kernel_size)
# Seconds per million Gaussians of SH degree 3 (one thread of a 2-core CPU) in each stage of a read, by kind of
# PLY: the share of the progress bar each stage fills.
READ_STAGES = {"binary": {"read": 0.71, "decode": 0.61, "check": 0.18},
               "ascii": {"read": 4.4, "decode": 0.6, "check": 0.2},
               "compressed": {"read": 0.09, "decode": 0.70, "check": 0.18}}


def _ply_layout(num_rest: int) -> dict[str, list[str]]:
    """Property names of each block of the INRIA layout, in file order."""
    return {
        "means": ["x", "y", "z"],
        "normals": ["nx", "ny", "nz"],
        "sh_dc": ["f_dc_0", "f_dc_1", "f_dc_2"],
        "sh_rest": [f"f_rest_{i}" for i in range(num_rest)],
        "opacity_logits": ["opacity"],
        "log_scales": ["scale_0", "scale_1", "scale_2"],
        "quats": ["rot_0", "rot_1", "rot_2", "rot_3"],
    }


def _vertices(path: Path, ply: PlyData) -> np.ndarray:
    """The 'vertex' element's structured array; a ValueError when it is missing or has list properties."""
    if _PLY_ELEMENT not in ply:
        names = [element.name for element in ply.elements]
        raise ValueError(f"{path}: no '{_PLY_ELEMENT}' element (found {names}); expected an INRIA 3DGS PLY")
    element = ply[_PLY_ELEMENT]
    lists = [p.name for p in element.properties if p.is_list]
    if lists:
        raise ValueError(f"{path}: property {lists[0]} is a list; expected a scalar number")
    return element.data


def _ply_columns(path: Path, data: np.ndarray, blocks: dict[str, list[str]],
                 work: ChunkedWork) -> dict[str, torch.Tensor]:
    """Each block's named scalar properties as one float32 tensor [N, len(names)], filled a chunk of rows at a
    time (``work``: one pass)."""
    available = set(data.dtype.names or ())
    missing = [name for names in blocks.values() for name in names if name not in available]
    if missing:
        noun = "property" if len(missing) == 1 else "properties"
        raise ValueError(f"{path}: element '{_PLY_ELEMENT}' lacks {noun} {', '.join(missing)}")
    tables = {key: np.empty((len(data), len(names)), dtype=np.float32) for key, names in blocks.items()}
    with np.errstate(over="ignore", invalid="ignore"):  # float64 overflow -> inf, rejected by validation
        for rows in work.chunks():
            chunk = data[rows]
            for key, names in blocks.items():
                for column, name in enumerate(names):
                    tables[key][rows, column] = chunk[name]
    return {key: torch.from_numpy(table) for key, table in tables.items()}


def _sh_rest_count(path: Path, property_names: tuple[str, ...]) -> int:
    count = sum(1 for name in property_names if _REST_PROPERTY.fullmatch(name))
    if count not in _SH_DEGREE_FOR_REST_COUNT:
        raise ValueError(
            f"{path}: f_rest_*: found {counted(count, 'property', 'properties')}, expected 0, 9, 24 or 45 "
            "(SH degree 0 to 3)"
        )
    return count


def _fold_filter_3d(path: Path, scene: GaussianScene, filter_3d: torch.Tensor) -> GaussianScene:
    """Mip-Splatting's 3D filter f [N] folded into log-scales and opacity logits (float64 maths);
    non-finite parameters stay non-finite, for :func:`validate_scene` to report."""
    f = filter_3d.double()
    bad = ~(torch.isfinite(f) & (f >= 0))
    if bad.any():
        raise ValueError(
            f"{path}: {_FILTER_3D}: {int(bad.sum()):,} of {counted(len(f), 'value')} "
            f"{'is not a finite number' if int(bad.sum()) == 1 else 'are not finite numbers'} >= 0 "
            f"(first at index {int(bad.nonzero()[0, 0])})"
        )
    s2 = torch.exp(2 * scene.log_scales.double())
    widened = s2 + f[:, None] ** 2
    log_coef = 0.5 * (torch.log(s2) - torch.log(widened)).sum(1)  # log sqrt(det ratio) <= 0
    opacity = torch.sigmoid(scene.opacity_logits.double()) * torch.exp(log_coef)
    logits = logit(opacity).clamp(min=-1e4)  # opacity 0 -> a logit far below the 1/255 cull
    return GaussianScene(
        means=scene.means,
        quats=scene.quats,
        log_scales=(0.5 * torch.log(widened)).float(),
        opacity_logits=logits.float(),
        sh=scene.sh,
        blur_px2=MIP_SPLATTING_BLUR_PX2,
        antialiased=True,
    )


def read_ply(path: str | os.PathLike, *, drop_invalid: bool = False, progress: ProgressFn | None = None,
             should_stop: StopFn | None = None, notes: NoteFn | None = None) -> GaussianScene:
    """Read an INRIA 3DGS PLY (ASCII or binary of either byte order) as float32 tensors, or a
    PlayCanvas compressed PLY. Layout and Mip-Splatting's ``filter_3D`` in the module docstring.
    Validated with :func:`~artnvg_core.scene.validate_scene`. ``progress`` follows the whole read in the
    file's bytes, filling once over its stages (:data:`READ_STAGES`); ``should_stop`` ends it between chunks
    (:class:`~artnvg_core.progress.Cancelled`). ``notes`` is told of invalid Gaussians dropped
    (:func:`~artnvg_core.notes.tell`).
    """
    path = Path(path)
    require_file(path)
    ply = read_ply_header(path)
    compressed = compressed_ply.is_compressed_ply(ply)
    kind = "compressed" if compressed else "ascii" if ply.text else "binary"
    stages = Stages(progress, path.stat().st_size, READ_STAGES[kind])
    read_ply_elements(path, ply, (_PLY_ELEMENT, *compressed_ply.ELEMENTS), progress=stages["read"],
                      should_stop=should_stop)
    decode = compressed_ply.scene_from_compressed_ply if compressed else _inria_scene
    scene = decode(path, ply, progress=stages["decode"], should_stop=should_stop)
    return validate_scene(scene, str(path), drop_invalid=drop_invalid, should_stop=should_stop,
                          progress=stages["check"], notes=notes)[0]


def _inria_scene(path: Path, ply: PlyData, *, progress: ProgressFn | None,
                 should_stop: StopFn | None) -> GaussianScene:
    """The scene of a read INRIA PLY, not yet validated, its columns gathered a chunk of Gaussians at a time
    (``progress``, ``should_stop``)."""
    data = _vertices(path, ply)
    num_rest = _sh_rest_count(path, data.dtype.names or ())
    layout = _ply_layout(num_rest)
    del layout["normals"]
    gaussian_properties = {name for key in ("sh_dc", "opacity_logits", "log_scales", "quats") for name in layout[key]}
    if not gaussian_properties & set(data.dtype.names or ()):
        raise ValueError(f"{path}: a point cloud or mesh, not a Gaussian scene: its vertices have none of a Gaussian's "
                         "properties (f_dc_*, opacity, scale_*, rot_*); expected a trained 3DGS scene (e.g. 3DGS's "
                         "point_cloud/iteration_30000/point_cloud.ply or nerfstudio's ns-export gaussian-splat), not "
                         "a capture's points (COLMAP's or nerfstudio's sparse_pc.ply)")
    if _FILTER_3D in (data.dtype.names or ()):
        layout["filter_3d"] = [_FILTER_3D]
    columns = _ply_columns(path, data, layout, ChunkedWork(len(data), 1, progress, should_stop))
    n, coeffs_per_channel = len(data), num_rest // 3
    sh_rest = columns["sh_rest"].reshape(n, 3, coeffs_per_channel).transpose(1, 2)
    scene = GaussianScene(
        means=columns["means"].contiguous(),
        quats=columns["quats"].contiguous(),
        log_scales=columns["log_scales"].contiguous(),
        opacity_logits=columns["opacity_logits"][:, 0].contiguous(),
        sh=torch.cat([columns["sh_dc"][:, None, :], sh_rest], dim=1).contiguous(),
    )
    if "filter_3d" in columns:
        scene = _fold_filter_3d(path, scene, columns["filter_3d"][:, 0])
    return scene


def _ply_names(scene: GaussianScene) -> list[str]:
    """The properties :func:`_ply_rows` writes, in file order."""
    names = [name for names in _ply_layout(3 * (scene.sh.shape[1] - 1)).values() for name in names]
    return names + [_FILTER_3D] if scene.antialiased else names


def _ply_rows(scene: GaussianScene, rows: slice) -> np.ndarray:
    """The float32 table [R, P] of ``scene``'s Gaussians ``rows`` in the INRIA layout (zero normals), the columns
    of :func:`_ply_names`."""
    sh = scene.sh[rows]
    n, k = sh.shape[:2]
    blocks = [scene.means[rows], torch.zeros(n, 3), sh[:, 0, :], sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1)),
              scene.opacity_logits[rows, None], scene.log_scales[rows], scene.quats[rows]]
    if scene.antialiased:
        blocks.append(torch.zeros(n, 1))
    return torch.cat(blocks, dim=1).numpy()


def _write_ply_body(stream: BinaryIO, table: np.ndarray, binary: bool) -> None:
    """Rows of ``table`` as little-endian float32, or as text that round-trips float32 exactly."""
    if binary:
        stream.write(table.astype("<f4").tobytes())
    else:
        np.savetxt(stream, table, fmt="%.9g")  # 9 significant digits identify every float32


def write_ply(scene: GaussianScene, path: str | os.PathLike, *, binary: bool = True, overwrite: bool = True,
              progress: ProgressFn | None = None, should_stop: StopFn | None = None,
              notes: NoteFn | None = None) -> None:
    """Write ``scene`` as an INRIA 3DGS PLY, float32, atomically; with ``overwrite`` False never over an existing
    file (:func:`~artnvg_core.fileio.write_atomically`).

    Properties x y z nx ny nz (zeros) f_dc_* f_rest_* (channel-major) opacity
    scale_* rot_* (and a zero ``filter_3D`` when ``scene.antialiased``); binary
    little-endian by default, ASCII with ``binary=False``. Reading the file back
    gives bit-identical tensors in either format. A scene with non-finite values
    or zero quaternions is refused with a ValueError before anything is written. Rows are written a chunk
    at a time: ``progress`` counts them (Gaussians), ``should_stop`` ends the write between chunks
    (:class:`~artnvg_core.progress.Cancelled`, no file left). ``notes`` is told of a 2D filter the file cannot
    record (it reads back Mip-Splatting's when antialiased, else the classic one; :func:`~artnvg_core.notes.tell`).
    """
    path = Path(path)
    cpu = scene_to_write(scene, path, should_stop)
    read_back = (MIP_SPLATTING_BLUR_PX2, True) if cpu.antialiased else (DEFAULT_BLUR_PX2, False)
    tell_filter_change(notes, path, cpu, ".ply", *read_back)
    names = _ply_names(cpu)
    work = ChunkedWork(len(cpu), 1, progress, should_stop)
    header = "\n".join([
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        f"element {_PLY_ELEMENT} {len(cpu)}",
        *(f"property float {name}" for name in names),
        "end_header",
    ]) + "\n"

    def write(stream: BinaryIO) -> None:
        stream.write(header.encode("ascii"))
        for rows in work.chunks():
            _write_ply_body(stream, _ply_rows(cpu, rows), binary)

    write_atomically(path, write, overwrite=overwrite)
