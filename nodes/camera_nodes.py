"""Load Cameras and Group Neighbouring Views."""

from __future__ import annotations

from artnvg_core.cameras import load_cameras
from artnvg_core.grouping import DEFAULT_GROUP_SIZE, group_views

from .input_files import file_signature, list_input_files, resolve_input_path
from .node_errors import node_input
from .node_types import CAMERAS, CATEGORY, GROUPS

COLMAP_MARKERS = ("cameras.bin", "cameras.txt")


class LoadCameras:
    """Capture cameras from a nerfstudio transforms.json or a COLMAP model folder."""

    DISPLAY_NAME = "Load Cameras"
    CATEGORY = CATEGORY
    FUNCTION = "load"
    RETURN_TYPES = (CAMERAS,)
    RETURN_NAMES = ("cameras",)
    DESCRIPTION = __doc__

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "camera_source": (list_input_files(names=("transforms.json",), marker_files=COLMAP_MARKERS), {
                    "tooltip": "A transforms.json or a COLMAP model folder in ComfyUI's input folder."}),
            },
            "optional": {
                "path": ("STRING", {"default": "", "tooltip": (
                    "A nerfstudio .json file, a folder holding transforms.json, or a COLMAP folder (directly or in "
                    "sparse/0); when not blank it is used instead of camera_source. Relative paths start at the "
                    "input folder.")}),
            },
        }

    @classmethod
    def VALIDATE_INPUTS(cls, camera_source, path=""):
        source, input_name = resolve_input_path("camera_source", camera_source, path)
        if not source.exists():
            return f"{cls.DISPLAY_NAME}: input '{input_name}': camera file or folder not found: {source}"
        return True

    @classmethod
    def IS_CHANGED(cls, camera_source, path=""):
        source = resolve_input_path("camera_source", camera_source, path)[0]
        return file_signature(source / "transforms.json" if source.is_dir() else source)

    def load(self, camera_source, path=""):
        source, input_name = resolve_input_path("camera_source", camera_source, path)
        with node_input(self.DISPLAY_NAME, input_name):
            return (load_cameras(source),)


class GroupNeighbouringViews:
    """Split the cameras into balanced groups of nearby views, stylized together by Sample Group."""

    DISPLAY_NAME = "Group Neighbouring Views"
    CATEGORY = CATEGORY
    FUNCTION = "group"
    RETURN_TYPES = (GROUPS,)
    RETURN_NAMES = ("groups",)
    DESCRIPTION = __doc__

    @classmethod
    def INPUT_TYPES(cls):
        return {
            "required": {
                "cameras": (CAMERAS,),
                "group_size": ("INT", {"default": DEFAULT_GROUP_SIZE, "min": 1, "max": 256, "tooltip": (
                    "Most views per group (the paper uses 15): the fewest groups that hold them, sizes differing by at "
                    "most one.")}),
                "context": ("INT", {"default": 0, "min": 0, "max": 64, "tooltip": (
                    "Extra views each group borrows from its neighbours as shared context.")}),
            },
        }

    def group(self, cameras, group_size, context):
        with node_input(self.DISPLAY_NAME, "cameras"):
            return (group_views(cameras, group_size, context=context),)
