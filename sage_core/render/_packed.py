"""Packed pure-torch 2DGS compositing for one camera (docs/rendering.md §3).

Stage A (no grad, chunked): enumerate (surfel, pixel) candidates inside each surfel's tile
rectangle (trimmed to where α can reach 1/255), evaluate α, and keep significant pairs.
Stage B (differentiable): re-evaluate the kept pairs, sort them by (pixel, centre-depth rank),
get transmittance from a float64 segmented exclusive cumsum of log(1 − α) and composite with
``index_add``. Every buffer is channels-first internally, (ch, H·W).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ._project import ALPHA_MIN

ALPHA_MAX = 0.99
T_MIN = 1e-4


IMAGE_OUTPUTS: tuple[str, ...] = (
    "color", "alpha", "depth", "depth_sum", "median_depth",
    "normal_cam", "normal_world", "surf_normal_cam", "surf_normal_world", "distortion",
)  # fmt: skip
"""The image fields of ``rasterize_surfels``' result (``SurfelRender``), in order; the native
backend returns them in this order."""


@dataclass
class PackedImages:
    """Per-camera buffers, flattened over pixels (index = y·W + x).

    features: (D, HW) Σ w·f (no background), alpha: (HW,), depth_sum: (HW,) Σ w·z,
    normal: (3, HW) Σ w·n (camera frame), median: (HW,), distortion: (HW,), num_pairs: kept pairs.
    """

    features: torch.Tensor
    alpha: torch.Tensor
    depth_sum: torch.Tensor
    normal: torch.Tensor
    median: torch.Tensor
    distortion: torch.Tensor
    num_pairs: int


def eval_pairs(
    g: torch.Tensor, xf: torch.Tensor, yf: torch.Tensor, use3d: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Ray–splat intersection, low-pass filter and α for a list of (surfel, pixel) pairs (§1.3–1.5).

    g: (12, P) per-pair rows Tu − c_x·Tw (3), Tv − c_y·Tw (3), Tw (3), c_x, c_y, opacity, where c
    is the low-pass centre. Shifting the rows by the centre leaves h = k × l unchanged (k and l are
    computed from x − c_x and y − c_y) and keeps float32 cancellation small.
    xf, yf: (P,) pixel-centre coordinates. use3d: (P,) bool branch choice from an earlier no-grad
    evaluation of the same pairs (it guards the division for 2D-branch pairs), or None to decide here.
    Returns alpha (P,), z (P,) (intersection depth on the 3D branch, centre depth on the 2D branch),
    h_z (P,) and use3d (P,).
    """
    tu0, tu1, tu2, tv0, tv1, tv2, tw0, tw1, tw2, cx, cy, o = g.unbind(0)
    dx = xf - cx
    dy = yf - cy
    k0 = dx * tw0 - tu0
    k1 = dx * tw1 - tu1
    k2 = dx * tw2 - tu2
    l0 = dy * tw0 - tv0
    l1 = dy * tw1 - tv1
    l2 = dy * tw2 - tv2
    hx = k1 * l2 - k2 * l1
    hy = k2 * l0 - k0 * l2
    hz = k0 * l1 - k1 * l0
    rho2d = 2.0 * (dx * dx + dy * dy)
    if use3d is None:
        u = hx / hz
        v = hy / hz
        rho3d = u * u + v * v
        use3d = rho3d <= rho2d
    else:
        hz_s = torch.where(use3d, hz, torch.ones_like(hz))
        u = hx / hz_s
        v = hy / hz_s
        rho3d = u * u + v * v
    rho = torch.where(use3d, rho3d, rho2d)
    z = torch.where(use3d, tw0 * u + tw1 * v + tw2, tw2)
    alpha = (o * torch.exp(-0.5 * rho)).clamp_max(ALPHA_MAX)
    return alpha, z, hz, use3d


class _PairEval(torch.autograd.Function):
    """α and depth of (surfel, pixel) pairs with a hand-written backward that recomputes the
    intersection instead of storing ~20 per-pair intermediates (same maths as :func:`eval_pairs`).

    table: (12, Nv) per-surfel rows (see ``eval_pairs``); rank: (K,) surfel of each pair;
    xf, yf: (K,) pixel centres; use3d: (K,) branch. Returns alpha (K,), z (K,), h_z (K,).
    """

    @staticmethod
    def forward(ctx, table, rank, xf, yf, use3d):  # type: ignore[override]
        g = table.index_select(1, rank)
        alpha, z, hz, _ = eval_pairs(g, xf, yf, use3d)
        ctx.save_for_backward(table, rank, xf, yf, use3d)
        ctx.mark_non_differentiable(hz)
        return alpha, z, hz

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_alpha, g_z, _g_hz):  # type: ignore[override]
        table, rank, xf, yf, use3d = ctx.saved_tensors
        tu0, tu1, tu2, tv0, tv1, tv2, tw0, tw1, tw2, cx, cy, o = table.index_select(1, rank).unbind(0)
        dx = xf - cx
        dy = yf - cy
        k0, k1, k2 = dx * tw0 - tu0, dx * tw1 - tu1, dx * tw2 - tu2
        l0, l1, l2 = dy * tw0 - tv0, dy * tw1 - tv1, dy * tw2 - tv2
        hx = k1 * l2 - k2 * l1
        hy = k2 * l0 - k0 * l2
        hz = torch.where(use3d, k0 * l1 - k1 * l0, torch.ones_like(dx))
        u = hx / hz
        v = hy / hz
        rho = torch.where(use3d, u * u + v * v, 2.0 * (dx * dx + dy * dy))
        e = torch.exp(-0.5 * rho)
        G = o * e
        g_a = torch.where(G <= ALPHA_MAX, g_alpha, torch.zeros_like(g_alpha))  # the clamp passes no gradient
        g_o = g_a * e
        g_rho = -0.5 * g_a * G
        zero = torch.zeros_like(dx)
        # 3D branch: ρ = u² + v², z = Tw·(u, v, 1)
        g_u = torch.where(use3d, 2.0 * g_rho * u + g_z * tw0, zero)
        g_v = torch.where(use3d, 2.0 * g_rho * v + g_z * tw1, zero)
        g_hx = g_u / hz
        g_hy = g_v / hz
        g_hz = -(g_u * u + g_v * v) / hz
        # h = k × l: ∂/∂k = l × g_h, ∂/∂l = g_h × k
        g_k0 = l1 * g_hz - l2 * g_hy
        g_k1 = l2 * g_hx - l0 * g_hz
        g_k2 = l0 * g_hy - l1 * g_hx
        g_l0 = g_hy * k2 - g_hz * k1
        g_l1 = g_hz * k0 - g_hx * k2
        g_l2 = g_hx * k1 - g_hy * k0
        g_z3 = torch.where(use3d, g_z, zero)
        g_tw0 = dx * g_k0 + dy * g_l0 + g_z3 * u
        g_tw1 = dx * g_k1 + dy * g_l1 + g_z3 * v
        g_tw2 = dx * g_k2 + dy * g_l2 + g_z  # both branches: z contains Tw2 with slope 1
        # 2D branch: ρ = 2(dx² + dy²)
        g_rho2 = torch.where(use3d, zero, 4.0 * g_rho)
        g_dx = g_k0 * tw0 + g_k1 * tw1 + g_k2 * tw2 + g_rho2 * dx
        g_dy = g_l0 * tw0 + g_l1 * tw1 + g_l2 * tw2 + g_rho2 * dy
        rows = torch.stack(
            [-g_k0, -g_k1, -g_k2, -g_l0, -g_l1, -g_l2, g_tw0, g_tw1, g_tw2, -g_dx, -g_dy, g_o]
        )
        return torch.zeros_like(table).index_add(1, rank, rows), None, None, None, None


def _significant(alpha: torch.Tensor, z: torch.Tensor, hz: torch.Tensor, near: float) -> torch.Tensor:
    return (hz != 0) & (z >= near) & (alpha >= ALPHA_MIN)


def _segment_starts(pix: torch.Tensor) -> torch.Tensor:
    """For pixel ids sorted ascending (K,), the index of the first pair of each pair's run (K,)."""
    K = pix.shape[0]
    idx = torch.arange(K, device=pix.device)
    is_start = torch.ones(K, dtype=torch.bool, device=pix.device)
    if K > 1:
        is_start[1:] = pix[1:] != pix[:-1]
    return torch.cummax(torch.where(is_start, idx, torch.zeros_like(idx)), 0).values


def segmented_exclusive_cumsum(x: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
    """Σ_{j<i, same run} x_j for runs given by ``starts`` (K,) -> (K,). Use float64 inputs."""
    ex = torch.cumsum(x, 0) - x
    return ex - ex[starts]


def distortion_autograd(
    w: torch.Tensor, m: torch.Tensor, pix: torch.Tensor, starts: torch.Tensor, num_pixels: int
) -> torch.Tensor:
    """Per-pixel Σ_i w_i Σ_{j<i} w_j (m_i − m_j)² by the one-pass running sums (§2.3, §3.4).

    Plain autograd over segmented cumsums; the renderer uses :func:`distortion_closed_form`, which
    has the same value and an exact closed-form backward that stores far less.
    w, m: (K,) float64 weights and normalized depths of pairs sorted by pixel and compositing
    order; pix: (K,) pixel ids; starts: (K,) run starts. m is shifted per pixel by its first pair's
    (detached) value, which leaves the loss and its gradient unchanged and avoids cancellation.
    Returns (num_pixels,) float64.
    """
    mt = m - m.detach()[starts]
    A = segmented_exclusive_cumsum(w, starts)
    M1 = segmented_exclusive_cumsum(w * mt, starts)
    M2 = segmented_exclusive_cumsum(w * mt * mt, starts)
    per_pair = w * (mt * mt * A + M2 - 2.0 * mt * M1)
    return torch.zeros(num_pixels, dtype=w.dtype, device=w.device).index_add(0, pix, per_pair)


class _Distortion(torch.autograd.Function):
    """Distortion with the exact backward of §2.3 from the per-pixel totals A_f, M1_f, M2_f."""

    @staticmethod
    def forward(ctx, w, m, pix, starts, num_pixels):  # type: ignore[override]
        mt = m - m[starts]
        A = segmented_exclusive_cumsum(w, starts)
        M1 = segmented_exclusive_cumsum(w * mt, starts)
        M2 = segmented_exclusive_cumsum(w * mt * mt, starts)
        per_pair = w * (mt * mt * A + M2 - 2.0 * mt * M1)
        zeros = torch.zeros(num_pixels, dtype=w.dtype, device=w.device)
        out = zeros.index_add(0, pix, per_pair)
        totals = torch.stack(
            [zeros.index_add(0, pix, w), zeros.index_add(0, pix, w * mt), zeros.index_add(0, pix, w * mt * mt)]
        )
        ctx.save_for_backward(w, mt, pix, totals)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        w, mt, pix, totals = ctx.saved_tensors
        g = grad.index_select(0, pix)
        Af, M1f, M2f = totals.index_select(1, pix).unbind(0)
        dw = g * (mt * mt * Af - 2.0 * mt * M1f + M2f) if ctx.needs_input_grad[0] else None
        dm = g * 2.0 * w * (mt * Af - M1f) if ctx.needs_input_grad[1] else None
        return dw, dm, None, None, None


def distortion_closed_form(
    w: torch.Tensor, m: torch.Tensor, pix: torch.Tensor, starts: torch.Tensor, num_pixels: int
) -> torch.Tensor:
    """Same as :func:`distortion_autograd`, with ∂L/∂w_k = m_k²A_f − 2m_kM1_f + M2_f and
    ∂L/∂m_k = 2w_k(m_kA_f − M1_f) (totals over the pixel's contributors) as the backward."""
    return _Distortion.apply(w, m, pix, starts, num_pixels)


class _WeightedPixelSum(torch.autograd.Function):
    """out[:, p] = Σ_{k: pix_k = p} w_k · payload[:, rank_k]; stores only w and the index lists."""

    @staticmethod
    def forward(ctx, payload, w, rank, pix, num_pixels):  # type: ignore[override]
        vals = payload.index_select(1, rank) * w
        out = torch.zeros(payload.shape[0], num_pixels, dtype=vals.dtype, device=vals.device).index_add(1, pix, vals)
        ctx.save_for_backward(payload, w, rank, pix)
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        payload, w, rank, pix = ctx.saved_tensors
        g = grad.index_select(1, pix)  # (ch, K)
        dpay = dw = None
        if ctx.needs_input_grad[1]:
            dw = (g * payload.index_select(1, rank)).sum(0)
        if ctx.needs_input_grad[0]:
            dpay = torch.zeros_like(payload).index_add(1, rank, g * w)
        return dpay, dw, None, None, None


class _PixelSum(torch.autograd.Function):
    """out[:, p] = Σ_{k: pix_k = p} vals[:, k]; stores only the pixel ids."""

    @staticmethod
    def forward(ctx, vals, pix, num_pixels):  # type: ignore[override]
        ctx.save_for_backward(pix)
        return torch.zeros(vals.shape[0], num_pixels, dtype=vals.dtype, device=vals.device).index_add(1, pix, vals)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        (pix,) = ctx.saved_tensors
        return grad.index_select(1, pix), None, None


def normalized_depth(z: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """m(z) = far/(far − near)·(1 − near/z): maps [near, far] to [0, 1]."""
    return far / (far - near) * (1.0 - near / z)


def _candidates(
    table: torch.Tensor,
    boxes: torch.Tensor,
    width: int,
    near: float,
    chunk_pairs: int,
    progress: Callable[[int, int], None] | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Stage A. table: (12, Nv) in compositing (depth-rank) order; boxes: (Nv, 4) pixel boxes.

    Returns (rank (Kc,), pixel (Kc,), use3d (Kc,)) of significant pairs, rank ascending.
    """
    device = table.device
    bw = boxes[:, 2] - boxes[:, 0]
    bh = boxes[:, 3] - boxes[:, 1]
    counts = (bw * bh).clamp_min(0)
    total = int(counts.sum())
    empty = torch.zeros(0, dtype=torch.long, device=device)
    if total == 0:
        return empty, empty, torch.zeros(0, dtype=torch.bool, device=device)
    ends = torch.cumsum(counts, 0)
    chunk_of = torch.div(ends - counts, max(1, int(chunk_pairs)), rounding_mode="floor")
    _, per_chunk = torch.unique_consecutive(chunk_of, return_counts=True)
    bounds = [0] + torch.cumsum(per_chunk, 0).tolist()
    out_rank, out_pix, out_3d = [], [], []
    for ci in range(len(bounds) - 1):
        s0, s1 = bounds[ci], bounds[ci + 1]
        cnt = counts[s0:s1]
        P = int(cnt.sum())
        if P == 0:
            continue
        local = torch.repeat_interleave(torch.arange(s0, s1, device=device), cnt, output_size=P)
        first = torch.cumsum(cnt, 0) - cnt
        off = torch.arange(P, device=device) - torch.repeat_interleave(first, cnt, output_size=P)
        bwl = bw[local]
        oy = torch.div(off, bwl, rounding_mode="floor")
        px = boxes[local, 0] + (off - oy * bwl)
        py = boxes[local, 1] + oy
        del off, oy, bwl
        g = table.index_select(1, local)
        alpha, z, hz, use3d = eval_pairs(g, px.to(table.dtype) + 0.5, py.to(table.dtype) + 0.5)
        keep = _significant(alpha, z, hz, near)
        out_rank.append(local[keep])
        out_pix.append((py * width + px)[keep])
        out_3d.append(use3d[keep])
        if progress is not None:
            progress(ci + 1, len(bounds) - 1)
    return torch.cat(out_rank), torch.cat(out_pix), torch.cat(out_3d)


def composite_packed(
    table: torch.Tensor,
    payload: torch.Tensor,
    boxes: torch.Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    chunk_pairs: int,
    progress: Callable[[int, int], None] | None = None,
) -> PackedImages:
    """Render one camera from surfels already sorted by centre depth.

    table: (12, Nv) rows Tu − c_x·Tw, Tv − c_y·Tw, Tw, low-pass centre c (2), opacity; differentiable.
    payload: (D + 3, Nv) features then camera-frame normals; differentiable.
    boxes: (Nv, 4) int64 candidate pixel boxes (see ``candidate_pixel_boxes``).
    """
    HW = width * height
    dtype, device = table.dtype, table.device
    Nv = table.shape[1]
    with torch.no_grad():
        rank, pix, use3d = _candidates(table.detach(), boxes, width, near, chunk_pairs, progress)
        key = pix * max(Nv, 1) + rank
        key, order = torch.sort(key)
        pix = torch.div(key, max(Nv, 1), rounding_mode="floor")
        rank = key - pix * max(Nv, 1)
        use3d = use3d[order]
        del key, order
        xf = (pix % width).to(dtype) + 0.5
        yf = torch.div(pix, width, rounding_mode="floor").to(dtype) + 0.5
        starts = _segment_starts(pix)

    alpha, z, hz = _PairEval.apply(table, rank, xf, yf, use3d)
    with torch.no_grad():
        sig = _significant(alpha, z, hz, near)  # identical to stage A; guards against any drift
    la = torch.where(sig, torch.log1p(-alpha.double()), torch.zeros((), dtype=torch.float64, device=device))
    logT = segmented_exclusive_cumsum(la, starts)
    T64 = torch.exp(logT)
    with torch.no_grad():
        T_ng = T64.detach()
        contrib = sig & (T_ng * (1.0 - alpha.detach().double()) >= T_MIN)
        median_ok = contrib & (T_ng > 0.5)
    T = T64.to(dtype)
    w = torch.where(contrib, alpha * T, torch.zeros_like(alpha))

    feat_normal = _WeightedPixelSum.apply(payload, w, rank, pix, HW)  # (D + 3, HW)
    a_d = _PixelSum.apply(torch.stack([w, w * z]), pix, HW)  # (2, HW)
    D = payload.shape[0] - 3

    with torch.no_grad():
        idx = torch.where(median_ok, torch.arange(pix.shape[0], device=device), torch.full_like(pix, -1))
        med_idx = torch.full((HW,), -1, dtype=torch.long, device=device).scatter_reduce(
            0, pix, idx, reduce="amax", include_self=True
        )
        has_med = med_idx >= 0
    zeros = torch.zeros(HW, dtype=dtype, device=device)
    median = torch.where(has_med, z[med_idx.clamp_min(0)], zeros) if z.numel() else zeros

    m = normalized_depth(z.double(), near, far)
    dist = distortion_closed_form(w.double(), m, pix, starts, HW).to(dtype)
    return PackedImages(
        features=feat_normal[:D],
        alpha=a_d[0],
        depth_sum=a_d[1],
        normal=feat_normal[D:],
        median=median,
        distortion=dist,
        num_pairs=int(pix.shape[0]),
    )

