"""ComfyUI core's Gaussian splat and 3D file types, where the running ComfyUI has them (never required).

ComfyUI's ``comfy_api.latest.Types`` gained (2026) a splat type: ``SPLAT`` (link type "SPLAT"; the
releases before its rename call it ``GAUSSIAN``, link type "GAUSSIAN"). It holds a batch of B splats
in activated form (see ``artnvg_core.activated``) as (B, N, ...) tensors zero-padded to a common N,
``counts`` [B] giving the real lengths (None when every item has N): positions (B, N, 3), scales
(B, N, 3) linear, rotations (B, N, 4) unit w x y z, opacities (B, N, 1) in [0, 1], sh (B, N, K, 3).
Those tensors are all it declares: nothing says how the splats were trained to be rendered. The
pack's splats carry that as one more attribute, ``render_settings`` = ``{"eps2d": blur_px2,
"rasterize_mode": "classic" | "antialiased"}`` (gsplat ``rasterization()``'s own keywords, so a
renderer can pass them on), read back by :func:`splat_to_scene`; a splat without it (made by the core
or another pack) is classic, 0.3 px^2.

``Types.File3D`` is a 3D file. The core types a saved splat file by its container: "FILE_3D_PLY",
"FILE_3D_SPZ", "FILE_3D_SPLAT", "FILE_3D_KSPLAT", and "FILE_3D_SPLAT_ANY" for a node whose format is
a choice (the core's own Splat-to-File node); Preview Gaussian Splat takes all of them.
ComfyUI 0.3.64 has none of these types: the constants below then say so, and nothing else changes.

The pack's scene converts to and from the splat type here and nowhere else. A splat made by
:func:`scene_to_splat` whose values are unchanged converts back to the very same scene (bit-exact;
re-deriving the raw values could move scales and opacities by 1 float32 ulp).
"""

from __future__ import annotations

import dataclasses
import math
import weakref
from dataclasses import fields
from pathlib import Path

import torch

from artnvg_core.activated import ActivatedGaussians, activate, deactivate
from artnvg_core.scene import GaussianScene

from .comfy_bridge import comfy_io, comfy_types


_TYPES = comfy_types()
# the core splat class and its link type name; (None, "SPLAT") when this ComfyUI has none
SPLAT_CLASS, SPLAT = next(((getattr(_TYPES, name), name) for name in ("SPLAT", "GAUSSIAN") if hasattr(_TYPES, name)),
                          (None, "SPLAT"))
FILE3D_CLASS = getattr(_TYPES, "File3D", None)
# the link type of "a splat file in any container", where this ComfyUI has it (None otherwise)
FILE3D_SPLAT_ANY = getattr(getattr(comfy_io(), "File3DSplatAny", None), "io_type", None)
RENDER_SETTINGS = "render_settings"  # the attribute of a splat holding its scene's render settings
RASTERIZE_MODES = ("classic", "antialiased")

MISSING_SPLAT = (
    "Needs ComfyUI's core Gaussian splat type (comfy_api.latest Types.SPLAT, or Types.GAUSSIAN before its "
    "rename; ComfyUI releases of 2026). This ComfyUI lacks it, so this node cannot run here."
)
MODEL_3D = "model_3d: the saved file as ComfyUI's 3D file type, for Preview Gaussian Splat."
MISSING_FILE3D = (
    "On a ComfyUI with 3D file types (comfy_api.latest Types.File3D, 2026) it also outputs the saved file as "
    "model_3d, for Preview Gaussian Splat; this ComfyUI lacks them, so it has no model_3d output."
)

_ORIGINS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # splat -> the scene it was made from


def _same_values(a: ActivatedGaussians, b: ActivatedGaussians) -> bool:
    return all(torch.equal(getattr(a, f.name), getattr(b, f.name)) for f in fields(a))


def scene_to_splat(scene: GaussianScene):
    """A core splat (batch of one, on the CPU) holding ``scene``. Raises RuntimeError without the core type."""
    if SPLAT_CLASS is None:
        raise RuntimeError(MISSING_SPLAT)
    a = activate(scene.to("cpu"))
    splat = SPLAT_CLASS(a.positions[None], a.scales[None], a.rotations[None], a.opacities[None, :, None], a.sh[None])
    setattr(splat, RENDER_SETTINGS, {"eps2d": scene.blur_px2, "rasterize_mode": RASTERIZE_MODES[scene.antialiased]})
    _ORIGINS[splat] = scene
    return splat


def _render_settings(splat, source: str) -> dict:
    """``blur_px2`` and ``antialiased`` of a splat's ``render_settings`` (module docstring); classic without it."""
    settings = getattr(splat, RENDER_SETTINGS, None)
    if settings is None:
        return {}
    blur, mode = settings.get("eps2d", 0.3), settings.get("rasterize_mode", "classic")
    if not (isinstance(blur, (int, float)) and math.isfinite(blur) and blur >= 0):
        raise ValueError(f"{source}: {RENDER_SETTINGS}['eps2d']: expected a finite number >= 0, got {blur!r}")
    if mode not in RASTERIZE_MODES:
        raise ValueError(f"{source}: {RENDER_SETTINGS}['rasterize_mode']: expected one of {RASTERIZE_MODES}, "
                         f"got {mode!r}")
    return {"blur_px2": float(blur), "antialiased": mode == "antialiased"}


def splat_to_scene(splat, source: str = "splat") -> GaussianScene:
    """The scene (float32, CPU) of a core splat holding one item, with the splat's render settings
    (module docstring); ``source`` names it in errors.

    The item is cut to its real length ``counts[0]`` when counts are given. A batch of several
    splats, an SH degree above 3, invalid values and invalid render settings raise ValueError naming
    ``source`` and the field.
    """
    settings = _render_settings(splat, source)
    positions = splat.positions
    if positions.ndim != 3 or positions.shape[0] != 1:
        raise ValueError(f"{source}: positions: expected a batch of one splat (1, N, 3), got shape "
                         f"{tuple(positions.shape)}; convert one item at a time")
    n = positions.shape[1]
    counts = getattr(splat, "counts", None)
    if counts is not None:
        n = int(counts.reshape(-1)[0])
        if not 0 < n <= positions.shape[1]:
            raise ValueError(f"{source}: counts: {n} is not a length in 1..{positions.shape[1]}")
    opacities = splat.opacities[0, :n]
    a = ActivatedGaussians(
        positions=positions[0, :n],
        scales=splat.scales[0, :n],
        rotations=splat.rotations[0, :n],
        opacities=opacities[:, 0] if opacities.ndim == 2 and opacities.shape[1] == 1 else opacities,
        sh=splat.sh[0, :n],
    ).map(lambda t: t.detach().to("cpu", torch.float32))
    origin = _ORIGINS.get(splat)
    if origin is not None and _same_values(activate(origin.to("cpu")), a):
        return dataclasses.replace(origin, **settings)
    return dataclasses.replace(deactivate(a, source), **settings)


def file3d_link_type(suffixes: tuple[str, ...]) -> str:
    """The core's link type of a splat file whose container is one of ``suffixes``, chosen when the node
    runs: "FILE_3D_SPLAT_ANY" where this ComfyUI has it, else each container's own type listed
    ("FILE_3D_PLY,FILE_3D_SPZ", ...)."""
    return FILE3D_SPLAT_ANY or ",".join(f"FILE_3D_{suffix.lstrip('.').upper()}" for suffix in suffixes)


def file3d(path: Path):
    """A core File3D of the file at ``path`` (its format from the extension), or None without the type."""
    return FILE3D_CLASS(str(path)) if FILE3D_CLASS is not None else None
