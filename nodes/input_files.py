"""Files a loader node offers: those in ComfyUI's input folder, or an explicit path.

A loader has a list input (a path relative to the input folder, as listed by
:func:`list_input_files`) and a text input ``path``; a non-blank ``path`` wins. Relative
``path`` values are taken relative to the input folder, ``~`` is expanded. Symbolic links
to files are listed; linked folders are not entered. :class:`InputFile` declares the two
inputs of one loader and finds, checks and watches the file they choose.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
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


@dataclass(frozen=True)
class InputFile:
    """A loader's two inputs: list input ``name`` (what ``listing`` returns when ComfyUI asks) and text input
    ``path``. ``what`` names the file in errors (e.g. "scene file"); ``exists`` tells whether a chosen path
    can be loaded; ``watched`` gives the file whose changes make the node run again (default: the chosen one)."""

    name: str
    what: str
    listing: Callable[[], list[str]]
    tooltip: str
    path_tooltip: str
    exists: Callable[[Path], bool] = Path.is_file
    watched: Callable[[Path], Path] | None = None

    def list_input(self) -> tuple:
        """The declaration of input ``name``, with the files listed now: a COMBO, whose value ComfyUI leaves
        to :meth:`check` (see ``prompt_checks``)."""
        return ("COMBO", {"options": self.listing(), "tooltip": self.tooltip})

    @property
    def path_input(self) -> tuple:
        """The declaration of input ``path``."""
        return ("STRING", {"default": "", "tooltip": self.path_tooltip})

    def resolve(self, listed: str, path: str) -> tuple[Path, str]:
        """The file to load and the name of the input that chose it (:func:`resolve_input_path`)."""
        return resolve_input_path(self.name, listed, path)

    def check(self, node: str, listed: str, path: str) -> bool | str:
        """True, or the message naming ``node``, the input and the path, and saying what to do."""
        file, input_name = self.resolve(listed, path)
        if not self.exists(file):
            return (f"{node}: input '{input_name}': {self.what} not found: {file}. Put it into ComfyUI's input "
                    f"folder ({input_directory()}) and pick it in '{self.name}', or type its full path into 'path' "
                    f"(the shipped workflows' demo files come back into the input folder when ComfyUI restarts)")
        return True

    def signature(self, listed: str, path: str) -> str:
        """A loader's ``IS_CHANGED`` answer: :func:`file_signature` of the watched file (the chosen one by default)."""
        file = self.resolve(listed, path)[0]
        return file_signature(self.watched(file) if self.watched else file)
