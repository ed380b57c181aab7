"""What the capture loaders (nerfstudio, COLMAP) share: text reading, bounds on values, view names,
pinhole matrices, the note on the lens distortion they ignore, the finished camera set."""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import torch

from ..counted import counted
from ..notes import NoteFn, tell
from .camera_set import CameraSet

# Bytes a camera text file (transforms.json, COLMAP cameras.txt / images.txt) may have, checked before it
# is read: a transforms.json of a million frames takes about 120 MB.
MAX_CAMERA_TEXT_BYTES = 512 * 2**20
# Magnitude an intrinsic (focal length, principal point; pixels) or a camera position may have: beyond
# it no view renders (its squares overflow float32 in the projection), whatever the scene's units.
MAX_CAMERA_VALUE = 1e9

# Camera models (nerfstudio's ``camera_model`` / COLMAP's) that are pinhole
# cameras once their distortion is ignored.
PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def check_text_size(path: Path) -> None:
    """ValueError naming ``path`` when it is larger than :data:`MAX_CAMERA_TEXT_BYTES`, before it is read."""
    try:
        size = path.stat().st_size
    except OSError as error:
        raise ValueError(f"{path}: cannot read the file ({error.strerror or error})") from None
    if size > MAX_CAMERA_TEXT_BYTES:
        raise ValueError(f"{path}: {size:,} bytes, more than the {MAX_CAMERA_TEXT_BYTES:,} a camera file may have "
                         "(a million views take about 120 MB); not read")


def read_text(path: Path) -> str:
    """A UTF-8 text file's contents; a missing, unreadable, non-UTF-8 or oversized
    (:func:`check_text_size`) file is a ValueError naming it."""
    check_text_size(path)
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not UTF-8 text (at byte offset {error.start}); save it as UTF-8") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot read the file ({error.strerror or error})") from None


def _stem(file: str) -> str:
    """``Path(file).stem`` without making a Path for common names (a million of them load in seconds)."""
    return Path(file).stem if file.endswith(("/", ".")) else os.path.splitext(os.path.basename(file))[0]


def view_names(files: list[str], source: Path) -> list[str]:
    """Unique view names for image files (relative paths): each file's stem, or, where stems
    repeat (``a/0001.jpg``, ``b/0001.jpg``), the path without its suffix joined by ``_``
    (``a_0001``, ``b_0001``). Names that still repeat are a ValueError naming them."""
    stems = [_stem(f) for f in files]
    stem_counts = Counter(stems)
    names = ["_".join(p for p in Path(f.replace("\\", "/")).with_suffix("").parts if p not in (".", "..", "/"))
             if stem_counts[s] > 1 else s for f, s in zip(files, stems)]
    name_counts = Counter(names)
    clashes = sorted({f"{i}" for i, n in enumerate(names) if name_counts[n] > 1}, key=int)
    if clashes:
        raise ValueError(f"{source}: views {', '.join(clashes[:6])} (in load order) have image files that give "
                         "them one name; views are named after their image files (renders are saved as NAME.png), "
                         "so each must be distinct")
    return names


def check_distinct_images(files: list[str], field: Callable[[int], str], source: Path, folder: str = "") -> None:
    """ValueError naming ``source``, the fields ``field(i)`` and ``field(j)`` and the image when views ``i < j``
    name one image: ``files`` are their image paths, relative to ``folder`` or absolute, compared joined to it
    with ``.`` and ``..`` folded (``images/a.png`` is ``./images/a.png``) and nothing read from the disk. A view
    is one image seen from one pose: a second pose for it contradicts the first."""
    first = {}
    for index, file in enumerate(files):
        image = os.path.normpath(os.path.join(folder, file))
        earlier = first.setdefault(image, index)
        if earlier != index:
            raise ValueError(f"{source}: {field(earlier)} and {field(index)} both name the image {image}; "
                             "an image is one view, seen from one pose: list it once")


def pinhole_matrix(fx: float, fy: float, cx: float, cy: float) -> list[list[float]]:
    """K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels) as nested lists."""
    return [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]


# Lens distortion coefficients, as nerfstudio names them (OpenCV's model: k1..k4 radial, p1, p2 tangential); a COLMAP
# model's are a part of them. The loaders ignore them (pinhole cameras) and say so (:func:`tell_distortion`).
DISTORTION_NAMES = ("k1", "k2", "k3", "k4", "p1", "p2")
TOLD_SHIFT_PX = 1.0  # a lens that moves no image corner by this many pixels goes untold: no render would show it


def corner_shift(intrinsics: torch.Tensor, width: int, height: int, coefficients: torch.Tensor) -> torch.Tensor:
    """[C] float64: how many pixels the lens distortion ``coefficients`` [C, 6] (:data:`DISTORTION_NAMES`) move the
    farthest of the four image corners of each view of ``intrinsics`` [C, 3, 3] and size ``width`` x ``height``:
    OpenCV's model, x' = x (1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸) + 2 p1 x y + p2 (r² + 2 x²) (y' alike) on the
    normalised coordinates x = (u - cx) / fx, y = (v - cy) / fy."""
    k = intrinsics.to(torch.float64)
    focal = torch.stack([k[:, 0, 0], k[:, 1, 1]], -1)[:, None]  # [C, 1, 2]
    centre = torch.stack([k[:, 0, 2], k[:, 1, 2]], -1)[:, None]
    corners = torch.tensor([[0, 0], [width, 0], [0, height], [width, height]], dtype=torch.float64)
    x, y = ((corners - centre) / focal).unbind(-1)  # [C, 4] each
    r2 = x * x + y * y
    k1, k2, k3, k4, p1, p2 = coefficients.to(torch.float64)[:, :, None].unbind(1)  # [C, 1] each
    radial = k1 * r2 + k2 * r2**2 + k3 * r2**3 + k4 * r2**4
    dx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    dy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return (torch.stack([dx, dy], -1) * focal).norm(dim=-1).amax(1)


def tell_distortion(notes: NoteFn | None, source: Path, intrinsics: torch.Tensor, width: int, height: int,
                    coefficients: torch.Tensor) -> None:
    """Tell ``notes`` (:func:`~artnvg_core.notes.tell`), once, that the lens distortion ``coefficients`` [C, 6]
    (:data:`DISTORTION_NAMES`, 0 where the file ``source`` gives none) of views of ``intrinsics`` [C, 3, 3] and size
    ``width`` x ``height`` are ignored, when they move an image corner by :data:`TOLD_SHIFT_PX` or more
    (:func:`corner_shift`; a phone's or a DSLR's capture, fitted by COLMAP, moves them by less than a pixel): which,
    in how many views, what that means and how many pixels at most. Nothing otherwise."""
    distorted = coefficients != 0
    if not distorted.any():
        return
    shift = corner_shift(intrinsics, width, height, coefficients).max().item()
    if shift < TOLD_SHIFT_PX:
        return
    names = ", ".join(name for name, given in zip(DISTORTION_NAMES, distorted.any(0).tolist()) if given)
    views = int(distorted.any(1).sum())
    tell(notes, source, f"lens distortion ignored ({names} non-zero in {views:,} of {counted(len(coefficients), 'view')}):"
                        f" the views are rendered as pinhole cameras, as undistorted images; photos taken through the "
                        f"lens differ from them by up to {shift:.1f} px towards the image corners")


def check_camera_value(value: float, where: str) -> float:
    """``value`` when finite and within :data:`MAX_CAMERA_VALUE`; else a ValueError naming ``where``."""
    if not abs(value) <= MAX_CAMERA_VALUE:
        raise ValueError(f"{where}: expected a finite number within +-{MAX_CAMERA_VALUE:g}, got {value:g}")
    return value


def loaded_camera_set(world_to_cam: torch.Tensor, intrinsics, width: int, height: int, names, image_paths,
                      view: Callable[[int], str]) -> CameraSet:
    """A loader's float32 CPU CameraSet from float64 poses and intrinsics. ``view(index)`` says where a view
    comes from (e.g. "transforms.json: frame 3"); a view whose values are not finite in float32 is a
    ValueError naming it and the field."""
    world_to_cam = world_to_cam.to(torch.float32)
    intrinsics = torch.as_tensor(intrinsics, dtype=torch.float64).reshape(-1, 3, 3).to(torch.float32)
    for field, values in (("pose", world_to_cam), ("intrinsics", intrinsics)):
        bad = (~torch.isfinite(values.flatten(1))).any(1).nonzero()
        if len(bad):
            raise ValueError(f"{view(int(bad[0, 0]))}: {field}: values beyond float32's range (not finite once converted)")
    return CameraSet(
        world_to_cam=world_to_cam,
        intrinsics=intrinsics,
        width=width,
        height=height,
        names=list(names),
        image_paths=list(image_paths),
    )

