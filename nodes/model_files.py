"""Files a loader node offers from one of ComfyUI's model folders (``models/csgo``...), and the message when the
chosen one is not there: the file, the folders looked in (and what they hold), where to get it and where to save it.

A :class:`ModelFile` declares the loader's list input as a COMBO, which ComfyUI does not compare with the value
(its own "Value not in list" says neither where it looked nor where to get the file): the pack's prompt check
(``prompt_checks``) asks :meth:`ModelFile.check` before anything runs, so an empty folder, a file named but not
there, and a file deleted after the server started are all refused with this message; the loader asks again
(:meth:`ModelFile.path`) as it runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from artnvg_core.diffusion.model_files import ModelSource

from .comfy_bridge import model_file_path, model_files, model_folder_paths
from .node_errors import NodeInputError

_LISTED = 5  # files of the folder a message names; then how many more


@dataclass(frozen=True)
class ModelFile:
    """A loader's input ``name``: a file of ComfyUI's model folder ``folder``, the model ``source`` (its Hugging Face
    repository and file: where to get it); ``tooltip`` is the input's tooltip."""

    name: str
    folder: str
    source: ModelSource
    tooltip: str

    def list_input(self) -> tuple:
        """The declaration of input ``name``, with the folder's files listed now: a COMBO, whose value ComfyUI leaves
        to :meth:`check`."""
        return ("COMBO", {"options": model_files(self.folder), "tooltip": self.tooltip})

    def check(self, node: str, file: str) -> str | None:
        """A loader's ``check_files`` answer (``prompt_checks``): None when ``file`` is in the folder, else the message
        naming ``node``, the input, the file, the folders looked in with what they hold, where to get the file and
        the path to save it as."""
        if file.strip() and model_file_path(self.folder, file) is not None:
            return None
        folders = model_folder_paths(self.folder)
        present = model_files(self.folder)
        held = ", ".join(f"'{name}'" for name in present[:_LISTED]) or "nothing"
        if len(present) > _LISTED:
            held += f" and {len(present) - _LISTED} more"
        looked = ", ".join(folders) or f"ComfyUI's models/{self.folder}"
        saved_as = Path(folders[0] if folders else f"models/{self.folder}") / (file.strip() or
                                                                               Path(self.source.repo_path).name)
        chosen = f"'{file}' is not in" if file.strip() else "no file chosen from"
        return (f"{node}: input '{self.name}': {chosen} the '{self.folder}' model folder (looked in {looked}; found "
                f"{held}). Get the {self.source.description} from {self.source.url} "
                f"(`{self.source.download_command}`) and save it as {saved_as}")

    def path(self, node: str, file: str) -> Path:
        """The full path of ``file`` in the folder; a :class:`~.node_errors.NodeInputError` with :meth:`check`'s
        message when it is not there."""
        missing = self.check(node, file)
        if missing:
            raise NodeInputError(missing)
        return model_file_path(self.folder, file)
