"""Adaptive density control of free surfels (3DGS, with GaussianAvatars' binding inheritance).

SAGE itself never densifies (its surfels are initialised and may rebind); this is the mechanism of
the GaussianAvatars baseline, which starts from one surfel per triangle and grows the set where
the photometric loss keeps pulling surfel centres across the image:

* **statistics**: after every backward pass, each surfel the rasterizer kept for the view (inside
  the view and touching a tile: 3DGS's ``radii > 0``) adds the norm of the loss gradient with
  respect to its projected centre in normalised device coordinates, ‖∂L/∂μ_ndc‖, and counts one
  view (3DGS's ``xyz_gradient_accum`` / ``denom``); a kept surfel that received no gradient
  (occluded) adds 0 and still counts. The norm is recovered from the world-space gradient of the
  posed centre: with the camera-frame centre x_c = R·μ + t at depth z and focal lengths
  (f_x, f_y), ∂L/∂u ≈ (∂L/∂x_c)_x · z / f_x in pixels (likewise v), and ∂L/∂u_ndc = ∂L/∂u · W / 2;
* **densify** (every ``densify_every`` steps after ``densify_from``, before ``densify_until``):
  surfels whose mean statistic reaches ``densify_grad_threshold`` are cloned when their largest
  world scale is at most ``percent_dense`` × the scene extent, and split into two otherwise: the
  children are drawn from the parent's 2D Gaussian in its plane and get its scales divided by
  1.6; the parent is removed. Children inherit the parent's triangle (binding), region and
  attributes (their local offsets stay in the parent triangle's frame);
* **prune** (with every densification): surfels whose opacity is below ``prune_opacity``, and
  once the step is past ``opacity_reset_every`` those larger than 0.1 × the scene extent; as in
  GaussianAvatars a triangle never loses its last surfels (when every surfel of a triangle is
  marked, none of them is removed);
* **opacity reset** (every ``opacity_reset_every`` steps before ``densify_until``, and at
  ``densify_from`` with ``opacity_reset_at_start``, GaussianAvatars' rule on a white background):
  every opacity is lowered to at most 0.01 and its Adam state cleared.

3DGS also prunes surfels whose screen radius exceeded 20 pixels, but its code (and GaussianAvatars')
zeroes the radii it compares just before the comparison, so that rule never removes anything; it
is left out here.

The scene extent is 1.1 × the largest distance of a training camera centre from their mean
(3DGS's ``cameras_extent``). Shapes: N surfels; statistics are (N,) float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from ..avatar.model import Avatar
from ..geometry.rotations import quat_normalize, quat_to_matrix
from ..render import RenderCamera

SPLIT_CHILDREN = 2
SPLIT_SCALE_DIVISOR = 1.6
RESET_OPACITY = 0.01
BIG_FRACTION = 0.1


@dataclass
class DensifySchedule:
    """When and how strongly to densify (the ``densify`` section of :class:`sage_core.config.Phase1Config`;
    :meth:`from_config`). Steps are 1-based counts of finished optimisation steps."""

    start: int
    stop: int
    every: int
    grad_threshold: float
    percent_dense: float
    prune_opacity: float
    reset_every: int
    reset_at_start: bool = False

    @classmethod
    def from_config(cls, d: Any) -> DensifySchedule:
        """From a :class:`sage_core.config.DensifyConfig`."""
        return cls(d.start, d.until, d.every, d.grad_threshold, d.percent_dense, d.prune_opacity, d.opacity_reset_every, d.reset_at_start)

    def densify_now(self, step: int) -> bool:
        """Whether to densify after step ``step``: past ``start`` (strictly, as 3DGS), before ``stop``,
        on a multiple of ``every``."""
        return self.every > 0 and self.start < step < self.stop and step % self.every == 0

    def reset_now(self, step: int) -> bool:
        """Whether to reset the opacities after step ``step`` (only before ``stop``): on a multiple of
        ``reset_every``, and at ``start`` with ``reset_at_start``."""
        if step >= self.stop:
            return False
        return (self.reset_every > 0 and step % self.reset_every == 0) or (self.reset_at_start and step == self.start)

    def prune_large_now(self, step: int) -> bool:
        """Whether a densification after step ``step`` also prunes surfels larger than 0.1 × the
        scene extent: past the first reset interval (3DGS's and GaussianAvatars' rule)."""
        return step > self.reset_every


def scene_extent(camera_centres: torch.Tensor) -> float:
    """1.1 × the largest distance of a camera centre (C, 3) from their mean (3DGS's extent)."""
    c = camera_centres.to(torch.float64)
    return 1.1 * float((c - c.mean(0)).norm(dim=-1).max()) if c.shape[0] > 1 else 1.0


def ndc_gradient_norm(means: torch.Tensor, grad: torch.Tensor, camera: RenderCamera) -> torch.Tensor:
    """‖∂L/∂μ_ndc‖ per surfel (see the module doc). means, grad: (N, 3) world -> (N,)."""
    R, t = camera.w2c[:3, :3].to(grad), camera.w2c[:3, 3].to(grad)
    z = (means.detach().to(grad) @ R[2]) + t[2]
    g_c = grad @ R.T
    fx, fy = float(camera.K[0, 0]), float(camera.K[1, 1])
    gu = g_c[:, 0] * z / fx * (0.5 * camera.width)
    gv = g_c[:, 1] * z / fy * (0.5 * camera.height)
    return torch.sqrt(gu * gu + gv * gv)


def keep_last_per_face(remove: torch.Tensor, binding: torch.Tensor) -> torch.Tensor:
    """``remove`` (N,) bool without the surfels of triangles it would empty (GaussianAvatars' rule:
    when every surfel bound to a triangle is marked, all of them stay). binding: (N,) int64."""
    if not bool(remove.any()):
        return remove
    n_faces = int(binding.max()) + 1
    total = torch.bincount(binding, minlength=n_faces)
    marked = torch.bincount(binding[remove], minlength=n_faces)
    emptied = (marked == total) & (total > 0)
    return remove & ~emptied[binding]


class DensityControl:
    """Gradient statistics and the densify / prune / reset operations on a free-attribute avatar.

    avatar: an :class:`Avatar` with ``attributes="free"``; schedule: :class:`DensifySchedule`;
    extent: the scene extent (world units); generator: CPU generator for the split samples.
    """

    def __init__(self, avatar: Avatar, schedule: DensifySchedule, extent: float, generator: torch.Generator) -> None:
        if avatar.attributes != "free":
            raise ValueError("adaptive density control needs free surfel attributes")
        self.avatar = avatar
        self.schedule = schedule
        self.extent = float(extent)
        self.generator = generator
        self.resets = 0
        self.clear_statistics()

    def clear_statistics(self) -> None:
        n, dev = len(self.avatar.surfels), self.avatar.surfels.mu_loc.device
        self.grad_sum = torch.zeros(n, dtype=torch.float64, device=dev)
        self.count = torch.zeros(n, dtype=torch.float64, device=dev)

    # ------------------------------------------------------------------ statistics
    @torch.no_grad()
    def accumulate(self, means: torch.Tensor, camera: RenderCamera, visible: torch.Tensor) -> None:
        """Add one view's statistic. means: the posed (N, 3) centres whose ``.grad`` is set (None: no
        gradient reached them, every kept surfel adds 0); visible: (N,) bool, the surfels the
        rasterizer kept for this view."""
        seen = visible.to(device=self.count.device, dtype=torch.bool)
        if means.grad is not None:
            norm = ndc_gradient_norm(means, means.grad, camera).to(torch.float64)
            self.grad_sum += torch.where(seen, norm, torch.zeros_like(norm))
        self.count += seen.to(torch.float64)

    # ------------------------------------------------------------------ operations
    def world_scale_max(self) -> torch.Tensor:
        """(N,) largest canonical world scale k_b·exp(s_loc) of every surfel."""
        s = self.avatar.surfels
        return (self.avatar.k_c[s.binding][:, None] * torch.exp(s.s_loc.detach())).amax(-1)

    @torch.no_grad()
    def densify_and_prune(self, optimizer: torch.optim.Optimizer, step: int) -> dict[str, int]:
        """Clone, split and prune after step ``step`` (see the module doc); clears the statistics.
        Returns the counts."""
        sc, s = self.schedule, self.avatar.surfels
        mean_grad = torch.where(self.count > 0, self.grad_sum / self.count.clamp_min(1.0), torch.zeros_like(self.grad_sum))
        hot = mean_grad >= sc.grad_threshold
        big = self.world_scale_max() > sc.percent_dense * self.extent
        clone, split = hot & ~big, hot & big
        n0 = len(s)
        rows = [self._clone_rows(clone), self._split_rows(split)]
        added = {k: torch.cat([r[k] for r in rows], 0) for k in rows[0]}
        s.extend(added, optimizer)
        remove = torch.cat([split, torch.zeros(len(s) - n0, dtype=torch.bool, device=split.device)])
        remove |= torch.sigmoid(s.opacity.detach()) < sc.prune_opacity
        if sc.prune_large_now(step):
            remove |= self.world_scale_max() > BIG_FRACTION * self.extent
        remove = keep_last_per_face(remove, s.binding)
        s.prune(remove, optimizer)
        self._sync_avatar()
        self.clear_statistics()
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(remove.sum()) - int(split.sum()), "surfels": len(s)}

    def _rows(self, sel: torch.Tensor) -> dict[str, torch.Tensor]:
        return {k: v.detach()[sel].clone() for k, v in self.avatar.surfels._row_tensors().items()}

    def _clone_rows(self, sel: torch.Tensor) -> dict[str, torch.Tensor]:
        return self._rows(sel)

    def _split_rows(self, sel: torch.Tensor) -> dict[str, torch.Tensor]:
        """SPLIT_CHILDREN children per selected surfel, sampled in the parent's plane (triangle-local units)."""
        parent = self._rows(sel)
        m = int(sel.sum())
        out = {k: v.repeat_interleave(SPLIT_CHILDREN, 0) for k, v in parent.items()}
        if m == 0:
            return out
        s_loc = out["s_loc"]
        eps = torch.randn((m * SPLIT_CHILDREN, 2), generator=self.generator, dtype=torch.float64).to(s_loc)
        offset_plane = torch.cat([eps * torch.exp(s_loc), torch.zeros_like(eps[:, :1])], -1)  # (M2, 3) in the surfel frame
        rot = quat_to_matrix(quat_normalize(out["q_loc"]))  # surfel frame -> triangle-local
        out["mu_loc"] = out["mu_loc"] + (rot @ offset_plane[..., None]).squeeze(-1)
        out["s_loc"] = s_loc - math.log(SPLIT_SCALE_DIVISOR)
        return out

    @torch.no_grad()
    def reset_opacity(self, optimizer: torch.optim.Optimizer) -> None:
        """Lower every opacity to at most RESET_OPACITY and clear the opacity's optimizer state."""
        s = self.avatar.surfels
        cap = math.log(RESET_OPACITY / (1.0 - RESET_OPACITY))
        s.opacity.data.clamp_(max=cap)
        for v in optimizer.state.get(s.opacity, {}).values():
            if isinstance(v, torch.Tensor) and v.dim() > 0:
                v.zero_()
        self.resets += 1

    def _sync_avatar(self) -> None:
        """Per-surfel avatar state that follows the set's rows (the shape network's base size)."""
        av = self.avatar
        with torch.no_grad():
            _, _, sc = av.surfels.pose(av.R_c, av.T_c, av.k_c)
            av.base_scale = sc.prod(-1).sqrt().to(av.base_scale.dtype)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        return {"grad_sum": self.grad_sum.clone(), "count": self.count.clone(), "resets": self.resets}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        n = len(self.avatar.surfels)
        if state["grad_sum"].shape[0] != n:
            raise ValueError(f"density statistics hold {state['grad_sum'].shape[0]} surfels, the avatar {n}")
        self.grad_sum = state["grad_sum"].to(self.grad_sum)
        self.count = state["count"].to(self.count)
        self.resets = int(state["resets"])
