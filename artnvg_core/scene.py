"""Gaussian scenes: the raw stored 3DGS parameters and their file I/O.

Conventions (INRIA 3DGS layout, see DESIGN.md):

- ``means``          [N, 3]  world positions
- ``quats``          [N, 4]  rotation quaternions, w x y z, *unnormalised*
- ``log_scales``     [N, 3]  natural log of the per-axis standard deviations
- ``opacity_logits`` [N]     opacity before the sigmoid
- ``sh``             [N, K, 3] spherical-harmonic coefficients, DC first,
  K = (degree + 1) ** 2; colour = SH(dir) + 0.5, clamped at 0. ``SH_C0`` is
  the degree-0 basis constant.

File I/O: :func:`load_scene` dispatches to :func:`read_ply` (INRIA 3DGS PLY)
and :func:`read_splatfacto_ckpt` (nerfstudio checkpoint); :func:`write_ply`
writes the INRIA layout atomically. Every reader validates with
:func:`validate_scene`: bad input raises ``ValueError`` naming the file and the
field; with ``drop_invalid=True`` invalid Gaussians are dropped instead and
reported as a warning on the ``artnvg_core.scene`` logger.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass, fields
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch
from plyfile import PlyData, PlyListProperty

from .fileio import write_atomically

_log = logging.getLogger(__name__)

SH_C0 = 0.28209479177387814


def sh_degree_for(num_coeffs: int) -> int:
    """SH degree d for K = (d + 1)^2 coefficients per channel (d in 0..3)."""
    for degree in range(4):
        if (degree + 1) ** 2 == num_coeffs:
            return degree
    raise ValueError(f"sh: {num_coeffs} coefficients per channel is not (d+1)^2 for d in 0..3")


@dataclass
class GaussianScene:
    """Raw 3DGS parameters of N Gaussians (shapes in the module docstring)."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor

    def __post_init__(self) -> None:
        n = self.means.shape[0] if self.means.ndim == 2 else -1
        expected = {
            "means": (n, 3),
            "quats": (n, 4),
            "log_scales": (n, 3),
            "opacity_logits": (n,),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if tuple(value.shape) != shape or n < 0:
                raise ValueError(f"GaussianScene.{name}: expected shape {shape}, got {tuple(value.shape)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"GaussianScene.sh: expected shape ({n}, K, 3), got {tuple(self.sh.shape)}")
        sh_degree_for(self.sh.shape[1])

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_for(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    def tensors(self) -> dict[str, torch.Tensor]:
        """The parameters by field name, in declaration order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def map(self, fn) -> "GaussianScene":
        """A new scene with ``fn`` applied to every parameter tensor."""
        return GaussianScene(**{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device=None, dtype=None) -> "GaussianScene":
        return self.map(lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> "GaussianScene":
        return self.map(lambda t: t.detach().clone())

    def select(self, index: torch.Tensor) -> "GaussianScene":
        """Subset by boolean mask or integer index over the N Gaussians."""
        return self.map(lambda t: t[index])


# --------------------------------------------------------------------------- validation


def _invalid_gaussians(scene: GaussianScene) -> list[tuple[str, str, torch.Tensor]]:
    """(field, problem, bad-mask [N]) for every check, in field order."""
    n = len(scene)
    checks = [
        (name, "non-finite values", ~torch.isfinite(value).reshape(n, -1).all(dim=1))
        for name, value in scene.tensors().items()
    ]
    checks.append(("quats", "a zero norm", torch.linalg.vector_norm(scene.quats, dim=1) == 0))
    return checks


def validate_scene(scene: GaussianScene, source: str, *, drop_invalid: bool = False) -> tuple[GaussianScene, int]:
    """Check that every Gaussian is finite in all fields and has a non-zero quaternion.

    Returns ``(scene, dropped)``. Without ``drop_invalid`` the first failing check
    raises ``ValueError`` naming ``source`` (the file), the field, how many
    Gaussians fail and the first failing index, and ``dropped`` is 0. With
    ``drop_invalid`` the failing Gaussians are removed, counted in ``dropped``
    and reported as a warning on the ``artnvg_core.scene`` logger. A scene with
    no (remaining) Gaussians is always an error.
    """
    n = len(scene)
    if n == 0:
        raise ValueError(f"{source}: the scene contains no Gaussians")
    invalid = torch.zeros(n, dtype=torch.bool, device=scene.device)
    reasons = []
    for name, problem, bad in _invalid_gaussians(scene):
        count = int(bad.sum())
        if count == 0:
            continue
        first = int(bad.nonzero()[0, 0])
        if not drop_invalid:
            raise ValueError(
                f"{source}: {name}: {count} of {n} Gaussians have {problem} (first at index {first}); "
                "pass drop_invalid=True to drop invalid Gaussians"
            )
        invalid |= bad
        reasons.append(f"{name}: {count} with {problem}")
    dropped = int(invalid.sum())
    if dropped == n:
        raise ValueError(f"{source}: all {n} Gaussians are invalid ({'; '.join(reasons)})")
    if dropped:
        _log.warning("%s: dropped %d of %d invalid Gaussians (%s)", source, dropped, n, "; ".join(reasons))
        scene = scene.select(~invalid)
    return scene, dropped


def _require_file(path: Path) -> None:
    if not path.is_file():
        raise ValueError(f"{path}: scene file not found")


# --------------------------------------------------------------------------- INRIA PLY

_PLY_ELEMENT = "vertex"
_SH_DEGREE_FOR_REST_COUNT = {3 * ((d + 1) ** 2 - 1): d for d in range(4)}  # 0, 9, 24, 45
_REST_PROPERTY = re.compile(r"f_rest_\d+")


def _ply_layout(num_rest: int) -> dict[str, list[str]]:
    """Property names of each block of the INRIA layout, in file order."""
    return {
        "means": ["x", "y", "z"],
        "normals": ["nx", "ny", "nz"],
        "sh_dc": ["f_dc_0", "f_dc_1", "f_dc_2"],
        "sh_rest": [f"f_rest_{i}" for i in range(num_rest)],
        "opacity_logits": ["opacity"],
        "log_scales": ["scale_0", "scale_1", "scale_2"],
        "quats": ["rot_0", "rot_1", "rot_2", "rot_3"],
    }


def _read_ply_vertices(path: Path) -> tuple[np.ndarray, set[str]]:
    """The 'vertex' element's structured array and the names of its list properties."""
    try:
        with np.errstate(all="ignore"):  # out-of-range text values become inf, rejected by validation
            ply = PlyData.read(str(path))
    except Exception as error:  # plyfile and numpy raise many types on corrupt bytes
        raise ValueError(f"{path}: not a readable PLY file ({type(error).__name__}: {error})") from error
    if _PLY_ELEMENT not in ply:
        names = [element.name for element in ply.elements]
        raise ValueError(f"{path}: no '{_PLY_ELEMENT}' element (found {names}); expected an INRIA 3DGS PLY")
    element = ply[_PLY_ELEMENT]
    return element.data, {p.name for p in element.properties if isinstance(p, PlyListProperty)}


def _ply_columns(path: Path, data: np.ndarray, list_names: set[str], names: list[str]) -> torch.Tensor:
    """The named scalar properties as one float32 tensor [N, len(names)]."""
    available = set(data.dtype.names or ())
    missing = [name for name in names if name not in available]
    if missing:
        noun = "property" if len(missing) == 1 else "properties"
        raise ValueError(f"{path}: element '{_PLY_ELEMENT}' lacks {noun} {', '.join(missing)}")
    lists = [name for name in names if name in list_names]
    if lists:
        raise ValueError(f"{path}: property {lists[0]} is a list; expected a scalar number")
    table = np.empty((len(data), len(names)), dtype=np.float32)
    with np.errstate(over="ignore", invalid="ignore"):  # float64 overflow -> inf, rejected by validation
        for column, name in enumerate(names):
            table[:, column] = data[name]
    return torch.from_numpy(table)


def _sh_rest_count(path: Path, property_names: tuple[str, ...]) -> int:
    count = sum(1 for name in property_names if _REST_PROPERTY.fullmatch(name))
    if count not in _SH_DEGREE_FOR_REST_COUNT:
        raise ValueError(
            f"{path}: f_rest_*: found {count} properties, expected 0, 9, 24 or 45 (SH degree 0 to 3)"
        )
    return count


def read_ply(path: str | os.PathLike, *, drop_invalid: bool = False) -> GaussianScene:
    """Read an INRIA 3DGS PLY (ASCII or binary of either byte order) as float32 tensors.

    Needs properties x y z, f_dc_0..2, f_rest_0..M-1 with M in {0, 9, 24, 45}
    (SH degree 0..3), opacity, scale_0..2 and rot_0..3 (w x y z), in any order;
    normals and other properties are ignored. ``f_rest`` is channel-major:
    ``f_rest[c * (K-1) + j]`` is ``sh[:, 1 + j, c]``. Validated with
    :func:`validate_scene`.
    """
    path = Path(path)
    _require_file(path)
    data, list_names = _read_ply_vertices(path)
    num_rest = _sh_rest_count(path, data.dtype.names or ())
    layout = _ply_layout(num_rest)
    del layout["normals"]
    columns = {key: _ply_columns(path, data, list_names, names) for key, names in layout.items()}
    n, coeffs_per_channel = len(data), num_rest // 3
    sh_rest = columns["sh_rest"].reshape(n, 3, coeffs_per_channel).transpose(1, 2)
    scene = GaussianScene(
        means=columns["means"].contiguous(),
        quats=columns["quats"].contiguous(),
        log_scales=columns["log_scales"].contiguous(),
        opacity_logits=columns["opacity_logits"][:, 0].contiguous(),
        sh=torch.cat([columns["sh_dc"][:, None, :], sh_rest], dim=1).contiguous(),
    )
    return validate_scene(scene, str(path), drop_invalid=drop_invalid)[0]


def _ply_table(scene: GaussianScene) -> tuple[list[str], np.ndarray]:
    """Property names and the float32 table [N, P] of ``scene`` in the INRIA layout (zero normals)."""
    cpu = scene.map(lambda t: t.detach().to("cpu", torch.float32))
    n, k = cpu.sh.shape[:2]
    blocks = {
        "means": cpu.means,
        "normals": torch.zeros(n, 3),
        "sh_dc": cpu.sh[:, 0, :],
        "sh_rest": cpu.sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1)),
        "opacity_logits": cpu.opacity_logits[:, None],
        "log_scales": cpu.log_scales,
        "quats": cpu.quats,
    }
    layout = _ply_layout(3 * (k - 1))
    names = [name for key in blocks for name in layout[key]]
    return names, torch.cat(list(blocks.values()), dim=1).numpy()


def _write_ply_body(stream: BinaryIO, table: np.ndarray, binary: bool) -> None:
    """Rows of ``table`` as little-endian float32, or as text that round-trips float32 exactly."""
    if binary:
        stream.write(table.astype("<f4").tobytes())
    else:
        np.savetxt(stream, table, fmt="%.9g")  # 9 significant digits identify every float32


def write_ply(scene: GaussianScene, path: str | os.PathLike, *, binary: bool = True) -> None:
    """Write ``scene`` as an INRIA 3DGS PLY, float32, atomically.

    Properties x y z nx ny nz (zeros) f_dc_* f_rest_* (channel-major) opacity
    scale_* rot_*; binary little-endian by default, ASCII with ``binary=False``.
    Reading the file back gives bit-identical tensors in either format.
    """
    path = Path(path)
    names, table = _ply_table(scene)
    header = "\n".join([
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        f"element {_PLY_ELEMENT} {len(table)}",
        *(f"property float {name}" for name in names),
        "end_header",
    ]) + "\n"

    def write(stream: BinaryIO) -> None:
        stream.write(header.encode("ascii"))
        _write_ply_body(stream, table, binary)

    write_atomically(path, write)


# --------------------------------------------------------------------------- nerfstudio splatfacto

_SPLATFACTO_PREFIX = "_model.gauss_params."
_SPLATFACTO_REQUIRED = ("means", "scales", "quats", "features_dc", "opacities")


def _splatfacto_params(path: Path) -> dict[str, torch.Tensor]:
    """The ``_model.gauss_params.*`` tensors of a checkpoint, by short name, as float32."""
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch.load raises many types on corrupt or foreign files
        raise ValueError(f"{path}: not a loadable torch checkpoint ({type(error).__name__}: {error})") from error
    pipeline = checkpoint.get("pipeline") if isinstance(checkpoint, dict) else None
    if not isinstance(pipeline, dict):
        raise ValueError(f"{path}: expected a nerfstudio checkpoint, a dict with a 'pipeline' state dict")
    params = {
        key.removeprefix(_SPLATFACTO_PREFIX): value
        for key, value in pipeline.items()
        if isinstance(key, str) and key.startswith(_SPLATFACTO_PREFIX) and isinstance(value, torch.Tensor)
    }
    missing = [_SPLATFACTO_PREFIX + name for name in _SPLATFACTO_REQUIRED if name not in params]
    if missing:
        raise ValueError(f"{path}: not a splatfacto checkpoint, pipeline lacks tensors {', '.join(missing)}")
    return {name: value.detach().to(torch.float32) for name, value in params.items()}


def _expect_shape(path: Path, name: str, value: torch.Tensor, shape: tuple[int, ...]) -> None:
    if tuple(value.shape) != shape:
        raise ValueError(f"{path}: {_SPLATFACTO_PREFIX}{name}: expected shape {shape}, got {tuple(value.shape)}")


def read_splatfacto_ckpt(path: str | os.PathLike, *, drop_invalid: bool = False) -> GaussianScene:
    """Read the Gaussians of a nerfstudio splatfacto ``.ckpt`` (loaded with ``weights_only=True``).

    Uses ``pipeline["_model.gauss_params.*"]``: means [N, 3], scales [N, 3] (log),
    quats [N, 4] (w x y z), opacities [N, 1] (logits), features_dc [N, 3] and
    features_rest [N, K-1, 3]. At SH degree 0 (features_rest empty or absent)
    splatfacto renders colour = sigmoid(features_dc), which is converted to the
    SH DC coefficient (sigmoid(f) - 0.5) / SH_C0. Validated with :func:`validate_scene`.
    """
    path = Path(path)
    _require_file(path)
    params = _splatfacto_params(path)
    n = params["means"].shape[0] if params["means"].ndim == 2 else -1
    shapes = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "features_dc": (n, 3), "opacities": (n, 1)}
    for name, shape in shapes.items():
        _expect_shape(path, name, params[name], shape)
    rest = params.get("features_rest", torch.zeros(n, 0, 3))
    if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3 or rest.shape[1] + 1 not in (1, 4, 9, 16):
        raise ValueError(
            f"{path}: {_SPLATFACTO_PREFIX}features_rest: expected shape ({n}, K-1, 3) with K-1 in "
            f"0, 3, 8, 15 (SH degree 0 to 3), got {tuple(rest.shape)}"
        )
    dc = params["features_dc"]
    if rest.shape[1] == 0:
        dc = ((torch.sigmoid(dc.double()) - 0.5) / SH_C0).float()
    scene = GaussianScene(
        means=params["means"].contiguous(),
        quats=params["quats"].contiguous(),
        log_scales=params["scales"].contiguous(),
        opacity_logits=params["opacities"][:, 0].contiguous(),
        sh=torch.cat([dc[:, None, :], rest], dim=1).contiguous(),
    )
    return validate_scene(scene, str(path), drop_invalid=drop_invalid)[0]


# --------------------------------------------------------------------------- dispatch

_SCENE_READERS = {".ply": read_ply, ".ckpt": read_splatfacto_ckpt}
_SUPPORTED = ".ply (INRIA 3DGS PLY) or .ckpt (nerfstudio splatfacto checkpoint)"


def load_scene(path: str | os.PathLike, *, drop_invalid: bool = False) -> GaussianScene:
    """Read a Gaussian scene with :func:`read_ply` (``.ply``) or :func:`read_splatfacto_ckpt` (``.ckpt``)."""
    path = Path(path)
    reader = _SCENE_READERS.get(path.suffix.lower())
    if reader is None:
        raise ValueError(f"{path}: unsupported scene file type {path.suffix!r}; expected {_SUPPORTED}")
    if not path.is_file():
        raise ValueError(f"{path}: scene file not found; expected {_SUPPORTED}")
    return reader(path, drop_invalid=drop_invalid)
