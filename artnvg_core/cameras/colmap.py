"""COLMAP sparse models (``cameras`` + ``images``, binary or text): already OpenCV world-to-camera."""

from __future__ import annotations

import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import torch

from ..counted import counted
from ..notes import NoteFn
from .camera_set import MAX_IMAGE_SIDE, CameraSet
from .common import (
    PERSPECTIVE_MODELS,
    check_camera_value,
    check_distinct_images,
    check_text_size,
    loaded_camera_set,
    pinhole_matrix,
    tell_distortion,
    view_names,
)
from .geometry import quat_to_rotmat

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


MAX_VIEWS = 1_000_000  # images (and cameras) a binary model may declare
_MAX_NAME_BYTES = 4096  # an image name (a relative path) in images.bin
_MAX_LINE_CHARS = 64 * 2**20  # a line of cameras.txt / images.txt (a 2D-points line of a million points fits)


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
    record: int = 0  # its position in the file (errors name it, not its name)
    image_id: int = 0


def _check_new_id(places: dict[int, str], path: Path, what: str, id_: int, place: str) -> None:
    """Keep ``place`` (e.g. "line 7") in ``places`` as where ``what`` ``id_`` (e.g. "image id" 3) is given; a
    ValueError naming the file, the id and both places when it was given before (which the reader would
    otherwise keep one of, silently)."""
    earlier = places.setdefault(id_, place)
    if earlier != place:
        raise ValueError(f"{path}: {what} {id_} is given twice, at {earlier} and at {place}; give each its own id")


def find_colmap_model(folder: Path) -> tuple[Path, str] | None:
    """(model folder, '.bin' or '.txt') of the COLMAP model in ``folder``, ``folder/sparse/0``, ``folder/sparse``
    or ``folder/0`` (``folder`` is a ``sparse`` folder of numbered models, of which COLMAP's first is ``0``)."""
    for candidate in (folder, folder / "sparse" / "0", folder / "sparse", folder / "0"):
        for ext in (".bin", ".txt"):
            if (candidate / f"cameras{ext}").is_file() and (candidate / f"images{ext}").is_file():
                return candidate, ext
    return None


class _BinaryReader:
    """Little-endian reads from a binary model file, a context manager (the file is open inside it). Skipped
    bytes are never read: an images.bin of many 2D points costs what its image records do. Truncation
    raises ValueError naming the file."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.stream = open(path, "rb")
        except OSError as error:
            raise ValueError(f"{path}: cannot read the file ({error.strerror or error})") from None
        self.size = os.fstat(self.stream.fileno()).st_size

    def __enter__(self) -> "_BinaryReader":
        return self

    def __exit__(self, *exception) -> None:
        self.stream.close()

    @property
    def left(self) -> int:
        return self.size - self.stream.tell()

    def records(self, count: int, smallest: int, what: str) -> range:
        """``range(count)`` for ``count`` records of at least ``smallest`` bytes each; a ValueError, before any
        is read, when the bytes left cannot hold them or they are more than :data:`MAX_VIEWS`."""
        if count > MAX_VIEWS or count * smallest > self.left:
            raise ValueError(f"{self.path}: the header says {counted(count, what)}; the file has "
                             f"{counted(self.left, 'byte')} left, room for at most {self.left // smallest:,}, and a "
                             f"model may have {MAX_VIEWS:,}")
        return range(count)

    def end(self, count: int, what: str) -> None:
        """ValueError unless every byte was read: the header's count of ``what`` covers every record."""
        if self.left:
            raise ValueError(f"{self.path}: the header says {counted(count, what)}, but the file has "
                             f"{counted(self.left, 'byte')} more after the last of them (the count is wrong or the "
                             "file is corrupt)")

    def _truncated(self, what: str, at: int) -> ValueError:
        return ValueError(f"{self.path}: file ends inside {what} at byte {at} (truncated?)")

    def unpack(self, fmt: str, what: str) -> tuple:
        size, at = struct.calcsize("<" + fmt), self.stream.tell()
        data = self.stream.read(size)
        if len(data) < size:
            raise self._truncated(what, at)
        return struct.unpack("<" + fmt, data)

    def skip(self, size: int, what: str) -> None:
        if size > self.left:
            raise self._truncated(what, self.stream.tell())
        self.stream.seek(size, os.SEEK_CUR)

    def c_string(self, what: str) -> str:
        at = self.stream.tell()
        chunk = self.stream.read(_MAX_NAME_BYTES + 1)
        end = chunk.find(b"\0")
        if end < 0:
            if len(chunk) <= _MAX_NAME_BYTES:
                raise self._truncated(what, at)
            raise ValueError(f"{self.path}: {what} at byte {at}: longer than {_MAX_NAME_BYTES} bytes (corrupt?)")
        self.stream.seek(at + end + 1)
        try:
            return chunk[:end].decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"{self.path}: {what} (at byte {at}) is not UTF-8") from None


def _read_cameras_bin(path: Path) -> dict[int, _ColmapCamera]:
    with _BinaryReader(path) as reader:
        (count,) = reader.unpack("Q", "the camera count")
        cameras, places = {}, {}
        for index in reader.records(count, struct.calcsize("<IiQQ") + 3 * 8, "camera"):
            camera_id, model_id, width, height = reader.unpack("IiQQ", f"camera {index}")
            _check_new_id(places, path, "camera id", camera_id, f"camera record {index}")
            if model_id not in _COLMAP_MODELS:
                raise ValueError(f"{path}: camera {camera_id}: unknown camera model id {model_id}")
            model, num_params = _COLMAP_MODELS[model_id]
            params = reader.unpack(f"{num_params}d", f"the parameters of camera {camera_id}")
            cameras[camera_id] = _ColmapCamera(model, width, height, params)
        reader.end(count, "camera")
        return cameras


def _read_images_bin(path: Path) -> list[_ColmapImage]:
    with _BinaryReader(path) as reader:
        (count,) = reader.unpack("Q", "the image count")
        images, places = [], {}
        for index in reader.records(count, struct.calcsize("<I7dI") + 1 + 8, "image"):
            image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.unpack("I7dI", f"image {index}")
            _check_new_id(places, path, "image id", image_id, f"image record {index}")
            name = reader.c_string(f"the name of image {image_id}")
            (num_points,) = reader.unpack("Q", f"the 2D point count of image {image_id}")
            reader.skip(num_points * struct.calcsize("<ddq"), f"the 2D points of image {image_id}")
            images.append(_ColmapImage((qw, qx, qy, qz), (tx, ty, tz), camera_id, name, index, image_id))
        reader.end(count, "image")
        return images


def _text_records(path: Path) -> list[tuple[int, str]]:
    """(line number, line) of a COLMAP text file, comments dropped, blank lines kept; a file over
    :data:`~.common.MAX_CAMERA_TEXT_BYTES`, a line over :data:`_MAX_LINE_CHARS` or text that is not UTF-8
    is a ValueError naming the file (and the line)."""
    check_text_size(path)
    records = []
    try:
        with open(path, encoding="utf-8", newline=None) as text:
            for number, line in enumerate(iter(lambda: text.readline(_MAX_LINE_CHARS + 1), ""), 1):
                if len(line) > _MAX_LINE_CHARS:
                    raise ValueError(f"{path}: line {number}: longer than {_MAX_LINE_CHARS:,} characters")
                if not line.startswith("#"):
                    records.append((number, line.strip()))
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not UTF-8 text; save it as UTF-8") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot read the file ({error.strerror or error})") from None
    return records


def _text_line_error(path: Path, number: int, expected: str, line: str) -> ValueError:
    """The error of a line that is not what ``expected`` says (it tells how many fields it has, never what they say)."""
    return ValueError(f"{path}: line {number}: expected {expected}, got a line of "
                      f"{counted(len(line.split()), 'field')}")


def _read_cameras_txt(path: Path) -> dict[int, _ColmapCamera]:
    expected = "CAMERA_ID MODEL WIDTH HEIGHT PARAMS..."
    cameras, places = {}, {}
    for number, line in _text_records(path):
        if not line:
            continue
        fields = line.split()
        if len(fields) < 4 or fields[1] not in _COLMAP_PARAM_COUNTS:
            if len(fields) >= 4:
                raise ValueError(f"{path}: line {number}: unknown camera model (expected one of "
                                 f"{', '.join(_COLMAP_PARAM_COUNTS)})")
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
        _check_new_id(places, path, "camera id", camera_id, f"line {number}")
        cameras[camera_id] = _ColmapCamera(model, width, height, params)
    return cameras


def _image_line(line: str) -> _ColmapImage | None:
    """The record of an images.txt image line ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``, else None."""
    fields = line.split(maxsplit=9)
    if len(fields) != 10:
        return None
    try:
        image_id = int(fields[0])
        numbers = [float(f) for f in fields[1:8]]
        camera_id = int(fields[8])
    except ValueError:
        return None
    return _ColmapImage(tuple(numbers[:4]), tuple(numbers[4:]), camera_id, fields[9], image_id=image_id)


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
    images, places = [], {}
    index = 0
    while index < len(records):
        number, line = records[index]
        index += 1
        if not line:  # stray blank line between records or at the end
            continue
        image = _image_line(line)
        if image is None:
            raise _text_line_error(path, number, expected, line)
        _check_new_id(places, path, "image id", image.image_id, f"line {number}")
        image.record = len(images)
        images.append(image)
        if index < len(records) and (not records[index][1] or _is_points_line(records[index][1])):
            index += 1  # its 2D points
        elif index < len(records) and _image_line(records[index][1]) is None:
            number, line = records[index]
            raise _text_line_error(path, number, "the 2D points (X Y POINT3D_ID ...) of the image line before", line)
    return images


def _colmap_intrinsics(camera: _ColmapCamera, where: str) -> list[list[float]]:
    if camera.model not in PERSPECTIVE_MODELS:
        raise ValueError(
            f"{where}: camera model {camera.model} is not supported; expected one of {', '.join(PERSPECTIVE_MODELS)}"
        )
    if not (0 < camera.width <= MAX_IMAGE_SIDE and 0 < camera.height <= MAX_IMAGE_SIDE):
        raise ValueError(f"{where}: image size {camera.width}x{camera.height}: expected 1 to {MAX_IMAGE_SIDE} pixels a side")
    p = camera.params
    fx, fy, cx, cy = (p[0], p[0], p[1], p[2]) if camera.model in _SINGLE_FOCAL_MODELS else p[:4]
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise ValueError(f"{where}: focal lengths must be finite and positive and the principal point finite, "
                         f"got fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    for name, value in zip(("fx", "fy", "cx", "cy"), (fx, fy, cx, cy)):
        check_camera_value(value, f"{where}: {name}")
    return pinhole_matrix(fx, fy, cx, cy)


def _colmap_distortion(camera: _ColmapCamera) -> list[float]:
    """The camera's distortion parameters as :data:`~.common.DISTORTION_NAMES` (k1..k4, p1, p2): SIMPLE_RADIAL's k
    is k1, RADIAL's k1 k2, OPENCV's k1 k2 p1 p2; none for the pinhole models."""
    rest = camera.params[3:] if camera.model in _SINGLE_FOCAL_MODELS else camera.params[4:]
    radial, tangential = (rest[:2], rest[2:4]) if camera.model == "OPENCV" else (rest, ())
    return [*radial, *[0.0] * (4 - len(radial)), *tangential, *[0.0] * (2 - len(tangential))]


def _image_file(model_dir: Path, name: str) -> Path | None:
    """The image ``name`` in an ``images`` folder one or two levels above the model, else None (also for a name
    the file system refuses, e.g. one too long: ``os.path.isfile`` says False where ``Path.is_file`` raised)."""
    for images_dir in (model_dir.parent / "images", model_dir.parent.parent / "images"):
        if os.path.isfile(images_dir / name):
            return images_dir / name
    return None


def load_colmap(path, *, notes: NoteFn | None = None) -> CameraSet:
    """Cameras of a COLMAP sparse model, sorted by image name.

    ``path`` is the model folder (``cameras`` + ``images`` as ``.bin`` or
    ``.txt``; binary preferred when both exist) or a folder holding it as
    ``sparse/0``, ``sparse`` or ``0``. Supported camera models: SIMPLE_PINHOLE,
    PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, their radial/tangential
    distortion ignored: when any is non-zero, ``notes`` is told so once
    (:func:`~.common.tell_distortion`; logged without). COLMAP poses are already OpenCV world-to-camera.
    ``names`` are the image name stems; COLMAP does not store the image
    folder, so ``image_paths`` are set only where the file exists in an
    ``images/`` folder one or two levels above the model folder (else None).

    Raises ValueError for a missing model, malformed or truncated files,
    unsupported models, unknown or repeated camera or image ids, an image named
    twice (:func:`~.common.check_distinct_images`), or mixed image sizes.
    """
    path = Path(path)
    found = find_colmap_model(path)
    if found is None:
        raise ValueError(
            f"{path}: no COLMAP model found; expected cameras.bin + images.bin or cameras.txt + images.txt "
            "in this folder or in its sparse/0, sparse or 0 subfolder"
        )
    model_dir, ext = found
    cameras_file, images_file = model_dir / f"cameras{ext}", model_dir / f"images{ext}"
    if ext == ".bin":
        cameras, images = _read_cameras_bin(cameras_file), _read_images_bin(images_file)
    else:
        cameras, images = _read_cameras_txt(cameras_file), _read_images_txt(images_file)
    if not images:
        raise ValueError(f"{images_file}: the model has no registered images")
    check_distinct_images([image.name for image in images], lambda index: f"image record {index}'s NAME", images_file)

    images.sort(key=lambda image: image.name)
    poses, intrinsics, distortion = [], [], []
    size = None
    for image in images:
        where = f"{images_file}: image record {image.record}"
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
        distortion.append(_colmap_distortion(camera))
        quat = torch.tensor(image.quat, dtype=torch.float64)
        if not torch.isfinite(quat).all() or quat.norm() < 1e-12:
            raise ValueError(f"{where}: quaternion QW QX QY QZ must be finite and non-zero, got {image.quat}")
        pose = torch.eye(4, dtype=torch.float64)
        pose[:3, :3] = quat_to_rotmat(quat)
        pose[:3, 3] = torch.tensor([check_camera_value(t, f"{where}: T{axis}")
                                    for t, axis in zip(image.translation, "XYZ")], dtype=torch.float64)
        poses.append(pose)
    cameras = loaded_camera_set(
        torch.stack(poses),
        intrinsics,
        size[0],
        size[1],
        view_names([image.name for image in images], images_file),
        [_image_file(model_dir, image.name) for image in images],
        lambda index: f"{images_file}: image record {images[index].record}",
    )
    tell_distortion(notes, cameras_file, torch.tensor(intrinsics, dtype=torch.float64), size[0], size[1],
                    torch.tensor(distortion, dtype=torch.float64))
    return cameras

