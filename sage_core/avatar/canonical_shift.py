"""Move everything an avatar holds in canonical space by one translation, leaving the FLAME mesh.

An avatar's canonical content is its surfels (bound to the canonical FLAME triangles by an offset in
each triangle's frame) and three fields queried at canonical points: the SDF, the appearance
network and the shape network. :func:`shift_canonical` translates all of it by ``delta`` relative to
the mesh:

* fields: f_new(x) = f_old(x − delta). Every field normalises its input by buffers (the hash grids'
  boxes, the networks' centres); moving those buffers by ``delta`` is the whole change, so the
  shifted fields are the old ones exactly (nothing is resampled or refitted);
* surfels: canonical centre μ_c = k_c·R_c·μ_loc + T_c moves by ``delta``:
  μ_loc += R_cᵀ·delta / k_c on each surfel's triangle; rotations and scales stay.

Posed at a frame whose global translation is moved by R0·delta (R0 the frame's global rotation)
the avatar renders exactly as before: the mesh moves by R0·delta in the world and the content stays
where it was. That is how phase 1 re-anchors a training timestep whose tracked pose was off
(:mod:`sage_core.train.registration`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from .model import Avatar


@torch.no_grad()
def shift_canonical(avatar: Avatar, delta: torch.Tensor) -> None:
    """Translate the avatar's canonical content (surfels, SDF, appearance and shape fields) by
    ``delta`` (3,) relative to its FLAME mesh, in place (see the module doc)."""
    d = torch.as_tensor(delta, dtype=torch.float32, device=avatar.canonical_vertices.device).reshape(3)
    for grid in (avatar.sdf.encoding, getattr(avatar.appearance, "grid", None)):
        if grid is None:
            continue
        grid.bbox_min.add_(d.to(grid.bbox_min))
        grid.bbox_max.add_(d.to(grid.bbox_max))
    nets = [avatar.sdf, avatar.appearance] + ([avatar.shape] if avatar.shape is not None else [])
    for net in nets:
        net.center.add_(d.to(net.center))
    s = avatar.surfels
    b = s.binding
    local = (avatar.R_c[b].transpose(1, 2) @ d.to(avatar.R_c)[:, None]).squeeze(-1) / avatar.k_c[b][:, None]
    s.mu_loc.add_(local.to(s.mu_loc))
