"""Gaussian scene files: :func:`load_scene` and :func:`save_scene` choose the format by extension.

Read: ``.ply`` (INRIA 3DGS, Mip-Splatting, PlayCanvas/SuperSplat compressed),
``.splat`` (antimatter15), ``.spz`` (Niantic, versions 1-4), ``.ksplat``
(mkkellogg GaussianSplats3D, levels 0-2), ``.ckpt`` (nerfstudio splatfacto).
Written: ``.ply`` (INRIA), ``.spz`` (version 3, or 2 for older readers),
``.splat``, ``.ksplat`` (level 0). Each format's module states its layout,
coordinate convention and quantisation; scenes are held in the INRIA layout
and the PLY's axes, and axes are converted only inside the reader and writer
of a format that stores others (SPZ). Every reader validates the scene (bad input: ValueError naming
the file and the field); every writer refuses an invalid scene before
writing and writes atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..cameras.camera_set import CameraSet
from ..fileio import require_regular_file
from ..notes import NoteFn
from ..progress import ProgressFn, StopFn, check_stop
from ..scene import GaussianScene
from . import ksplat, splat, spz
from .common import scene_to_write
from .ksplat import read_ksplat, write_ksplat
from .ply import read_ply, write_ply
from .splat import read_splat, write_splat
from .splatfacto import read_splatfacto_ckpt
from .spz import read_spz, write_spz

READERS = {".ply": read_ply, ".splat": read_splat, ".spz": read_spz, ".ksplat": read_ksplat,
           ".ckpt": read_splatfacto_ckpt}
WRITERS = {".ply": write_ply, ".spz": write_spz, ".splat": write_splat, ".ksplat": write_ksplat}
GEOMETRY_CHECKS = {".spz": spz.check_geometry, ".splat": splat.check_geometry, ".ksplat": ksplat.check_geometry}
SCENE_SUFFIXES = tuple(READERS)
SPZ_AXES = spz.AXES
SPZ_VERSIONS = spz.WRITTEN_VERSIONS
SAVE_SUFFIXES = tuple(WRITERS)
# The first bytes that tell a format whatever a file's extension: (signature, extension, what starts so). A
# .splat (headerless), a .ksplat (a small version number) and a .ckpt (a zip archive or a pickle) have none.
SIGNATURES = ((b"ply", ".ply", "a PLY header"),
              (b"\x1f\x8b", ".spz", "a gzip stream, as an SPZ file of version 1-3"),
              (b"NGSP", ".spz", "'NGSP', as an SPZ file of version 4"))
_DESCRIBED = ".ply (INRIA 3DGS or compressed PLY), .splat, .spz, .ksplat or .ckpt (nerfstudio splatfacto checkpoint)"


def _check_option(name: str, value, allowed: tuple) -> None:
    if value not in allowed:
        raise ValueError(f"{name}: expected one of {', '.join(map(str, allowed))}, got {value!r}")


def check_scene_path(path: str | os.PathLike) -> Path:
    """``path`` as a scene file :func:`load_scene` reads, checked before any work: ValueError naming it, and
    the formats read, when it is missing, a folder or another file that is not a regular one, or of a type
    no reader knows (by its extension, any case)."""
    path = Path(path)
    try:
        require_regular_file(path, "scene file")
    except ValueError as error:
        raise ValueError(f"{error}; expected {_DESCRIBED}") from None
    if path.suffix.lower() not in READERS:
        raise ValueError(f"{path}: unsupported scene file type {path.suffix!r}; expected {_DESCRIBED}")
    return path


def check_scene_content(path: Path) -> None:
    """ValueError naming ``path`` when its extension's format starts with a signature (:data:`SIGNATURES`; a PLY,
    an SPZ) and the file does not: it says what the file starts with, and the extension to give it where that is
    another format's signature."""
    suffix = path.suffix.lower()
    if not any(extension == suffix for _, extension, _ in SIGNATURES):
        return
    head = _head(path)
    found = _signature_of(head)
    if found is not None and found[0] == suffix:
        return
    start = f"it starts with bytes {head.hex(' ')}" if head else "it is empty"
    if found is not None:
        raise ValueError(f"{path}: not a {suffix} file ({start}: {found[1]}); rename it {found[0]}")
    raise ValueError(f"{path}: not a {suffix} file ({start}, no format's signature; a headerless antimatter15 .splat "
                     "or a .ksplat cannot be recognized by its content: if it is one, rename it .splat or .ksplat)")


def _head(path: Path) -> bytes:
    with open(path, "rb") as stream:
        return stream.read(8)


def _signature_of(head: bytes) -> tuple[str, str] | None:
    """(extension, description) of the format whose signature ``head`` starts with (:data:`SIGNATURES`), else None."""
    return next(((extension, what) for signature, extension, what in SIGNATURES if head.startswith(signature)), None)


def load_scene(path: str | os.PathLike, *, drop_invalid: bool = False, spz_axes: str = "auto",
               cameras: CameraSet | None = None, progress: ProgressFn | None = None,
               should_stop: StopFn | None = None, notes: NoteFn | None = None) -> GaussianScene:
    """Read a Gaussian scene, the reader chosen by the file's extension (any case; :func:`check_scene_path`),
    whose signature the file must start with where the format has one (:func:`check_scene_content`).
    ``spz_axes``: the axes of a ``.spz`` that does not name its own: "ply", "rub" or "auto" (the reading that
    puts the scene in front of ``cameras`` when given, else the PLY's axes, as most writers store them;
    :mod:`.spz`). ``progress`` follows the whole read in the file's bytes, one bar filling once over the format's
    stages (reading, decoding, checking), each its share of the bar by its measured time (the readers'
    ``READ_STAGES``); ``should_stop`` ends the read between chunks (:class:`~artnvg_core.progress.Cancelled`; a
    splatfacto ``.ckpt`` old-style pickle, not a zip archive, loads in one ``torch.load`` before its chunks).
    ``notes`` is called once with each note for the user on what the read did to the scene (invalid Gaussians
    dropped, the axes taken for a ``.spz`` that names none, SH terms above degree 3 dropped); without it each is
    logged as a warning."""
    _check_option("spz_axes", spz_axes, SPZ_AXES)
    path = check_scene_path(path)
    check_scene_content(path)
    check_stop(should_stop)
    reader = READERS[path.suffix.lower()]
    if reader is read_spz:
        return read_spz(path, drop_invalid=drop_invalid, axes=spz_axes, cameras=cameras, progress=progress,
                        should_stop=should_stop, notes=notes)
    try:
        return reader(path, drop_invalid=drop_invalid, progress=progress, should_stop=should_stop, notes=notes)
    except ValueError as error:  # a format with no signature (.splat...): it may be another one, renamed
        found = _signature_of(_head(path))
        if found is None or found[0] == path.suffix.lower():
            raise
        raise ValueError(f"{error}; it starts with {found[1]}: if it is one, rename it {found[0]}") from error


def writable_scene_path(path: str | os.PathLike, option: str | None = None) -> Path:
    """``path`` when its extension (any case) names a format :func:`save_scene` writes, checked before
    any work; otherwise a ValueError naming ``path`` (after ``option``, e.g. ``--out``, when given) and the
    extensions written (a path without one, such as a folder's, is told that a file name is wanted)."""
    where = f"{option + ': ' if option else ''}{os.fspath(path) or 'the output path is empty'}"
    path = Path(path)
    if not path.suffix:  # a folder ("out/" reads as "out") or a name without its extension
        example = f"{path.with_suffix('.ply')}, or {path / 'NAME.ply'} in folder {path}" if path.name else "out.ply"
        raise ValueError(f"{where}: a scene file name is wanted, ending in one of {', '.join(SAVE_SUFFIXES)} "
                         f"(e.g. {example})")
    if path.suffix.lower() not in WRITERS:
        raise ValueError(f"{where}: cannot write scene file type {path.suffix!r}; "
                         f"expected one of {', '.join(SAVE_SUFFIXES)}")
    return path


def check_geometry_writable(scene: GaussianScene, path: str | os.PathLike) -> None:
    """The refusals :func:`save_scene` would make of ``scene``'s geometry (means, log-scales, quaternions)
    for ``path``'s format, made now: for callers about to change the appearance alone (a finetune that
    keeps the geometry), so that a scene the format cannot hold is refused before the work, not after.
    ValueError naming ``path`` and the field."""
    path = writable_scene_path(path)
    check = GEOMETRY_CHECKS.get(path.suffix.lower())
    if check is not None:
        check(scene_to_write(scene, path), path)


def save_scene(scene: GaussianScene, path: str | os.PathLike, *, spz_axes: str = "auto",
               spz_version: int = 3, overwrite: bool = True, progress: ProgressFn | None = None,
               should_stop: StopFn | None = None, notes: NoteFn | None = None) -> None:
    """Write ``scene`` atomically, the format chosen by the extension: .ply, .spz, .splat or .ksplat;
    a ``.spz`` in the PLY's axes (``spz_axes`` "auto" or "ply") or in RUB ("rub"), with no record of them,
    as SPZ version ``spz_version``: 3, or 2 for readers of versions 1-2 only (spz-js). With ``overwrite``
    False never over an existing file: FileExistsError naming ``path`` when one holds it by the time the new
    one is complete (:func:`~artnvg_core.fileio.write_atomically`). ``progress`` follows the Gaussians written,
    a chunk at a time, and ``should_stop`` ends the write between chunks (:class:`~artnvg_core.progress.Cancelled`:
    no file, partial or whole, is left). ``notes`` is called once with each note for the user on what the format
    changes of the scene (SH terms it cannot hold, a 2D filter it cannot record, far Gaussians moved onto an SPZ's
    range), before the file is written; without it each is logged as a warning."""
    path = writable_scene_path(path)
    if not path.parent.is_dir():  # else found only once the file is written, after the work
        raise ValueError(f"{path}: not written: its folder {path.parent} does not exist")
    _check_option("spz_axes", spz_axes, SPZ_AXES)
    _check_option("spz_version", spz_version, SPZ_VERSIONS)
    if path.suffix.lower() == ".spz":
        write_spz(scene, path, axes=spz_axes, version=spz_version, overwrite=overwrite, progress=progress,
                  should_stop=should_stop, notes=notes)
    else:
        WRITERS[path.suffix.lower()](scene, path, overwrite=overwrite, progress=progress, should_stop=should_stop,
                                     notes=notes)
