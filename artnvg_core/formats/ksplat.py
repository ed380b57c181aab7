"""mkkellogg GaussianSplats3D ``.ksplat`` (its ``SplatBuffer``): read compression levels 0-2, write level 0.

Layout (little-endian), as SplatBuffer.js reads it: a 4096-byte header (version major, minor
as bytes 0-1, then uint32 maxSectionCount at 4, sectionCount 8, maxSplatCount 12, splatCount 16,
uint16 compressionLevel at 20, float32 sceneCenter at 24, min / max SH coefficient at 36 / 40),
``maxSectionCount`` 1024-byte section headers (uint32 splatCount 0, maxSplatCount 4, bucketSize 8,
bucketCount 12, float32 bucketBlockSize 16, uint16 bucketStorageSizeBytes 20, uint32
compressionScaleRange 24, storageSizeBytes 28, fullBucketCount 32, partiallyFilledBucketCount 36,
uint16 sphericalHarmonicsDegree 40), then each section's data: partially filled bucket lengths
(uint32), bucket centres (3 float32 each), and ``maxSplatCount`` records of

- level 0: centre 3 x float32, linear scale 3 x float32, rotation w x y z 4 x float32, RGBA 4 x
  uint8, SH 9 or 24 x float32 (44 + 4 x 9|24 bytes);
- level 1: centre 3 x uint16 relative to its bucket's centre ((v - range) x blockSize / 2 /
  range), scale and rotation as float16, RGBA, SH as float16;
- level 2: as level 1 with SH as uint8 from the header's min..max (default -1.5..1.5).

Colour is SH_C0 * f_dc + 0.5 and opacity sigmoid(logit), as bytes / 255 (as ``.splat``). SH
(degrees 1 and 2 only) is stored per degree channel-major: the 9 degree-1 values are R's three
coefficients, then G's, then B's; the 15 degree-2 values likewise. Coordinates are the PLY's
axes, stored as they are. Scales that underflowed to 0 (float16 below 6e-8) are read as the
smallest normal float32 (a flat Gaussian, as the viewer draws it).

Written at level 0, one section: means, linear scales (log-scales in [-87, 88]), unit quaternions
and SH degree 1-2 coefficients as float32 (exact to float32 rounding); colour and opacity as
``.splat`` writes them (within 0.5 / 255, colour clamped to [0, 1]); degree-3 SH terms and a scene's
2D filter (the format records none: read back classic) dropped, each with a note for the user.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np
import torch

from ..cameras.geometry import normalize_quats
from ..counted import counted
from ..fileio import write_atomically
from ..notes import NoteFn
from ..progress import ProgressFn, Stages, StopFn
from ..scene import GaussianScene, validate_scene
from .common import ChunkedWork, require_file, scene_to_write
from .splat import colour_and_opacity, linear_scales, rgba_bytes, tell_dropped

HEADER_BYTES, SECTION_HEADER_BYTES = 4096, 1024
VERSION = (0, 1)
_HEADER = struct.Struct("<BBxxIIIIH2x3fff")
_SECTION = struct.Struct("<IIIIfHxxIIIIH")
_SH_VALUES = {0: 0, 1: 9, 2: 24}  # stored SH values per Gaussian by degree
_DEFAULT_SCALE_RANGE = {0: 1, 1: 32767, 2: 32767}
_DEFAULT_SH_RANGE = 1.5
_BUCKET_BYTES = 12  # a bucket's centre at levels 1-2: 3 x float32
# Seconds per million Gaussians of SH degree 2 (one thread of a 2-core CPU) in each stage of a read: the share of
# the progress bar each fills.
READ_STAGES = {"read": 0.06, "decode": 0.22, "check": 0.11}


def _record(level: int, degree: int) -> np.dtype:
    """The per-Gaussian record of compression ``level`` with SH ``degree``."""
    half = "<f4" if level == 0 else "<f2"
    fields = [("center", "<f4" if level == 0 else "<u2", 3), ("scale", half, 3), ("rotation", half, 4),
              ("rgba", "u1", 4)]
    if degree:
        fields.append(("sh", {0: "<f4", 1: "<f2", 2: "u1"}[level], _SH_VALUES[degree]))
    return np.dtype(fields)


def _sh_rest(values: np.ndarray, degree: int) -> np.ndarray:
    """[N, 0|9|24] stored SH (channel-major per degree) -> [N, 0|3|8, 3] coefficients (channel inner)."""
    if degree == 0:
        return np.zeros((len(values), 0, 3))
    blocks = [values[:, :9].reshape(-1, 3, 3)] + ([values[:, 9:].reshape(-1, 3, 5)] if degree == 2 else [])
    return np.concatenate([b.transpose(0, 2, 1) for b in blocks], 1)


def _stored_sh(rest: np.ndarray) -> np.ndarray:
    """[N, 3|8, 3] coefficients -> [N, 9|24] stored SH (inverse of :func:`_sh_rest`)."""
    blocks = [rest[:, :3]] + ([rest[:, 3:8]] if rest.shape[1] > 3 else [])
    return np.concatenate([b.transpose(0, 2, 1).reshape(len(rest), -1) for b in blocks], 1)


def _bucket_of_each(path: Path, s: int, section: dict, count: int) -> np.ndarray:
    """[count] bucket index of each record: full buckets of ``bucketSize`` first, then the partially
    filled ones with their stored lengths. The lengths' sum is checked against ``count`` before any
    array of that size is made: memory follows ``count``, which the file's bytes bound, never a length
    read from the file. ValueError naming ``path`` and section ``s`` when the buckets do not hold
    exactly ``count`` Gaussians."""
    full = min(section["full"] * section["bucket_size"], count)
    lengths = section["lengths"]
    held = section["full"] * section["bucket_size"] + int(lengths.sum())
    if held != count:
        raise ValueError(f"{path}: section {s}: its buckets (fullBucketCount {section['full']}, bucketSize "
                         f"{section['bucket_size']}, {len(lengths)} partly filled of lengths adding up to "
                         f"{int(lengths.sum())}) hold {counted(held, 'Gaussian')}, not its splatCount {count}")
    index = np.arange(full) // max(section["bucket_size"], 1)
    partial = np.repeat(section["full"] + np.arange(len(lengths)), lengths)
    return np.concatenate([index, partial])


def read_ksplat(path: str | os.PathLike, *, drop_invalid: bool = False, progress: ProgressFn | None = None,
                should_stop: StopFn | None = None, notes: NoteFn | None = None) -> GaussianScene:
    """Read a ``.ksplat`` file of compression level 0, 1 or 2 (layout in the module docstring). Its sections'
    headers are checked first, then their records decoded a chunk of Gaussians at a time: ``progress`` follows the
    whole read in the file's bytes, filling once over its stages (:data:`READ_STAGES`), ``should_stop`` ends it
    between chunks (:class:`~artnvg_core.progress.Cancelled`). ``notes`` is told of invalid Gaussians dropped
    (:func:`~artnvg_core.notes.tell`)."""
    path = Path(path)
    require_file(path)
    stages = Stages(progress, path.stat().st_size, READ_STAGES)
    data = path.read_bytes()
    if len(data) < HEADER_BYTES:
        raise ValueError(f"{path}: header: {counted(len(data), 'byte')}, expected {HEADER_BYTES}")
    major, minor, sections, _, _, _, level, *_, sh_min, sh_max = _HEADER.unpack_from(data)
    if (major, minor) < VERSION or major != VERSION[0]:
        raise ValueError(f"{path}: version: {major}.{minor} is not a supported .ksplat version (0.1 or later 0.x)")
    if level not in _DEFAULT_SCALE_RANGE:
        raise ValueError(f"{path}: compressionLevel: {level}, expected 0, 1 or 2")
    if HEADER_BYTES + sections * SECTION_HEADER_BYTES > len(data):
        raise ValueError(f"{path}: maxSectionCount: {sections} section headers do not fit the {len(data)}-byte file")
    sh_min, sh_max = sh_min or -_DEFAULT_SH_RANGE, sh_max or _DEFAULT_SH_RANGE
    offset, parts = HEADER_BYTES + sections * SECTION_HEADER_BYTES, []
    for s in range(sections):
        (count, capacity, bucket_size, buckets, block, bucket_bytes, scale_range, _, full, partial,
         degree) = _SECTION.unpack_from(data, HEADER_BYTES + s * SECTION_HEADER_BYTES)
        if degree not in _SH_VALUES:
            raise ValueError(f"{path}: section {s}: sphericalHarmonicsDegree: {degree}, expected 0, 1 or 2")
        if count > capacity:
            raise ValueError(f"{path}: section {s}: splatCount: {count}, more than its maxSplatCount {capacity}")
        record = _record(level, degree)
        meta = partial * 4
        storage = meta + bucket_bytes * buckets + record.itemsize * capacity
        if offset + storage > len(data):
            raise ValueError(f"{path}: section {s}: its counts need {counted(storage, 'byte')}, the file holds "
                             f"{len(data) - offset} after its start (truncated, or the counts are wrong)")
        part = {"rows": np.frombuffer(data, record, count, offset + meta + bucket_bytes * buckets), "degree": degree}
        if level > 0:
            if buckets and bucket_bytes != _BUCKET_BYTES:
                raise ValueError(f"{path}: section {s}: bucketStorageSizeBytes: {bucket_bytes}, expected "
                                 f"{_BUCKET_BYTES} (a bucket's centre, 3 float32)")
            section = {"full": full, "bucket_size": bucket_size,
                       "lengths": np.frombuffer(data, "<u4", partial, offset).astype(np.int64)}
            scale_range = scale_range or _DEFAULT_SCALE_RANGE[level]
            if full + partial > buckets:
                raise ValueError(f"{path}: section {s}: fullBucketCount {full} + partiallyFilledBucketCount "
                                 f"{partial} is more than its bucketCount {buckets}")
            part["bucket"] = _bucket_of_each(path, s, section, count)
            part["centres"] = np.frombuffer(data, "<f4", 3 * buckets, offset + meta).reshape(-1, 3).astype(np.float64)
            part["range"], part["block"] = scale_range, block
        parts.append(part)
        offset += storage
    if offset != len(data):
        raise ValueError(f"{path}: the file holds {counted(len(data) - offset, 'byte')} after its last section")
    degree = min((p["degree"] for p in parts), default=0)
    total = sum(len(p["rows"]) for p in parts)
    if total == 0:
        raise ValueError(f"{path}: the scene contains no Gaussians")
    scene = GaussianScene(means=torch.empty(total, 3), quats=torch.empty(total, 4), log_scales=torch.empty(total, 3),
                          opacity_logits=torch.empty(total), sh=torch.empty(total, (degree + 1) ** 2, 3))
    work, start, tiny = ChunkedWork(total, 1, stages["decode"], should_stop), 0, np.finfo(np.float32).tiny
    for part in parts:
        for rows in work.chunks(start, start + len(part["rows"])):
            local = slice(rows.start - start, rows.stop - start)
            records = part["rows"][local]
            means = records["center"].astype(np.float64)
            if level > 0:
                scale_range = part["range"]
                means = (means - scale_range) * (part["block"] / 2 / scale_range) + part["centres"][part["bucket"][local]]
            sh = records["sh"].astype(np.float64) if part["degree"] else np.zeros((len(records), 0))
            if level == 2 and part["degree"]:
                sh = sh / 255 * (sh_max - sh_min) + sh_min
            dc, opacity_logits = colour_and_opacity(records["rgba"])
            scales = np.abs(records["scale"].astype(np.float64))
            scene.means[rows] = torch.from_numpy(means)
            scene.quats[rows] = torch.from_numpy(records["rotation"].astype(np.float64))
            scene.log_scales[rows] = torch.from_numpy(np.log(np.maximum(scales, tiny)))
            scene.opacity_logits[rows] = opacity_logits
            rest = _sh_rest(sh, part["degree"])[:, : (degree + 1) ** 2 - 1]
            scene.sh[rows] = torch.cat([dc, torch.from_numpy(rest).float()], 1)
        start += len(part["rows"])
    return validate_scene(scene, str(path), drop_invalid=drop_invalid, should_stop=should_stop,
                          progress=stages["check"], notes=notes)[0]


def check_geometry(cpu: GaussianScene, path: Path) -> None:
    """What :func:`write_ksplat` refuses of the geometry alone (log-scales outside [-87, 88]), checked now."""
    linear_scales(cpu, path, ".ksplat")


def _rows(cpu: GaussianScene, scales: np.ndarray, degree: int, rows: slice) -> np.ndarray:
    """The level-0 records with SH ``degree`` of Gaussians ``rows`` of ``cpu``, whose linear scales are ``scales``."""
    part = cpu.select(rows)
    records = np.zeros(len(part), _record(0, degree))
    records["center"] = part.means.numpy()
    records["scale"] = scales[rows]
    records["rotation"] = normalize_quats(part.quats.double()).numpy()
    records["rgba"] = rgba_bytes(part)
    if degree:
        records["sh"] = _stored_sh(part.sh[:, 1 : (degree + 1) ** 2].double().numpy())
    return records


def write_ksplat(scene: GaussianScene, path: str | os.PathLike, *, overwrite: bool = True,
                 progress: ProgressFn | None = None, should_stop: StopFn | None = None,
                 notes: NoteFn | None = None) -> None:
    """Write ``scene`` as a level-0 ``.ksplat`` atomically (module docstring); with ``overwrite`` False never
    over an existing file (:func:`~artnvg_core.fileio.write_atomically`). Records are written a chunk of
    Gaussians at a time: ``progress`` counts them, ``should_stop`` ends the write between chunks
    (:class:`~artnvg_core.progress.Cancelled`, no file left). ``notes`` is told what the format drops (degree-3
    SH, a 2D filter other than classic; :func:`~artnvg_core.notes.tell`).

    Refused with a ValueError before writing: non-finite values, zero quaternions, log-scales
    outside [-87, 88].
    """
    path = Path(path)
    cpu = scene_to_write(scene, path, should_stop)
    scales = linear_scales(cpu, path, ".ksplat")
    degree = min(cpu.sh_degree, 2)
    tell_dropped(cpu, path, ".ksplat", degree, notes)
    n, record = len(cpu), _record(0, degree)
    header = bytearray(HEADER_BYTES)
    _HEADER.pack_into(header, 0, *VERSION, 1, 1, n, n, 0, 0.0, 0.0, 0.0, -_DEFAULT_SH_RANGE, _DEFAULT_SH_RANGE)
    section = bytearray(SECTION_HEADER_BYTES)
    _SECTION.pack_into(section, 0, n, n, 0, 0, 0.0, 0, 0, record.itemsize * n, 0, 0, degree)
    work = ChunkedWork(n, 1, progress, should_stop)

    def write(stream) -> None:
        stream.write(bytes(header) + bytes(section))
        for rows in work.chunks():
            stream.write(_rows(cpu, scales, degree, rows).tobytes())

    write_atomically(path, write, overwrite=overwrite)
