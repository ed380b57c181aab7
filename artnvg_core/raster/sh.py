"""Real spherical harmonics (degrees 0-3) as used by 3DGS and gsplat."""

from __future__ import annotations

import torch

from ..scene import SH_C0
from .projection import ALPHA_MIN
from .torch_backend import T_MIN

# The cap that keeps colours and their gradients finite for any finite coefficients (float32 sums
# of huge terms overflow to inf, and inf colours give NaN gradients). A composited Gaussian weighs
# more than ALPHA_MIN * T_MIN, so a colour channel at COLOR_MAX already makes its pixel >= 1:
# the cap changes no image clamped to [0, 1].
COLOR_MAX = 1.0 / (ALPHA_MIN * T_MIN)

SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_to_color(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Colour of each Gaussian seen along ``dirs``.

    sh: [N, K, 3] coefficients, DC first; only the first (degree + 1)^2 are used.
    dirs: [N, 3] viewing directions (camera centre -> Gaussian), any length > 0.
    Returns [N, 3] = SH(dirs) + 0.5 clamped to [0, COLOR_MAX] (no image clamped to [0, 1] changes).
    """
    c = sh.unbind(1)  # one stack in the backward pass, where slicing would write 16 zero-filled copies
    result = SH_C0 * c[0]
    if degree > 0:
        d = torch.nn.functional.normalize(dirs, dim=-1, eps=1e-12)
        x, y, z = (v[:, None] for v in d.unbind(-1))
        result = result - SH_C1 * y * c[1] + SH_C1 * z * c[2] - SH_C1 * x * c[3]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            result = (
                result
                + SH_C2[0] * xy * c[4]
                + SH_C2[1] * yz * c[5]
                + SH_C2[2] * (2 * zz - xx - yy) * c[6]
                + SH_C2[3] * xz * c[7]
                + SH_C2[4] * (xx - yy) * c[8]
            )
            if degree > 2:
                result = (
                    result
                    + SH_C3[0] * y * (3 * xx - yy) * c[9]
                    + SH_C3[1] * xy * z * c[10]
                    + SH_C3[2] * y * (4 * zz - xx - yy) * c[11]
                    + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * c[12]
                    + SH_C3[4] * x * (4 * zz - xx - yy) * c[13]
                    + SH_C3[5] * z * (xx - yy) * c[14]
                    + SH_C3[6] * x * (xx - 3 * yy) * c[15]
                )
    return torch.clamp(result + 0.5, 0.0, COLOR_MAX)
