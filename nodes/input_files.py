"""Files a loader node offers: those in ComfyUI's input folder, or an explicit path.

A loader has a list input (a path relative to the input folder, as listed by
:func:`list_input_files`) and a text input ``path``; a non-blank ``path`` wins. Relative
``path`` values are taken relative to the input folder, ``~`` is expanded. Symbolic links
to files are listed; linked folders are not entered.
"""

from __future__ import annotations

import os
from pathlib import Path

from .comfy_bridge import input_directory


def list_input_files(
    *, suffixes: tuple[str, ...] = (), names: tuple[str, ...] = (), marker_files: tuple[str, ...] = ()
) -> list[str]:
    """Sorted POSIX paths, relative to the input folder, of what a loader can read from it.

    Lists files whose lower-case name ends with one of ``suffixes`` (e.g. ``.ply``) or
    equals one of ``names`` (e.g. ``transforms.json``), and subfolders holding one of
    ``marker_files`` (e.g. a COLMAP model's ``cameras.bin``). Hidden folders are skipped.
    """
    root = input_directory()
    found = []
    for folder, subfolders, files in os.walk(root):
        subfolders[:] = [d for d in subfolders if not d.startswith(".")]
        relative = Path(folder).relative_to(root)
        if relative.parts and any(marker in files for marker in marker_files):
            found.append(relative.as_posix())
        found.extend((relative / name).as_posix() for name in files
                     if name.lower().endswith(suffixes) or name.lower() in names)
    return sorted(found)


def resolve_input_path(listed_input: str, listed: str, path: str) -> tuple[Path, str]:
    """The file to load and the name of the input that chose it.

    ``path`` (input ``path``) when not blank, else ``listed`` (the list input named ``listed_input``).
    """
    if path.strip():
        return input_directory() / Path(path.strip()).expanduser(), "path"
    return input_directory() / listed, listed_input


def file_signature(path: Path) -> str:
    """Changes whenever the file (or folder entry) at ``path`` changes; '' when it is missing."""
    try:
        stat = path.stat()
    except OSError:
        return ""
    return f"{path}:{stat.st_mtime_ns}:{stat.st_size}"
