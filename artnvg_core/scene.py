"""Gaussian scenes: the raw stored 3DGS parameters and their validation (no file format).

Conventions (INRIA 3DGS layout, see docs/design.md):

- ``means``          [N, 3]  world positions
- ``quats``          [N, 4]  rotation quaternions, w x y z, *unnormalised*
- ``log_scales``     [N, 3]  natural log of the per-axis standard deviations
- ``opacity_logits`` [N]     opacity before the sigmoid
- ``sh``             [N, K, 3] spherical-harmonic coefficients, DC first,
  K = (degree + 1) ** 2; colour = SH(dir) + 0.5, clamped at 0. ``SH_C0`` is
  the degree-0 basis constant.

How the trainer rendered them (defaults: gsplat "classic", the INRIA renderer):

- ``blur_px2``       variance (px^2) of the 2D low-pass filter added to every
  projected covariance: 0.3 (3DGS, gsplat, splatfacto); Mip-Splatting's 2D Mip
  filter uses 0.1.
- ``antialiased``    the 2D filter's opacity compensation, gsplat's
  ``rasterize_mode="antialiased"``: opacity x sqrt(det(S) / det(S + blur I)),
  S the projected 2D covariance (splatfacto ``rasterize_mode="antialiased"``,
  Mip-Splatting, SPZ files flagged antialiased).

Scenes are read and written by :mod:`artnvg_core.formats` (``load_scene``, ``save_scene``),
which this module does not import; every reader validates with :func:`validate_scene`: bad input raises
``ValueError`` naming the file and the field; with ``drop_invalid=True``
invalid Gaussians are dropped instead and the user told so (:mod:`artnvg_core.notes`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from .counted import counted
from .notes import NoteFn, tell
from .progress import ProgressFn, StopFn, check_stop

SH_C0 = 0.28209479177387814
DEFAULT_BLUR_PX2 = 0.3  # the 2D low-pass of 3DGS, gsplat and splatfacto (px^2)
# The end of every invalid-Gaussian refusal; callers with their own words for the option replace it.
DROP_INVALID_HINT = "pass drop_invalid=True to drop invalid Gaussians"


def sh_degree_for(num_coeffs: int) -> int:
    """SH degree d for K = (d + 1)^2 coefficients per channel (d in 0..3)."""
    for degree in range(4):
        if (degree + 1) ** 2 == num_coeffs:
            return degree
    raise ValueError(f"sh: {num_coeffs} coefficients per channel is not (d+1)^2 for d in 0..3")


def logit(p: torch.Tensor) -> torch.Tensor:
    """Opacity logits log(p / (1 - p)), as log(p) - log1p(-p), of opacities ``p`` in [0, 1] (0 and 1 give
    -inf and +inf): the inverse of the sigmoid that turns ``opacity_logits`` into opacities. Computed in
    ``p``'s dtype; float64, rounded once to float32, gives correctly rounded float32 logits."""
    return p.log() - (-p).log1p()


@dataclass
class GaussianScene:
    """Raw 3DGS parameters of N Gaussians (shapes in the module docstring), floating-point tensors of one
    dtype on one device."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    blur_px2: float = DEFAULT_BLUR_PX2
    antialiased: bool = False

    def __post_init__(self) -> None:
        for name in _TENSOR_FIELDS:
            value = getattr(self, name)
            if not (isinstance(value, torch.Tensor) and value.is_floating_point()):
                kind = value.dtype if isinstance(value, torch.Tensor) else type(value).__name__
                raise ValueError(f"GaussianScene.{name}: expected a floating-point torch.Tensor, got {kind}")
            if (value.dtype, value.device) != (self.means.dtype, self.means.device):
                raise ValueError(f"GaussianScene.{name}: expected the means' dtype and device "
                                 f"({self.means.dtype} on {self.means.device}), got {value.dtype} on {value.device}")
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
        blur = self.blur_px2
        if isinstance(blur, bool) or not (isinstance(blur, (int, float)) and math.isfinite(blur) and blur >= 0):
            raise ValueError(f"GaussianScene.blur_px2: expected a finite number >= 0, got {blur!r}")
        if not isinstance(self.antialiased, bool):
            raise ValueError(f"GaussianScene.antialiased: expected True or False, got {self.antialiased!r}")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_for(self.sh.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def classic(self) -> bool:
        """True when rendered as gsplat's "classic" mode (0.3 px^2 blur, no compensation)."""
        return self.blur_px2 == DEFAULT_BLUR_PX2 and not self.antialiased

    def tensors(self) -> dict[str, torch.Tensor]:
        """The parameter tensors by field name, in declaration order."""
        return {name: getattr(self, name) for name in _TENSOR_FIELDS}

    def map(self, fn) -> "GaussianScene":
        """A new scene with ``fn`` applied to every parameter tensor (render settings kept)."""
        return dataclasses.replace(self, **{k: fn(v) for k, v in self.tensors().items()})

    def to(self, device=None, dtype=None) -> "GaussianScene":
        return self.map(lambda t: t.to(device=device, dtype=dtype))

    def widened(self) -> "GaussianScene":
        """This scene, or its float32 copy where it is float16 or bfloat16: too narrow to render or train in
        (:func:`~artnvg_core.raster.render` and :func:`~artnvg_core.finetune.finetune` work on that copy)."""
        return self.to(dtype=torch.float32) if self.means.dtype.itemsize < 4 else self

    def detach(self) -> "GaussianScene":
        return self.map(lambda t: t.detach().clone())

    def select(self, index) -> "GaussianScene":
        """Subset by a boolean mask [N], integer indices [K] in -N..N-1 (a tensor or a sequence) or a slice over the N
        Gaussians. ValueError otherwise."""
        if not isinstance(index, slice):
            index, n = torch.as_tensor(index, device=self.device), len(self)
            got = f"got {index.dtype} of shape {tuple(index.shape)}"
            if index.dtype == torch.bool:
                if tuple(index.shape) != (n,):
                    raise ValueError(f"GaussianScene.select: a boolean mask must have shape ({n},), {got}")
            elif index.ndim != 1 or (len(index) and (index.is_floating_point() or index.is_complex())):
                raise ValueError(f"GaussianScene.select: expected a boolean mask [N], integer indices [K] or a slice, {got}")
            else:
                index = index.long()  # not uint8, which torch would take for a mask; [] (float32) selects none
                if len(index) and not -n <= int(index.min()) <= int(index.max()) < n:
                    raise ValueError(f"GaussianScene.select: indices must lie in {-n}..{n - 1} for "
                                     f"{counted(n, 'Gaussian')}")
        return self.map(lambda t: t[index])


_TENSOR_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")


# --------------------------------------------------------------------------- validation


_SINGULAR_VERBS = {"have": "has", "lie": "lies", "are": "is"}  # the verbs describe_invalid's problems start with


def describe_invalid(name: str, bad, problem: str) -> str:
    """``"{name}: K of N Gaussians {problem} (first at index i)"`` for a bad-mask ``bad`` [N] (a torch
    or numpy bool array with a True entry): the one wording of a per-Gaussian error. ``problem`` starts with
    a verb of _SINGULAR_VERBS in the plural, made to agree with K: "1 of 4 Gaussians has a zero norm"."""
    count = int(bad.sum())
    verb, rest = problem.split(" ", 1)
    verb = _SINGULAR_VERBS[verb] if count == 1 else verb
    return f"{name}: {count:,} of {counted(len(bad), 'Gaussian')} {verb} {rest} (first at index {int(bad.nonzero()[0][0])})"


CHECKED_ROWS = 1 << 16  # Gaussians checked between two questions to should_stop (0.02 s at SH degree 3 on a CPU core)


def invalid_gaussians(scene: GaussianScene, should_stop: StopFn | None = None,
                      progress: ProgressFn | None = None) -> list[tuple[str, str, torch.Tensor]]:
    """(field, problem, bad-mask [N]) for every check, in field order; checked :data:`CHECKED_ROWS` Gaussians at a
    time, ``should_stop`` asked before each (:class:`~artnvg_core.progress.Cancelled`), ``progress`` told the
    Gaussians checked after each."""
    n, tensors = len(scene), scene.tensors()
    masks = [torch.empty(n, dtype=torch.bool, device=scene.device) for _ in range(len(tensors) + 1)]
    for start in range(0, n, CHECKED_ROWS):
        check_stop(should_stop)
        rows = slice(start, start + CHECKED_ROWS)
        for mask, value in zip(masks, tensors.values()):
            chunk = value[rows]
            mask[rows] = ~torch.isfinite(chunk).reshape(len(chunk), -1).all(dim=1)
        masks[-1][rows] = torch.linalg.vector_norm(scene.quats[rows], dim=1) == 0
        if progress is not None:
            progress(min(start + CHECKED_ROWS, n), n, {})
    checks = [(name, "non-finite values", mask) for name, mask in zip(tensors, masks)]
    return checks + [("quats", "a zero norm", masks[-1])]


def validate_scene(scene: GaussianScene, source: str, *, drop_invalid: bool = False,
                   should_stop: StopFn | None = None, progress: ProgressFn | None = None,
                   notes: NoteFn | None = None) -> tuple[GaussianScene, int]:
    """Check that every Gaussian is finite in all fields and has a non-zero quaternion.

    Returns ``(scene, dropped)``. Without ``drop_invalid`` the first failing check
    raises ``ValueError`` naming ``source`` (the file), the field, how many
    Gaussians fail and the first failing index, and ``dropped`` is 0. With
    ``drop_invalid`` the failing Gaussians are removed, counted in ``dropped``
    and told to ``notes`` (:func:`~artnvg_core.notes.tell`: else logged as a warning). A scene with
    no (remaining) Gaussians is always an error. ``should_stop`` and ``progress``: as :func:`invalid_gaussians`'s.
    """
    n = len(scene)
    if n == 0:
        raise ValueError(f"{source}: the scene contains no Gaussians")
    invalid = torch.zeros(n, dtype=torch.bool, device=scene.device)
    reasons = []
    for name, problem, bad in invalid_gaussians(scene, should_stop, progress):
        count = int(bad.sum())
        if count == 0:
            continue
        if not drop_invalid:
            raise ValueError(f"{source}: {describe_invalid(name, bad, f'have {problem}')}; {DROP_INVALID_HINT}")
        invalid |= bad
        reasons.append(f"{name}: {count} with {problem}")
    dropped = int(invalid.sum())
    if dropped == n:
        every = f"all {n:,} Gaussians are" if n > 1 else "its one Gaussian is"
        raise ValueError(f"{source}: {every} invalid ({'; '.join(reasons)})")
    if dropped:
        tell(notes, source, f"dropped {counted(dropped, 'invalid Gaussian')} of {n:,} ({'; '.join(reasons)})")
        scene = scene.select(~invalid)
    return scene, dropped

