"""A small stand-in of ComfyUI's ``comfy_api.latest`` splat and 3D file types, written from its source.

Mirrors ``comfy_api/latest/_util/geometry_types.py`` of comfyanonymous/ComfyUI (2026): the splat
class (``Types.SPLAT``; ``Types.GAUSSIAN`` before the rename) with its constructor
``(positions, scales, rotations, opacities, sh, counts=None)`` and ``Types.File3D(source,
file_format="")`` with ``format``, ``get_bytes()`` and ``save_to()``; and of ``comfy_api/latest/_io.py``
the link type ``IO.File3DSplatAny`` (``io_type`` "FILE_3D_SPLAT_ANY", a later addition). Only what the
pack uses.
"""

from __future__ import annotations

import shutil
import sys
import types
from pathlib import Path


class Splat:
    """(B, N, ...) activated splats: positions, linear scales, unit wxyz rotations, opacities (B, N, 1), sh (B, N, K, 3)."""

    def __init__(self, positions, scales, rotations, opacities, sh, counts=None):
        self.positions = positions
        self.scales = scales
        self.rotations = rotations
        self.opacities = opacities
        self.sh = sh
        self.counts = counts


class File3D:
    """A 3D file from a path (the only kind the pack makes)."""

    def __init__(self, source: str, file_format: str = ""):
        self._source = source
        self._format = file_format or Path(source).suffix.lstrip(".").lower()

    @property
    def format(self) -> str:
        return self._format

    def get_bytes(self) -> bytes:
        return Path(self._source).read_bytes()

    def save_to(self, path: str) -> str:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(self._source, path)
        return path


def install(monkeypatch, splat_name: str = "SPLAT", splat_any: bool = True) -> types.SimpleNamespace:
    """Make ``import comfy_api.latest`` give ``Types`` with ``splat_name`` and ``File3D``, and ``IO`` with
    the link type ``File3DSplatAny`` ("FILE_3D_SPLAT_ANY") when ``splat_any``; returns ``Types``."""
    api_types = types.SimpleNamespace(**{splat_name: Splat, "File3D": File3D})
    package, latest = types.ModuleType("comfy_api"), types.ModuleType("comfy_api.latest")
    latest.Types = api_types
    latest.IO = types.SimpleNamespace(**({"File3DSplatAny": types.SimpleNamespace(io_type="FILE_3D_SPLAT_ANY")}
                                         if splat_any else {}))
    package.latest = latest
    monkeypatch.setitem(sys.modules, "comfy_api", package)
    monkeypatch.setitem(sys.modules, "comfy_api.latest", latest)
    return api_types
