"""Camera sets: OpenCV world-to-camera poses plus pinhole intrinsics.

Conventions (DESIGN.md): OpenCV camera axes (x right, y down, z forward),
``world_to_cam`` [C, 4, 4] maps world points to camera coordinates,
``intrinsics`` [C, 3, 3] = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels
with pixel centres at +0.5 (the top-left pixel's centre is (0.5, 0.5)).
All views of a set share one ``width`` x ``height`` in pixels.
Other conventions (nerfstudio OpenGL camera-to-world, COLMAP) are converted
at load time, in this module only.

Loaders: :func:`load_cameras` (dispatch), :func:`load_nerfstudio`,
:func:`load_colmap`. Novel-view paths: :func:`orbit_path`,
:func:`interpolate_path` (built on :func:`look_at` and quaternion slerp;
:func:`quat_to_rotmat` / :func:`rotmat_to_quat` use w x y z order).
Loaders return float32 CPU tensors; all pose maths runs in float64.
Lens distortion is ignored everywhere: these are pinhole cameras.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import torch


MAX_IMAGE_SIDE = 16384  # pixels; a float32 RGB view this size already takes 3 GiB


@dataclass
class CameraSet:
    """C pinhole cameras of one image size (shapes in the module docstring).

    ``names`` are the views' image file stems (e.g. ``frame_00096``);
    ``image_paths`` the source images when known (else ``None`` entries).
    """

    world_to_cam: torch.Tensor
    intrinsics: torch.Tensor
    width: int
    height: int
    names: list[str]
    image_paths: list[Path | None] = field(default_factory=list)

    def __post_init__(self) -> None:
        c = self.world_to_cam.shape[0] if self.world_to_cam.ndim == 3 else -1
        if tuple(self.world_to_cam.shape) != (c, 4, 4) or c < 0:
            raise ValueError(f"CameraSet.world_to_cam: expected shape (C, 4, 4), got {tuple(self.world_to_cam.shape)}")
        if tuple(self.intrinsics.shape) != (c, 3, 3):
            raise ValueError(f"CameraSet.intrinsics: expected shape ({c}, 3, 3), got {tuple(self.intrinsics.shape)}")
        if not (0 < self.width <= MAX_IMAGE_SIDE and 0 < self.height <= MAX_IMAGE_SIDE):
            raise ValueError(f"CameraSet: image size must be 1 to {MAX_IMAGE_SIDE} pixels a side, "
                             f"got {self.width}x{self.height}")
        if len(self.names) != c:
            raise ValueError(f"CameraSet.names: expected {c} names, got {len(self.names)}")
        if not self.image_paths:
            self.image_paths = [None] * c
        if len(self.image_paths) != c:
            raise ValueError(f"CameraSet.image_paths: expected {c} entries, got {len(self.image_paths)}")

    def __len__(self) -> int:
        return self.world_to_cam.shape[0]

    @property
    def centers(self) -> torch.Tensor:
        """Camera centres in world coordinates, [C, 3]."""
        rot = self.world_to_cam[:, :3, :3]
        trans = self.world_to_cam[:, :3, 3:]
        return -(rot.transpose(1, 2) @ trans)[..., 0]

    def subset(self, indices) -> "CameraSet":
        """The views at ``indices`` (a sequence of ints), in that order."""
        idx = [int(i) for i in indices]
        for i in idx:
            if not -len(self) <= i < len(self):
                raise ValueError(f"CameraSet.subset: view index {i} out of range for {len(self)} views")
        sel = torch.tensor(idx, dtype=torch.long)
        return replace(
            self,
            world_to_cam=self.world_to_cam[sel],
            intrinsics=self.intrinsics[sel],
            names=[self.names[i] for i in idx],
            image_paths=[self.image_paths[i] for i in idx],
        )

    def scaled(self, factor: float) -> "CameraSet":
        """The same views at ``factor`` times the resolution (rounded to whole pixels).

        Intrinsics scale with the actual per-axis size ratio, so the image
        plane keeps covering the same field of view.
        """
        if not (math.isfinite(factor) and factor > 0):
            raise ValueError(f"CameraSet.scaled: factor must be a finite number > 0, got {factor}")
        width = max(1, round(self.width * factor))
        height = max(1, round(self.height * factor))
        if max(width, height) > MAX_IMAGE_SIDE:
            raise ValueError(f"CameraSet.scaled: factor {factor} makes {self.width}x{self.height} views "
                             f"{width}x{height}, above the {MAX_IMAGE_SIDE} pixels a side a view may have")
        k = self.intrinsics.clone()
        k[:, 0, :] *= width / self.width
        k[:, 1, :] *= height / self.height
        return replace(self, intrinsics=k, width=width, height=height)

    def to(self, device) -> "CameraSet":
        return replace(self, world_to_cam=self.world_to_cam.to(device), intrinsics=self.intrinsics.to(device))


# --------------------------------------------------------------------------- rotations

def normalize_quats(quat: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] of ``quat`` [..., 4] of any finite norm (1e-40 to 3e38 in float32):
    each is divided by its largest absolute component before the norm is taken, so the squares
    neither underflow nor overflow. The zero quaternion stays zero (which :func:`quat_to_rotmat`
    maps to the identity)."""
    largest = quat.detach().abs().amax(-1, keepdim=True)
    scaled = quat / torch.where(largest > 0, largest, torch.ones_like(largest))
    return torch.nn.functional.normalize(scaled, dim=-1, eps=1e-12)


def quat_to_rotmat(quat: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] (w x y z, any finite norm, normalised
    with :func:`normalize_quats`; the zero quaternion gives the identity)."""
    w, x, y, z = normalize_quats(quat).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(row, -1) for row in rows], -2)


def rotmat_to_quat(rot: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] (w x y z, w >= 0) of rotation matrices [..., 3, 3].

    Every entry of 4 q q^T is linear in the matrix; the row with the largest
    diagonal entry is the best-conditioned multiple of q (Shepperd's method).
    """
    r = rot
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    ww, xx, yy, zz = 1 + trace, 1 + 2 * r[..., 0, 0] - trace, 1 + 2 * r[..., 1, 1] - trace, 1 + 2 * r[..., 2, 2] - trace
    wx, wy, wz = r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]
    xy, xz, yz = r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1]
    outer = torch.stack(  # 4 q q^T
        [
            torch.stack([ww, wx, wy, wz], -1),
            torch.stack([wx, xx, xy, xz], -1),
            torch.stack([wy, xy, yy, yz], -1),
            torch.stack([wz, xz, yz, zz], -1),
        ],
        -2,
    )
    best = torch.stack([ww, xx, yy, zz], -1).argmax(-1)
    row = torch.gather(outer, -2, best[..., None, None].expand(*best.shape, 1, 4))[..., 0, :]
    quat = row / row.norm(dim=-1, keepdim=True)
    return torch.where(quat[..., :1] < 0, -quat, quat)


def _slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Shortest-arc spherical interpolation of unit quaternions q0, q1 [4] at t [T] -> [T, 4]."""
    if torch.dot(q0, q1) < 0:
        q1 = -q1
    cos = torch.dot(q0, q1).clamp(max=1.0)
    angle = torch.arccos(cos)
    t = t[:, None]
    if angle < 1e-8:
        mixed = (1 - t) * q0 + t * q1
    else:
        mixed = (torch.sin((1 - t) * angle) * q0 + torch.sin(t * angle) * q1) / torch.sin(angle)
    return mixed / mixed.norm(dim=-1, keepdim=True)


def _check_rotation(rot: torch.Tensor, where: str) -> None:
    """ValueError unless ``rot`` [3, 3] is orthonormal with determinant +1 (to 1e-3)."""
    error = (rot.T @ rot - torch.eye(3, dtype=rot.dtype)).abs().max().item()
    det = torch.linalg.det(rot).item()
    if not (error < 1e-3 and det > 0):
        raise ValueError(
            f"{where}: the top-left 3x3 block must be a rotation (orthonormal, determinant +1); "
            f"got max|R^T R - I| = {error:.3g}, det = {det:.3g}"
        )


def _rigid_inverse(pose: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms [..., 4, 4] (rotation + translation)."""
    rot_t = pose[..., :3, :3].transpose(-1, -2)
    inverse = torch.zeros_like(pose)
    inverse[..., :3, :3] = rot_t
    inverse[..., :3, 3] = -(rot_t @ pose[..., :3, 3:])[..., 0]
    inverse[..., 3, 3] = 1
    return inverse


def _view_names(files: list[str], source: Path) -> list[str]:
    """Unique view names for image files (relative paths): each file's stem, or, where stems
    repeat (``a/0001.jpg``, ``b/0001.jpg``), the path without its suffix joined by ``_``
    (``a_0001``, ``b_0001``). Names that still repeat are a ValueError naming them."""
    stems = [Path(f).stem for f in files]
    repeated = {s for s in stems if stems.count(s) > 1}
    names = ["_".join(p for p in Path(f.replace("\\", "/")).with_suffix("").parts if p not in (".", "..", "/"))
             if s in repeated else s for f, s in zip(files, stems)]
    clashes = sorted({f for f, n in zip(files, names) if names.count(n) > 1})
    if clashes:
        raise ValueError(f"{source}: image files {clashes[:6]} give views one name; views are named after "
                         "their image files (renders are saved as NAME.png), so each must be distinct")
    return names


def _pinhole_matrix(fx: float, fy: float, cx: float, cy: float) -> list[list[float]]:
    return [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]


def _camera_set(world_to_cam: torch.Tensor, intrinsics, width: int, height: int, names, image_paths) -> CameraSet:
    """A loader's float32 CPU CameraSet from float64 poses and intrinsics."""
    return CameraSet(
        world_to_cam=world_to_cam.to(torch.float32),
        intrinsics=torch.as_tensor(intrinsics, dtype=torch.float64).reshape(-1, 3, 3).to(torch.float32),
        width=width,
        height=height,
        names=list(names),
        image_paths=list(image_paths),
    )


# --------------------------------------------------------------------------- nerfstudio

# Camera models (nerfstudio's ``camera_model`` / COLMAP's) that are pinhole
# cameras once their distortion is ignored.
_PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")

# Flips the y and z camera axes: OpenGL (x right, y up, z back) <-> OpenCV (x right, y down, z forward).
_FLIP_YZ = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))

# ``applied_transform`` that nerfstudio assumes for old COLMAP conversions that did not record it.
_LEGACY_COLMAP_APPLIED_TRANSFORM = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]


def _read_text(path: Path) -> str:
    """A UTF-8 text file's contents; a missing, unreadable or non-UTF-8 file is a ValueError naming it."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not UTF-8 text (byte {error.object[error.start:error.start + 1]!r} at offset "
                         f"{error.start}); save it as UTF-8") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot read the file ({error.strerror or error})") from None


def _read_json_object(path: Path) -> dict:
    try:
        data = json.loads(_read_text(path))
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    return data


def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{where}: expected a finite number, got {value!r}")
    return float(value)


def _image_size(value, where: str) -> int:
    size = _number(value, where)
    if not 0 < size <= MAX_IMAGE_SIDE or size != int(size):
        raise ValueError(f"{where}: expected a whole number of pixels from 1 to {MAX_IMAGE_SIDE}, got {value!r}")
    return int(size)


def _affine_matrix(value, where: str) -> torch.Tensor:
    """A 4x4 float64 affine matrix from a JSON 3x4 or 4x4 nested list (bottom row 0 0 0 1)."""
    try:
        matrix = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        matrix = None
    if matrix is None or tuple(matrix.shape) not in ((3, 4), (4, 4)) or not torch.isfinite(matrix).all():
        raise ValueError(f"{where}: expected a 3x4 or 4x4 matrix of finite numbers, got {str(value)[:120]}")
    if matrix.shape[0] == 4:
        if not torch.allclose(matrix[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-6):
            raise ValueError(f"{where}: the bottom row must be [0, 0, 0, 1], got {matrix[3].tolist()}")
        return matrix
    return torch.cat([matrix, torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)])


def _frame_value(frame: dict, meta: dict, where: str, key: str, default=None):
    """A transforms.json key's value for one frame: the frame's own, else the top level's, else ``default``."""
    for source in (frame, meta):
        if key in source:
            return source[key]
    if default is None:
        raise ValueError(f"{where}: missing key '{key}' (neither in the frame nor at the top level)")
    return default


def _check_camera_model(model, where: str) -> None:
    if model not in _PERSPECTIVE_MODELS:
        raise ValueError(
            f"{where}: camera model {model!r} is not supported; expected one of {', '.join(_PERSPECTIVE_MODELS)}"
        )


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
        _check_rotation(applied_matrix[:3, :3], f"{transforms_path}: 'applied_transform'")
        transform = transform @ _rigid_inverse(applied_matrix)
    if "applied_scale" in meta:
        applied_scale = _number(meta["applied_scale"], f"{transforms_path}: 'applied_scale'")
        if applied_scale <= 0:
            raise ValueError(f"{transforms_path}: 'applied_scale' must be positive, got {applied_scale}")
        scale /= applied_scale
    _check_rotation(transform[:3, :3], f"{path}: 'transform' (after undoing the transforms.json 'applied_transform')")
    return transform, scale


def load_nerfstudio(path, *, dataparser_transforms=None) -> CameraSet:
    """Cameras of a nerfstudio ``transforms.json``, in file order.

    Intrinsics ``fl_x, fl_y, cx, cy, w, h`` (pixels) come from each frame or,
    where a frame lacks a key, from the top level; ``cx``/``cy`` default to
    ``w/2``/``h/2``. All frames must share one ``w`` x ``h``. Lens distortion
    (``k1..k4, p1, p2``) is ignored. ``transform_matrix`` is an OpenGL
    camera-to-world matrix; it is converted to an OpenCV world-to-camera one.
    ``names`` are the image file stems, ``image_paths`` the ``file_path``s
    resolved against the JSON file's folder.

    ``dataparser_transforms``: optional path of the ``dataparser_transforms.json``
    that nerfstudio writes into a training run's output folder. The poses are
    then mapped into that run's (e.g. a splatfacto checkpoint's) frame:
    ``c2w' = T @ c2w`` with the translation times ``scale``, where ``T`` is
    relative to this file's frame (its ``applied_transform`` undone).

    Raises ValueError naming the file, frame and key for missing or malformed
    entries, non-rigid matrices, unsupported camera models or mixed image sizes.
    """
    path = Path(path)
    meta = _read_json_object(path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path}: expected a non-empty list under 'frames', got {str(frames)[:80]}")
    if "camera_model" in meta:
        _check_camera_model(meta["camera_model"], f"{path}: 'camera_model'")

    poses, intrinsics, names, image_paths = [], [], [], []
    size = None
    for index, frame in enumerate(frames):
        where = f"{path}: frame {index}"
        if not isinstance(frame, dict):
            raise ValueError(f"{where}: expected a JSON object, got {type(frame).__name__}")

        value = partial(_frame_value, frame, meta, where)
        if "camera_model" in frame:
            _check_camera_model(frame["camera_model"], f"{where}: 'camera_model'")
        width = _image_size(value("w"), f"{where}: 'w'")
        height = _image_size(value("h"), f"{where}: 'h'")
        if size is None:
            size = (width, height)
        elif (width, height) != size:
            raise ValueError(
                f"{where}: image size {width}x{height} differs from the first frame's {size[0]}x{size[1]}; "
                "all frames must share one size"
            )
        fx, fy = (_number(value(key), f"{where}: '{key}'") for key in ("fl_x", "fl_y"))
        if fx <= 0 or fy <= 0:
            raise ValueError(f"{where}: focal lengths must be positive, got fl_x={fx}, fl_y={fy}")
        cx = _number(value("cx", width / 2), f"{where}: 'cx'")
        cy = _number(value("cy", height / 2), f"{where}: 'cy'")
        intrinsics.append(_pinhole_matrix(fx, fy, cx, cy))

        file_path = value("file_path")
        if not isinstance(file_path, str) or not file_path:
            raise ValueError(f"{where}: 'file_path' must be a non-empty string, got {file_path!r}")
        names.append(file_path)
        image_paths.append(path.parent / file_path)

        pose = _affine_matrix(value("transform_matrix"), f"{where}: 'transform_matrix'")
        _check_rotation(pose[:3, :3], f"{where}: 'transform_matrix'")
        poses.append(pose)

    cam_to_world = torch.stack(poses) @ _FLIP_YZ
    if dataparser_transforms is not None:
        transform, scale = _dataparser_rigid_transform(Path(dataparser_transforms), meta, path)
        cam_to_world = transform @ cam_to_world
        cam_to_world[:, :3, 3] *= scale
    return _camera_set(_rigid_inverse(cam_to_world), intrinsics, size[0], size[1], _view_names(names, path), image_paths)


# --------------------------------------------------------------------------- COLMAP

# COLMAP camera model id -> (name, number of parameters), as in COLMAP's models.h.
_COLMAP_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
}
_COLMAP_PARAM_COUNTS = dict(_COLMAP_MODELS.values())
# Supported models whose parameters start with a single focal length: f, cx, cy, ...
# (the others start with fx, fy, cx, cy, ...).
_SINGLE_FOCAL_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


@dataclass
class _ColmapCamera:
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass
class _ColmapImage:
    quat: tuple[float, float, float, float]  # world-to-camera rotation, w x y z
    translation: tuple[float, float, float]  # world-to-camera translation
    camera_id: int
    name: str


def _find_colmap_model(folder: Path) -> tuple[Path, str] | None:
    """(model folder, '.bin' or '.txt') of the COLMAP model in ``folder``, ``folder/sparse/0`` or ``folder/sparse``."""
    for candidate in (folder, folder / "sparse" / "0", folder / "sparse"):
        for ext in (".bin", ".txt"):
            if (candidate / f"cameras{ext}").is_file() and (candidate / f"images{ext}").is_file():
                return candidate, ext
    return None


class _BinaryReader:
    """Little-endian reads from a file's bytes; truncation raises ValueError naming the file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as error:
            raise ValueError(f"{path}: cannot read the file ({error.strerror or error})") from None
        self.offset = 0

    def unpack(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.offset + size > len(self.data):
            raise ValueError(f"{self.path}: file ends inside {what} at byte {self.offset} (truncated?)")
        values = struct.unpack_from("<" + fmt, self.data, self.offset)
        self.offset += size
        return values

    def skip(self, size: int, what: str) -> None:
        if self.offset + size > len(self.data):
            raise ValueError(f"{self.path}: file ends inside {what} at byte {self.offset} (truncated?)")
        self.offset += size

    def c_string(self, what: str) -> str:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise ValueError(f"{self.path}: file ends inside {what} at byte {self.offset} (truncated?)")
        raw = self.data[self.offset : end]
        self.offset = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{self.path}: {what} is not UTF-8: {raw[:80]!r}") from None


def _read_cameras_bin(path: Path) -> dict[int, _ColmapCamera]:
    reader = _BinaryReader(path)
    (count,) = reader.unpack("Q", "the camera count")
    cameras = {}
    for index in range(count):
        camera_id, model_id, width, height = reader.unpack("IiQQ", f"camera {index}")
        if model_id not in _COLMAP_MODELS:
            raise ValueError(f"{path}: camera {camera_id}: unknown camera model id {model_id}")
        model, num_params = _COLMAP_MODELS[model_id]
        params = reader.unpack(f"{num_params}d", f"the parameters of camera {camera_id}")
        cameras[camera_id] = _ColmapCamera(model, width, height, params)
    return cameras


def _read_images_bin(path: Path) -> list[_ColmapImage]:
    reader = _BinaryReader(path)
    (count,) = reader.unpack("Q", "the image count")
    images = []
    for index in range(count):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.unpack("I7dI", f"image {index}")
        name = reader.c_string(f"the name of image {image_id}")
        (num_points,) = reader.unpack("Q", f"the 2D point count of image {image_id}")
        reader.skip(num_points * struct.calcsize("<ddq"), f"the 2D points of image {image_id}")
        images.append(_ColmapImage((qw, qx, qy, qz), (tx, ty, tz), camera_id, name))
    return images


def _text_records(path: Path) -> list[tuple[int, str]]:
    """(line number, line) of a COLMAP text file, comments dropped, blank lines kept."""
    lines = _read_text(path).splitlines()
    return [(number, line.strip()) for number, line in enumerate(lines, 1) if not line.startswith("#")]


def _text_line_error(path: Path, number: int, expected: str, line: str) -> ValueError:
    return ValueError(f"{path}: line {number}: expected {expected}, got {line[:120]!r}")


def _read_cameras_txt(path: Path) -> dict[int, _ColmapCamera]:
    expected = "CAMERA_ID MODEL WIDTH HEIGHT PARAMS..."
    cameras = {}
    for number, line in _text_records(path):
        if not line:
            continue
        fields = line.split()
        if len(fields) < 4 or fields[1] not in _COLMAP_PARAM_COUNTS:
            if len(fields) >= 4:
                raise ValueError(f"{path}: line {number}: unknown camera model {fields[1]!r}")
            raise _text_line_error(path, number, expected, line)
        model = fields[1]
        if len(fields) != 4 + _COLMAP_PARAM_COUNTS[model]:
            count = _COLMAP_PARAM_COUNTS[model]
            raise _text_line_error(path, number, f"{expected} with {count} {model} parameters", line)
        try:
            camera_id, width, height = int(fields[0]), int(fields[2]), int(fields[3])
            params = tuple(float(p) for p in fields[4:])
        except ValueError:
            raise _text_line_error(path, number, expected, line) from None
        cameras[camera_id] = _ColmapCamera(model, width, height, params)
    return cameras


def _image_line(line: str) -> _ColmapImage | None:
    """The record of an images.txt image line ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``, else None."""
    fields = line.split(maxsplit=9)
    if len(fields) != 10:
        return None
    try:
        int(fields[0])
        numbers = [float(f) for f in fields[1:8]]
        camera_id = int(fields[8])
    except ValueError:
        return None
    return _ColmapImage(tuple(numbers[:4]), tuple(numbers[4:]), camera_id, fields[9])


def _is_points_line(line: str) -> bool:
    """True for an images.txt 2D-points line: ``X Y POINT3D_ID`` triples, or nothing."""
    fields = line.split()
    if len(fields) % 3:
        return False
    try:
        for start in range(0, len(fields), 3):
            float(fields[start]), float(fields[start + 1]), int(fields[start + 2])
    except ValueError:
        return False
    return True


def _read_images_txt(path: Path) -> list[_ColmapImage]:
    """Image records, read by structure: each image line is followed by its 2D-points line
    (possibly empty), as COLMAP writes them; files written without the points lines (an image
    line straight after an image line) are read too. Anything else is an error naming the line."""
    expected = "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"
    records = _text_records(path)
    images = []
    index = 0
    while index < len(records):
        number, line = records[index]
        index += 1
        if not line:  # stray blank line between records or at the end
            continue
        image = _image_line(line)
        if image is None:
            raise _text_line_error(path, number, expected, line)
        images.append(image)
        if index < len(records) and (not records[index][1] or _is_points_line(records[index][1])):
            index += 1  # its 2D points
        elif index < len(records) and _image_line(records[index][1]) is None:
            number, line = records[index]
            raise _text_line_error(path, number, f"the 2D points (X Y POINT3D_ID ...) of image {image.name!r}", line)
    return images


def _colmap_intrinsics(camera: _ColmapCamera, where: str) -> list[list[float]]:
    if camera.model not in _PERSPECTIVE_MODELS:
        raise ValueError(
            f"{where}: camera model {camera.model} is not supported; expected one of {', '.join(_PERSPECTIVE_MODELS)}"
        )
    if not (0 < camera.width <= MAX_IMAGE_SIDE and 0 < camera.height <= MAX_IMAGE_SIDE):
        raise ValueError(f"{where}: image size {camera.width}x{camera.height}: expected 1 to {MAX_IMAGE_SIDE} pixels a side")
    p = camera.params
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if camera.model in _SINGLE_FOCAL_MODELS else p[:4]
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise ValueError(f"{where}: focal lengths must be finite and positive and the principal point finite, "
                         f"got fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    return _pinhole_matrix(fx, fy, cx, cy)


def _image_file(model_dir: Path, name: str) -> Path | None:
    for images_dir in (model_dir.parent / "images", model_dir.parent.parent / "images"):
        if (images_dir / name).is_file():
            return images_dir / name
    return None


def load_colmap(path) -> CameraSet:
    """Cameras of a COLMAP sparse model, sorted by image name.

    ``path`` is the model folder (``cameras`` + ``images`` as ``.bin`` or
    ``.txt``; binary preferred when both exist) or a folder holding it as
    ``sparse/0`` or ``sparse``. Supported camera models: SIMPLE_PINHOLE,
    PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, their radial/tangential
    distortion ignored. COLMAP poses are already OpenCV world-to-camera.
    ``names`` are the image name stems; COLMAP does not store the image
    folder, so ``image_paths`` are set only where the file exists in an
    ``images/`` folder one or two levels above the model folder (else None).

    Raises ValueError for a missing model, malformed or truncated files,
    unsupported models, unknown camera ids or mixed image sizes.
    """
    path = Path(path)
    found = _find_colmap_model(path)
    if found is None:
        raise ValueError(
            f"{path}: no COLMAP model found; expected cameras.bin + images.bin or cameras.txt + images.txt "
            "in this folder or in its sparse/0 or sparse subfolder"
        )
    model_dir, ext = found
    cameras_file, images_file = model_dir / f"cameras{ext}", model_dir / f"images{ext}"
    if ext == ".bin":
        cameras, images = _read_cameras_bin(cameras_file), _read_images_bin(images_file)
    else:
        cameras, images = _read_cameras_txt(cameras_file), _read_images_txt(images_file)
    if not images:
        raise ValueError(f"{images_file}: the model has no registered images")

    images.sort(key=lambda image: image.name)
    poses, intrinsics = [], []
    size = None
    for image in images:
        where = f"{images_file}: image {image.name!r}"
        camera = cameras.get(image.camera_id)
        if camera is None:
            raise ValueError(f"{where}: camera id {image.camera_id} is not in {cameras_file}")
        if size is None:
            size = (camera.width, camera.height)
        elif (camera.width, camera.height) != size:
            raise ValueError(
                f"{where}: camera {image.camera_id} is {camera.width}x{camera.height} but the first image's is "
                f"{size[0]}x{size[1]}; all images must share one size"
            )
        intrinsics.append(_colmap_intrinsics(camera, f"{cameras_file}: camera {image.camera_id}"))
        quat = torch.tensor(image.quat, dtype=torch.float64)
        if not torch.isfinite(quat).all() or quat.norm() < 1e-12:
            raise ValueError(f"{where}: quaternion QW QX QY QZ must be finite and non-zero, got {image.quat}")
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = quat_to_rotmat(quat)
        pose[:3, 3] = torch.tensor(image.translation, dtype=torch.float64)
        poses.append(pose)
    return _camera_set(
        torch.stack(poses),
        intrinsics,
        size[0],
        size[1],
        _view_names([image.name for image in images], images_file),
        [_image_file(model_dir, image.name) for image in images],
    )


# --------------------------------------------------------------------------- dispatch

def load_cameras(path) -> CameraSet:
    """Cameras from a nerfstudio or COLMAP capture, chosen by layout.

    A ``.json`` file or a folder containing ``transforms.json`` loads with
    :func:`load_nerfstudio` (preferred when a folder holds both); a COLMAP
    model folder, or a folder with one in ``sparse/0`` or ``sparse``, with
    :func:`load_colmap`.
    """
    path = Path(path)
    if path.is_file() and path.suffix.lower() == ".json":
        return load_nerfstudio(path)
    if path.is_dir() and (path / "transforms.json").is_file():
        return load_nerfstudio(path / "transforms.json")
    if path.is_dir() and _find_colmap_model(path) is not None:
        return load_colmap(path)
    raise ValueError(
        f"{path}: not a supported camera source; expected a nerfstudio .json file (e.g. transforms.json), "
        "a folder containing transforms.json, or a COLMAP model folder (cameras.bin + images.bin or "
        "cameras.txt + images.txt, directly or in sparse/0)"
    )


# --------------------------------------------------------------------------- camera paths

def look_at(eye: torch.Tensor, target: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """OpenCV world-to-camera matrices [N, 4, 4] of cameras at ``eye`` [N, 3] looking at ``target`` [3].

    The camera's z axis points at the target and its y axis (down) is as
    close to ``-up`` as possible, so there is no roll about the view axis.
    """
    forward = target - eye
    right = torch.linalg.cross(forward, up.expand_as(forward))
    if (right.norm(dim=-1) <= 1e-9 * forward.norm(dim=-1) * up.norm()).any():
        raise ValueError("look_at: a view direction is zero or parallel to the up vector")
    forward = forward / forward.norm(dim=-1, keepdim=True)
    right = right / right.norm(dim=-1, keepdim=True)
    down = torch.linalg.cross(forward, right)
    pose = eye.new_zeros(eye.shape[0], 4, 4)
    pose[:, :3, :3] = torch.stack([right, down, forward], dim=1)
    pose[:, :3, 3] = -(pose[:, :3, :3] @ eye[..., None])[..., 0]
    pose[:, 3, 3] = 1
    return pose


def _path_camera_set(reference: CameraSet, world_to_cam: torch.Tensor) -> CameraSet:
    """Path views named ``path_0000``... with the single-view ``reference``'s intrinsics and size."""
    count = world_to_cam.shape[0]
    like = reference.world_to_cam
    return CameraSet(
        world_to_cam=world_to_cam.to(dtype=like.dtype, device=like.device),
        intrinsics=reference.intrinsics.expand(count, 3, 3).clone(),
        width=reference.width,
        height=reference.height,
        names=[f"path_{i:04d}" for i in range(count)],
    )


def _closest_point_to_axes(centers: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Least-squares point [3] nearest to the lines ``centers + s * directions`` ([C, 3], unit directions)."""
    projectors = torch.eye(3, dtype=centers.dtype) - directions[:, :, None] * directions[:, None, :]
    system = projectors.sum(0)
    eigenvalues = torch.linalg.eigvalsh(system)
    if eigenvalues[0] <= 1e-6 * eigenvalues[-1]:
        raise ValueError("orbit_path: the camera optical axes are (nearly) parallel, so have no centre; pass center=")
    return torch.linalg.solve(system, (projectors @ centers[..., None]).sum(0))[:, 0]


def _vector3(value, name: str) -> torch.Tensor:
    vector = torch.as_tensor(value, dtype=torch.float64).cpu()
    if tuple(vector.shape) != (3,) or not torch.isfinite(vector).all():
        raise ValueError(f"orbit_path: {name} must be 3 finite numbers, got {value!r}")
    return vector


def orbit_path(
    cameras: CameraSet, num_frames: int = 120, *, center=None, radius=None, height=None, up=None
) -> CameraSet:
    """``num_frames`` views on a horizontal circle around the scene, all looking at its centre.

    ``up`` (world vector) defaults to the mean of the cameras' up directions
    (their -y axes); ``center`` to the point nearest to all optical axes
    (least squares). The circle lies ``height`` above the centre along
    ``up`` with radius ``radius`` (world units), by default the cameras' mean
    elevation and mean horizontal distance. It starts at the first camera's
    azimuth and turns counter-clockwise about ``up``; frames are evenly spaced
    and do not repeat the start. Views are roll-free and use the first
    camera's intrinsics and image size.
    """
    if int(num_frames) != num_frames or num_frames < 1:
        raise ValueError(f"orbit_path: num_frames must be a positive integer, got {num_frames!r}")
    world_to_cam = cameras.world_to_cam.detach().cpu().to(torch.float64)
    rot = world_to_cam[:, :3, :3]
    centers = -(rot.transpose(1, 2) @ world_to_cam[:, :3, 3:])[..., 0]
    up = -rot[:, 1, :].mean(0) if up is None else _vector3(up, "up")
    if up.norm() < 1e-9:
        raise ValueError("orbit_path: the up direction is zero (the cameras' up vectors cancel out); pass up=")
    up = up / up.norm()
    center = _closest_point_to_axes(centers, rot[:, 2, :]) if center is None else _vector3(center, "center")

    offsets = centers - center
    elevations = offsets @ up
    horizontal = offsets - elevations[:, None] * up
    height = elevations.mean().item() if height is None else float(height)
    radius = horizontal.norm(dim=-1).mean().item() if radius is None else float(radius)
    if not (radius > 0 and math.isfinite(radius) and math.isfinite(height)):
        raise ValueError(f"orbit_path: radius must be positive and height finite, got radius={radius}, height={height}")

    start = horizontal[0]
    if start.norm() < 1e-9 * (1 + offsets[0].norm()):  # first camera straight above the centre
        start = torch.linalg.cross(up, torch.eye(3, dtype=torch.float64)[up.abs().argmin()])
    start = start / start.norm()
    side = torch.linalg.cross(up, start)
    angles = torch.arange(int(num_frames), dtype=torch.float64) * (2 * math.pi / num_frames)
    eyes = center + height * up + radius * (torch.cos(angles)[:, None] * start + torch.sin(angles)[:, None] * side)
    return _path_camera_set(cameras.subset([0]), look_at(eyes, center, up))


def _catmull_rom(points: torch.Tensor, steps: int, loop: bool) -> torch.Tensor:
    """Uniform Catmull-Rom spline through ``points`` [K, 3], ``steps`` samples per segment starting at each key."""
    count = points.shape[0]
    if loop:
        tangents = (points.roll(-1, 0) - points.roll(1, 0)) / 2
    else:
        padded = torch.cat([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
        tangents = (padded[2:] - padded[:-2]) / 2
    t = (torch.arange(steps, dtype=points.dtype) / steps)[:, None]
    h00, h10, h01, h11 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t, -2 * t**3 + 3 * t**2, t**3 - t**2
    segments = []
    for i in range(count if loop else count - 1):
        j = (i + 1) % count
        segments.append(h00 * points[i] + h10 * tangents[i] + h01 * points[j] + h11 * tangents[j])
    return torch.cat(segments)


def interpolate_path(
    cameras: CameraSet, view_indices, frames_per_segment: int = 30, *, loop: bool = False
) -> CameraSet:
    """A smooth path through the capture views ``view_indices`` (at least two), in that order.

    Camera centres follow a uniform Catmull-Rom spline and rotations a
    quaternion slerp (constant angular speed within a segment). Frame
    ``k * frames_per_segment`` is exactly key view k. An open path ends on the
    last key view ((K-1) * frames_per_segment + 1 frames); with ``loop`` it
    returns towards the first (K * frames_per_segment frames, the first not
    repeated). Views use the first key view's intrinsics and image size.
    """
    indices = [int(i) for i in view_indices]
    if len(indices) < 2:
        raise ValueError(f"interpolate_path: need at least 2 view indices, got {len(indices)}")
    if int(frames_per_segment) != frames_per_segment or frames_per_segment < 1:
        raise ValueError(f"interpolate_path: frames_per_segment must be a positive integer, got {frames_per_segment!r}")
    steps = int(frames_per_segment)
    keys = cameras.subset(indices)
    world_to_cam = keys.world_to_cam.detach().cpu().to(torch.float64)
    rot = world_to_cam[:, :3, :3]
    centers = -(rot.transpose(1, 2) @ world_to_cam[:, :3, 3:])[..., 0]
    quats = rotmat_to_quat(rot)

    count = len(indices)
    t = torch.arange(steps, dtype=torch.float64) / steps
    segment_quats = [_slerp(quats[i], quats[(i + 1) % count], t) for i in range(count if loop else count - 1)]
    path_quats = torch.cat(segment_quats)
    path_centers = _catmull_rom(centers, steps, loop)
    if not loop:  # close the open path on the last key view
        path_quats = torch.cat([path_quats, quats[-1:]])
        path_centers = torch.cat([path_centers, centers[-1:]])

    path_rot = quat_to_rotmat(path_quats)
    pose = torch.zeros(path_rot.shape[0], 4, 4, dtype=torch.float64)
    pose[:, :3, :3] = path_rot
    pose[:, :3, 3] = -(path_rot @ path_centers[..., None])[..., 0]
    pose[:, 3, 3] = 1
    return _path_camera_set(keys.subset([0]), pose)
