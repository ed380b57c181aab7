"""Niantic SPZ (``.spz``): read versions 1 to 4, write version 3 (or 2).

Containers, as nianticlabs/spz's reference reads them: versions 1-3 are one
gzip stream holding a 16-byte header (magic "NGSP", version, count, SH
degree, fractional bits, flags, reserved) and the attribute arrays; version
4 is a 32-byte plain header, optional extension records, a table of
(compressed, uncompressed) sizes and one zstd stream per attribute. Arrays,
per Gaussian: positions (24-bit signed fixed point with ``fractional bits``;
float16 in version 1), opacities (uint8, value / 255), colours (uint8, f_dc =
(b / 255 - 0.5) / 0.15), log-scales (uint8, b / 16 - 10), rotations (version
3+: the smallest three components, 2 + 3 x 10 bits; version 2: x y z as
uint8), SH coefficients (uint8, (b - 128) / 128, coefficient-major with the
colour channel inner). Flag 0x1 marks a scene trained antialiased (loaded
with ``GaussianScene.antialiased``, written from it). Reading version 4 needs
the ``zstandard`` package. Degree-4 SH is read as degree 3 (with a note for the user). Streams are
inflated only up to the size the header implies, which may be at most 64 times the file's
size (:mod:`.bounded`).

Axes: the format names none of its own except through the ``SPZ_ADOBE_coordinate_system``
extension record (in version 4's header zone, or after the arrays of a version 1-3 file flagged
0x2); a file carrying one is read in the axes it names (any of the 8 axis-flip systems; the
90-degree-rotated ones are refused). Files without one hold whatever their writer was given:
Niantic's library converts only when its caller names the source axes (``PackOptions.from``,
default UNSPECIFIED), so its own ply-to-spz path, spz-js and PlayCanvas splat-transform 3 store
the PLY's axes (x right, y down, z forward) unchanged, while the format's description and
splat-transform 2.1-2.7 store RUB (x right, y up, z back); docs/scenes_and_formats.md gives the
evidence. Such a file is read with ``axes``: "ply" or "rub" as named, or "auto": with cameras,
the reading that puts more of the scene inside their views; without, the PLY's axes (the
majority writers'), said in one note for the user. RUB is converted to the PLY's axes by flipping y and
z of positions, the x y z components of quaternions as (x, -y, -z), and each SH coefficient by the
parity of its basis function under that flip. Written in the PLY's axes with no record, as those
writers write (``axes="rub"``: in RUB).

Written as version 3 (gzip, which the stdlib writes; read by Niantic's library since
2.0 and by splat-transform) or, with ``version=2``, version 2 (rotations in 3 bytes; for
spz-js 1.2, which reads versions 1 and 2 only), with the reference's default quantisation:
12 fractional bits, SH degree-1 coefficients in 5 bits and higher degrees in 4. Positions then
hold |coordinate| < 2048 (2^23 / 2^bits). Far floaters, up to one Gaussian in a thousand
(:data:`MOST_MOVED`, rounded down), may lie beyond: each is moved along its ray from the origin
onto the range's edge (largest |coordinate| (2^23 - 1) / 2^bits), its scales multiplied by the same ratio,
so that it keeps its direction and apparent size seen from the origin, where a capture's cameras
stand; one note for the user says how many and the farthest. The reference writer wraps them into
garbage instead, and keeping them by giving up bits cost the bear capture's renders 10 dB
(docs/scenes_and_formats.md). When more lie beyond, the writer gives up fractional bits (the
range doubling with each) until all but that share fit, and moves the rest; more than that
share at |coordinate| >= 2^23 is refused. Round trip ply -> spz -> ply, per field: means within
0.5 / 2^bits (2^-13 at 12 bits), a moved Gaussian's of its new position; log-scales within 1/32
inside [-10, 5.9] (clamped outside), a moved Gaussian's after their shift; f_dc within
0.5 / (0.15 * 255) = 0.0131 inside [-3.33, 3.33] (clamped outside); opacity sigmoid(logit)
within 0.5 / 255; unit quaternion components within 0.002 (up to the sign of q; version 2:
x y z within 0.5 / 127.5 with w >= 0, w derived from them); SH degree-1 coefficients within
4.5 / 128 and higher degrees within 8.5 / 128 inside [-1, 0.99] (clamped outside).
"""

from __future__ import annotations

import gzip
import io
import logging
import math
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import torch

from ..cameras.camera_set import CameraSet
from ..cameras.geometry import normalize_quats
from ..counted import counted
from ..fileio import write_atomically
from ..notes import NoteFn, tell
from ..progress import ProgressFn, Stages, StopFn
from ..scene import DEFAULT_BLUR_PX2, GaussianScene, validate_scene
from .bounded import inflate_exactly, read_at_most, require_inflatable
from .common import (
    ChunkedWork,
    opacity_bytes,
    opacity_logits_from_bytes,
    require_file,
    scene_to_write,
    tell_filter_change,
    to_bytes,
)

_log = logging.getLogger(__name__)

MAGIC = 0x5053474E  # "NGSP" little-endian
LATEST_VERSION = 4
WRITTEN_VERSIONS = (2, 3)
COLOR_SCALE = 0.15
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
_LEGACY_HEADER = struct.Struct("<IIIBBBB")  # magic version count degree fractional_bits flags reserved
_HEADER = struct.Struct("<IIIBBBBI12x")  # ... numStreams tocByteOffset reserved[12]
_COORDINATE_EXTENSION = 0xADBE0003
RUB, RDF = 4, 6  # the reference's CoordinateSystem values; 1..8 differ by axis flips only
AXES = ("auto", "ply", "rub")  # how a file without a coordinate-system record is read (module docstring)
_NAMED = {"ply": RDF, "rub": RUB}
_MAX_TRAILER = 65536  # bytes of extension records read after a version 1-3 file's arrays
_FACING_SAMPLE = 65536, 64  # at most this many Gaussians and views decide "auto" with cameras
_SQRT1_2 = math.sqrt(0.5)
_NO_FLIP, _RUB_FLIP = torch.tensor([1.0, 1, 1]), torch.tensor([1.0, -1, -1])  # RDF <-> RUB
_MAX_DEGREE = 4
MOST_MOVED = 0.001  # the share of Gaussians the writer may move onto the positions' range (module docstring)
# Seconds per million Gaussians of SH degree 3 (one thread of a 2-core CPU) in each stage of a read: the share of
# the progress bar each fills.
READ_STAGES = {"inflate": 0.26, "decode": 0.42, "check": 0.16}


def _sh_flip_signs(x: float, y: float, z: float) -> np.ndarray:
    """[15] sign of each SH coefficient (degrees 1-3, basis order) when the axes flip by (x, y, z)."""
    return np.array([y, z, x, x * y, y * z, 1, x * z, 1, y, x * y * z, y, z, x, z, x], np.float64)


def _axis_flips(stored: int, path: Path) -> np.ndarray:
    """(x, y, z) signs taking coordinates in the reference's system ``stored`` to RDF (and back)."""
    if not 1 <= stored <= 8:
        raise ValueError(
            f"{path}: SPZ_ADOBE_coordinate_system: coordinate system {stored} is not supported "
            "(only the eight axis-flip systems 1-8, e.g. RUB 4 or RDF 6)"
        )
    differ = (stored - 1) ^ (RDF - 1)
    return np.array([-1.0 if differ >> bit & 1 else 1.0 for bit in range(3)])


def _stored_system(path: Path, zone: bytes) -> int | None:
    """The coordinate system named by an extension record in ``zone`` (None when none names one)."""
    offset = 0
    while offset + 8 <= len(zone):
        kind, length = struct.unpack_from("<II", zone, offset)
        if offset + 8 + length > len(zone):
            raise ValueError(f"{path}: extension record at byte {offset} runs past its zone "
                             f"({counted(length, 'byte')})")
        if kind == _COORDINATE_EXTENSION and length >= 4:
            return struct.unpack_from("<I", zone, offset + 8)[0] or RUB
        offset += 8 + length
    return None


def _array_sizes(count: int, degree: int, version: int) -> dict[str, int]:
    """Bytes of each attribute array, in file order."""
    return {
        "positions": count * 3 * (2 if version == 1 else 3),
        "alphas": count,
        "colors": count * 3,
        "scales": count * 3,
        "rotations": count * (4 if version >= 3 else 3),
        "sh": count * ((degree + 1) ** 2 - 1) * 3,
    }


def _check_header(path: Path, version: int, count: int, degree: int, valid_versions: range) -> None:
    if version not in valid_versions:
        raise ValueError(f"{path}: version: {version} is not a supported SPZ version ({valid_versions.start}-"
                         f"{valid_versions.stop - 1} in this container)")
    if count == 0 or count > 2**31 - 1:
        raise ValueError(f"{path}: numPoints: {count} is not a valid Gaussian count")
    if degree > _MAX_DEGREE:
        raise ValueError(f"{path}: shDegree: {degree} is above SPZ's maximum 4")


def _read_legacy(path: Path, raw: bytes, should_stop: StopFn | None,
                 progress: ProgressFn | None) -> tuple[dict, dict[str, bytes], int | None]:
    try:
        with gzip.GzipFile(fileobj=io.BytesIO(raw)) as stream:
            head = read_at_most(stream, _LEGACY_HEADER.size)
            if len(head) < _LEGACY_HEADER.size:
                raise ValueError(f"{path}: header: {counted(len(head), 'byte')}, expected {_LEGACY_HEADER.size}")
            magic, version, count, degree, fractional_bits, flags, _ = _LEGACY_HEADER.unpack_from(head)
            if magic != MAGIC:
                raise ValueError(f"{path}: magic: {magic:#010x}, expected {MAGIC:#010x} ('NGSP')")
            _check_header(path, version, count, degree, range(1, LATEST_VERSION + 1))
            sizes = _array_sizes(count, degree, version)
            field = f"numPoints: {counted(count, 'Gaussian')} of SH degree {degree}"
            require_inflatable(sum(sizes.values()), path, field)
            data = inflate_exactly(stream, sum(sizes.values()), path, field,
                                   trailing_allowed=bool(flags & FLAG_EXTENSIONS), should_stop=should_stop,
                                   progress=progress)
            trailer = read_at_most(stream, _MAX_TRAILER) if flags & FLAG_EXTENSIONS else None  # extension records
            system = None if trailer is None else _stored_system(path, bytes(trailer))
    except (OSError, EOFError, zlib.error) as error:
        raise ValueError(f"{path}: gzip stream: not readable ({error}); the file is truncated or corrupt") from error
    arrays, offset = {}, 0
    for name, size in sizes.items():
        arrays[name], offset = data[offset : offset + size], offset + size
    header = {"version": version, "count": count, "degree": degree, "bits": fractional_bits, "flags": flags}
    return header, arrays, system


def _read_v4(path: Path, raw: bytes, should_stop: StopFn | None,
             progress: ProgressFn | None) -> tuple[dict, dict[str, bytes], int | None]:
    if len(raw) < _HEADER.size:
        raise ValueError(f"{path}: header: {counted(len(raw), 'byte')}, expected {_HEADER.size}")
    _, version, count, degree, fractional_bits, flags, streams, toc = _HEADER.unpack_from(raw)
    _check_header(path, version, count, degree, range(4, LATEST_VERSION + 1))
    sizes = {name: size for name, size in _array_sizes(count, degree, version).items() if size}
    require_inflatable(sum(sizes.values()), path, f"numPoints: {counted(count, 'Gaussian')} of SH degree {degree}")
    if streams != len(sizes):
        raise ValueError(f"{path}: numStreams: {streams}, expected {len(sizes)} for SH degree {degree}")
    body = toc + 16 * streams
    if toc < _HEADER.size or body > len(raw):
        raise ValueError(f"{path}: tocByteOffset: {toc} puts the table outside the {len(raw)}-byte file")
    system = _stored_system(path, raw[_HEADER.size : toc]) if flags & FLAG_EXTENSIONS else None
    try:
        import zstandard
    except ImportError as error:
        raise ValueError(f"{path}: SPZ version 4 is zstd-compressed: pip install zstandard") from error
    arrays, offset = {}, body
    for index, (name, size) in enumerate(sizes.items()):
        compressed, uncompressed = struct.unpack_from("<QQ", raw, toc + 16 * index)
        if uncompressed != size:
            raise ValueError(f"{path}: {name} stream: {counted(uncompressed, 'byte')} uncompressed, expected "
                             f"{size} for {counted(count, 'Gaussian')}")
        if compressed > len(raw) - offset:
            raise ValueError(f"{path}: {name} stream: runs "
                             f"{counted(compressed - (len(raw) - offset), 'byte')} past the "
                             "end of the file (truncated)")
        reader = zstandard.ZstdDecompressor().stream_reader(raw[offset : offset + compressed])
        try:
            arrays[name] = inflate_exactly(reader, size, path, f"{name} stream", should_stop=should_stop)
        except zstandard.ZstdError as error:
            raise ValueError(f"{path}: {name} stream: not valid zstd data ({error})") from error
        offset += compressed
        if progress is not None:  # a stream at a time
            progress(index + 1, len(sizes), {})
    if offset != len(raw):
        raise ValueError(f"{path}: the file holds {counted(len(raw) - offset, 'byte')} after its last stream")
    header = {"version": version, "count": count, "degree": degree, "bits": fractional_bits, "flags": flags}
    return header, arrays, system


def _positions(path: Path, header: dict, raw: bytes) -> np.ndarray:
    count = header["count"]
    if header["version"] == 1:
        return np.frombuffer(raw, "<f2").reshape(count, 3).astype(np.float64)
    if header["bits"] > 23:
        raise ValueError(f"{path}: fractionalBits: {header['bits']}, expected at most 23")
    b = np.frombuffer(raw, np.uint8).reshape(count, 3, 3).astype(np.int32)
    fixed = b[..., 0] | b[..., 1] << 8 | b[..., 2] << 16
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    return fixed / float(1 << header["bits"])


def _rotations_xyzw(version: int, codes: np.ndarray) -> np.ndarray:
    """[N, 4] x y z w quaternions of rotation codes [N, 3] (version 1-2) or [N, 4] bytes (version 3+)."""
    if version < 3:
        xyz = codes / 127.5 - 1
        return np.concatenate([xyz, np.sqrt(np.maximum(0, 1 - (xyz**2).sum(1)))[:, None]], 1)
    comp = np.ascontiguousarray(codes).view("<u4")[:, 0].astype(np.int64)
    largest = comp >> 30
    q = np.zeros((len(comp), 4))
    for i in range(3, -1, -1):  # the last component is in the lowest 10 bits
        value = _SQRT1_2 * (comp & 511) / 511 * np.where(comp >> 9 & 1, -1.0, 1.0)
        take = largest != i
        q[take, i] = value[take]
        comp = np.where(take, comp >> 10, comp)
    rows = np.arange(len(q))
    q[rows, largest] = np.sqrt(np.maximum(0, 1 - (q**2).sum(1)))
    return q


def _check_axes(axes: str) -> None:
    if axes not in AXES:
        raise ValueError(f"spz axes: expected one of {', '.join(AXES)}, got {axes!r}")


def _facing_system(stored: np.ndarray, cameras: CameraSet) -> int:
    """RDF or RUB: the reading of ``stored`` positions [N, 3] that puts more of them inside the views of
    ``cameras`` (a stride sample of :data:`_FACING_SAMPLE` Gaussians and views; a tie reads RDF)."""
    gaussians, views = _FACING_SAMPLE
    points = torch.from_numpy(stored[:: -(-len(stored) // gaussians)])
    sample = cameras.subset(range(0, len(cameras), -(-len(cameras) // views)))
    as_ply, as_rub = (int(sample.in_view(points * flip).sum()) for flip in (_NO_FLIP, _RUB_FLIP))
    return RDF if as_ply >= as_rub else RUB


def _unrecorded_system(path: Path, axes: str, stored: np.ndarray, cameras: CameraSet | None,
                       notes: NoteFn | None) -> int:
    """The axes of a file without a coordinate-system record (module docstring); the PLY's axes taken by default
    told to ``notes``."""
    if axes != "auto":
        return _NAMED[axes]
    if cameras is not None and len(cameras):
        system = _facing_system(stored, cameras)
        _log.info("%s names no axes: read in %s, which puts more of it in front of the cameras", path,
                  "RUB" if system == RUB else "the PLY's axes")
        return system
    tell(notes, path, "the file names no axes: read in the PLY's axes (x right, y down, z forward), as "
                      "splat-transform, spz-js and Niantic's ply-to-spz write; if it is upside down, read it with spz "
                      "axes 'rub' (--spz-axes rub, the Load Gaussian Scene node's spz_axes)")
    return RDF


def read_spz(path: str | os.PathLike, *, drop_invalid: bool = False, axes: str = "auto",
             cameras: CameraSet | None = None, progress: ProgressFn | None = None,
             should_stop: StopFn | None = None, notes: NoteFn | None = None) -> GaussianScene:
    """Read an SPZ file of version 1 to 4 (layout and axes in the module docstring); a file without a
    coordinate-system record is read in ``axes``: "ply", "rub" or "auto" (by ``cameras`` when given,
    else the PLY's axes). The arrays are inflated a piece at a time, then decoded a chunk of Gaussians at a time:
    ``progress`` follows the whole read in the file's bytes, filling once over its stages (:data:`READ_STAGES`),
    ``should_stop`` ends it between pieces and chunks (:class:`~artnvg_core.progress.Cancelled`). ``notes`` is told
    (:func:`~artnvg_core.notes.tell`) of the PLY's axes taken for a file that names none when no cameras choose,
    of degree-4 SH read as degree 3 and of invalid Gaussians dropped."""
    path = Path(path)
    _check_axes(axes)
    require_file(path)
    raw = path.read_bytes()
    stages = Stages(progress, len(raw), READ_STAGES)
    if raw[:4] == struct.pack("<I", MAGIC):
        header, arrays, system = _read_v4(path, raw, should_stop, stages["inflate"])
    elif raw[:2] == b"\x1f\x8b":
        header, arrays, system = _read_legacy(path, raw, should_stop, stages["inflate"])
    else:
        raise ValueError(f"{path}: not an SPZ file: starts with neither 'NGSP' (version 4) nor a gzip stream")
    stored = _positions(path, header, arrays["positions"])
    if system is None:
        system = _unrecorded_system(path, axes, stored, cameras, notes)
    count, degree = header["count"], header["degree"]
    flips = _axis_flips(system, path)
    x, y, z = flips
    coefficients = (degree + 1) ** 2 - 1
    sh_codes = np.frombuffer(arrays.get("sh", b""), np.uint8).reshape(count, coefficients, 3)  # none in v4 at degree 0
    rotations = np.frombuffer(arrays["rotations"], np.uint8).reshape(count, -1)
    if degree > 3:
        tell(notes, path, f"SH degree {degree} read as degree 3 (the degree-4 terms are dropped)")
        sh_codes, degree = sh_codes[:, :15], 3
    signs = _sh_flip_signs(x, y, z)[: sh_codes.shape[1], None]
    colours = np.frombuffer(arrays["colors"], np.uint8).reshape(count, 1, 3)
    scales = np.frombuffer(arrays["scales"], np.uint8).reshape(count, 3)
    alphas = np.frombuffer(arrays["alphas"], np.uint8)
    scene = GaussianScene(means=torch.empty(count, 3), quats=torch.empty(count, 4), log_scales=torch.empty(count, 3),
                          opacity_logits=torch.empty(count), sh=torch.empty(count, 1 + sh_codes.shape[1], 3),
                          antialiased=bool(header["flags"] & FLAG_ANTIALIASED))
    for rows in ChunkedWork(count, 1, stages["decode"], should_stop).chunks():
        q = _rotations_xyzw(header["version"], rotations[rows])
        q[:, :3] *= (y * z, x * z, x * y)
        dc = (colours[rows] / 255 - 0.5) / COLOR_SCALE
        scene.means[rows] = torch.from_numpy(stored[rows] * flips)
        scene.quats[rows] = torch.from_numpy(q[:, [3, 0, 1, 2]])
        scene.log_scales[rows] = torch.from_numpy(scales[rows] / 16 - 10)
        scene.opacity_logits[rows] = torch.from_numpy(opacity_logits_from_bytes(alphas[rows]))
        scene.sh[rows] = torch.from_numpy(np.concatenate([dc, (sh_codes[rows] - 128.0) / 128 * signs], 1))
    return validate_scene(scene, str(path), drop_invalid=drop_invalid, should_stop=should_stop,
                          progress=stages["check"], notes=notes)[0]


def _fractional_bits(path: Path, extents: np.ndarray) -> int:
    """The most fractional bits, at most 12, at which the Gaussians' largest |coordinate| ``extents`` [N] fit
    SPZ's 24-bit signed fixed point, all but the farthest :data:`MOST_MOVED` of them (rounded down), which
    :func:`_onto_range` moves; refused when even 0 bits leave more of them out."""
    spared = int(len(extents) * MOST_MOVED)
    bulk = float(np.partition(extents, len(extents) - 1 - spared)[len(extents) - 1 - spared])
    bits = 12
    while bits >= 0 and math.floor(bulk * (1 << bits) + 0.5) >= 1 << 23:
        bits -= 1
    if bits < 0:
        huge = int((np.floor(extents + 0.5) >= 1 << 23).sum())
        raise ValueError(f"{path}: not written: means: {counted(huge, 'Gaussian')} of {len(extents):,} with a "
                         f"|coordinate| of 2^23 or more (up to {float(extents.max()):.6g}), beyond SPZ's 24-bit fixed "
                         f"point at any fractional bits; at most {spared:,} (one in {round(1 / MOST_MOVED):,}, "
                         "rounded down) may be moved onto its range")
    return bits


def _onto_range(path: Path, means: np.ndarray, log_scales: np.ndarray, bits: int,
                notes: NoteFn | None) -> tuple[np.ndarray, np.ndarray]:
    """``means`` [N, 3] and ``log_scales`` [N, 3] with each Gaussian beyond the range of ``bits`` fractional bits
    moved along its ray from the origin onto that range, its scales multiplied by the same ratio (so it keeps
    its direction and apparent size seen from the origin); one note to ``notes`` (:func:`~artnvg_core.notes.tell`) says
    how many and how far."""
    extents = np.abs(means).max(1)
    far = np.floor(extents * (1 << bits) + 0.5) >= 1 << 23
    if not far.any():
        return means, log_scales
    limit = ((1 << 23) - 1) / (1 << bits)
    ratio = limit / extents[far]
    means, log_scales = means.copy(), log_scales.copy()
    means[far] *= ratio[:, None]
    log_scales[far] += np.log(ratio)[:, None]
    tell(notes, path, f"{counted(int(far.sum()), 'Gaussian')} beyond SPZ's range at {bits} fractional bits "
                      f"(|coordinate| up to {limit:.6g}) moved onto it along their rays from the origin, their sizes "
                      "scaled alike (the same direction and apparent size from there); the farthest from "
                      f"|coordinate| {float(extents[far].max()):.6g}")
    return means, log_scales


def check_geometry(cpu: GaussianScene, path: Path) -> None:
    """What :func:`write_spz` refuses of the geometry alone (more than :data:`MOST_MOVED` of the Gaussians
    with a |coordinate| of 2^23 or more), checked now."""
    _fractional_bits(path, cpu.means.double().abs().amax(1).numpy())


def _quantized_sh(values: np.ndarray, bits: int) -> np.ndarray:
    """SH coefficients as bytes, rounded to a bucket of 2^(8 - bits) as the reference writer does."""
    bucket = 1 << (8 - bits)
    q = np.floor(values * 128 + 0.5) + 128
    return np.clip((q + bucket // 2) // bucket * bucket, 0, 255).astype(np.uint8)


def _smallest_three(q: np.ndarray) -> np.ndarray:
    """[N] uint32 smallest-three codes of unit quaternions [N, 4] (x y z w)."""
    largest = np.abs(q).argmax(1)
    rows = np.arange(len(q))
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    comp = largest.astype(np.uint64)
    for i in range(4):
        take = largest != i
        magnitude = np.floor(511 * np.abs(q[:, i]) / _SQRT1_2 + 0.5).astype(np.uint64)
        code = (comp << np.uint64(10)) | (q[:, i] < 0).astype(np.uint64) << np.uint64(9) | magnitude
        comp = np.where(take, code, comp)
    return comp.astype("<u4")


def _first_three(q: np.ndarray) -> np.ndarray:
    """[N, 3] uint8 version-2 codes of unit quaternions [N, 4] (x y z w): x y z of the sign with w >= 0."""
    q = q * np.where(q[:, 3:] < 0, -1.0, 1.0)
    return to_bytes(q[:, :3] * 127.5 + 127.5)


def _attribute_arrays(cpu: GaussianScene, means: np.ndarray, log_scales: np.ndarray, bits: int, flips: np.ndarray,
                      version: int) -> list:
    """The functions giving each attribute array's bytes (file order) of Gaussians ``rows`` (a slice): ``means``
    [N, 3] in the file's axes (``flips``) and ``log_scales`` [N, 3] as written (:func:`_onto_range`)."""
    x, y, z = flips
    degree = cpu.sh_degree
    signs = _sh_flip_signs(x, y, z)[: (degree + 1) ** 2 - 1, None]

    def positions(rows: slice) -> np.ndarray:
        fixed = np.floor(means[rows] * (1 << bits) + 0.5).astype(np.int64) & 0xFFFFFF
        return np.stack([fixed & 255, fixed >> 8 & 255, fixed >> 16], -1).astype(np.uint8)

    def rotations(rows: slice) -> np.ndarray:
        q = normalize_quats(cpu.quats[rows].double()).numpy()[:, [1, 2, 3, 0]] * (y * z, x * z, x * y, 1)
        return _smallest_three(q) if version == 3 else _first_three(q)

    def sh(rows: slice) -> np.ndarray:
        sh_rest = cpu.sh[rows, 1:].double().numpy() * signs
        return np.concatenate([_quantized_sh(sh_rest[:, :3], 5), _quantized_sh(sh_rest[:, 3:], 4)], 1)

    return [
        positions,
        lambda rows: opacity_bytes(cpu.opacity_logits[rows]),
        lambda rows: to_bytes(cpu.sh[rows, 0].double().numpy() * (COLOR_SCALE * 255) + 127.5),
        lambda rows: to_bytes((log_scales[rows] + 10) * 16),
        rotations,
        sh,
    ]


def write_spz(scene: GaussianScene, path: str | os.PathLike, *, axes: str = "auto", version: int = 3,
              overwrite: bool = True, progress: ProgressFn | None = None, should_stop: StopFn | None = None,
              notes: NoteFn | None = None) -> None:
    """Write ``scene`` as an SPZ file of ``version`` 3 (or 2) atomically, in the PLY's axes with no
    coordinate-system record, as splat-transform, spz-js and Niantic's ply-to-spz write (``axes`` "auto" or
    "ply"), or in RUB (``axes="rub"``); module docstring. With ``overwrite`` False never over an existing file
    (:func:`~artnvg_core.fileio.write_atomically`). Each attribute array is quantised and deflated a chunk of
    Gaussians at a time into one gzip stream: ``progress`` counts the chunks' Gaussians over the 6 arrays,
    ``should_stop`` ends the write between chunks (:class:`~artnvg_core.progress.Cancelled`, no file left).
    ``notes`` is told of far Gaussians moved onto the positions' range and of a 2D blur other than the default
    (the format records the antialiased flag alone; :func:`~artnvg_core.notes.tell`).

    Refused with a ValueError before writing: non-finite values, zero quaternions, more than one
    Gaussian in a thousand with a coordinate of magnitude 2^23 or more.
    """
    path = Path(path)
    _check_axes(axes)
    if version not in WRITTEN_VERSIONS:
        raise ValueError(f"spz version: expected one of {', '.join(map(str, WRITTEN_VERSIONS))}, got {version!r}")
    cpu = scene_to_write(scene, path, should_stop)
    flips = _axis_flips(RUB if axes == "rub" else RDF, path)
    means = cpu.means.double().numpy() * flips
    bits = _fractional_bits(path, np.abs(means).max(1))
    means, log_scales = _onto_range(path, means, cpu.log_scales.double().numpy(), bits, notes)
    tell_filter_change(notes, path, cpu, ".spz", DEFAULT_BLUR_PX2, cpu.antialiased)
    arrays = _attribute_arrays(cpu, means, log_scales, bits, flips, version)
    work = ChunkedWork(len(cpu), len(arrays), progress, should_stop)
    flags = FLAG_ANTIALIASED if cpu.antialiased else 0
    header = _LEGACY_HEADER.pack(MAGIC, version, len(cpu), cpu.sh_degree, bits, flags, 0)

    def write(stream) -> None:
        deflate = zlib.compressobj(6, zlib.DEFLATED, 31)  # gzip.compress(..., compresslevel=6, mtime=0)'s stream
        stream.write(deflate.compress(header))
        for array in arrays:
            for rows in work.chunks():
                stream.write(deflate.compress(np.ascontiguousarray(array(rows)).tobytes()))
        stream.write(deflate.flush())

    write_atomically(path, write, overwrite=overwrite)
