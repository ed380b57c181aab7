"""Cameras: OpenCV world-to-camera poses plus pinhole intrinsics, loaded, made or moved along paths.

Conventions (docs/design.md): OpenCV camera axes (x right, y down, z forward),
``world_to_cam`` [C, 4, 4] maps world points to camera coordinates,
``intrinsics`` [C, 3, 3] = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels
with pixel centres at +0.5 (the top-left pixel's centre is (0.5, 0.5)).
All views of a set share one ``width`` x ``height`` in pixels.
Other conventions (nerfstudio OpenGL camera-to-world, COLMAP) are converted
at load time, in their loader's module only.

Modules: :mod:`.camera_set` (:class:`CameraSet`), :mod:`.geometry` (quaternions
in w x y z order, rigid poses, :func:`look_at`), the loaders :mod:`.nerfstudio`
and :mod:`.colmap` (with :func:`load_cameras` here choosing between them),
:mod:`.paths` (:func:`orbit_path`, :func:`interpolate_path`) and :mod:`.framing`
(:func:`scene_frame`: where a scene is and which way is up; the views built around a
scene without cameras are :mod:`artnvg_core.orbit`'s). Loaders return float32 CPU
tensors; all pose maths runs in float64. Lens distortion is ignored everywhere:
these are pinhole cameras (a loader tells its ``notes`` when a file's coefficients are not zero).
"""

from __future__ import annotations

from pathlib import Path

from ..notes import NoteFn
from .camera_set import MAX_IMAGE_SIDE, CameraSet
from .colmap import find_colmap_model, load_colmap
from .geometry import look_at, normalize_quats, quat_to_rotmat, rotmat_to_quat
from .framing import UP_AXES, SceneFrame, parse_up, scene_frame
from .nerfstudio import load_nerfstudio
from .paths import NoOrbit, interpolate_path, orbit_path

__all__ = [
    "MAX_IMAGE_SIDE", "UP_AXES", "CameraSet", "camera_files", "SceneFrame", "interpolate_path", "load_cameras", "load_colmap",
    "load_nerfstudio", "look_at", "normalize_quats", "NoOrbit", "orbit_path", "parse_up", "quat_to_rotmat",
    "rotmat_to_quat", "scene_frame",
]


def camera_files(path) -> list[Path]:
    """The files :func:`load_cameras` reads for ``path``: a ``.json`` file itself, a folder's
    ``transforms.json`` (preferred when a folder holds both), or the ``cameras`` and ``images`` files of
    the COLMAP model in the folder, its ``sparse/0``, ``sparse`` or ``0``. A ValueError naming ``path`` otherwise."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{path}: camera file or folder not found")
    if path.is_file() and path.suffix.lower() == ".json":
        return [path]
    if path.is_dir() and (path / "transforms.json").is_file():
        return [path / "transforms.json"]
    model = find_colmap_model(path) if path.is_dir() else None
    if model is not None:
        folder, ext = model
        return [folder / f"cameras{ext}", folder / f"images{ext}"]
    raise ValueError(
        f"{path}: not a supported camera source; expected a nerfstudio .json file (e.g. transforms.json), "
        "a folder containing transforms.json, or a COLMAP model folder (cameras.bin + images.bin or "
        "cameras.txt + images.txt, directly or in sparse/0 or 0)"
    )


def load_cameras(path, *, notes: NoteFn | None = None) -> CameraSet:
    """Cameras from a nerfstudio or COLMAP capture, chosen by layout (:func:`camera_files`):
    :func:`load_nerfstudio` of a ``.json`` file or a folder's ``transforms.json``, else
    :func:`load_colmap` of the COLMAP model folder; ``notes`` is told of the lens distortion they ignore."""
    files = camera_files(path)
    if files[0].suffix.lower() == ".json":
        return load_nerfstudio(files[0], notes=notes)
    return load_colmap(files[0].parent, notes=notes)
