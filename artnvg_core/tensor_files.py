"""Weight files read straight onto the device that computes with them.

:func:`read_tensors` reads a ``.safetensors`` file or a ``torch.save`` file. A ``.safetensors`` header
(an 8-byte little-endian length, then JSON ``{name: {dtype, shape, data_offsets}}``, then the raw
bytes) is checked first by our own parser. For CUDA the tensors are allocated on the GPU and
:data:`READERS` threads read a part of the file each, through two pinned buffers in turn: while the GPU
copies one out, the file is read into the other, on a stream of the reader's own, so the readers mostly
wait in system calls (the interpreter lock released) and the default stream's work (rendering, say)
goes on beside them; no CPU copy of the file is made, and a ``dtype`` asked for is applied on the GPU.
For the CPU (and other devices) the safetensors library reads it, memory-mapped: pages are read as
they are used and stay shared with the page cache.

Reading before the loader asks: :func:`read_early` reads files in a thread of its own and hands each to
the :func:`read_tensors` call of the same file and device; :func:`read_ahead` asks the kernel to read
files into the page cache.
"""

from __future__ import annotations

import math
import os
import pickle
import struct
import threading
import zipfile
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import torch

from .counted import counted
from .json_objects import parse_json
from .statedict import is_state_dict

SAFETENSORS_DTYPES = {
    "F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "BF16": torch.bfloat16,
    "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8, "U8": torch.uint8,
    "BOOL": torch.bool, "F8_E4M3": torch.float8_e4m3fn, "F8_E5M2": torch.float8_e5m2,
}
MAX_HEADER_BYTES = 100 * 2**20  # as the safetensors library's own limit
STAGING_BYTES = 64 * 2**20  # each of the two pinned buffers of a CUDA reader
READERS = 4  # threads reading parts of one file onto a GPU at once (page cache to pinned memory is a CPU copy)


def read_tensors(path: str | os.PathLike, device: str | torch.device = "cpu",
                 dtype: torch.dtype | None = None) -> dict[str, torch.Tensor]:
    """The tensors of the ``.safetensors`` or ``torch.save`` file at ``path`` (names to tensors, or a ``.ckpt``'s
    ``{"state_dict": names to tensors, ...}``), on ``device``; floating-point tensors converted to ``dtype``
    there when given (others keep theirs). A malformed ``.safetensors`` header, a ``torch.save`` file that
    torch cannot load or that holds anything else, is a ValueError naming the file and what is wrong."""
    path, device = Path(path), torch.device(device)
    tensors = _taken_early(path, device)
    if tensors is None:
        tensors = read_safetensors(path, device) if path.suffix == ".safetensors" else _read_state_dict(path, device)
    return tensors if dtype is None else {k: _cast(v, dtype) for k, v in tensors.items()}


_early: dict[tuple, Future] = {}  # read_early's promised reads, by _early_key
_early_lock = threading.Lock()


def _early_key(path: str | os.PathLike, device: torch.device) -> tuple:
    stat = os.stat(path)
    return str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns, str(device)


def read_early(paths: Iterable[str | os.PathLike], device: str | torch.device) -> Callable[[], None]:
    """Promise the ``.safetensors`` files of ``paths``, read onto ``device``, to the :func:`read_tensors` calls
    of the same file (path, size, modification time) and device, each of which takes its file's tensors
    once (waiting while they are read) instead of reading; returns the function that reads them, one after
    another (run it in a thread of its own: it mostly waits in system calls). A file whose read fails is
    read again by its :func:`read_tensors` call, which reports the error. :func:`drop_early_reads` forgets
    what no call took. For files read before the code that reads them is imported (seconds, under the
    interpreter lock)."""
    device = torch.device(device)
    promised = []
    with _early_lock:
        for path in paths:
            key = _early_key(path, device) if Path(path).suffix == ".safetensors" else None
            if key is not None and key not in _early:
                _early[key] = Future()
                promised.append((Path(path), _early[key]))

    def read() -> None:
        for path, future in promised:
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(read_safetensors(path, device))
                except Exception:  # read again, and reported, by the read_tensors call
                    future.set_result(None)

    return read


def _taken_early(path: Path, device: torch.device) -> dict[str, torch.Tensor] | None:
    """The tensors :func:`read_early` promised for ``path`` on ``device`` (waited for), else None."""
    with _early_lock:
        future = _early.pop(_early_key(path, device), None) if _early else None
    return None if future is None else future.result()


def drop_early_reads() -> None:
    """Forget the reads :func:`read_early` promised that no :func:`read_tensors` call took (their memory
    is freed once read)."""
    with _early_lock:
        for future in _early.values():
            future.cancel()
        _early.clear()


def read_ahead(paths: Iterable[str | os.PathLike]) -> None:
    """Ask the kernel to read each file of ``paths`` whole into the page cache (``POSIX_FADV_WILLNEED``: the
    call may wait while it queues the reads, which go on in the kernel after it returns), so that a later
    read finds it there; files it cannot open are skipped; nothing on systems without the call. Run it
    in a thread of its own: it holds no interpreter lock while it waits."""
    if not hasattr(os, "posix_fadvise"):
        return
    for path in paths:
        try:
            descriptor = os.open(path, os.O_RDONLY)
        except OSError:
            continue
        try:
            os.posix_fadvise(descriptor, 0, os.fstat(descriptor).st_size, os.POSIX_FADV_WILLNEED)
        except OSError:
            pass
        finally:
            os.close(descriptor)


def read_torch_file(path: str | os.PathLike, device: str | torch.device = "cpu"):
    """What ``torch.save`` wrote at ``path`` (tensors, dicts of them ...), its tensors on ``device``. For a
    device other than the CPU a zip-format file is memory-mapped (no copy of the file in memory) and each
    tensor moved from the mapping; for the CPU, ``torch.load`` reads it as it always has."""
    device = torch.device(device)
    return torch.load(path, map_location=device, weights_only=True,
                      mmap=device.type != "cpu" and zipfile.is_zipfile(path))



def _read_state_dict(path: Path, device: torch.device) -> dict[str, torch.Tensor]:
    """:func:`read_torch_file` of a weights file: names to tensors, or such a mapping under ``"state_dict"`` (a
    PyTorch Lightning checkpoint, as the original Stability/CompVis ``.ckpt`` files and many fine-tunes are
    saved; its other entries, such as ``global_step``, are left aside), as ComfyUI's ``load_torch_file`` reads
    them. ValueError naming ``path`` when torch cannot load it or it holds anything else."""
    try:
        state = read_torch_file(path, device)
    except Exception as error:  # torch.load raises many types on corrupt or foreign files
        raise ValueError(f"weights '{path}': not a readable torch file ({load_failure(error)})") from error
    if isinstance(state, dict) and not is_state_dict(state) and is_state_dict(state.get("state_dict")):
        state = state["state_dict"]
    if not is_state_dict(state):
        raise ValueError(f"weights '{path}': not a state dict (a mapping of names to tensors, or one under "
                         "'state_dict' as in a .ckpt checkpoint)")
    return state


def load_failure(error: Exception) -> str:
    """Why ``torch.load(..., weights_only=True)`` failed, for a user: its refusal of a pickle that holds more
    than tensors and plain data in the project's words (torch's own text advises ``weights_only=False``,
    which would run the file's code, and quotes the pickle's names), any other error as its type and text."""
    if isinstance(error, pickle.UnpicklingError):
        return ("not a pickle of tensors and plain data: a corrupt file, another format, or Python objects, which "
                "are not loaded since loading them could run code")
    return f"{type(error).__name__}: {error}"


def _cast(tensor: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return tensor.to(dtype) if tensor.is_floating_point() else tensor


def safetensors_header(path: Path) -> tuple[int, dict[str, tuple[torch.dtype, list[int], int, int]]]:
    """(byte offset of the data, {name: (dtype, shape, begin, end)}) of a ``.safetensors`` file, offsets
    relative to the data; checked as the safetensors library checks them (each tensor's byte count, the
    tensors' data one after another covering the file's data exactly, ``__metadata__`` strings), and for
    keys given twice."""
    size = path.stat().st_size
    with open(path, "rb") as stream:
        head = stream.read(8)
        length = struct.unpack("<Q", head)[0] if len(head) == 8 else -1
        if not 0 < length <= min(MAX_HEADER_BYTES, size - 8):
            raise ValueError(f"weights '{path}': not a safetensors file (header length {length}, file "
                             f"{counted(size, 'byte')})")
        header = parse_json(stream.read(length), f"weights '{path}': safetensors header")
    start, entries = 8 + length, {}
    for name, info in header.items():
        if name == "__metadata__":
            if not isinstance(info, dict) or not all(isinstance(value, str) for value in info.values()):
                raise ValueError(f"weights '{path}': '__metadata__' of the safetensors header is not an object of "
                                 "strings")
            continue
        try:
            dtype, shape, (begin, end) = SAFETENSORS_DTYPES[info["dtype"]], info["shape"], info["data_offsets"]
            nbytes = math.prod(shape) * dtype.itemsize
            valid = (type(shape) is list and type(info["data_offsets"]) is list  # of ints: JSON true is no size
                     and all(type(n) is int and n >= 0 for n in (*shape, begin, end)))
        except (KeyError, TypeError, ValueError):
            valid = False
        if not valid or end - begin != nbytes or start + end > size:
            raise ValueError(f"weights '{path}': tensor '{name}' has a bad entry in the safetensors header "
                             f"(dtype, shape and data_offsets within the file's {counted(size, 'byte')} expected)")
        entries[name] = (dtype, shape, begin, end)
    covered = 0
    for name, (_, _, begin, end) in sorted(entries.items(), key=lambda item: item[1][2:]):
        if begin != covered:
            raise ValueError(f"weights '{path}': tensor '{name}' starts at byte {begin} of the data, not {covered} "
                             "where the tensors before it end (tensors overlap, or bytes between them belong to none)")
        covered = end
    if start + covered != size:
        raise ValueError(f"weights '{path}': the tensors' data ends at byte {covered}, the file's at {size - start} "
                         "(bytes that belong to no tensor)")
    return start, entries


def read_safetensors(path: Path, device: torch.device) -> dict[str, torch.Tensor]:
    """The tensors of a ``.safetensors`` file on ``device``, in the file's dtypes (see the module docstring)."""
    start, entries = safetensors_header(path)
    if device.type != "cuda":
        from safetensors.torch import load_file

        return load_file(str(path), device=str(device))
    return read_by_readers(path, start, entries, device)


def read_by_readers(path: Path, start: int, entries: dict[str, tuple[torch.dtype, list[int], int, int]],
                    device: torch.device) -> dict[str, torch.Tensor]:
    """The tensors ``entries`` (:func:`safetensors_header`) of the file at ``path``, allocated on ``device`` and
    filled by readers sharing the data (:func:`reader_spans`), each a thread of its own (:func:`_read_span`)."""
    ordered = sorted(entries.items(), key=lambda item: item[1][2])
    raw = {name: torch.empty(end - begin, dtype=torch.uint8, device=device) for name, (_, _, begin, end) in ordered}
    targets = [(raw[name], begin) for name, (_, _, begin, _) in ordered]
    spans = reader_spans(max((begin + len(target) for target, begin in targets), default=0))
    with ThreadPoolExecutor(len(spans) or 1) as pool:
        list(pool.map(lambda span: _read_span(path, start, targets, span, device), spans))
    return {name: raw[name].view(dtype).view(shape) for name, (dtype, shape, _, _) in entries.items()}


def reader_spans(length: int) -> list[tuple[int, int]]:
    """How :func:`read_safetensors` shares ``length`` bytes among its readers: contiguous (start, end) spans
    covering them, cut at whole pages, at most :data:`READERS`, one per two staging buffers' worth at least."""
    readers = max(1, min(READERS, length // (2 * STAGING_BYTES)))
    step = -(-length // readers // 4096) * 4096
    return [(low, min(low + step, length)) for low in range(0, length, step)] if length else []


def _read_span(path: Path, start: int, targets: list[tuple[torch.Tensor, int]], span: tuple[int, int],
               device: torch.device) -> None:
    """One reader of :func:`read_safetensors`: the bytes ``span`` of the data into ``targets`` through its own
    file handle, buffers and (CUDA) stream. The stream first waits for what the device was given before (the
    targets' memory may have been a tensor that queued work still reads)."""
    stream = torch.cuda.Stream(device) if device.type == "cuda" else None
    if stream is not None:
        stream.wait_stream(torch.cuda.current_stream(device))
    with open(path, "rb", buffering=0) as file, torch.cuda.stream(stream):
        if hasattr(os, "posix_fadvise"):
            os.posix_fadvise(file.fileno(), start + span[0], span[1] - span[0], os.POSIX_FADV_SEQUENTIAL)
        stream_into(file, start, targets, span=span)


def _read_into(file, target: torch.Tensor) -> None:
    """Fill the uint8 CPU tensor ``target`` from ``file``'s position; a file that ends first is a ValueError."""
    view, done = memoryview(target.numpy()), 0
    while done < len(view):
        count = file.readinto(view[done:])
        if not count:
            raise ValueError(f"weights '{getattr(file, 'name', file)}': the file ends before its tensors do")
        done += count


def stream_into(file, start: int, targets: list[tuple[torch.Tensor, int]], chunk_bytes: int = STAGING_BYTES,
                span: tuple[int, int] | None = None) -> None:
    """Copy the bytes of ``file`` from ``start`` on into ``targets``: (uint8 tensor, offset from ``start``)
    pairs in ascending offsets, all on one device, through two buffers of ``chunk_bytes`` used in turn;
    with ``span`` (offsets from ``start``, end excluded), only the bytes of that span, into the parts of the
    targets it covers. For CUDA targets the buffers are pinned and the copies asynchronous on the current
    stream: the file is read into one buffer while the other is copied out; returns once every copy is
    done."""
    cuda = bool(targets) and targets[0][0].is_cuda
    buffers = [torch.empty(chunk_bytes, dtype=torch.uint8, pin_memory=cuda) for _ in range(2)]
    copied = [None, None]  # per buffer, the event after the last copy out of it
    position, end = span or (0, max((offset + len(target) for target, offset in targets), default=0))
    turn, first = 0, 0
    file.seek(start + position)
    while position < end:
        buffer, count = buffers[turn], min(chunk_bytes, end - position)
        if copied[turn] is not None:
            copied[turn].synchronize()
        _read_into(file, buffer[:count])
        while first < len(targets) and targets[first][1] + len(targets[first][0]) <= position:
            first += 1
        index = first
        while index < len(targets) and targets[index][1] < position + count:
            target, offset = targets[index]
            low, high = max(offset, position), min(offset + len(target), position + count)
            if high > low:
                target[low - offset:high - offset].copy_(buffer[low - position:high - position], non_blocking=cuda)
            index += 1
        if cuda:
            copied[turn] = torch.cuda.Event()
            copied[turn].record()
        position, turn = position + count, 1 - turn
    if cuda:
        torch.cuda.current_stream().synchronize()
