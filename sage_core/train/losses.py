"""Training losses (SAGE §1–2, 2DGS, NeuS / MonoSDF regularisers) and the loss-term table.

Each loss function returns a 0-d tensor. Images are channels-last ``(H, W, C)``; per-ray quantities
are ``(R, ...)``.

A phase declares its objective once, as a tuple of :class:`LossTerm` (name, weight field, first
step, whether it runs during phase 1's polish, the function that computes it), and
:func:`add_terms` runs that table each step: it skips the terms that are off (weight 0, not
started, not applicable to the step), computes the others in table order, records each one under
its name and returns the weighted sum. The tables are ``sage_core.train.phase1.PHASE1_TERMS`` and
``sage_core.train.phase2.PHASE2_TERMS``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Generic, Protocol, TypeVar

import torch
import torch.nn.functional as F

from ..image_metrics import SSIMTarget, ssim


class StepContext(Protocol):
    """What :func:`add_terms` reads of a phase's per-step context (the rest is the phase's own)."""

    step: int
    """The step being made (0-based: the trainer's step count before it advances)."""
    polish: bool
    """Whether the step lies in phase 1's polish (always False in phase 2)."""


Ctx = TypeVar("Ctx", bound=StepContext)


@dataclass(frozen=True)
class LossTerm(Generic[Ctx]):
    """One term of a phase's objective.

    name: key of the term in the step's output (the per-term metrics). weight: the field of the
    phase config's ``loss`` section holding its weight, or a function of the step context (e.g. a
    pseudo view's weight); None: weight 1. compute: the term's value (0-d tensor) for a step
    context, or None when the step has nothing to measure it on. start: the field of the ``schedule``
    section holding its first step (None: from step 0). polish: whether the term stays on during
    phase 1's polish. when: a condition on the step context beyond weight and start (None: always).
    group: terms of one group are summed on their own before their sum joins the total (the order
    of the floating-point additions, kept as the phases always summed them).
    """

    name: str
    weight: str | Callable[[Ctx], float] | None
    compute: Callable[[Ctx], torch.Tensor | None]
    start: str | None = None
    polish: bool = True
    when: Callable[[Ctx], bool] | None = None
    group: str | None = None

    def weight_of(self, ctx: Ctx, weights: Any) -> float:
        """The term's weight at this step (``weights``: the config's ``loss`` section)."""
        if self.weight is None:
            return 1.0
        if callable(self.weight):
            return float(self.weight(ctx))
        return float(getattr(weights, self.weight))

    def active(self, ctx: Ctx, weight: float, schedule: Any) -> bool:
        """Whether the term is computed at this step (``schedule``: the config's ``schedule`` section)."""
        if weight <= 0 or (ctx.polish and not self.polish):
            return False
        if self.start is not None and ctx.step < int(getattr(schedule, self.start)):
            return False
        return self.when is None or bool(self.when(ctx))


def add_terms(
    table: tuple[LossTerm[Ctx], ...], ctx: Ctx, weights: Any, schedule: Any, terms: dict[str, torch.Tensor]
) -> torch.Tensor | None:
    """Run a loss-term table for one step: each active term's value goes into ``terms`` under its
    name; returns Σ weight·value in table order (a group's terms summed first, from zero), or None
    when no term is active."""
    total: torch.Tensor | None = None
    group: str | None = None
    subtotal: torch.Tensor | None = None

    def close(total: torch.Tensor | None, subtotal: torch.Tensor | None) -> torch.Tensor | None:
        if subtotal is None:
            return total
        return subtotal if total is None else total + subtotal

    for term in table:
        if term.group != group:
            total, subtotal, group = close(total, subtotal), None, term.group
        w = term.weight_of(ctx, weights)
        if not term.active(ctx, w, schedule):
            continue
        value = term.compute(ctx)
        if value is None:
            continue
        terms[term.name] = value
        part = value if term.weight is None else w * value
        if group is None:
            total = part if total is None else total + part
        else:
            subtotal = (value.new_zeros(()) if subtotal is None else subtotal) + part
    return close(total, subtotal)


def _masked_mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype)
    while m.dim() < x.dim():
        m = m.unsqueeze(-1)
    m = m.expand_as(x)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def rgb_loss(
    pred: torch.Tensor, gt: torch.Tensor, ssim_weight: float = 0.2, target: SSIMTarget | None = None
) -> torch.Tensor:
    """L_rgb = (1 − w)·L1 + w·(1 − SSIM), w = 0.2 (3DGS / 2DGS). pred, gt: (H, W, 3); target: gt's
    kept :func:`ssim_target` (of ``gt.permute(2, 0, 1)[None]``), made here when None."""
    l1 = (pred - gt).abs().mean()
    if ssim_weight == 0:
        return l1
    s = ssim(pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None] if target is None else target).mean()
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - s)


def point_sdf_loss(sdf: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """L_pt = mean |f(x_G)| / scale. sdf: (N,) SDF values at the canonical surfel centres."""
    return sdf.abs().mean() / scale


def align_loss(surfel_normals: torch.Tensor, sdf_grad: torch.Tensor) -> torch.Tensor:
    """L_align = mean |1 − |t3ᵀ n̂||, n̂ = ∇f/‖∇f‖. surfel_normals: (N, 3) unit t3; sdf_grad: (N, 3)."""
    n = sdf_grad / sdf_grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return (1.0 - (surfel_normals * n).sum(-1).abs()).abs().mean()


def depth_loss(sdf_depth: torch.Tensor, surfel_depth: torch.Tensor, mask: torch.Tensor | None = None, scale: float = 1.0) -> torch.Tensor:
    """L_D: mean |t_sdf − t_surfel| / scale over the mask.

    Both are distances along the same canonical rays (R,). The surfel depth is metric in the same
    space as the SDF, so no MonoSDF scale/shift fit is needed. The caller decides what is
    detached; phase 1 detaches the surfel side so the surfels' depth supervises the SDF.
    """
    return _masked_mean((sdf_depth - surfel_depth).abs(), mask) / scale


def normal_loss(sdf_normal: torch.Tensor, surfel_normal: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_N (MonoSDF): mean ‖n̂ − n̄‖₁ + mean (1 − n̂·n̄), both normalised. (R, 3) each, canonical space."""
    a = F.normalize(sdf_normal, dim=-1, eps=1e-12)
    b = F.normalize(surfel_normal, dim=-1, eps=1e-12)
    l1 = (a - b).abs().sum(-1)
    ang = 1.0 - (a * b).sum(-1)
    return _masked_mean(l1, mask) + _masked_mean(ang, mask)


def eikonal_loss(grad: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """mean (‖∇f‖ − 1)². grad: (M, 3) (or (R, S, 3) with mask (R, S))."""
    return _masked_mean((grad.norm(dim=-1) - 1.0) ** 2, mask)


def normal_smoothness_loss(normal_a: torch.Tensor, normal_b: torch.Tensor) -> torch.Tensor:
    """MonoSDF smoothness mean ‖n(x) − n(x + δ)‖ of unit SDF normals (M, 3) at x and x + δ."""
    a = F.normalize(normal_a, dim=-1, eps=1e-12)
    b = F.normalize(normal_b, dim=-1, eps=1e-12)
    return (a - b).norm(dim=-1).mean()


def normal_consistency_loss(render_normal: torch.Tensor, surf_normal: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """2DGS L_n = mean_pix (1 − Σ_ch N_r·N_s).

    render_normal: (H, W, 3) Σ w·n (unnormalised, as rasterized); surf_normal: (H, W, 3) normal from
    the rendered depth, already multiplied by A.detach() (``SurfelRender.surf_normal_*``). Both in
    the same frame.
    """
    return _masked_mean(1.0 - (render_normal * surf_normal).sum(-1), mask)


def distortion_loss(distortion: torch.Tensor) -> torch.Tensor:
    """2DGS depth distortion: mean of the per-pixel Σ_i w_i Σ_{j<i} w_j (m_i − m_j)². (H, W)."""
    return distortion.mean()


def neus_rgb_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """L1 between the NeuS colours of sampled rays and the image. (R, 3) each."""
    return (pred - gt).abs().mean()


def mask_bce_loss(opacity: torch.Tensor, mask: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Binary cross-entropy of ray opacities against a soft foreground mask (NeuS "with mask").

    opacity: (R,) accumulated weights in [0, 1]; mask: (R,) in [0, 1]. The opacity is clamped to
    [eps, 1 - eps] so a fully transparent or opaque ray keeps a finite loss.
    """
    o = opacity.clamp(eps, 1.0 - eps)
    return F.binary_cross_entropy(o, mask.to(o.dtype))


def alpha_mask_loss(alpha: torch.Tensor, mask: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |alpha − mask| of a rendered alpha against the foreground mask, (H, W) each; with a
    per-pixel weight (H, W) the mean of weight·|alpha − mask| over all pixels."""
    d = (alpha.reshape(mask.shape) - mask).abs()
    return d.mean() if weight is None else (d * weight).mean()


def local_position_loss(mu_loc: torch.Tensor, threshold: float = 1.0) -> torch.Tensor:
    """GaussianAvatars' position term: mean relu(‖μ_loc‖ − threshold) of the local offsets (N, 3),
    in units of the bound triangle's scale k (free surfels may stray that far before it acts); 0
    for N = 0."""
    return torch.relu(mu_loc.norm(dim=-1) - threshold).sum() / max(1, mu_loc.shape[0])


def local_scale_loss(s_loc: torch.Tensor, threshold: float = 0.6) -> torch.Tensor:
    """GaussianAvatars' scale term: mean ‖relu(exp(s_loc) − threshold)‖ of the log local scales
    (N, 2), relative to k (keeps surfels from growing far beyond their triangle); 0 for N = 0."""
    return torch.relu(torch.exp(s_loc) - threshold).norm(dim=-1).sum() / max(1, s_loc.shape[0])
