"""nerfstudio ``transforms.json`` cameras (OpenGL camera-to-world, converted to OpenCV world-to-camera here)."""

from __future__ import annotations

import math
from functools import partial
from pathlib import Path

import torch

from ..counted import counted
from ..json_objects import parse_json
from .camera_set import MAX_IMAGE_SIDE, CameraSet
from ..notes import NoteFn
from .common import (
    DISTORTION_NAMES,
    PERSPECTIVE_MODELS,
    MAX_CAMERA_VALUE,
    check_camera_value,
    check_distinct_images,
    loaded_camera_set,
    read_text,
    tell_distortion,
    view_names,
)
from .geometry import check_rotation, rigid_inverse

# Flips the y and z camera axes: OpenGL (x right, y up, z back) <-> OpenCV (x right, y down, z forward).
_FLIP_YZ = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))

# ``applied_transform`` that nerfstudio assumes for old COLMAP conversions that did not record it.
_LEGACY_COLMAP_APPLIED_TRANSFORM = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]


def _read_json_object(path: Path) -> dict:
    """The JSON object in ``path`` (:func:`~artnvg_core.json_objects.parse_json`): every number read as a float,
    a key given twice in one object refused."""
    return parse_json(read_text(path), str(path), parse_int=float)


def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: expected a number, got {_kind(value)}")
    if not math.isfinite(value):
        raise ValueError(f"{where}: expected a finite number within float range, got {value}")
    return float(value)


def _kind(value) -> str:
    """What ``value`` (from JSON) is, without quoting it: "a string", "a list of 3 items"..."""
    if isinstance(value, list):
        return f"a list of {counted(len(value), 'item')}"
    return {str: "a string", dict: "an object", bool: "true or false", type(None): "null"}.get(type(value), "a number")


def _image_size(value, where: str) -> int:
    size = _number(value, where)
    if not 0 < size <= MAX_IMAGE_SIDE or size != int(size):
        raise ValueError(f"{where}: expected a whole number of pixels from 1 to {MAX_IMAGE_SIDE}, got {value!r}")
    return int(size)


_KNOWN_MODELS = ("OPENCV_FISHEYE", "EQUIRECTANGULAR", "FISHEYE624", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE")
_BOTTOM_ROW = [0.0, 0.0, 0.0, 1.0]


def _matrix_rows(value, where: str) -> list[list]:
    """The four rows of a JSON 3x4 or 4x4 nested list (a 3x4 one gets the row 0 0 0 1); only the shape is
    checked here, in plain Python, so that a million frames are read in seconds (:func:`_matrices` and
    :func:`_check_affine` check the values)."""
    rows = value if isinstance(value, list) and len(value) in (3, 4) else None
    if rows is None or not all(isinstance(row, list) and len(row) == 4 for row in rows):
        raise ValueError(f"{where}: expected a 3x4 or 4x4 matrix of numbers, got {_kind(value)}")
    return rows if len(rows) == 4 else [*rows, _BOTTOM_ROW]


def _matrices(rows: list[list[list]], where) -> torch.Tensor:
    """[C, 4, 4] float64 of the :func:`_matrix_rows` of C matrices; ValueError naming ``where(index)`` of the
    first that holds something other than numbers."""
    try:
        matrices = torch.tensor(rows, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        matrices = None
    if matrices is not None and matrices.ndim == 3:  # torch reads an empty string as an empty list: [C, 4, 4, 0]
        return matrices
    for index, matrix in enumerate(rows):
        if any(isinstance(number, (str, list, dict)) or number is None for row in matrix for number in row):
            raise ValueError(f"{where(index)}: expected a 3x4 or 4x4 matrix of numbers, got something else among them")
    raise AssertionError("_matrices found nothing but numbers in matrices torch refused")


def _check_affine(matrices: torch.Tensor, where) -> None:
    """ValueError naming ``where(index)`` of the first of ``matrices`` [C, 4, 4] with a value beyond float
    range or a bottom row other than 0 0 0 1."""
    finite = torch.isfinite(matrices).flatten(1).all(1)
    bottom = (matrices[:, 3] - torch.tensor(_BOTTOM_ROW, dtype=matrices.dtype)).abs().amax(1) <= 1e-6
    bad = (~(finite & bottom)).nonzero()
    if len(bad):
        index = int(bad[0, 0])
        if not finite[index]:
            raise ValueError(f"{where(index)}: expected finite numbers within float range, got "
                             f"{matrices[index][~torch.isfinite(matrices[index])][0]}")
        raise ValueError(f"{where(index)}: the bottom row must be [0, 0, 0, 1], got {matrices[index, 3].tolist()}")


def _affine_matrix(value, where: str) -> torch.Tensor:
    """A 4x4 float64 affine matrix from a JSON 3x4 or 4x4 nested list (bottom row 0 0 0 1)."""
    matrix = _matrices([_matrix_rows(value, where)], lambda _: where)
    _check_affine(matrix, lambda _: where)
    return matrix[0]


def _frame_value(frame: dict, meta: dict, where: str, key: str, default=None):
    """A transforms.json key's value for one frame: the frame's own, else the top level's, else ``default``."""
    for source in (frame, meta):
        if key in source:
            return source[key]
    if default is None:
        raise ValueError(f"{where}: missing key '{key}' (neither in the frame nor at the top level)")
    return default


def _check_camera_model(model, where: str) -> None:
    if model not in PERSPECTIVE_MODELS:
        named = f" {model}" if model in _KNOWN_MODELS else ""  # a file's own text is never quoted
        raise ValueError(f"{where}: camera model{named} not supported; expected one of {', '.join(PERSPECTIVE_MODELS)}")


def _dataparser_rigid_transform(path: Path, meta: dict, transforms_path: Path) -> tuple[torch.Tensor, float]:
    """(rigid 4x4, scale) mapping the transforms.json frame to nerfstudio's dataparser frame.

    nerfstudio saves ``transform`` relative to the *original* data frame, i.e.
    already composed with the transforms.json's ``applied_transform`` A, and
    ``scale`` multiplied by its ``applied_scale``; both are undone here.
    """
    data = _read_json_object(path)
    for key in ("transform", "scale"):
        if key not in data:
            raise ValueError(f"{path}: missing key '{key}' (expected nerfstudio dataparser_transforms.json)")
    transform = _affine_matrix(data["transform"], f"{path}: 'transform'")
    scale = _number(data["scale"], f"{path}: 'scale'")
    if scale <= 0:
        raise ValueError(f"{path}: 'scale' must be positive, got {scale}")
    applied = meta.get("applied_transform")
    if applied is None and (transforms_path.parent / "colmap" / "sparse" / "0").is_dir():
        applied = _LEGACY_COLMAP_APPLIED_TRANSFORM
    if applied is not None:
        applied_matrix = _affine_matrix(applied, f"{transforms_path}: 'applied_transform'")
        check_rotation(applied_matrix[:3, :3], f"{transforms_path}: 'applied_transform'")
        transform = transform @ rigid_inverse(applied_matrix)
    if "applied_scale" in meta:
        applied_scale = _number(meta["applied_scale"], f"{transforms_path}: 'applied_scale'")
        if applied_scale <= 0:
            raise ValueError(f"{transforms_path}: 'applied_scale' must be positive, got {applied_scale}")
        scale /= applied_scale
    check_rotation(transform[:3, :3], f"{path}: 'transform' (after undoing the transforms.json 'applied_transform')")
    return transform, scale


def _check_frame(path: Path, meta: dict, index: int, frame, size: tuple[int, int] | None) -> tuple[int, int]:
    """Every check of frame ``index`` but its matrix, one value at a time: ValueError naming the file, the frame
    and the key; else the frame's (width, height). ``size``: the first frame's."""
    where = f"{path}: frame {index}"
    if not isinstance(frame, dict):
        raise ValueError(f"{where}: expected a JSON object, got {_kind(frame)}")
    value = partial(_frame_value, frame, meta, where)
    if "camera_model" in frame:
        _check_camera_model(frame["camera_model"], f"{where}: 'camera_model'")
    width = _image_size(value("w"), f"{where}: 'w'")
    height = _image_size(value("h"), f"{where}: 'h'")
    if size is not None and (width, height) != size:
        raise ValueError(f"{where}: image size {width}x{height} differs from the first frame's {size[0]}x{size[1]}; "
                         "all frames must share one size")
    fx, fy = (check_camera_value(_number(value(key), f"{where}: '{key}'"), f"{where}: '{key}'")
              for key in ("fl_x", "fl_y"))
    if fx <= 0 or fy <= 0:
        raise ValueError(f"{where}: focal lengths must be positive, got fl_x={fx}, fl_y={fy}")
    for key, default in (("cx", width / 2), ("cy", height / 2)):
        check_camera_value(_number(value(key, default), f"{where}: '{key}'"), f"{where}: '{key}'")
    file_path = value("file_path")
    if not isinstance(file_path, str) or not file_path:
        raise ValueError(f"{where}: 'file_path' must be a non-empty string, got {_kind(file_path)}")
    return width, height


def _check_frames(path: Path, meta: dict, frames: list) -> None:
    """:func:`_check_frame` of every frame in file order: raises for the first that is wrong."""
    size = None
    for index, frame in enumerate(frames):
        frame_size = _check_frame(path, meta, index, frame, size)
        size = size or frame_size


def _intrinsics(path: Path, meta: dict, frames: list) -> tuple[int, int, torch.Tensor]:
    """(width, height, K [C, 3, 3] float64) of the frames. Read in bulk (JSON numbers are floats, see
    :func:`_read_json_object`), then checked as tensors; only when something is wrong are the frames
    checked one by one (:func:`_check_frames`), for the message that names the first bad one."""
    defaults = {key: meta.get(key) for key in ("w", "h", "fl_x", "fl_y", "cx", "cy", "camera_model")}
    rows = []
    for frame in frames:
        model = frame.get("camera_model", defaults["camera_model"]) if isinstance(frame, dict) else None
        if not isinstance(frame, dict) or model not in (None, *PERSPECTIVE_MODELS):
            break  # named frame by frame below
        w, h, fx, fy, cx, cy = (frame.get(key, defaults[key]) for key in ("w", "h", "fl_x", "fl_y", "cx", "cy"))
        rows.append((w, h, fx, fy, w / 2 if cx is None and type(w) is float else cx,
                     h / 2 if cy is None and type(h) is float else cy))
    else:
        if all(type(v) is float for row in rows for v in row):
            table = torch.tensor(rows, dtype=torch.float64)
            width, height = table[0, :2].tolist()
            sizes_ok = ((table[:, 0] == width) & (table[:, 1] == height)).all() and 0 < width <= MAX_IMAGE_SIDE and \
                0 < height <= MAX_IMAGE_SIDE and width == int(width) and height == int(height)
            if sizes_ok and (table[:, 2:4] > 0).all() and (table[:, 2:].abs() <= MAX_CAMERA_VALUE).all():
                k = torch.zeros(len(rows), 3, 3, dtype=torch.float64)
                k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2] = table[:, 2:].unbind(1)
                k[:, 2, 2] = 1
                return int(width), int(height), k
    _check_frames(path, meta, frames)
    raise AssertionError("_check_frames found nothing wrong with frames the bulk check refused")


def _distortion(meta: dict, frames: list[dict]) -> torch.Tensor:
    """[C, 6] float64: each frame's :data:`~.common.DISTORTION_NAMES` coefficients (the frame's own, else the top
    level's; 0 where neither gives a number)."""
    def number(value) -> float:
        return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else 0.0

    top = [number(meta.get(name)) for name in DISTORTION_NAMES]
    if not any(isinstance(frame, dict) and not frame.keys().isdisjoint(DISTORTION_NAMES) for frame in frames):
        return torch.tensor([top], dtype=torch.float64).expand(len(frames), -1)
    return torch.tensor([[number(frame[name]) if name in frame else value for name, value in zip(DISTORTION_NAMES, top)]
                         for frame in frames], dtype=torch.float64)


def _check_positions(cam_to_world: torch.Tensor, where) -> None:
    """ValueError naming ``where(index, axis)`` ("x", "y" or "z") of the first camera of ``cam_to_world``
    [C, 4, 4] whose position lies beyond :data:`MAX_CAMERA_VALUE` (or is not finite)."""
    far = (~(cam_to_world[:, :3, 3].abs() <= MAX_CAMERA_VALUE)).nonzero()
    if len(far):
        index, axis = far[0].tolist()
        check_camera_value(cam_to_world[index, axis, 3].item(), where(index, "xyz"[axis]))


def load_nerfstudio(path, *, dataparser_transforms=None, notes: NoteFn | None = None) -> CameraSet:
    """Cameras of a nerfstudio ``transforms.json``, in file order.

    Intrinsics ``fl_x, fl_y, cx, cy, w, h`` (pixels) come from each frame or,
    where a frame lacks a key, from the top level; ``cx``/``cy`` default to
    ``w/2``/``h/2``. All frames must share one ``w`` x ``h``. Lens distortion
    (``k1..k4, p1, p2``) is ignored; when any is non-zero, ``notes`` is told so once
    (:func:`~.common.tell_distortion`; logged without). ``transform_matrix`` is an OpenGL
    camera-to-world matrix; it is converted to an OpenCV world-to-camera one.
    ``names`` are the image file stems, ``image_paths`` the ``file_path``s
    resolved against the JSON file's folder.

    ``dataparser_transforms``: optional path of the ``dataparser_transforms.json``
    that nerfstudio writes into a training run's output folder. The poses are
    then mapped into that run's (e.g. a splatfacto checkpoint's) frame:
    ``c2w' = T @ c2w`` with the translation times ``scale``, where ``T`` is
    relative to this file's frame (its ``applied_transform`` undone).

    Raises ValueError naming the file, frame and key for missing or malformed
    entries, non-rigid matrices, unsupported camera models, mixed image sizes
    or two frames of one image (:func:`~.common.check_distinct_images`).
    """
    path = Path(path)
    meta = _read_json_object(path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        got = _kind(frames) if frames is not None else "nothing"
        raise ValueError(f"{path}: 'frames': expected a non-empty list, got {got}")
    if "camera_model" in meta:
        _check_camera_model(meta["camera_model"], f"{path}: 'camera_model'")

    width, height, intrinsics = _intrinsics(path, meta, frames)
    names = [frame.get("file_path", meta.get("file_path")) for frame in frames]
    if not all(type(name) is str and name for name in names):
        _check_frames(path, meta, frames)
    check_distinct_images(names, lambda index: f"frames[{index}].file_path", path, folder=str(path.parent))
    image_paths = [path.parent / name for name in names]
    poses = []
    for index, frame in enumerate(frames):
        where = f"{path}: frame {index}"
        poses.append(_matrix_rows(_frame_value(frame, meta, where, "transform_matrix"), f"{where}: 'transform_matrix'"))

    def matrix_of(index: int) -> str:
        return f"{path}: frame {index}: 'transform_matrix'"

    cam_to_world = _matrices(poses, matrix_of)
    _check_affine(cam_to_world, matrix_of)
    check_rotation(cam_to_world[:, :3, :3], matrix_of)
    _check_positions(cam_to_world, lambda index, axis: f"{matrix_of(index)}: the camera position's {axis}")
    cam_to_world = cam_to_world @ _FLIP_YZ
    if dataparser_transforms is not None:
        dataparser = Path(dataparser_transforms)
        transform, scale = _dataparser_rigid_transform(dataparser, meta, path)
        cam_to_world = transform @ cam_to_world
        cam_to_world[:, :3, 3] *= scale
        _check_positions(cam_to_world, lambda index, axis: f"{dataparser}: 'transform' and 'scale' put frame {index} "
                                                           f"of {path} at {axis}")
    world_to_cam = rigid_inverse(cam_to_world)
    cameras = loaded_camera_set(world_to_cam, intrinsics, width, height, view_names(names, path), image_paths,
                                lambda index: f"{path}: frame {index}")
    tell_distortion(notes, path, intrinsics, width, height, _distortion(meta, frames))
    return cameras

