"""What the capture loaders (nerfstudio, COLMAP) share: text reading, view names, pinhole matrices."""

from __future__ import annotations

from pathlib import Path

import torch

from .camera_set import CameraSet

# Camera models (nerfstudio's ``camera_model`` / COLMAP's) that are pinhole
# cameras once their distortion is ignored.
PERSPECTIVE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def read_text(path: Path) -> str:
    """A UTF-8 text file's contents; a missing, unreadable or non-UTF-8 file is a ValueError naming it."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as error:
        raise ValueError(f"{path}: not UTF-8 text (byte {error.object[error.start:error.start + 1]!r} at offset "
                         f"{error.start}); save it as UTF-8") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot read the file ({error.strerror or error})") from None


def view_names(files: list[str], source: Path) -> list[str]:
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


def pinhole_matrix(fx: float, fy: float, cx: float, cy: float) -> list[list[float]]:
    """K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels) as nested lists."""
    return [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]


def loaded_camera_set(world_to_cam: torch.Tensor, intrinsics, width: int, height: int, names, image_paths) -> CameraSet:
    """A loader's float32 CPU CameraSet from float64 poses and intrinsics."""
    return CameraSet(
        world_to_cam=world_to_cam.to(torch.float32),
        intrinsics=torch.as_tensor(intrinsics, dtype=torch.float64).reshape(-1, 3, 3).to(torch.float32),
        width=width,
        height=height,
        names=list(names),
        image_paths=list(image_paths),
    )

