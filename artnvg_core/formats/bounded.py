"""Decompression bounded by its file's size and by what the file's header says it holds.

A compressed stream can inflate to far more than its file (deflate up to about 1000x, zstd
more). A header's sizes are therefore trusted only up to :data:`MAX_INFLATION` times the file's
own bytes (:func:`require_inflatable`, before anything is inflated), and streams are inflated
piece by piece, stopping one byte past the size the header implies: a stream that holds more is
refused after inflating ``size + 1`` bytes, and memory follows the bytes actually inflated. Zip containers
(splatfacto checkpoints, written by ``torch.save``) must store their records uncompressed, so
nothing in them can inflate past the file's own size.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import BinaryIO

from ..counted import counted
from ..progress import ProgressFn, StopFn, check_stop

CHUNK = 1 << 24  # bytes inflated per read
# At most this many bytes inflated per byte of the file (files under INFLATION_FLOOR / MAX_INFLATION
# bytes may inflate to INFLATION_FLOOR). Real SPZ scenes inflate 1.3x (SH degree 0) to 4.5x (degree 3
# with zero higher terms); only degenerate scenes (many identical Gaussians) come near 64x.
MAX_INFLATION = 64
INFLATION_FLOOR = 1 << 24


def require_inflatable(size: int, path: Path, field: str) -> None:
    """ValueError naming ``path`` and ``field`` when ``size`` bytes (what a header says its streams
    inflate to) is more than :data:`MAX_INFLATION` times the file's size (at least :data:`INFLATION_FLOOR`):
    refused before anything is inflated or allocated."""
    file_size = path.stat().st_size
    cap = max(MAX_INFLATION * file_size, INFLATION_FLOOR)
    if size > cap:
        raise ValueError(f"{path}: {field}: needs {size:,} bytes inflated from a {file_size:,}-byte file, more "
                         f"than the cap of {MAX_INFLATION}x the file's size ({cap:,} bytes); the header's counts "
                         "are wrong or the file is a decompression bomb")


def read_at_most(stream: BinaryIO, limit: int, should_stop: StopFn | None = None,
                 progress: ProgressFn | None = None) -> bytearray:
    """Up to ``limit`` bytes of a decompressing ``stream``, read ``CHUNK`` bytes at a time (``should_stop`` asked
    before each: :class:`~artnvg_core.progress.Cancelled`; ``progress`` told the bytes read of ``limit`` after)."""
    data = bytearray()
    while len(data) < limit:
        check_stop(should_stop)
        piece = stream.read(min(CHUNK, limit - len(data)))
        if not piece:
            break
        data += piece
        if progress is not None:
            progress(len(data), limit, {})
    return data


def inflate_exactly(stream: BinaryIO, size: int, path: Path, field: str, *, trailing_allowed: bool = False,
                    should_stop: StopFn | None = None, progress: ProgressFn | None = None) -> bytearray:
    """The next ``size`` bytes of ``stream``; ValueError naming ``path`` and ``field`` when it ends
    sooner or, unless ``trailing_allowed``, holds more (found by inflating one byte past ``size``).
    ``should_stop`` and ``progress``: as :func:`read_at_most`'s."""
    data = read_at_most(stream, size if trailing_allowed else size + 1, should_stop, progress)
    if len(data) < size:
        raise ValueError(f"{path}: {field}: {counted(size, 'byte')} expected, the stream ends after {len(data):,} "
                         "(truncated, or the header's counts are wrong)")
    if len(data) > size:
        raise ValueError(f"{path}: {field}: the stream holds more than the {counted(size, 'byte')} expected "
                         "(refused without inflating the rest)")
    return data


def require_stored_zip(path: Path) -> bool:
    """Whether ``path`` is a zip file (e.g. a ``torch.save`` checkpoint), checked to hold its records all stored
    uncompressed within the file; ValueError naming the first record that is compressed or reaches past the file's end.
    A file is a zip archive when it begins with a local file header (``PK\\x03\\x04``), as ``torch.load`` tells
    one (not ``zipfile.is_zipfile``, whose answer for a damaged archive differs between Python versions); others
    pass (they hold no compressed streams). An archive whose directory zipfile cannot read is a ValueError naming it."""
    size = path.stat().st_size
    with open(path, "rb") as stream:
        if stream.read(4) != b"PK\x03\x04":
            return False
    try:
        with zipfile.ZipFile(path) as archive:
            records = archive.infolist()
    except (zipfile.BadZipFile, NotImplementedError, UnicodeDecodeError, EOFError, OSError) as error:
        raise ValueError(f"{path}: not a readable zip archive ({error}); the file is truncated or corrupt") from error
    for record in records:
        if record.compress_type != zipfile.ZIP_STORED:
            raise ValueError(f"{path}: record {record.filename!r} is compressed ({counted(record.file_size, 'byte')} "
                             f"from {record.compress_size:,}); torch.save stores records uncompressed, so "
                             "this file was made otherwise and is refused rather than inflated")
        if record.file_size != record.compress_size or record.header_offset + record.file_size > size:
            raise ValueError(f"{path}: record {record.filename!r} claims {counted(record.file_size, 'byte')}, more than "
                             "the file holds (truncated or corrupt)")
    return True
