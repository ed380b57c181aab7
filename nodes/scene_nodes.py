"""Load Gaussian Scene and Save Gaussian Scene."""

from __future__ import annotations

import itertools
import re
from collections.abc import Iterator
from pathlib import Path

from artnvg_core.counted import counted
from artnvg_core.fileio import check_output_folder, check_output_name
from artnvg_core.formats import (
    SAVE_SUFFIXES,
    SCENE_SUFFIXES,
    SPZ_AXES,
    SPZ_VERSIONS,
    check_scene_path,
    load_scene,
    save_scene,
)
from artnvg_core.scene import DROP_INVALID_HINT

from .comfy_bridge import cancellable, interrupt_requested, output_directory, progress_bar, shown_notes
from .input_files import InputFile, list_input_files
from .node_base import ArtNVGNode
from .node_errors import NodeInputError, node_input
from .node_types import CAMERAS, SCENE
from .preview3d import preview_camera
from .splat_interop import FILE3D_CLASS, MISSING_FILE3D, MODEL_3D, file3d, file3d_link_type

SCENE_FILE = InputFile(
    "scene_file",
    "scene file",
    lambda: list_input_files(suffixes=SCENE_SUFFIXES),
    tooltip="A .ply, .splat, .spz, .ksplat or .ckpt file in ComfyUI's input folder (subfolders included).",
    path_tooltip=("Scene file path; when not blank it is used instead of scene_file. "
                  "Relative paths start at the input folder."),
    exists=Path.exists,  # a folder is there, and check_scene_path names it as one
    validate=check_scene_path,
)


class LoadGaussianScene(ArtNVGNode):
    """A Gaussian scene file from the input folder or a path: ``.ply`` (INRIA 3DGS, Mip-Splatting or
    PlayCanvas/SuperSplat compressed), ``.splat``, ``.spz`` (Niantic), ``.ksplat`` (GaussianSplats3D) or a
    nerfstudio splatfacto ``.ckpt``."""

    DISPLAY_NAME = "Load Gaussian Scene"
    FUNCTION = "load"
    RETURN_TYPES = (SCENE,)
    RETURN_NAMES = ("scene",)
    REQUIRED = {"scene_file": SCENE_FILE.list_input}
    OPTIONAL = {
        "path": SCENE_FILE.path_input,
        "drop_invalid": ("BOOLEAN", {"default": False, "tooltip": (
            "Drop Gaussians with non-finite values or zero quaternions instead of failing.")}),
        "spz_axes": (list(SPZ_AXES), {"default": "auto", "tooltip": (
            "Axes of a .spz file that names none of its own. auto: those that put the scene in front of the "
            "connected cameras, else ply. ply: the PLY's (y down), as splat-transform, SuperSplat, spz-js and "
            "Niantic's ply-to-spz write them. rub: the SPZ description's (y up).")}),
        "cameras": (CAMERAS, {"tooltip": (
            "Optional: the capture's cameras; with spz_axes auto they decide the axes of a .spz that names none.")}),
    }

    @classmethod
    def check_files(cls, scene_file="", path="", **_other_inputs) -> str | None:
        """The message when the chosen file is missing (``prompt_checks``), else None."""
        return SCENE_FILE.check(cls.DISPLAY_NAME, scene_file, path)

    @classmethod
    def IS_CHANGED(cls, scene_file, path="", drop_invalid=False, spz_axes="auto", cameras=None, node_id=None):
        return SCENE_FILE.signature(scene_file, path)

    @cancellable
    def load(self, scene_file, path="", drop_invalid=False, spz_axes="auto", cameras=None, node_id=None):
        """The scene read with the node's progress bar moving (seconds for millions of Gaussians) and ComfyUI's
        Cancel stopping it; what the read did to the scene (invalid Gaussians dropped, the axes taken for a .spz)
        in the node's UI text after the scene's size, under the node in the editor and once on the console."""
        file, input_name = SCENE_FILE.readable(self.DISPLAY_NAME, scene_file, path)
        notes: list[str] = []
        with node_input(self.DISPLAY_NAME, input_name):
            try:
                scene = load_scene(file, drop_invalid=drop_invalid, spz_axes=spz_axes, cameras=cameras,
                                   progress=progress_bar(), should_stop=interrupt_requested, notes=notes.append)
            except ValueError as error:  # the library's advice names its argument; the node has a toggle
                if DROP_INVALID_HINT not in str(error):
                    raise
                raise ValueError(str(error).replace(DROP_INVALID_HINT, "turn drop_invalid on to drop them")) from None
        loaded = f"loaded {file.name} ({counted(len(scene), 'Gaussian')}, SH degree {scene.sh_degree})"
        return {"ui": {"text": [loaded, *shown_notes(notes, self.DISPLAY_NAME)]}, "result": (scene,)}


def _prefix_target(filename_prefix: str, suffix: str) -> Path:
    """``<output>/<prefix>`` (symlinks and ``..`` resolved), checked before any work: inside the output folder,
    short enough that ``<prefix>_NNNNN<suffix>`` and its temporary fit the file system's names, in a folder
    that is one or can be made and written (not a file), ending in a file name, not a folder (``artnvg/`` would
    resolve to the file ``artnvg_00001.ply`` beside that folder). Creates nothing."""
    if filename_prefix.replace("\\", "/").rsplit("/", 1)[-1].strip() in ("", ".", ".."):
        raise ValueError(f"'{filename_prefix}' ends in a folder, not a file name; add one (e.g. artnvg/stylized "
                         "saves artnvg/stylized_00001.ply)")
    root = output_directory().resolve()
    target = (root / filename_prefix).resolve()
    if target == root or root not in target.parents:
        raise ValueError(f"'{filename_prefix}' must name a file inside the output folder {root}")
    check_output_name(target.with_name(f"{target.name}_00001{suffix}"), "the saved file")
    check_output_folder(target.parent, "the saved file's folder")
    return target


def _numbered_paths(filename_prefix: str, suffix: str) -> Iterator[Path]:
    """``<output>/<prefix>_NNNNN<suffix>`` from the counter after the highest one there, upwards; the prefix
    may name subfolders (made here). A name is only a candidate: the save claims it when its file is complete,
    never over a file (:func:`~artnvg_core.fileio.publish_new`), and goes on to the next one when another writer
    (a second ComfyUI sharing the folder) took it meanwhile."""
    target = _prefix_target(filename_prefix, suffix)
    target.parent.mkdir(parents=True, exist_ok=True)
    numbered = re.compile(re.escape(target.name) + r"_(\d{5,})" + re.escape(suffix))
    taken = [int(m.group(1)) for existing in target.parent.iterdir() if (m := numbered.fullmatch(existing.name))]
    first = max(taken, default=0) + 1
    return (target.parent / f"{target.name}_{number:05d}{suffix}" for number in itertools.count(first))


def saved_text(name: str, size: int, gaussians: int) -> str:
    """What Save Gaussian Scene shows under itself: the file (inside the output folder), its size, its Gaussians."""
    return f"wrote output/{name} ({size / 1e6:.1f} MB, {counted(gaussians, 'Gaussian')})"


SPZ_VERSION_CHOICES = [str(v) for v in sorted(SPZ_VERSIONS, reverse=True)]  # "3", the default, first


class SaveGaussianScene(ArtNVGNode):
    """Write the scene into ComfyUI's output folder (``<prefix>_00001.ply``, ...): an INRIA 3DGS PLY, or
    by ``format`` a Niantic ``.spz`` (``spz_version`` 3, or 2 for spz-js), an antimatter15 ``.splat`` or a
    GaussianSplats3D ``.ksplat`` (smaller files, quantised).

    model_file: the file written, as a path inside the output folder (connect it to Preview Any to keep it
    in view, and to Preview 3D's model_file). camera_info: a Preview 3D camera that frames the scene's bulk,
    not its stray Gaussians."""

    DISPLAY_NAME = "Save Gaussian Scene"
    FUNCTION = "save"
    RETURN_TYPES = ("STRING", "LOAD3D_CAMERA") + ((file3d_link_type(SAVE_SUFFIXES),) if FILE3D_CLASS is not None else ())
    RETURN_NAMES = ("model_file", "camera_info") + (("model_3d",) if FILE3D_CLASS is not None else ())
    OUTPUT_NODE = True
    DESCRIPTION = __doc__ + "\n\n" + (MODEL_3D if FILE3D_CLASS is not None else MISSING_FILE3D)
    REQUIRED = {
        "scene": (SCENE,),
        "filename_prefix": ("STRING", {"default": "artnvg/stylized", "tooltip": (
            "File name start inside the output folder; may contain subfolders. "
            "A five-digit counter and the format's extension are appended.")}),
    }
    OPTIONAL = {
        "format": ([suffix.lstrip(".") for suffix in SAVE_SUFFIXES], {"default": "ply", "tooltip": (
            "ply: INRIA 3DGS PLY, exact. spz: Niantic SPZ, about 10x smaller, quantised. "
            "splat: antimatter15 .splat, SH degree 0 only. ksplat: GaussianSplats3D level 0, SH up to "
            "degree 2.")}),
        "spz_version": (SPZ_VERSION_CHOICES, {"default": "3", "tooltip": (
            "SPZ version of a .spz (other formats ignore it). 3: read by Niantic's spz library, "
            "splat-transform and SuperSplat. 2: also read by spz-js and similar older readers (versions 1-2 only); "
            "rotations stored a little coarser.")}),
    }

    REPORTED_INPUT = "filename_prefix"  # what each of its messages names: the others are choices ComfyUI checks

    @classmethod
    def check_files(cls, filename_prefix="", format="ply", **_other_inputs) -> str | None:
        """The message when the file this node would write cannot be (``prompt_checks``: refused before the
        graph runs, not after its work), else None."""
        try:
            _prefix_target(filename_prefix, f".{format}")
        except ValueError as error:
            return f"{cls.DISPLAY_NAME}: input 'filename_prefix': {error}"
        return None

    @cancellable
    def save(self, scene, filename_prefix, format="ply", spz_version="3", node_id=None):
        """The scene written with the node's progress bar moving and ComfyUI's Cancel stopping it, no file left; what
        the format changes of the scene (dropped SH terms, far Gaussians moved) in the node's UI text after the
        file's name, under the node in the editor and once on the console."""
        with node_input(self.DISPLAY_NAME, "format"):
            if f".{format}" not in SAVE_SUFFIXES:
                raise ValueError(f"expected one of {[s.lstrip('.') for s in SAVE_SUFFIXES]}, got {format!r}")
        with node_input(self.DISPLAY_NAME, "spz_version"):
            if spz_version not in SPZ_VERSION_CHOICES:
                raise ValueError(f"expected one of {SPZ_VERSION_CHOICES}, got {spz_version!r}")
        with node_input(self.DISPLAY_NAME, "filename_prefix"):
            names = _numbered_paths(filename_prefix, f".{format}")
        report = progress_bar()
        for file in names:
            notes: list[str] = []  # what the format changes of the scene, told once per file written
            try:
                with node_input(self.DISPLAY_NAME, "scene"):
                    save_scene(scene, file, spz_version=int(spz_version), overwrite=False, progress=report,
                               should_stop=interrupt_requested, notes=notes.append)
                break
            except FileExistsError:
                continue  # taken while this file was written: the next number
            except OSError as error:
                raise NodeInputError(f"{self.DISPLAY_NAME}: cannot write {file}: {error}") from error
        relative = file.relative_to(output_directory().resolve())
        subfolder = relative.parent.as_posix()
        written = saved_text(relative.as_posix(), file.stat().st_size, len(scene))
        ui = {"scenes": [{"filename": relative.name, "subfolder": "" if subfolder == "." else subfolder, "type": "output"}],
              "text": [written, *shown_notes(notes, self.DISPLAY_NAME)]}
        result = (relative.as_posix(), preview_camera(scene))
        return {"ui": ui, "result": result + ((file3d(file),) if FILE3D_CLASS is not None else ())}
