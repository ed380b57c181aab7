"""Atomic file writing (one file, or a group that appears whole or not at all), checks of output
paths before long work, and of input files before they are read (:func:`require_regular_file`).
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import tempfile
import uuid
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO, Callable


def write_atomically(path: str | os.PathLike, write: Callable[[BinaryIO], None], *, overwrite: bool = True) -> None:
    """Call ``write`` on a temporary file beside ``path`` (:func:`temporary_path`), then give the complete file
    the name ``path``: renamed onto it, or with ``overwrite`` False only while no file holds the name
    (:func:`publish_new`: FileExistsError naming ``path`` when one does, nothing of the existing file touched).

    On any failure (or interruption) the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    sweep_temporaries(path.parent)
    temporary = temporary_path(path)
    try:
        with open(temporary, "xb") as stream:
            write(stream)
        if overwrite:
            os.replace(temporary, path)
        else:
            publish_new(temporary, path)
    except OSError as error:  # e.g. a full disk: named by the file being written, not the temporary one
        raise _naming(error, {temporary: path}, path) from error
    finally:
        temporary.unlink(missing_ok=True)


def publish_new(complete: Path, path: Path) -> None:
    """Give the complete file ``complete`` the name ``path`` too, unless a file (or link) already holds it:
    FileExistsError then, and nothing changes. Two writers that picked one free name thus never write over
    each other: the one that comes second learns it and can pick another, and a reader of ``path`` sees no
    file or the whole one, never a part. A hard link claims the name atomically (a rename would replace the
    file there); the caller removes ``complete``. Where the file system has no hard links (FAT, exFAT, some
    network shares) the name is claimed by creating it empty and exclusively (O_EXCL), then ``complete`` is
    renamed onto it at once: there a reader may see it empty for that instant, never part of the file."""
    try:
        os.link(complete, path)
        return
    except FileExistsError:
        raise
    except OSError:  # no hard links here: claim the name empty, and fill it in one rename
        pass
    with open(path, "xb"):
        pass
    try:
        os.replace(complete, path)
    except BaseException:
        path.unlink(missing_ok=True)
        raise


def _naming(error: OSError, temporaries: dict[Path, Path], default) -> OSError:
    """``error`` (same errno and type) naming the file the user asked for: a temporary's target, or
    ``default`` when it names no file."""
    filename = error.filename
    target = temporaries.get(Path(filename)) if filename is not None else default
    if target is None:
        return error
    return OSError(error.errno, error.strerror or str(error), str(target))


# A temporary's name: hidden, the writer's process id, a random part, and the target's suffix (writers may go
# by it): ".scene.4242.0f3a9c1e.partial.ply" for scene.ply.
_TEMPORARY = re.compile(r"\.(?P<stem>.*)\.(?P<pid>\d+)\.[0-9a-f]{8}\.partial(?P<suffix>.*)")
_TEMPORARY_EXTRA = len(".") + len(".4294967295") + len(".0123abcd") + len(".partial")  # bytes it adds to a name


def temporary_path(path: Path) -> Path:
    """A hidden, unique name beside ``path`` that keeps its suffix and names the writing process, so that
    :func:`sweep_temporaries` knows it once that process has gone (killed while it wrote)."""
    return path.with_name(f".{path.stem}.{os.getpid()}.{uuid.uuid4().hex[:8]}.partial{path.suffix}")


def sweep_temporaries(folder: Path) -> None:
    """Remove the temporaries (:func:`temporary_path`) in ``folder`` whose writer no longer runs on this machine:
    what a process killed while writing (SIGKILL, a power cut) left behind."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for entry in entries:
        match = _TEMPORARY.fullmatch(entry.name)
        if match and not _process_runs(int(match["pid"])) and entry.is_file(follow_symlinks=False):
            Path(entry.path).unlink(missing_ok=True)


def _process_runs(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (one that cannot be asked about counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True  # another user's process, or no such pid to test: left alone
    return True


def _name_limit(folder: Path) -> int:
    """Bytes a file name may have in ``folder`` (the nearest existing folder's file system; 255 when unknown)."""
    for candidate in (folder, *folder.parents):
        try:
            return os.pathconf(candidate, "PC_NAME_MAX")
        except (OSError, ValueError):  # not there yet (or its own name too long): ask its parent
            continue
    return 255


def check_output_name(path: str | os.PathLike, option: str) -> Path:
    """``path`` when each of its names, and its file's temporary (:func:`temporary_path`), fits the file system
    (NAME_MAX, mostly 255 bytes): checked before any work, since an over-long name fails only when the file
    is written. ValueError naming ``option``."""
    path = Path(path)
    limit = _name_limit(path.parent)
    for part in path.parts:
        if len(os.fsencode(part)) > limit:
            raise ValueError(f"{option}: the name {part[:40]}... is {len(os.fsencode(part))} bytes long; this file "
                             f"system allows {limit}")
    if len(os.fsencode(path.name)) + _TEMPORARY_EXTRA > limit:
        raise ValueError(f"{option}: the file name {path.name[:40]}... is {len(os.fsencode(path.name))} bytes long; "
                         f"it may have at most {limit - _TEMPORARY_EXTRA} here (the file system allows {limit}, and the "
                         f"file is first written under a temporary name {_TEMPORARY_EXTRA} bytes longer)")
    return path


def check_output_file(path: str | os.PathLike, option: str) -> Path:
    """``path`` as a file a command will write, checked before any long work: ValueError naming
    ``option`` when it is empty, an existing folder, under a file, or in a folder that cannot be
    written. Creates nothing (a probe file is made and removed)."""
    if not str(path).strip():
        raise ValueError(f"{option}: the output path is empty")
    path = check_output_name(path, option)
    if path.is_dir():
        raise ValueError(f"{option}: {path} is a folder; give a file name (e.g. {path / 'out'}{path.suffix})")
    _check_writable_folder(path.parent, option, path)
    return path


def check_output_folder(path: str | os.PathLike, option: str) -> Path:
    """``path`` as a folder a command will write files into: ValueError naming ``option`` when it
    is empty, an existing file, under a file, or cannot be written. Creates nothing."""
    if not str(path).strip():
        raise ValueError(f"{option}: the output folder is empty")
    path = check_output_name(Path(path) / "x", option).parent
    if path.exists() and not path.is_dir():
        raise ValueError(f"{option}: {path} exists and is not a folder")
    _check_writable_folder(path, option, path)
    return path


def _check_writable_folder(folder: Path, option: str, target: Path) -> None:
    existing = folder
    while not existing.exists():  # the folders still to be made must go in one that exists
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{option}: cannot write {target}: {existing} is a file, not a folder")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as error:
        raise ValueError(f"{option}: cannot write {target}: folder {existing} is not writable ({error.strerror})") from None


def file_identity(path: Path) -> tuple:
    """What makes two paths one file: device and inode for a file that exists (hard links and symlinks
    included), else the path with symlinks and ``..`` resolved."""
    try:
        status = path.stat()
    except OSError:
        return ("path", os.path.realpath(path))
    return ("file", status.st_dev, status.st_ino)


def refuse_overwrites(outputs: Sequence[tuple[str, str | os.PathLike]],
                      inputs: Sequence[tuple[str, str | os.PathLike | None]]) -> None:
    """Before any work: ValueError when one of ``outputs`` ((label, path) pairs, e.g. ("--out", "a.ply"))
    is the same file as one of ``inputs`` (None entries skipped) or as another output, by resolved path
    or, for files that exist, by device and inode (hard links). The message names both labels and paths."""
    seen: dict[tuple, tuple[str, Path]] = {}
    for label, path in inputs:
        if path is not None:
            seen.setdefault(file_identity(Path(path)), (label, Path(path)))
    kept_inputs = set(seen)
    for label, path in outputs:
        key = file_identity(Path(path))
        if key in seen:
            other_label, other = seen[key]
            what = "its own input" if key in kept_inputs else "another output of the same run"
            raise ValueError(f"{label}: {path} is the same file as {other_label} {other}: the run would write "
                             f"over {what}; choose another path")
        seen[key] = (label, Path(path))


@contextlib.contextmanager
def written_together(*paths: str | os.PathLike) -> Iterator[list[Path]]:
    """Files that appear together or not at all: yields a temporary path beside each of ``paths``
    (same suffix) for the block to write; when it ends without error every one is renamed onto its
    path, else all are removed and no path is touched. Missing parent folders are created. A
    ValueError raised in the block names the paths, not the temporaries."""
    targets = [Path(p) for p in paths]
    temporaries = [temporary_path(t) for t in targets]
    try:
        for target in targets:
            target.parent.mkdir(parents=True, exist_ok=True)
            sweep_temporaries(target.parent)
        try:
            yield temporaries
        except ValueError as error:
            message = str(error)
            for temporary, target in zip(temporaries, targets):
                message = message.replace(str(temporary), str(target))
            if message == str(error):
                raise
            raise ValueError(message) from error
        except OSError as error:  # e.g. a full disk: named by the files being written
            named = _naming(error, dict(zip(temporaries, targets)), ", ".join(str(t) for t in targets))
            if named is error:
                raise
            raise named from error
        missing = [str(t) for t in temporaries if not t.is_file()]
        if missing:
            raise RuntimeError(f"written_together: the block did not write {missing}")
        folders = [str(t) for t in targets if t.is_dir()]
        if folders:
            raise ValueError(f"cannot write over folders {folders}")
        for temporary, target in zip(temporaries, targets):
            os.replace(temporary, target)
    finally:
        for temporary in temporaries:
            temporary.unlink(missing_ok=True)


def require_regular_file(path: str | os.PathLike, what: str) -> Path:
    """``path`` as a regular file to read; ValueError naming ``path`` and ``what`` (e.g. "scene file")
    when it is missing, unreadable, or not a regular file (a FIFO, which a read would wait on for
    ever, a device or a folder)."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise ValueError(f"{path}: {what} not found") from None
    except OSError as error:
        raise ValueError(f"{path}: {what} cannot be read ({error.strerror})") from None
    if not stat.S_ISREG(mode):
        kind = "folder" if stat.S_ISDIR(mode) else "FIFO (named pipe)" if stat.S_ISFIFO(mode) else "special file"
        raise ValueError(f"{path}: {what} is a {kind}, not a regular file")
    try:
        path.open("rb").close()  # a regular file: opening it never waits
    except OSError as error:
        raise ValueError(f"{path}: {what} cannot be read ({error.strerror})") from None
    return path
