"""The PLY container (header, elements), read in time and memory bounded by the file's size.

A header is at most :data:`MAX_HEADER_BYTES` and parsed line by line. Only the elements a reader
asks for are read, each as a numpy structured array of its scalar properties; every other element
is skipped by its byte count, never built row by row: a fixed-size element's bytes are its count
times its row size, a list element's are found from the list lengths (one strided look when every
row has the same lengths, else one pass over the length fields). An element that needs more bytes
than the file has left is refused before anything is read, and the counts must account for every
byte (binary) or line (ASCII) of the data. ASCII data is read a block of lines at a time and parsed
by numpy's loadtxt a chunk of rows at a time (blank lines skipped; other elements' lines counted).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ..counted import counted
from ..progress import ProgressFn, StopFn, check_stop
from .common import ChunkedWork

MAX_HEADER_BYTES = 1 << 20  # an INRIA 3DGS header of SH degree 3 takes about 1.5 kB
TEXT_BLOCK_BYTES = 1 << 24  # ASCII data read per block: about 21,000 rows of SH degree 3
MAX_LINE_BYTES = 1 << 24  # an ASCII data line: an INRIA row of SH degree 3 takes about 800 bytes

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}  # list lengths
_FORMATS = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass
class PlyProperty:
    """One property: ``dtype`` a numpy type code (e.g. "f4"); a list has ``count_dtype`` for its length."""

    name: str
    dtype: str
    count_dtype: str | None = None

    @property
    def is_list(self) -> bool:
        return self.count_dtype is not None


@dataclass
class PlyElement:
    """One element: ``count`` rows of ``properties``; ``data`` its rows as a structured array when read."""

    name: str
    count: int
    properties: list[PlyProperty]
    data: np.ndarray | None = None

    @property
    def property_names(self) -> list[str]:
        return [p.name for p in self.properties]


@dataclass
class PlyData:
    """A PLY file's header: its elements in file order (their ``data`` once read), its ``format`` (ascii,
    binary_little_endian or binary_big_endian) and the offset of its first data byte, ``start``."""

    elements: list[PlyElement]
    format: str
    start: int

    @property
    def text(self) -> bool:
        return self.format == "ascii"

    def __contains__(self, name: str) -> bool:
        return any(element.name == name for element in self.elements)

    def __getitem__(self, name: str) -> PlyElement:
        return next(element for element in self.elements if element.name == name)


def _header_lines(path: Path, stream: BinaryIO) -> list[str]:
    """The header's lines from ``ply`` to ``end_header`` (excluded); the stream is left at the first data byte."""
    head = stream.read(MAX_HEADER_BYTES)
    lines, position = [], 0
    while (stop := head.find(b"\n", position)) >= 0:
        line, position = head[position:stop].strip(), stop + 1
        if line == b"end_header":
            break
        lines.append(line)
    else:
        raise ValueError(f"{path}: not a readable PLY file (no end_header line within the first "
                         f"{MAX_HEADER_BYTES:,} bytes: the header is truncated or far longer than a scene's)")
    if not lines or lines[0] != b"ply":
        raise ValueError(f"{path}: not a readable PLY file (it does not start with a line 'ply')")
    stream.seek(position)
    try:
        return [line.decode("ascii") for line in lines]
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a readable PLY file (the header is not ASCII text)") from None


def _header(path: Path, stream: BinaryIO) -> tuple[str, list[PlyElement]]:
    """(format, elements) of the header; the stream is left at the first data byte."""
    lines = _header_lines(path, stream)
    fmt, elements = None, []
    for number, line in enumerate(lines[1:], 2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3 and words[1] in _FORMATS and words[2] == "1.0" and fmt is None:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append(PlyElement(words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in _TYPES:
            elements[-1].properties.append(PlyProperty(words[2], _TYPES[words[1]]))
        elif (words[0] == "property" and elements and len(words) == 5 and words[1] == "list"
              and words[2] in _TYPES and words[3] in _TYPES and _TYPES[words[2]][0] in "iu"):
            elements[-1].properties.append(PlyProperty(words[4], _TYPES[words[3]], _TYPES[words[2]]))
        else:
            raise ValueError(f"{path}: not a readable PLY file (header line {number} is not a PLY header line "
                             "of this version)")
    names = [element.name for element in elements]
    for element in elements:
        if names.count(element.name) > 1:
            raise ValueError(f"{path}: not a readable PLY file (element '{element.name}' is declared twice)")
        if not element.properties:
            raise ValueError(f"{path}: not a readable PLY file (element '{element.name}' declares no properties)")
        if len(set(element.property_names)) != len(element.properties):
            raise ValueError(f"{path}: not a readable PLY file (element '{element.name}' declares a property twice)")
    if fmt is None:
        raise ValueError(f"{path}: not a readable PLY file (no 'format ascii|binary_little_endian|"
                         "binary_big_endian 1.0' line)")
    return fmt, elements


def _counts_error(path: Path, elements: list[PlyElement], holds: str) -> ValueError:
    counts = ", ".join(f"{element.name} {element.count}" for element in elements)
    return ValueError(f"{path}: the header's element counts ({counts}) disagree with the data size: the file "
                      f"holds {holds}; the file is corrupt or its counts were edited")


def _too_short(path: Path, element: PlyElement, needed: int, left: int) -> ValueError:
    rows = counted(element.count, "row") + (" needs" if element.count == 1 else " need")
    return ValueError(f"{path}: element '{element.name}': {rows} at least {counted(needed, 'byte')}, but the file "
                      f"has {left:,} left (truncated, or the header's counts are wrong)")


def _scalar_dtype(element: PlyElement, order: str) -> np.dtype:
    return np.dtype([(p.name, order + p.dtype) for p in element.properties])


def _list_element_bytes(path: Path, element: PlyElement, data: np.ndarray, order: str) -> int:
    """Bytes of a binary element with list properties at the start of ``data`` (uint8, the rest of the file);
    the caller has checked that rows of empty lists would fit."""
    if element.count == 0:
        return 0
    fields, first, offset = [], [], 0  # a row with the list lengths of the first row
    for prop in element.properties:
        if prop.is_list:
            size = np.dtype(prop.count_dtype).itemsize
            length = int(np.frombuffer(data, order + prop.count_dtype, 1, offset)[0]) if offset + size <= len(data) else 0
            if length < 0:
                raise ValueError(f"{path}: element '{element.name}': a list of negative length in its first row")
            fields += [(f"{prop.name} length", order + prop.count_dtype), (prop.name, order + prop.dtype, (length,))]
            first.append(length)
            offset += size + length * np.dtype(prop.dtype).itemsize
        else:
            fields.append((prop.name, order + prop.dtype))
            offset += np.dtype(prop.dtype).itemsize
        if offset > len(data):
            raise ValueError(f"{path}: element '{element.name}': the file ends inside its first row")
    row = np.dtype(fields)
    if element.count * row.itemsize <= len(data):  # one strided look: every row's lengths as the first's?
        rows = np.frombuffer(data, row, element.count)
        if all((rows[f"{p.name} length"] == length).all()
               for p, length in zip([p for p in element.properties if p.is_list], first)):
            return element.count * row.itemsize
    steps = [(struct.Struct(order + _STRUCT_CODES[p.count_dtype]), np.dtype(p.dtype).itemsize) if p.is_list
             else (None, np.dtype(p.dtype).itemsize) for p in element.properties]
    offset = 0
    for index in range(element.count):  # rows of differing lengths: one pass over their length fields
        for length_field, size in steps:
            if length_field is None:
                offset += size
            elif offset + length_field.size <= len(data) and (length := length_field.unpack_from(data, offset)[0]) >= 0:
                offset += length_field.size + length * size
            else:
                raise ValueError(f"{path}: element '{element.name}': row {index}: the file ends inside it, or a "
                                 "list length is negative")
    if offset > len(data):
        raise ValueError(f"{path}: element '{element.name}': the file ends inside its last row")
    return offset


def _scalar(element: PlyElement) -> bool:
    return not any(p.is_list for p in element.properties)


def _read_binary(path: Path, stream: BinaryIO, fmt: str, elements: list[PlyElement], wanted: set[str],
                 progress: ProgressFn | None, should_stop: StopFn | None) -> None:
    order = _FORMATS[fmt]
    start = stream.tell()
    size = os.fstat(stream.fileno()).st_size
    data = np.memmap(stream, np.uint8, "r", start) if size > start else np.zeros(0, np.uint8)
    read = [element for element in elements if element.name in wanted and _scalar(element)]
    work, done, offset = ChunkedWork(sum(element.count for element in read), 1, progress, should_stop), 0, 0
    for element in elements:
        left = len(data) - offset
        smallest = sum(np.dtype(p.count_dtype if p.is_list else p.dtype).itemsize for p in element.properties)
        if element.count * smallest > left:
            raise _too_short(path, element, element.count * smallest, left)
        if not _scalar(element):
            offset += _list_element_bytes(path, element, data[offset:], order)
            continue
        dtype = _scalar_dtype(element, order)
        if element.name in wanted:
            rows = np.frombuffer(data[offset:offset + element.count * dtype.itemsize], dtype)
            element.data = np.empty(element.count, dtype)
            for chunk in work.chunks(done, done + element.count):
                element.data[chunk.start - done:chunk.stop - done] = rows[chunk.start - done:chunk.stop - done]
            done += element.count
        offset += element.count * dtype.itemsize
    if offset != len(data):
        raise _counts_error(path, elements, f"{counted(len(data) - offset, 'byte')} more than those records need")


class _TextLines:
    """The data lines of an ASCII PLY at ``path``, blank ones skipped, taken a number at a time from ``stream``,
    which is read :data:`TEXT_BLOCK_BYTES` at a time: memory follows the lines taken, not the file (a line longer
    than :data:`MAX_LINE_BYTES` is refused)."""

    def __init__(self, path: Path, stream: BinaryIO, size: int):
        self.path, self.stream, self.left, self.lines, self.tail = path, stream, size, [], b""

    def _read_block(self) -> bool:
        """The next block's complete lines added to ``lines``; False at the end of the file (``size`` bytes)."""
        block = self.stream.read(min(TEXT_BLOCK_BYTES, self.left))
        self.left -= len(block)
        text = self.tail + block
        cut = len(text) if not block else text.rfind(b"\n") + 1  # the last line may lack its newline
        self.lines += [line for line in text[:cut].split(b"\n") if line.strip()]
        self.tail = text[cut:]
        if len(self.tail) > MAX_LINE_BYTES:
            raise ValueError(f"{self.path}: a data line longer than {counted(MAX_LINE_BYTES, 'byte')}; not a PLY "
                             "of numbers in text")
        return bool(block)

    def take(self, count: int) -> list[bytes]:
        """The next ``count`` lines (fewer where the file ends sooner)."""
        while len(self.lines) < count and self._read_block():
            pass
        taken, self.lines = self.lines[:count], self.lines[count:]
        return taken

    def count_rest(self) -> int:
        """How many lines are left (read through to the end of the file)."""
        left = len(self.lines)
        self.lines = []
        while self._read_block():
            left, self.lines = left + len(self.lines), []
        return left + len(self.lines)


def _text_rows(path: Path, element: PlyElement, lines: list[bytes]) -> np.ndarray:
    """Rows of a scalar ``element`` parsed from ``lines`` as float64 [len(lines), properties]."""
    width = len(element.properties)
    try:
        values = np.loadtxt(lines, dtype=np.float64, comments=None, ndmin=2, encoding="latin1")
    except ValueError:
        values = None  # ragged rows, or text that is no number
    if values is None or values.shape != (len(lines), width):
        raise ValueError(f"{path}: element '{element.name}': a row holds something other than numbers, "
                         f"or not {width} of them")
    return values


def _read_text(path: Path, stream: BinaryIO, elements: list[PlyElement], wanted: set[str],
               progress: ProgressFn | None, should_stop: StopFn | None) -> None:
    size = left = os.fstat(stream.fileno()).st_size - stream.tell()
    for element in elements:  # before anything is made: a row of k numbers takes at least 2k bytes, "0 0\n"
        smallest = 2 * len(element.properties) * element.count
        if smallest - 1 > left:  # the last row may lack its newline
            raise _too_short(path, element, smallest, left)
        left -= smallest
    lines, declared = _TextLines(path, stream, size), sum(element.count for element in elements)
    work, start = ChunkedWork(declared, 1, progress, should_stop), 0
    for element in elements:
        scalar = element.name in wanted and _scalar(element)
        if scalar:
            element.data = np.empty(element.count, _scalar_dtype(element, "="))
        for rows in work.chunks(start, start + element.count):
            taken = lines.take(rows.stop - rows.start)
            if len(taken) < rows.stop - rows.start:
                held = counted(rows.start + len(taken), "data line")
                raise _counts_error(path, elements, f"{held} for {counted(declared, 'record')}")
            if scalar:
                values = _text_rows(path, element, taken)
                with np.errstate(all="ignore"):  # out-of-range values -> inf, rejected by the scene's validation
                    for column, prop in enumerate(element.properties):
                        element.data[prop.name][rows.start - start:rows.stop - start] = values[:, column]
        start += element.count
    if left := lines.count_rest():
        raise _counts_error(path, elements, f"{counted(declared + left, 'data line')} for {counted(declared, 'record')}")


def read_ply_header(path: Path) -> PlyData:
    """The header of the PLY at ``path``, no element read yet; a ValueError naming ``path`` when it is not a
    well-formed PLY header (module docstring)."""
    with open(path, "rb") as stream:
        fmt, elements = _header(path, stream)
        return PlyData(elements, fmt, stream.tell())


def read_ply_elements(path: Path, ply: PlyData, wanted: tuple[str, ...], *, progress: ProgressFn | None = None,
                      should_stop: StopFn | None = None) -> None:
    """The scalar elements of ``ply`` (:func:`read_ply_header` of ``path``) named in ``wanted`` read (their ``data``
    set), every other element skipped; a ValueError naming ``path`` when the counts do not account for the data or
    a row is not numbers (module docstring). Read a chunk of rows at a time: ``progress`` follows the rows read
    (binary: of the elements read; ASCII: every element's lines), ``should_stop`` ends the read between chunks
    (:class:`~artnvg_core.progress.Cancelled`)."""
    check_stop(should_stop)
    with open(path, "rb") as stream:
        stream.seek(ply.start)
        if ply.text:
            _read_text(path, stream, ply.elements, set(wanted), progress, should_stop)
        else:
            _read_binary(path, stream, ply.format, ply.elements, set(wanted), progress, should_stop)
