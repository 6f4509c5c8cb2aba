"""Rendering an :class:`~sage_core.avatar.model.Avatar`: rasterizing posed surfels, shading, exposure.

* :func:`render`: pose the avatar for one frame (:func:`sage_core.avatar.posing.posed`, colours for
  the camera centre) and rasterize the surfels with :func:`sage_core.render.rasterize_surfels` for
  one unbatched :class:`~sage_core.render.RenderCamera`; returns the :class:`SurfelRender` (colour
  (H, W, 3), alpha (H, W), depth (H, W), normals (H, W, 3), ...) and the :class:`PosedSurfels`.
* :func:`shade_colors`: albedo × world irradiance of posed (possibly corrected) surfels, for an
  avatar with ``shading="sh2"`` (:mod:`sage_core.avatar.shading`); identity otherwise.
* Exposure gains: phase 1 learns one gain per training frame (timestep, camera index) and stores them
  with the avatar as plain data; :func:`check_exposure_gains` validates them, :func:`exposure_gain`
  looks one up (None for any other frame: novel views and expressions use gain 1) and
  :func:`exposure_gains_plain` gives the list saved in the avatar file.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

import torch

from ..flame.frames import surfel_frames
from ..render import RenderCamera, SurfelRender, rasterize_surfels
from .correction import SurfelCorrection
from .posing import CanonicalSurfels, PosedMesh, PosedSurfels, posed
from .shading import shade

if TYPE_CHECKING:
    from .model import Avatar


def camera_centre(camera: RenderCamera, like: torch.Tensor) -> torch.Tensor:
    """(3,) world centre −Rᵀ·t of an unbatched camera, in the dtype and device of ``like``."""
    w2c = camera.w2c.to(like)
    return -(w2c[:3, :3].T @ w2c[:3, 3])


def render(
    avatar: Avatar,
    camera: RenderCamera,
    flame_inputs: dict[str, torch.Tensor],
    background: torch.Tensor | float = 1.0,
    correction: SurfelCorrection | None = None,
    canonical: CanonicalSurfels | None = None,
    vertex_transform: Callable[[torch.Tensor], torch.Tensor] | None = None,
    shade_colors: bool = True,
    light_transform: torch.Tensor | None = None,
    mesh: PosedMesh | None = None,
    **raster_kwargs: Any,
) -> tuple[SurfelRender, PosedSurfels]:
    """Pose and rasterize for one (unbatched) camera (the arguments of :meth:`Avatar.render`;
    ``shade_colors`` is its ``shade``); raster_kwargs go to ``rasterize_surfels``."""
    centre = camera_centre(camera, avatar.canonical_vertices)
    p = posed(avatar, flame_inputs, centre, correction=correction, canonical=canonical, vertex_transform=vertex_transform,
              shade_colors=shade_colors, light_transform=light_transform, mesh=mesh)  # fmt: skip
    img = rasterize_surfels(p.means, p.quats, p.scales, p.opacities, p.colors, camera, background, **raster_kwargs)
    return img, p


def shade_colors(
    avatar: Avatar, colors: torch.Tensor, quats: torch.Tensor, vertices: torch.Tensor, light_transform: torch.Tensor | None = None
) -> torch.Tensor:
    """Albedo × world irradiance of posed surfels (identity when the avatar's ``shading`` is "none").

    colors: (N, 3) albedo (``posed(..., shade=False).colors``); quats: (N, 4) posed, possibly
    corrected, surfel rotations; vertices: (V, 3) the posed mesh they are bound to;
    light_transform: optional (3, 3) orthogonal map of the world normals -> (N, 3).
    """
    if avatar.light is None:
        return colors
    R_p, _, _ = surfel_frames(vertices.detach(), avatar.faces)
    return shade(avatar.light, colors, quats, R_p[avatar.surfels.binding][..., 2], light_transform)


# ---------------------------------------------------------------------- exposure gains
def check_exposure_gains(gains: dict[tuple[int, int], Any]) -> dict[tuple[int, int], torch.Tensor]:
    """Validated per-training-frame exposure gains: {(timestep, camera index): (C,) float32 CPU
    tensor}, C = 1 or 3 positive finite numbers (ValueError otherwise)."""
    out: dict[tuple[int, int], torch.Tensor] = {}
    for (t, c), g in gains.items():
        v = torch.as_tensor(g, dtype=torch.float32).detach().cpu().reshape(-1).clone()
        if v.numel() not in (1, 3) or not bool(torch.isfinite(v).all()) or bool((v <= 0).any()):
            raise ValueError(f"exposure gain of timestep {t}, camera {c} must be 1 or 3 positive numbers, got {v.tolist()}")
        out[(int(t), int(c))] = v
    return out


def exposure_gain(avatar: Avatar, timestep: int, camera_index: int) -> torch.Tensor | None:
    """(C,) exposure gain of a training frame on the avatar's device, or None when the frame has none
    stored (novel views and expressions: gain 1)."""
    g = avatar.exposure_gains.get((int(timestep), int(camera_index)))
    return None if g is None else g.to(avatar.device)


def exposure_gains_plain(gains: dict[tuple[int, int], torch.Tensor]) -> list[dict[str, Any]]:
    """The gains as plain data, sorted: [{"timestep", "camera", "gain": [C floats]}]."""
    return [{"timestep": t, "camera": c, "gain": [float(x) for x in g]} for (t, c), g in sorted(gains.items())]
