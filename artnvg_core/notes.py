"""Notes for the user: what the library did to a scene that they should know and would not otherwise see (SH terms a
format drops, Gaussians moved onto an SPZ's range, invalid Gaussians dropped while reading, the axes a ``.spz`` that
names none is read in, an up direction guessed for the views around a scene), told to the caller's ``notes`` (a node's
text, a command's printed lines), else logged."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable

_log = logging.getLogger(__name__)
NoteFn = Callable[[str], None]


def tell(notes: NoteFn | None, source: str | os.PathLike, note: str) -> None:
    """``note``, about the file or data named ``source``, to ``notes``; without it logged as a warning after
    ``source``."""
    if notes is None:
        _log.warning("%s: %s", source, note)
    else:
        notes(note)
