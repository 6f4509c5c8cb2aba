"""The surfel set: per-surfel binding to a triangle, local residuals and optional free attributes.

State (per-surfel tensors have N index-aligned rows):

* buffers ``binding`` (N,) int64 face ids and ``region_id`` (N,) int64 labels into
  :data:`sage_core.avatar.init.REGION_NAMES`, plus ``face_region`` (F,) int64 (the label of every
  face, used to relabel after rebinding; empty when unknown);
* optional buffer ``wrinkle`` (N, 2): wrinkle shading (:mod:`sage_core.avatar.wrinkles`), the
  darkening amplitude and the area compression at which it applies in full; absent (None, not in the
  state dict) until phase 2 sets it with :meth:`SurfelSet.set_wrinkle`;
* optional buffer ``color_prior`` (N, 4): a fixed colour (RGB) and its blend weight in [0, 1] that
  replaces the attribute colour of surfels no training view saw (the mouth interior), set by phase 2
  with :meth:`SurfelSet.set_color_prior`; absent (None) otherwise;
* optional buffer ``unseen_floor`` (N, 2): for surfels no training view saw (the unseen fill of
  phase 2, :mod:`sage_core.train.unseen_fill`), a lower bound of the attribute opacity and a gain
  (≥ 1) on the in-plane scales, so that the unseen surface stays covered (0 and 1: none); set with
  :meth:`SurfelSet.set_unseen_floor`; absent (None) otherwise;
* parameters ``mu_loc`` (N, 3), ``q_loc`` (N, 4) wxyz and ``s_loc`` (N, 2) log in-plane scales,
  all relative to the bound triangle's frame (docs/formats.md §6, surfel convention);
* with ``attributes="free"``: ``sh_dc`` (N, 1, 3), ``sh_rest`` (N, (d+1)²−1, 3) (absent at degree
  0) and ``opacity`` (N,) logit. With ``attributes="mlp"`` colour and opacity come from networks
  elsewhere and the set holds none of them, only, once :meth:`SurfelSet.enable_opacity_offset` was
  called (phase 1 with ``lr.opacity_offset`` > 0), ``opacity_offset`` (N,): a logit added to the
  appearance network's opacity of each surfel (:meth:`SurfelSet.offset_opacities`).

Binding and labels are buffers, so rebinding survives ``state_dict`` / ``load_state_dict``; use
:meth:`SurfelSet.from_state_dict` when the number of surfels differs from the receiving set's.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping

import numpy as np
import torch
from torch import nn

from .binding import local_to_world, nearest_triangles, point_triangle_distance, world_to_local
from .init import REGION_HAIR, SurfelInit

SH_C0 = 0.28209479177387814
ATTRIBUTE_MODES = ("free", "mlp")
_PARAMS = ("mu_loc", "q_loc", "s_loc", "sh_dc", "sh_rest", "opacity", "opacity_offset")
_BUFFERS = ("binding", "region_id", "wrinkle", "color_prior", "unseen_floor")


def _logit(p: float) -> float:
    return float(np.log(p / (1.0 - p)))


class SurfelSet(nn.Module):
    """Surfels bound to mesh triangles.

    Args:
        binding: (N,) int64 face ids.
        mu_loc: (N, 3); q_loc: (N, 4) wxyz; s_loc: (N, 2) log scales relative to k.
        region_id: (N,) int64 labels (default 0).
        face_region: (F,) int64 label of every face, or None if unknown.
        attributes: "free" (per-surfel SH colour and opacity parameters) or "mlp" (none).
        sh_degree: SH degree of the free colour (0–3).
        rgb: (N, 3) initial colour in [0, 1] for the free SH DC term (default 0.5 grey: DC = 0).
        opacity: initial opacity in (0, 1) for the free attributes.
    """

    binding: torch.Tensor
    region_id: torch.Tensor
    opacity_offset: nn.Parameter | None
    face_region: torch.Tensor
    wrinkle: torch.Tensor | None
    color_prior: torch.Tensor | None
    unseen_floor: torch.Tensor | None

    def __init__(
        self,
        binding: torch.Tensor,
        mu_loc: torch.Tensor,
        q_loc: torch.Tensor,
        s_loc: torch.Tensor,
        region_id: torch.Tensor | None = None,
        face_region: torch.Tensor | None = None,
        *,
        attributes: str = "free",
        sh_degree: int = 0,
        rgb: torch.Tensor | None = None,
        opacity: float = 0.1,
    ) -> None:
        super().__init__()
        if attributes not in ATTRIBUTE_MODES:
            raise ValueError(f"attributes must be one of {ATTRIBUTE_MODES}, got {attributes!r}")
        if not 0 <= sh_degree <= 3:
            raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
        if not 0.0 < opacity < 1.0:
            raise ValueError(f"opacity must lie in (0, 1), got {opacity}")
        N = binding.shape[0]
        for name, x, width in (("mu_loc", mu_loc, 3), ("q_loc", q_loc, 4), ("s_loc", s_loc, 2)):
            if tuple(x.shape) != (N, width):
                raise ValueError(f"{name} must be ({N}, {width}), got {tuple(x.shape)}")
        device, dtype = mu_loc.device, mu_loc.dtype
        self.attributes = attributes
        self.sh_degree = int(sh_degree)
        self.register_buffer("binding", binding.detach().to(device=device, dtype=torch.long).clone())
        rid = torch.zeros(N, dtype=torch.long) if region_id is None else region_id.detach()
        if tuple(rid.shape) != (N,):
            raise ValueError(f"region_id must be ({N},), got {tuple(rid.shape)}")
        self.register_buffer("region_id", rid.to(device=device, dtype=torch.long).clone())
        fr = torch.zeros(0, dtype=torch.long) if face_region is None else face_region.detach().reshape(-1)
        self.register_buffer("face_region", fr.to(device=device, dtype=torch.long).clone())
        self.register_buffer("wrinkle", None)
        self.register_buffer("color_prior", None)
        self.register_buffer("unseen_floor", None)
        self.register_parameter("opacity_offset", None)
        self.mu_loc = nn.Parameter(mu_loc.detach().clone())
        self.q_loc = nn.Parameter(q_loc.detach().to(device=device, dtype=dtype).clone())
        self.s_loc = nn.Parameter(s_loc.detach().to(device=device, dtype=dtype).clone())
        if attributes == "free":
            if rgb is None:
                dc = torch.zeros(N, 1, 3, device=device, dtype=dtype)
            else:
                if tuple(rgb.shape) != (N, 3):
                    raise ValueError(f"rgb must be ({N}, 3), got {tuple(rgb.shape)}")
                dc = ((rgb.detach().to(device=device, dtype=dtype) - 0.5) / SH_C0)[:, None, :]
            self.sh_dc = nn.Parameter(dc)
            n_rest = (sh_degree + 1) ** 2 - 1
            if n_rest:
                self.sh_rest = nn.Parameter(torch.zeros(N, n_rest, 3, device=device, dtype=dtype))
            self.opacity = nn.Parameter(torch.full((N,), _logit(opacity), device=device, dtype=dtype))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_init(cls, init: SurfelInit, **kwargs: Any) -> SurfelSet:
        """Build from :func:`sage_core.avatar.init.init_surfels`'s result; kwargs as the constructor."""
        return cls(init.binding, init.mu_loc, init.q_loc, init.s_loc, init.region_id, init.face_region, **kwargs)

    @classmethod
    def from_state_dict(cls, state: Mapping[str, torch.Tensor]) -> SurfelSet:
        """A set shaped like ``state`` (any N) with its values loaded; the mode and SH degree are
        inferred (free attributes iff ``opacity`` is present)."""
        free = "opacity" in state
        n_rest = state["sh_rest"].shape[1] if "sh_rest" in state else 0
        degree = int(round((n_rest + 1) ** 0.5)) - 1
        obj = cls(
            state["binding"], state["mu_loc"], state["q_loc"], state["s_loc"], state["region_id"],
            state.get("face_region"), attributes="free" if free else "mlp", sh_degree=degree,
        )
        if "opacity_offset" in state:
            obj.enable_opacity_offset()
        if state.get("wrinkle") is not None:
            obj.set_wrinkle(state["wrinkle"])
        if state.get("color_prior") is not None:
            obj.set_color_prior(state["color_prior"])
        if state.get("unseen_floor") is not None:
            obj.set_unseen_floor(state["unseen_floor"])
        obj.load_state_dict(state)
        return obj

    def _set_optional_rows(self, name: str, value: torch.Tensor | None, width: int) -> None:
        """Set the optional per-surfel buffer ``name`` to value (N, width), or remove it with None."""
        if value is not None:
            if tuple(value.shape) != (len(self), width):
                raise ValueError(f"{name} must be ({len(self)}, {width}), got {tuple(value.shape)}")
            value = value.detach().to(device=self.binding.device, dtype=self.mu_loc.dtype).clone()
        setattr(self, name, value)

    def set_wrinkle(self, wrinkle: torch.Tensor | None) -> None:
        """Set (or with None remove) the wrinkle shading buffer: (N, 2) amplitude in [0, 1] and full
        compression in (0, 1] per surfel (see :mod:`sage_core.avatar.wrinkles`)."""
        self._set_optional_rows("wrinkle", wrinkle, 2)

    def set_color_prior(self, prior: torch.Tensor | None) -> None:
        """Set (or with None remove) the colour prior: (N, 4) RGB and blend weight per surfel."""
        self._set_optional_rows("color_prior", prior, 4)

    def blend_color_prior(self, colors: torch.Tensor) -> torch.Tensor:
        """colors (N, 3) blended with the colour prior where it has weight (unchanged without one)."""
        if self.color_prior is None:
            return colors
        w = self.color_prior[:, 3:4].to(colors)
        return colors * (1.0 - w) + self.color_prior[:, :3].to(colors) * w

    def set_unseen_floor(self, floor: torch.Tensor | None) -> None:
        """Set (or with None remove) the unseen floor: (N, 2) per surfel, the lower bound of its
        opacity (0: none) and the gain on its in-plane scales (1: none)."""
        self._set_optional_rows("unseen_floor", floor, 2)

    def apply_unseen_floor(self, opacities: torch.Tensor, scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """opacities (N,) raised to the floor and scales (N, 2) times the gain (unchanged without
        the buffer)."""
        if self.unseen_floor is None:
            return opacities, scales
        f = self.unseen_floor
        return torch.maximum(opacities, f[:, 0].to(opacities)), scales * f[:, 1:2].to(scales)

    def enable_opacity_offset(self) -> None:
        """Give an ``attributes="mlp"`` set its per-surfel opacity offset (N,), zero (no change) at
        first; a no-op when it has one. The offset is a parameter: train it by adding it to an
        optimizer (phase 1's ``opacity_offset`` group)."""
        if self.attributes != "mlp":
            raise AttributeError("only a surfel set with attribute networks (attributes='mlp') has an opacity offset")
        if self.opacity_offset is None:
            self.opacity_offset = nn.Parameter(torch.zeros(len(self), device=self.mu_loc.device, dtype=self.mu_loc.dtype))

    def offset_opacities(self, opacities: torch.Tensor) -> torch.Tensor:
        """opacities (N,) in [0, 1] (the appearance network's) with the opacity offset o (N,) added to
        their logits: sigmoid(logit(a) + o) = a·e^o / (1 − a + a·e^o), which keeps a = 0 and a = 1
        exact (the offset is clamped to ±30 so that e^o stays finite); unchanged without an offset."""
        if self.opacity_offset is None:
            return opacities
        e = torch.exp(self.opacity_offset.to(opacities).clamp(-30.0, 30.0))
        return opacities * e / (1.0 - opacities + opacities * e)

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        return int(self.binding.shape[0])

    @property
    def n(self) -> int:
        return len(self)

    def pose(self, R: torch.Tensor, T: torch.Tensor, k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """World means (..., N, 3), unit quats (..., N, 4) and scales (..., N, 2) (not log) for
        surfel frames R (..., F, 3, 3), T (..., F, 3), k (..., F) of one or a batch of frames."""
        return local_to_world(self.mu_loc, self.q_loc, self.s_loc, self.binding, R, T, k)

    def canonical_positions(self, R_c: torch.Tensor, T_c: torch.Tensor, k_c: torch.Tensor) -> torch.Tensor:
        """(N, 3) positions in canonical space from the canonical mesh's frames (F, 3, 3), (F, 3), (F,)."""
        Rb = R_c[self.binding]
        return k_c[self.binding, None] * (Rb @ self.mu_loc[..., None]).squeeze(-1) + T_c[self.binding]

    def opacities(self) -> torch.Tensor:
        """(N,) sigmoid of the free opacity logits."""
        self._need_free()
        return torch.sigmoid(self.opacity)

    def sh_coeffs(self) -> torch.Tensor:
        """(N, (d+1)², 3) free SH coefficients (DC first, 3DGS order)."""
        self._need_free()
        if self.sh_degree == 0:
            return self.sh_dc
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    def hair_mask(self) -> torch.Tensor:
        """(N,) bool: surfels bound to hair triangles."""
        return self.region_id == REGION_HAIR

    def _need_free(self) -> None:
        if self.attributes != "free":
            raise AttributeError("this surfel set has no free attributes (attributes='mlp')")

    def extra_repr(self) -> str:
        return f"n={len(self)}, attributes={self.attributes!r}, sh_degree={self.sh_degree}"

    # ------------------------------------------------------------------ rebinding
    @torch.no_grad()
    def rebind(
        self,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        allowed_faces: torch.Tensor | np.ndarray | None = None,
        *,
        tolerance: float = 1e-6,
        frames: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
        method: str = "auto",
        optimizer: torch.optim.Optimizer | None = None,
    ) -> int:
        """Bind every surfel to its nearest canonical triangle, keeping its canonical pose.

        vertices: (V, 3) canonical mesh; faces: (F, 3); allowed_faces: (F,) bool mask or face ids
        a surfel may bind to (None: all; a surfel bound outside it always moves). A surfel moves
        only when its current triangle is farther than the nearest allowed one by more than
        ``tolerance`` (world units), so ties keep their binding. frames: the canonical
        (R, T, k) from :func:`sage_core.flame.surfel_frames` if already computed.
        Changed surfels get mu_loc/q_loc/s_loc re-expressed in the new frame (their canonical
        position, rotation and scales are unchanged), and region_id from ``face_region`` when it is
        known. Parameters are updated in place (optimizer references stay valid); with
        ``optimizer`` given, the per-row state (e.g. Adam's moments, which were measured in the old
        frame) of the changed rows of mu_loc, q_loc and s_loc is zeroed. Returns the number of
        surfels that changed triangle.
        """
        from ..flame.frames import surfel_frames

        faces = faces.to(device=self.binding.device, dtype=torch.long)
        vertices = vertices.to(device=self.binding.device, dtype=self.mu_loc.dtype)
        if self.face_region.numel() and self.face_region.shape[0] != faces.shape[0]:
            raise ValueError(f"face_region has {self.face_region.shape[0]} labels, the mesh {faces.shape[0]} faces")
        R, T, k = frames if frames is not None else surfel_frames(vertices, faces)
        means, quats, scales = self.pose(R, T, k)
        new_face, new_dist = nearest_triangles(means, vertices, faces, candidates=allowed_faces, method=method)
        tri = vertices[faces[self.binding]]
        cur_dist = point_triangle_distance(means, tri[:, 0], tri[:, 1], tri[:, 2])
        if allowed_faces is not None:
            allowed = torch.as_tensor(allowed_faces, device=self.binding.device)
            if allowed.dtype != torch.bool:
                mask = torch.zeros(faces.shape[0], dtype=torch.bool, device=self.binding.device)
                mask[allowed.long()] = True
                allowed = mask
            cur_dist = torch.where(allowed[self.binding], cur_dist, torch.full_like(cur_dist, float("inf")))
        changed = (new_face != self.binding) & (cur_dist > new_dist + tolerance)
        n_changed = int(changed.sum())
        if n_changed == 0:
            return 0
        idx = torch.nonzero(changed, as_tuple=False).reshape(-1)
        mu, q, s = world_to_local(means[idx], quats[idx], scales[idx], new_face[idx], R, T, k)
        self.mu_loc.data[idx] = mu
        self.q_loc.data[idx] = q
        self.s_loc.data[idx] = s
        self.binding[idx] = new_face[idx]
        if self.face_region.numel():
            self.region_id[idx] = self.face_region[new_face[idx]]
        if optimizer is not None:
            for p in (self.mu_loc, self.q_loc, self.s_loc):
                for v in optimizer.state.get(p, {}).values():
                    if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == p.shape[0]:
                        v[idx.to(v.device)] = 0
        return n_changed

    # ------------------------------------------------------------------ pruning
    def _row_tensors(self) -> dict[str, torch.Tensor]:
        out: dict[str, torch.Tensor] = {}
        for name in _PARAMS + _BUFFERS:
            if hasattr(self, name) and isinstance(getattr(self, name), torch.Tensor):
                out[name] = getattr(self, name)
        return out

    @torch.no_grad()
    def index_select(self, rows: torch.Tensor, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Keep the surfels ``rows`` ((M,) int64, in that order; or an (N,) bool keep mask), in place.

        Every per-surfel parameter and buffer is row-selected. Parameters are replaced by new
        ones; with ``optimizer`` given, its param groups and per-parameter state (tensors with N
        rows, e.g. Adam's moments) follow the same rows."""
        rows = rows.to(self.binding.device)
        if rows.dtype == torch.bool:
            if tuple(rows.shape) != (len(self),):
                raise ValueError(f"keep mask must be ({len(self)},), got {tuple(rows.shape)}")
            rows = torch.nonzero(rows, as_tuple=False).reshape(-1)
        rows = rows.long()
        for name, x in self._row_tensors().items():
            if name in _BUFFERS:
                setattr(self, name, x[rows].clone())
                continue
            new = nn.Parameter(x.data[rows].clone(), requires_grad=x.requires_grad)
            if optimizer is not None:
                replace_optimizer_param(optimizer, x, new, rows)
            setattr(self, name, new)

    @torch.no_grad()
    def extend(self, rows: Mapping[str, torch.Tensor], optimizer: torch.optim.Optimizer | None = None) -> int:
        """Append M new surfels, in place.

        rows: the new rows of every per-surfel parameter and of the ``binding`` and ``region_id``
        buffers (name -> (M, ...) tensor); the optional buffers (``wrinkle``, ``color_prior``, ``unseen_floor``) must be
        absent from the set. Parameters are replaced by longer ones; with ``optimizer`` given, its
        param groups follow and the per-row state (e.g. Adam's moments) of the new rows starts at
        zero. Returns M."""
        present = self._row_tensors()
        for name in ("wrinkle", "color_prior", "unseen_floor"):
            if name in present:
                raise ValueError(f"cannot extend a surfel set that has the {name!r} buffer")
        missing = [n for n in present if n not in rows]
        extra = [n for n in rows if n not in present]
        if missing or extra:
            raise ValueError(f"extend needs exactly the rows of {sorted(present)} (missing {missing}, unknown {extra})")
        m = int(rows["binding"].shape[0])
        for name, x in present.items():
            r = rows[name].to(device=x.device, dtype=x.dtype)
            if tuple(r.shape) != (m, *x.shape[1:]):
                raise ValueError(f"{name}: expected ({m}, {', '.join(map(str, x.shape[1:]))}) rows, got {tuple(r.shape)}")
            if name in _BUFFERS:
                setattr(self, name, torch.cat([x, r], 0))
                continue
            new = nn.Parameter(torch.cat([x.data, r], 0), requires_grad=x.requires_grad)
            if optimizer is not None:
                extend_optimizer_param(optimizer, x, new, m)
            setattr(self, name, new)
        return m

    def prune(self, remove: torch.Tensor, optimizer: torch.optim.Optimizer | None = None) -> int:
        """Remove the surfels where ``remove`` ((N,) bool) is True, in place (3DGS convention);
        see :meth:`index_select` for the optimizer. Returns how many were removed."""
        if remove.dtype != torch.bool or tuple(remove.shape) != (len(self),):
            raise ValueError(f"remove must be a ({len(self)},) bool mask")
        n_removed = int(remove.sum())
        if n_removed:
            self.index_select(~remove, optimizer)
        return n_removed

def _swap_optimizer_param(
    optimizer: torch.optim.Optimizer, old: torch.Tensor, new: nn.Parameter, per_row: Callable[[torch.Tensor], torch.Tensor]
) -> bool:
    """Swap ``old`` for ``new`` in ``optimizer``'s param groups; state tensors whose first
    dimension matches ``old``'s go through ``per_row``, other entries (e.g. Adam's ``step``) are
    copied. Returns False if ``old`` is not in the optimizer."""
    for group in optimizer.param_groups:
        for i, p in enumerate(group["params"]):
            if p is not old:
                continue
            group["params"][i] = new
            state = optimizer.state.pop(old, None)
            if state:
                optimizer.state[new] = {
                    key: per_row(v) if isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == old.shape[0] else v
                    for key, v in state.items()
                }
            return True
    return False


def replace_optimizer_param(
    optimizer: torch.optim.Optimizer, old: torch.Tensor, new: nn.Parameter, rows: torch.Tensor
) -> bool:
    """Swap ``old`` for ``new`` in ``optimizer``'s param groups and carry its state over.

    rows: (M,) int64 rows of ``old`` that ``new`` holds. State tensors whose first dimension
    matches ``old``'s are row-selected; other state entries (e.g. Adam's ``step``) are copied.
    Returns False if ``old`` is not in the optimizer.
    """
    return _swap_optimizer_param(optimizer, old, new, lambda v: v[rows.to(v.device)].clone())


def extend_optimizer_param(optimizer: torch.optim.Optimizer, old: torch.Tensor, new: nn.Parameter, n_new: int) -> bool:
    """Swap ``old`` for ``new`` (``old``'s rows followed by ``n_new`` more) in ``optimizer``'s param
    groups; state tensors whose first dimension matches ``old``'s get ``n_new`` zero rows, other
    state entries (e.g. Adam's ``step``) are copied. Returns False if ``old`` is not in the optimizer."""
    return _swap_optimizer_param(optimizer, old, new, lambda v: torch.cat([v, v.new_zeros((n_new, *v.shape[1:]))], 0))
