"""Files a loader node offers: those in ComfyUI's input folder, or an explicit path.

A loader has a list input (a path relative to the input folder, as listed by
:func:`list_input_files`) and a text input ``path``; a non-blank ``path`` wins. Relative
``path`` values are taken relative to the input folder, ``~`` is expanded. Symbolic links
to files are listed; linked folders are not entered. :class:`InputFile` declares the two
inputs of one loader and finds, checks and watches the file they choose.

A node reads only inside ComfyUI's input, output and model folders
(:func:`~.comfy_bridge.readable_folders`), judged after symbolic links and ``..`` are resolved:
a client that can post a prompt learns nothing about other files. A path outside them is
refused with one message, the same whether or not anything is there, unless the server was
started with the environment variable :data:`ANY_PATH_SETTING` set to 1 (docs/comfyui.md).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from .comfy_bridge import input_directory, readable_folders
from .node_errors import NodeInputError

ANY_PATH_SETTING = "ARTNVG_READ_ANY_PATH"  # "1": nodes may read files outside ComfyUI's folders


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

    ``path`` (input ``path``) when not blank, else ``listed`` (the list input named ``listed_input``). A path is
    taken without the spaces around it and the quotes around those, which Windows' *Copy as path* adds
    (``"C:\\scans\\scene.ply"``).
    """
    typed = path.strip()
    if len(typed) >= 2 and typed[0] == typed[-1] and typed[0] in "\"'":
        typed = typed[1:-1].strip()
    if typed:
        return input_directory() / Path(typed).expanduser(), "path"
    return input_directory() / listed, listed_input


def any_path_allowed() -> bool:
    """Whether the user let nodes read outside ComfyUI's folders (:data:`ANY_PATH_SETTING` is "1")."""
    return os.environ.get(ANY_PATH_SETTING, "").strip() == "1"


def outside_folders(path: Path) -> bool:
    """Whether ``path``, its symbolic links and ``..`` resolved, lies outside every readable folder (and the
    user has not allowed any path). Looks at names only: the answer says nothing of what exists there."""
    if any_path_allowed():
        return False
    try:
        resolved = Path(os.path.realpath(path))
    except ValueError:  # a NUL character: no folder holds such a name
        return True
    return not any(resolved.is_relative_to(os.path.realpath(folder)) for folder in readable_folders())


def outside_message(node: str, input_name: str, value: str) -> str:
    """The refusal of a path outside ComfyUI's folders: the same whether or not it exists."""
    return (f"{node}: input '{input_name}': {value!r} is outside ComfyUI's input, output and model folders, "
            f"which are all a node may read; put the file into the input folder ({input_directory()}), or start "
            f"ComfyUI with the environment variable {ANY_PATH_SETTING}=1 to let the pack read any path on this "
            "machine (docs/comfyui.md)")


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
    is there to load; ``validate`` (optional) is the library's check of one that is, a ValueError saying why
    it cannot be loaded (a folder given for a file); ``watched`` gives the file whose changes make the node
    run again (default: the chosen one); ``read`` the files loading it reads (a folder's files; default: the
    chosen one), each of which must lie inside ComfyUI's folders (module docstring)."""

    name: str
    what: str
    listing: Callable[[], list[str]]
    tooltip: str
    path_tooltip: str
    exists: Callable[[Path], bool] = Path.is_file
    watched: Callable[[Path], Path] | None = None
    read: Callable[[Path], list[Path]] = lambda file: [file]
    validate: Callable[[Path], object] | None = None

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

    def _refusal(self, node: str, listed: str, path: str) -> str | None:
        """The message when the chosen path, or a file loading it reads, lies outside ComfyUI's folders."""
        file, input_name = self.resolve(listed, path)
        try:
            read = self.read(file) if not outside_folders(file) and self.exists(file) else []
        except (OSError, ValueError):  # not loadable: the loader says why, naming the chosen path only
            read = []
        if outside_folders(file) or any(outside_folders(part) for part in read):
            return outside_message(node, input_name, path.strip() if input_name == "path" else listed)
        return None

    def readable(self, node: str, listed: str, path: str) -> tuple[Path, str]:
        """The file to load and the name of the input that chose it, as :meth:`resolve`; a
        :class:`NodeInputError` when it lies outside ComfyUI's folders (module docstring)."""
        refusal = self._refusal(node, listed, path)
        if refusal:
            raise NodeInputError(refusal)
        return self.resolve(listed, path)

    def check(self, node: str, listed: str, path: str) -> str | None:
        """A loader's ``check_files`` answer (``prompt_checks``): the message naming ``node``, the input and the
        path, and saying what to do, else None."""
        refusal = self._refusal(node, listed, path)
        if refusal:
            return refusal
        file, input_name = self.resolve(listed, path)
        advice = (f"Put it into ComfyUI's input folder ({input_directory()}) and pick it in '{self.name}', or type "
                  "its path into 'path' (the shipped workflows' demo files come back into the input folder when "
                  "ComfyUI restarts)")
        if not (listed.strip() or path.strip()):  # else the input folder itself would be the chosen one
            return f"{node}: input '{self.name}': no {self.what} chosen. {advice}"
        try:
            found = self.exists(file)
        except OSError as error:  # a name too long for the file system, a folder this process may not enter
            return f"{node}: input '{input_name}': cannot look for {file}: {error.strerror}"
        if not found:
            return f"{node}: input '{input_name}': {self.what} not found: {file}. {advice}"
        if self.validate is not None:
            try:
                self.validate(file)
            except ValueError as error:
                return f"{node}: input '{input_name}': {error}"
        return None

    def signature(self, listed: str, path: str) -> str:
        """A loader's ``IS_CHANGED`` answer: :func:`file_signature` of the watched file (the chosen one by default)."""
        if self._refusal("", listed, path):
            return ""
        file = self.resolve(listed, path)[0]
        return file_signature(self.watched(file) if self.watched else file)
