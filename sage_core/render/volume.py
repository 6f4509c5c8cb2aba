"""NeuS volume rendering of the canonical SDF and appearance networks, in pure torch (CPU and CUDA).

Sampling: rays are clipped to the SDF box (slab test); ``n_samples`` stratified samples are placed in
[near, far]; then NeuS-style up-sampling adds ``n_importance`` samples in ``up_sample_steps`` rounds, round h
using a fixed ``inv_s = 64 * 2**h`` and the exact discrete NeuS alpha of each section from the SDF at its two
end points, and drawing new samples by inverse-CDF sampling of those section weights (no gradient).
The final pass evaluates the SDF, its gradient and the appearance at section mid points and uses the NeuS
alpha with cos annealing (docs/rendering.md §9.2):

    c = d . grad f,  c~ = -(relu(-c/2 + 1/2) (1 - r) + relu(-c) r),  r = cos_anneal_ratio
    f_prev = f - c~ delta/2,  f_next = f + c~ delta/2,  Phi = sigmoid(inv_s * . / length_unit)
    alpha = clip((Phi_prev - Phi_next + 1e-5) / (Phi_prev + 1e-5), 0, 1),  w_i = alpha_i prod_{j<i} (1 - alpha_j)

Transmittance products run in float64.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import torch
from torch import nn

AppearanceFn = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""Colour of points: ``(x (M,3), view_dir (M,3), normal (M,3), feature (M,F)) -> (rgb (M,3), opacity (M,))``
(the appearance network, or a call of it with its parameters detached)."""


class SDFField(Protocol):
    """What the renderer needs from an SDF: a box and an autograd gradient."""

    bbox_min: torch.Tensor
    bbox_max: torch.Tensor

    def sdf(self, x: torch.Tensor) -> torch.Tensor: ...

    def gradient(
        self, x: torch.Tensor, create_graph: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]: ...


class SVariance(nn.Module):
    """Learnable NeuS sharpness: ``inv_s = clip(exp(10 * var), min_inv_s, max_inv_s)``; var0 = 0.3 (inv_s ~ 20)."""

    def __init__(self, init: float = 0.3, min_inv_s: float = 1e-6, max_inv_s: float = 1e6) -> None:
        super().__init__()
        self.variance = nn.Parameter(torch.tensor(float(init)))
        self.min_inv_s = float(min_inv_s)
        self.max_inv_s = float(max_inv_s)

    def forward(self) -> torch.Tensor:
        """-> inv_s, a 0-d tensor."""
        return torch.exp(self.variance * 10.0).clamp(self.min_inv_s, self.max_inv_s)


@dataclass
class NeuSOutput:
    """Per-ray results (R rays); per-sample tensors (S samples per ray) only when requested.

    color: (R, 3) sum_i w_i c_i + (1 - sum_i w_i) * background.
    depth: (R,) sum_i w_i t_i, t the distance along the unit ray direction (divide by weights_sum for the
        expected hit distance); 0 for rays that miss the box.
    normal: (R, 3) sum_i w_i n_i, unnormalized, n = grad f / |grad f| in world (canonical) space.
    weights_sum: (R,) sum_i w_i (opacity of the ray).
    hit: (R,) bool, the ray intersects the SDF box.
    t, weights, sdf: (R, S) sample distances, weights, SDF values (0 for missed rays).
    gradients: (R, S, 3) SDF gradients at the samples (differentiable when rendering with grad enabled:
        use them for the eikonal loss on ``sample_mask``).
    sample_mask: (R, S) bool, samples of rays that hit the box.
    """

    color: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    weights_sum: torch.Tensor
    hit: torch.Tensor
    t: torch.Tensor | None = None
    weights: torch.Tensor | None = None
    sdf: torch.Tensor | None = None
    gradients: torch.Tensor | None = None
    sample_mask: torch.Tensor | None = None


def ray_box_intersect(
    rays_o: torch.Tensor, rays_d: torch.Tensor, bbox_min: torch.Tensor, bbox_max: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test. rays_o, rays_d: (R, 3) (d need not be unit) -> t_near (R,), t_far (R,) in units of |d|;
    a ray misses when t_far <= max(t_near, 0)."""
    safe_d = torch.where(rays_d.abs() < 1e-12, torch.full_like(rays_d, 1e-12), rays_d)
    inv = 1.0 / safe_d
    t0 = (bbox_min.to(rays_o) - rays_o) * inv
    t1 = (bbox_max.to(rays_o) - rays_o) * inv
    t_near = torch.minimum(t0, t1).amax(-1)
    t_far = torch.maximum(t0, t1).amin(-1)
    return t_near, t_far


def neus_alpha(
    sdf: torch.Tensor,
    cos: torch.Tensor,
    dists: torch.Tensor,
    inv_s: torch.Tensor | float,
    cos_anneal_ratio: float,
) -> torch.Tensor:
    """NeuS alpha of samples at section mid points.

    sdf, cos (= d . grad f), dists: (...,) -> alpha (...,) in [0, 1]. ``inv_s`` already per length unit.
    """
    r = float(cos_anneal_ratio)
    if r == 1.0:  # the annealed term has weight 0 (the same values and gradients without it)
        iter_cos = -torch.relu(-cos)
    else:
        iter_cos = -(torch.relu(-cos * 0.5 + 0.5) * (1.0 - r) + torch.relu(-cos) * r)
    prev = sdf - iter_cos * dists * 0.5
    nxt = sdf + iter_cos * dists * 0.5
    prev_cdf = torch.sigmoid(prev * inv_s)
    next_cdf = torch.sigmoid(nxt * inv_s)
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)


def _weights_from_alpha(alpha: torch.Tensor) -> torch.Tensor:
    """alpha: (R, S) -> weights (R, S) = alpha_i prod_{j<i}(1 - alpha_j), transmittance in float64."""
    one_minus = (1.0 - alpha.double()).clamp_min(0.0) + 1e-7
    trans = torch.cumprod(torch.cat([torch.ones_like(one_minus[:, :1]), one_minus[:, :-1]], -1), -1)
    return alpha * trans.to(alpha.dtype)


def _section_alpha(sdf: torch.Tensor, inv_s: float) -> torch.Tensor:
    """Discrete NeuS alpha of sections between consecutive samples: sdf (R, S) -> (R, S-1)."""
    prev_cdf = torch.sigmoid(sdf[:, :-1] * inv_s)
    next_cdf = torch.sigmoid(sdf[:, 1:] * inv_s)
    return ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0)


def _sample_pdf(
    edges: torch.Tensor, weights: torch.Tensor, n: int, perturb: bool, generator: torch.Generator | None
) -> torch.Tensor:
    """Inverse-CDF samples: edges (R, S) sorted, weights (R, S-1) -> (R, n) piecewise uniform in sections."""
    w = weights + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)  # (R, S)
    r = edges.shape[0]
    if perturb:
        u = torch.rand((r, n), generator=generator, device="cpu", dtype=edges.dtype).to(edges.device)
        u, _ = torch.sort(u, -1)
    else:
        u = torch.linspace(0.5 / n, 1.0 - 0.5 / n, n, dtype=edges.dtype, device=edges.device).expand(r, n)
    u = u.contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(0, edges.shape[1] - 1)
    above = idx.clamp(0, edges.shape[1] - 1)
    c0, c1 = torch.gather(cdf, 1, below), torch.gather(cdf, 1, above)
    e0, e1 = torch.gather(edges, 1, below), torch.gather(edges, 1, above)
    denom = torch.where(c1 - c0 < 1e-5, torch.ones_like(c0), c1 - c0)
    return e0 + (u - c0) / denom * (e1 - e0)


def _render_hits(
    sdf_net: SDFField,
    app_net: AppearanceFn,
    o: torch.Tensor,
    d: torch.Tensor,
    near: torch.Tensor,
    far: torch.Tensor,
    inv_s: torch.Tensor,
    n_samples: int,
    n_importance: int,
    up_sample_steps: int,
    cos_anneal_ratio: float,
    perturb: bool,
    generator: torch.Generator | None,
    length_unit: float,
    create_graph: bool,
) -> dict[str, torch.Tensor]:
    r = o.shape[0]
    dtype, device = o.dtype, o.device
    if perturb:
        u = torch.rand((r, n_samples), generator=generator, device="cpu", dtype=dtype).to(device)
    else:
        u = torch.full((r, n_samples), 0.5, dtype=dtype, device=device)
    bins = torch.arange(n_samples, dtype=dtype, device=device)[None]
    z = near[:, None] + (far - near)[:, None] * (bins + u) / n_samples  # (R, S)

    if n_importance > 0 and up_sample_steps > 0:
        with torch.no_grad():
            f = sdf_net.sdf((o[:, None] + d[:, None] * z[..., None]).reshape(-1, 3)).reshape(r, -1)
            base = n_importance // up_sample_steps
            counts = [base + (1 if h < n_importance - base * up_sample_steps else 0) for h in range(up_sample_steps)]
            for h, k in enumerate(counts):
                if k == 0:
                    continue
                s = 64.0 * 2**h / length_unit
                alpha = _section_alpha(f, s)
                w = _weights_from_alpha(alpha)
                z_new = _sample_pdf(z, w, k, perturb, generator)
                f_new = sdf_net.sdf((o[:, None] + d[:, None] * z_new[..., None]).reshape(-1, 3)).reshape(r, -1)
                z, order = torch.sort(torch.cat([z, z_new], -1), -1)
                f = torch.gather(torch.cat([f, f_new], -1), 1, order)
        z = z.detach()

    dists = z[:, 1:] - z[:, :-1]
    last = ((far - near) / n_samples)[:, None]
    dists = torch.cat([dists, last], -1)
    mid = z + 0.5 * dists
    s_tot = mid.shape[1]
    pts = (o[:, None] + d[:, None] * mid[..., None]).reshape(-1, 3)
    dirs = d[:, None].expand(-1, s_tot, -1).reshape(-1, 3)
    sdf, grad, feature = sdf_net.gradient(pts, create_graph=create_graph)
    normal = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    rgb, _ = app_net(pts, dirs, normal, feature)
    cos = (dirs * grad).sum(-1)
    alpha = neus_alpha(sdf, cos, dists.reshape(-1), inv_s / length_unit, cos_anneal_ratio).reshape(r, s_tot)
    weights = _weights_from_alpha(alpha)
    return {
        "color": (weights[..., None] * rgb.reshape(r, s_tot, 3)).sum(1),
        "depth": (weights * mid).sum(1),
        "normal": (weights[..., None] * normal.reshape(r, s_tot, 3)).sum(1),
        "weights_sum": weights.sum(1),
        "t": mid,
        "weights": weights,
        "sdf": sdf.reshape(r, s_tot),
        "gradients": grad.reshape(r, s_tot, 3),
    }


def _rows_of_all_rays(
    pieces: list[torch.Tensor], hit_idx: torch.Tensor, shape: tuple[int, ...], dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """One per-ray output for all R rays, ``shape`` (R, ...): ``pieces`` are the chunks' rows of the rays
    ``hit_idx`` (H,) that hit the box, in that order; they are placed at their rays over zeros, or returned
    as they are when every ray hit."""
    if not pieces:
        return torch.zeros(shape, dtype=dtype, device=device)
    rows = pieces[0] if len(pieces) == 1 else torch.cat(pieces, 0)
    if hit_idx.shape[0] == shape[0]:  # hit_idx is arange(R)
        return rows
    return torch.zeros(shape, dtype=dtype, device=device).index_copy(0, hit_idx, rows)


def render_neus(
    sdf_net: SDFField,
    app_net: AppearanceFn,
    rays_o: torch.Tensor,
    rays_d: torch.Tensor,
    inv_s: SVariance | torch.Tensor | float,
    n_samples: int = 64,
    n_importance: int = 64,
    up_sample_steps: int = 4,
    cos_anneal_ratio: float = 1.0,
    background: torch.Tensor | float = 1.0,
    near_min: float = 0.0,
    length_unit: float = 1.0,
    chunk: int = 4096,
    perturb: bool = False,
    generator: torch.Generator | None = None,
    return_samples: bool = False,
) -> NeuSOutput:
    """Render rays through the canonical SDF with NeuS.

    sdf_net: an ``SDFField`` (``SDFNetwork`` or any object with bbox_min/bbox_max, ``sdf``, ``gradient``).
    app_net: callable ``(x (M,3), view_dir (M,3), normal (M,3), feature (M,F)) -> (rgb (M,3), opacity (M,))``.
    rays_o, rays_d: (R, 3) origins and directions (directions are normalized here).
    inv_s: an ``SVariance`` module, a 0-d tensor or a float (sharpness per ``length_unit``).
    n_samples: stratified samples in [near, far]; n_importance / up_sample_steps: NeuS up-sampling.
    cos_anneal_ratio: r = min(1, step / cos_anneal_end) (cos_anneal_end 20000 in NeuS).
    background: (3,), (R, 3) or a scalar colour composited with weight 1 - sum w.
    near_min: smallest t (e.g. to skip the region behind a camera inside the box).
    length_unit: the SDF is divided by it inside the logistic, so that inv_s (init ~20) means the same for a
        world-unit SDF as for a unit-box scene; pass ``sdf_net.half_extent`` for an ``SDFNetwork``.
    chunk: rays per network pass; perturb/generator: random stratification and up-sampling (CPU generator).
    return_samples: also return the per-sample tensors (t, weights, sdf, gradients, sample_mask).

    Gradients (for the eikonal loss and the rendered normal) keep their graph when grad mode is enabled.
    """
    if isinstance(inv_s, SVariance):
        inv_s_t = inv_s()
    else:
        inv_s_t = torch.as_tensor(inv_s, dtype=rays_o.dtype, device=rays_o.device)
    r = rays_o.shape[0]
    dtype, device = rays_o.dtype, rays_o.device
    d = rays_d / rays_d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t_near, t_far = ray_box_intersect(rays_o, d, sdf_net.bbox_min, sdf_net.bbox_max)
    t_near = t_near.clamp_min(near_min)
    hit = t_far > t_near
    s_tot = n_samples + (n_importance if up_sample_steps > 0 else 0)
    create_graph = torch.is_grad_enabled()

    keys = ["color", "depth", "normal", "weights_sum"]
    if return_samples:
        keys += ["t", "weights", "sdf", "gradients"]
    pieces: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    hit_idx = torch.nonzero(hit, as_tuple=False).reshape(-1)
    for start in range(0, hit_idx.shape[0], max(1, chunk)):
        idx = hit_idx[start : start + chunk]
        out = _render_hits(
            sdf_net, app_net, rays_o[idx], d[idx], t_near[idx], t_far[idx], inv_s_t,
            n_samples, n_importance, up_sample_steps, cos_anneal_ratio, perturb, generator,
            float(length_unit), create_graph,
        )  # fmt: skip
        for k in keys:
            pieces[k].append(out[k])
    shapes = {"color": (3,), "depth": (), "normal": (3,), "weights_sum": (), "t": (s_tot,),
              "weights": (s_tot,), "sdf": (s_tot,), "gradients": (s_tot, 3)}  # fmt: skip
    full = {k: _rows_of_all_rays(pieces[k], hit_idx, (r, *shapes[k]), dtype, device) for k in keys}
    color, depth, normal, wsum = full["color"], full["depth"], full["normal"], full["weights_sum"]

    bg = torch.as_tensor(background, dtype=dtype, device=device)
    bg = bg.expand(r, 3) if bg.dim() <= 1 else bg
    color = color + (1.0 - wsum)[:, None] * bg
    result = NeuSOutput(color=color, depth=depth, normal=normal, weights_sum=wsum, hit=hit)
    if return_samples:
        result.t = full["t"]
        result.weights = full["weights"]
        result.sdf = full["sdf"]
        result.gradients = full["gradients"]
        result.sample_mask = hit[:, None].expand(r, s_tot).clone()
    return result


def default_length_unit(sdf_net: object) -> float:
    """``sdf_net.half_extent`` when present (SDFNetwork), else 1."""
    return float(getattr(sdf_net, "half_extent", 1.0))
