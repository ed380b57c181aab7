"""Diffusion models loaded once per process: the latest loaded set is handed out again for the same key.

Loading SDXL, the Tile ControlNet, the image encoder and CSGO takes tens of seconds, and a compiled
set keeps its compiled graphs; a process that stylizes several scenes (a batch on the command line,
ComfyUI running a workflow again with another input) should pay that once. :func:`load_once` keeps
the latest set with the key it was loaded under and returns it while the key stays the same.

A key names everything the set depends on: the model files (:func:`file_key`: path, size and
modification time of every file, so an edited file loads afresh), the device, the dtype and the
options applied after loading (memory mode, compiled blocks). Only one set is kept (full-size
models take 12 GiB of GPU memory): loading under another key drops the kept set first.
:func:`forget_models` drops it (before worker processes load their own copies, say).
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

_lock = threading.Lock()
_kept: list[tuple[Hashable, object]] = []  # at most one (key, models)


def file_key(path: str | os.PathLike | None) -> tuple | None:
    """(resolved path, then (relative name, size, mtime_ns) of the file or of every file under the folder),
    or None for None (the Hugging Face cache). A path that does not exist gives its name alone (the load
    itself reports it)."""
    if path is None:
        return None
    root = Path(path).expanduser().resolve()
    if root.is_file():
        stat = root.stat()
        return str(root), (("", stat.st_size, stat.st_mtime_ns),)
    entries = []
    for folder, _, names in sorted(os.walk(root)):
        for name in sorted(names):
            stat = (Path(folder) / name).stat()
            entries.append((os.path.relpath(Path(folder) / name, root), stat.st_size, stat.st_mtime_ns))
    return str(root), tuple(entries)


def load_once(key: Hashable, load: Callable[[], T]) -> T:
    """The kept set when it was loaded under ``key``; otherwise drop it, ``load()`` and keep the result.
    A failing ``load`` keeps nothing."""
    with _lock:
        if _kept and _kept[0][0] == key:
            return _kept[0][1]
        _kept.clear()
        models = load()
        _kept.append((key, models))
        return models


def forget_models() -> None:
    """Drop the kept set (its memory is freed once no one else holds it)."""
    with _lock:
        _kept.clear()
