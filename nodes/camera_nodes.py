"""Load Cameras, Cameras Around Scene and Group Neighbouring Views."""

from __future__ import annotations

from pathlib import Path

from artnvg_core.cameras import camera_files, load_cameras, parse_up
from artnvg_core.orbit import orbit_cameras, parse_elevations
from artnvg_core.grouping import DEFAULT_GROUP_SIZE, group_views

from .comfy_bridge import shown_notes
from .input_files import InputFile, list_input_files
from .node_base import ArtNVGNode
from .node_errors import node_input
from .node_types import CAMERAS, GROUPS, SCENE

COLMAP_MARKERS = ("cameras.bin", "cameras.txt")

CAMERA_SOURCE = InputFile(
    "camera_source",
    "camera file or folder",
    lambda: list_input_files(names=("transforms.json",), marker_files=COLMAP_MARKERS),
    tooltip="A transforms.json or a COLMAP model folder in ComfyUI's input folder.",
    path_tooltip=(
        "A nerfstudio .json file, a folder holding transforms.json, or a COLMAP folder (directly or in "
        "sparse/0); when not blank it is used instead of camera_source. Relative paths start at the "
        "input folder."),
    exists=Path.exists,
    watched=lambda source: source / "transforms.json" if source.is_dir() else source,
    read=camera_files,
    validate=camera_files,  # a scene file or a folder without a capture: named before the graph runs
)


class LoadCameras(ArtNVGNode):
    """Capture cameras from a nerfstudio transforms.json or a COLMAP model folder."""

    DISPLAY_NAME = "Load Cameras"
    FUNCTION = "load"
    RETURN_TYPES = (CAMERAS,)
    RETURN_NAMES = ("cameras",)
    REQUIRED = {"camera_source": CAMERA_SOURCE.list_input}
    OPTIONAL = {"path": CAMERA_SOURCE.path_input}

    @classmethod
    def check_files(cls, camera_source="", path="", **_other_inputs) -> str | None:
        """The message when the chosen file or folder is missing (``prompt_checks``), else None."""
        return CAMERA_SOURCE.check(cls.DISPLAY_NAME, camera_source, path)

    @classmethod
    def camera_count(cls, camera_source="", path="", **_other_inputs) -> int | None:
        """How many cameras the node will load (``prompt_checks``: the view indices of the nodes it feeds, checked
        before the graph runs); None when its file does not load (:meth:`check_files` or the node names it) or an input
        comes through a link (a ``[node id, slot]``: known as the graph runs)."""
        if not (isinstance(camera_source, str) and isinstance(path, str)) or cls.check_files(camera_source, path):
            return None
        try:  # its notes are told when the node runs
            return len(load_cameras(CAMERA_SOURCE.resolve(camera_source, path)[0], notes=lambda _note: None))
        except (OSError, ValueError):
            return None

    @classmethod
    def IS_CHANGED(cls, camera_source, path="", node_id=None):
        return CAMERA_SOURCE.signature(camera_source, path)

    def load(self, camera_source, path="", node_id=None):
        """The cameras; what the load ignored (lens distortion) under the node in the editor and once on the
        console."""
        source, input_name = CAMERA_SOURCE.readable(self.DISPLAY_NAME, camera_source, path)
        notes: list[str] = []
        with node_input(self.DISPLAY_NAME, input_name):
            cameras = load_cameras(source, notes=notes.append)
        shown_notes(notes, self.DISPLAY_NAME)
        return (cameras,)


class CamerasAroundScene(ArtNVGNode):
    """Cameras for a scene that came without any: views on rings around the scene's centre, all looking at
    it, at the distance where its main subject fills the view. For Render Views, Finetune and the rest
    exactly like loaded capture cameras."""

    DISPLAY_NAME = "Cameras Around Scene"
    FUNCTION = "place"
    RETURN_TYPES = (CAMERAS,)
    RETURN_NAMES = ("cameras",)
    REQUIRED = {
        "scene": (SCENE,),
        "count": ("INT", {"default": 60, "min": 1, "max": 10000, "tooltip": (
            "Number of views, shared out over the rings (60: four neighbouring-view groups of 15).")}),
        "fov_deg": ("FLOAT", {"default": 50.0, "min": 1.0, "max": 179.0, "step": 0.5, "tooltip": (
            "Horizontal field of view in degrees.")}),
        "width": ("INT", {"default": 512, "min": 8, "max": 8192, "tooltip": "Image width in pixels."}),
        "height": ("INT", {"default": 512, "min": 8, "max": 8192, "tooltip": "Image height in pixels."}),
        "up": ("STRING", {"default": "auto", "tooltip": (
            "The world direction shown up in every view: auto (detected from the scene; a guess is "
            "noted under the node), an axis such as -y or +z, or three numbers x, y, z.")}),
        "elevations": ("STRING", {"default": "10, 30", "tooltip": (
            "One ring of views per angle (degrees above the horizontal plane through the centre), "
            "comma-separated, each between -90 and 90.")}),
        "distance_factor": ("FLOAT", {"default": 1.0, "min": 0.1, "max": 100.0, "step": 0.05, "tooltip": (
            "1: the main subject just fills the view; larger shows more of the surroundings.")}),
    }
    VALUE_CHECKS = {"up": parse_up, "elevations": parse_elevations}  # as orbit_cameras reads them

    @classmethod
    def camera_count(cls, count=None, **_other_inputs) -> int | None:
        """How many cameras the node will place (``prompt_checks``, as :meth:`LoadCameras.camera_count`): ``count``
        when it is one the node takes, else None (through a link: known as the graph runs)."""
        return count if isinstance(count, int) and cls.check_values(count=count) is None else None

    def place(self, scene, count, fov_deg, width, height, up, elevations, distance_factor, node_id=None):
        """The cameras; a guessed up direction (no ground found) said under the node and once on the console."""
        notes: list[str] = []
        with node_input(self.DISPLAY_NAME):
            cameras = orbit_cameras(scene, count, fov_deg=fov_deg, width=width, height=height, up=up,
                                    elevations_deg=elevations, distance_factor=distance_factor, notes=notes.append,
                                    up_option="set this node's up input to -y or another axis")
        shown_notes(notes, self.DISPLAY_NAME)
        return (cameras,)


class GroupNeighbouringViews(ArtNVGNode):
    """Split the cameras into balanced groups of nearby views, stylized together by Sample Group."""

    DISPLAY_NAME = "Group Neighbouring Views"
    FUNCTION = "group"
    RETURN_TYPES = (GROUPS,)
    RETURN_NAMES = ("groups",)
    REQUIRED = {
        "cameras": (CAMERAS,),
        "group_size": ("INT", {"default": DEFAULT_GROUP_SIZE, "min": 1, "max": 256, "tooltip": (
            "Most views per group (the paper uses 15): the fewest groups that hold them, sizes differing by at "
            "most one.")}),
        "context": ("INT", {"default": 0, "min": 0, "max": 64, "tooltip": (
            "Extra views each group borrows from its neighbours as shared context.")}),
    }

    def group(self, cameras, group_size, context, node_id=None):
        with node_input(self.DISPLAY_NAME, "cameras"):
            return (group_views(cameras, group_size, context=context),)
