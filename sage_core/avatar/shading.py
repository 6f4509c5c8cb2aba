"""World-space diffuse irradiance for the optional albedo × world-normal shading model.

With ``Avatar(shading="sh2")`` a surfel's colour is ``albedo · E(n_w)``: the albedo is what the
appearance network (or the free per-surfel SH) produces in head space, and E is the irradiance of a
light that is fixed in the world, evaluated at the surfel's world normal n_w. When the head turns, or
an expression turns the surface, n_w turns with it and the shading follows; a baked head-space
colour cannot do that.

E is a second-order real spherical-harmonic expansion of the unit world normal, one per channel:

    E_c(n) = max(Σ_{k<9} L_{k,c} · Y_k(n), floor),

with Y_k the orthonormal real SH basis of :func:`sage_core.geometry.sh.sh_basis` (3DGS order and
signs): Y_0 = 0.282095; Y_1..3 = 0.488603·(−y, z, −x); Y_4..8 = 1.092548·xy, −1.092548·yz,
0.315392·(2z² − x² − y²), −1.092548·xz, 0.546274·(x² − y²). Order 2 suffices because diffuse irradiance
is band-limited: it is the distant lighting convolved with the clamped cosine, whose SH coefficients
vanish for odd bands above 1 and decay like l^(−5/2) for even ones, so the nine coefficients of bands
0–2 reproduce the irradiance of any lighting to within a few percent (Ramamoorthi & Hanrahan 2001);
higher bands would only let the light fit noise and texture.

The stored parameter is ``coeffs`` (9, 3) with ``coeffs[0] = Y_0·L_0`` (the band-0 term, which is
also the mean of the unclamped E over the sphere) and ``coeffs[k] = L_k`` for k ≥ 1. It starts at
``coeffs[0] = 1`` and zero elsewhere, so an untrained light gives exactly E ≡ 1 and shades nothing.
The floor keeps E positive (a colour cannot be explained by negative light).
:meth:`SHIrradiance.mean_prior` holds the mean near 1 so that the albedo keeps the image's
brightness scale.
"""

from __future__ import annotations

import torch
from torch import nn

from ..geometry.rotations import quat_normalize, quat_to_matrix
from ..geometry.sh import sh_basis

SHADING_MODES: tuple[str, ...] = ("none", "sh2")
N_COEFFS = 9


class SHIrradiance(nn.Module):
    """Order-2 SH irradiance of the unit world normal (see the module doc).

    coeffs: (9, 3) parameter, SH coefficient × channel (row 0 the band-0 term Y_0·L_0); floor: the
    smallest irradiance returned.
    """

    def __init__(self, floor: float = 0.05) -> None:
        super().__init__()
        if not floor > 0:
            raise ValueError(f"the irradiance floor must be positive, got {floor}")
        self.floor = float(floor)
        init = torch.zeros(N_COEFFS, 3)
        init[0] = 1.0
        self.coeffs = nn.Parameter(init)

    def irradiance(self, normals: torch.Tensor) -> torch.Tensor:
        """normals: (N, 3) unit world normals -> (N, 3) irradiance per channel, ≥ ``floor``."""
        c = self.coeffs.to(normals.dtype)
        higher = sh_basis(normals, 2)[:, 1:]  # (N, 8)
        e = c[0] + higher @ c[1:]
        return e.clamp_min(self.floor)

    def forward(self, normals: torch.Tensor) -> torch.Tensor:
        return self.irradiance(normals)

    def mean_irradiance(self) -> torch.Tensor:
        """(3,) mean of the unclamped irradiance over the sphere, Y_0·L_0 per channel."""
        return self.coeffs[0]

    def mean_prior(self) -> torch.Tensor:
        """0-d weak prior mean_c (Y_0·L_{0,c} − 1)²: the mean irradiance stays near 1, which fixes the
        albedo / light scale ambiguity (albedo·s and E/s render alike)."""
        return ((self.mean_irradiance() - 1.0) ** 2).mean()


def orient_outward(normals: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Flip each normal to the side of its reference direction: n·sign(n·r) (sign(0) taken as +).

    normals, reference: (N, 3) -> (N, 3). A surfel's normal ±t3 is ambiguous; the reference is the
    outward normal of its bound triangle.
    """
    s = (normals * reference).sum(-1, keepdim=True)
    return torch.where(s < 0, -normals, normals)


def shade_foreground(
    color: torch.Tensor, alpha: torch.Tensor, irradiance: torch.Tensor, background: torch.Tensor | float
) -> torch.Tensor:
    """Shade the foreground of a composited colour: E·(C − (1 − α)·b) + (1 − α)·b.

    color: (R, 3) composited on ``background``; alpha: (R,) accumulated opacity; irradiance: (R, 3)
    -> (R, 3). Used for a volume-rendered ray shaded with its expected normal.
    """
    bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
    back = (1.0 - alpha)[:, None] * bg
    return irradiance * (color - back) + back


def world_normals(quats: torch.Tensor, triangle_normals: torch.Tensor) -> torch.Tensor:
    """Outward unit world normals of posed surfels, without gradient.

    quats: (N, 4) posed surfel rotations (wxyz); triangle_normals: (N, 3) outward normals of their
    posed bound triangles (the third column of the surfel frame) -> (N, 3): ±t3, towards the triangle
    normal.
    """
    with torch.no_grad():
        n = quat_to_matrix(quat_normalize(quats.detach()))[..., 2]
        return orient_outward(n, triangle_normals.detach().to(n))


def shade(
    light: SHIrradiance,
    colors: torch.Tensor,
    quats: torch.Tensor,
    triangle_normals: torch.Tensor,
    light_transform: torch.Tensor | None = None,
) -> torch.Tensor:
    """Albedo × world irradiance: c = albedo · E(n_w) with n_w = :func:`world_normals` (no gradient).

    colors: (N, 3) albedo; quats, triangle_normals as in :func:`world_normals`; light_transform:
    optional (3, 3) orthogonal map applied to the normals before the irradiance (a mirrored view sees
    the mirror image of the light) -> (N, 3).
    """
    n = world_normals(quats, triangle_normals)
    if light_transform is not None:
        n = n @ light_transform.to(n).T
    return colors * light.irradiance(n)
