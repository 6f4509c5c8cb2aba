"""Tile-based 2DGS compositing in Triton: the ``backend="triton"`` path of ``rasterize_surfels``.

The projection (splat matrix, low-pass centre, culling, candidate boxes) stays in torch and is shared
with the packed backend; this module replaces the packed compositing of one camera:

* binning (torch): every surfel is listed in each 16×16 tile its candidate pixel box touches, tile
  by tile in compositing order (the surfels arrive sorted by centre depth);
* forward kernel: one program per tile, one lane per pixel; it walks the tile's list front to back
  with hbb1's rules (α = min(0.99, o·e^(−ρ/2)), skip h_z = 0, z < near or α < 1/255, stop before the
  first surfel with T·(1 − α) < 1e-4) and stops once every pixel of the tile has terminated. It
  accumulates features and normals, alpha, Σw·z with the intersection depth, the median depth and
  the distortion on normalized depth;
* backward kernel: per tile, back to front from each pixel's last contributor, recomputing the
  intersection and recovering T by division; it reduces the per-pixel gradients of each surfel
  over the tile and adds them atomically to the per-surfel gradients of the table and payload.

T is carried in float64 (as the packed backend's float64 log-transmittance), so the termination
and median decisions agree with the torch backend. CPU tensors run only under Triton's interpreter
(``TRITON_INTERPRET=1`` set before this module is imported); CUDA tensors run compiled kernels.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import triton
import triton.language as tl

from ._packed import ALPHA_MAX, T_MIN, PackedImages
from ._project import ALPHA_MIN, TILE

INTERPRETED: bool = bool(triton.knobs.runtime.interpret)
"""Whether this module's kernels were built for Triton's CPU interpreter (decided at import)."""

_BLOCK = TILE * TILE
_NUM_WARPS = 8
_CHUNK = 32


def device_supported(device: torch.device) -> bool:
    """True when the kernels can run on tensors of ``device`` (CUDA, or any device when interpreted)."""
    return INTERPRETED or device.type == "cuda"


@triton.jit
def _load_surfel(tab_ptr, r):
    """The 12 table entries of surfel r: shifted Tu (3), shifted Tv (3), Tw (3), c_x, c_y, opacity."""
    b = tab_ptr + r * 12
    return (
        tl.load(b),
        tl.load(b + 1),
        tl.load(b + 2),
        tl.load(b + 3),
        tl.load(b + 4),
        tl.load(b + 5),
        tl.load(b + 6),
        tl.load(b + 7),
        tl.load(b + 8),
        tl.load(b + 9),
        tl.load(b + 10),
        tl.load(b + 11),
    )


@triton.jit
def _intersect(tu0, tu1, tu2, tv0, tv1, tv2, tw0, tw1, tw2, cx, cy, o, px, py, near, ALPHA_MAX_C, ALPHA_MIN_C):
    """Ray–splat intersection, low-pass filter and α of one surfel at a block of pixel centres (px, py)."""
    dx = px - cx
    dy = py - cy
    k0 = dx * tw0 - tu0
    k1 = dx * tw1 - tu1
    k2 = dx * tw2 - tu2
    l0 = dy * tw0 - tv0
    l1 = dy * tw1 - tv1
    l2 = dy * tw2 - tv2
    hx = k1 * l2 - k2 * l1
    hy = k2 * l0 - k0 * l2
    hz = k0 * l1 - k1 * l0
    hz_ok = hz != 0.0
    hzs = tl.where(hz_ok, hz, 1.0)
    u = hx / hzs
    v = hy / hzs
    rho2d = 2.0 * (dx * dx + dy * dy)
    use3d = hz_ok & (u * u + v * v <= rho2d)
    rho = tl.where(use3d, u * u + v * v, rho2d)
    z = tl.where(use3d, tw0 * u + tw1 * v + tw2, tw2)
    ex = tl.exp(-0.5 * rho)
    G = o * ex
    alpha = tl.minimum(G, ALPHA_MAX_C)
    sig = hz_ok & (z >= near) & (alpha >= ALPHA_MIN_C)
    return dx, dy, k0, k1, k2, l0, l1, l2, hzs, u, v, use3d, ex, G, alpha, z, sig


@triton.jit
def _forward_kernel(
    tab_ptr,
    pay_ptr,
    off_ptr,
    lst_ptr,
    out_pay_ptr,
    out_s_ptr,
    aux_ptr,
    tfin_ptr,
    auxi_ptr,
    W,
    H,
    GX,
    P,
    near,
    cm,
    ALPHA_MAX_C: tl.constexpr,
    ALPHA_MIN_C: tl.constexpr,
    T_MIN_C: tl.constexpr,
    TILE_C: tl.constexpr,
    BLOCK: tl.constexpr,
    CP: tl.constexpr,
    CHUNK: tl.constexpr,
):
    pid = tl.program_id(0)
    tx = pid % GX
    ty = pid // GX
    lane = tl.arange(0, BLOCK)
    x = tx * TILE_C + lane % TILE_C
    y = ty * TILE_C + lane // TILE_C
    inside = (x < W) & (y < H)
    pidx = (y * W + x).to(tl.int64)
    dt = tab_ptr.dtype.element_ty
    px = x.to(dt) + 0.5
    py = y.to(dt) + 0.5
    ch = tl.arange(0, CP)
    chm = ch < P

    start = tl.load(off_ptr + pid)
    end = tl.load(off_ptr + pid + 1)
    T = tl.where(inside, 1.0, 0.0).to(tl.float64)
    alive = inside
    zero = tl.zeros([BLOCK], dtype=dt)
    acc = tl.zeros([BLOCK, CP], dtype=dt)
    A = zero
    Dz = zero
    M1 = zero
    M2 = zero
    dist = zero
    z0 = zero
    med = zero
    med_i = tl.full([BLOCK], -1, tl.int32)
    last = tl.full([BLOCK], 0, tl.int32) + start
    cnt = tl.full([BLOCK], 0, tl.int32)
    j0 = start
    # the all-terminated test is a block reduction, so it runs once per CHUNK surfels
    while (j0 < end) & (tl.max(alive.to(tl.int32), axis=0) > 0):
        j1 = tl.minimum(j0 + CHUNK, end)
        for j in range(j0, j1):
            r = tl.load(lst_ptr + j).to(tl.int64)
            tu0, tu1, tu2, tv0, tv1, tv2, tw0, tw1, tw2, cx, cy, o = _load_surfel(tab_ptr, r)
            _dx, _dy, _k0, _k1, _k2, _l0, _l1, _l2, _hzs, _u, _v, _use3d, _ex, _G, alpha, z, sig = _intersect(
                tu0, tu1, tu2, tv0, tv1, tv2, tw0, tw1, tw2, cx, cy, o, px, py, near, ALPHA_MAX_C, ALPHA_MIN_C
            )
            sig = sig & alive
            t_next = T * (1.0 - alpha.to(tl.float64))
            contrib = sig & (t_next >= T_MIN_C)
            alive = alive & ~(sig & (t_next < T_MIN_C))
            w = tl.where(contrib, alpha * T.to(dt), 0.0)
            pay = tl.load(pay_ptr + r * P + ch, mask=chm, other=0.0)
            acc += w[:, None] * pay[None, :]
            med = tl.where(contrib & (T > 0.5), z, med)
            med_i = tl.where(contrib & (T > 0.5), j, med_i)
            z0 = tl.where(contrib & (cnt == 0), z, z0)
            zs = tl.where(contrib, z, 1.0)
            z0s = tl.where(z0 > 0.0, z0, 1.0)
            mt = cm * (zs - z0s) / (zs * z0s)
            dist += w * (mt * mt * A + M2 - 2.0 * mt * M1)
            A += w
            Dz += w * z
            M1 += w * mt
            M2 += w * mt * mt
            T = tl.where(contrib, t_next, T)
            last = tl.where(contrib, j + 1, last)
            cnt += contrib.to(tl.int32)
        j0 = j1

    pm = inside[:, None] & chm[None, :]
    tl.store(out_pay_ptr + pidx[:, None] * P + ch[None, :], acc, mask=pm)
    tl.store(out_s_ptr + pidx * 4, A, mask=inside)
    tl.store(out_s_ptr + pidx * 4 + 1, Dz, mask=inside)
    tl.store(out_s_ptr + pidx * 4 + 2, med, mask=inside)
    tl.store(out_s_ptr + pidx * 4 + 3, dist, mask=inside)
    tl.store(aux_ptr + pidx * 3, z0, mask=inside)
    tl.store(aux_ptr + pidx * 3 + 1, M1, mask=inside)
    tl.store(aux_ptr + pidx * 3 + 2, M2, mask=inside)
    tl.store(tfin_ptr + pidx, T, mask=inside)
    tl.store(auxi_ptr + pidx * 3, last, mask=inside)
    tl.store(auxi_ptr + pidx * 3 + 1, med_i, mask=inside)
    tl.store(auxi_ptr + pidx * 3 + 2, cnt, mask=inside)


@triton.jit
def _backward_kernel(
    tab_ptr,
    pay_ptr,
    off_ptr,
    lst_ptr,
    out_s_ptr,
    aux_ptr,
    tfin_ptr,
    auxi_ptr,
    g_pay_ptr,
    g_s_ptr,
    gtab_ptr,
    gpay_ptr,
    W,
    H,
    GX,
    P,
    near,
    cm,
    ALPHA_MAX_C: tl.constexpr,
    ALPHA_MIN_C: tl.constexpr,
    TILE_C: tl.constexpr,
    BLOCK: tl.constexpr,
    CP: tl.constexpr,
):
    pid = tl.program_id(0)
    tx = pid % GX
    ty = pid // GX
    lane = tl.arange(0, BLOCK)
    x = tx * TILE_C + lane % TILE_C
    y = ty * TILE_C + lane // TILE_C
    inside = (x < W) & (y < H)
    pidx = (y * W + x).to(tl.int64)
    dt = tab_ptr.dtype.element_ty
    px = x.to(dt) + 0.5
    py = y.to(dt) + 0.5
    ch = tl.arange(0, CP)
    chm = ch < P

    start = tl.load(off_ptr + pid)
    last = tl.load(auxi_ptr + pidx * 3, mask=inside, other=0)
    last = tl.where(inside, last, start)
    med_i = tl.load(auxi_ptr + pidx * 3 + 1, mask=inside, other=-1)
    T = tl.load(tfin_ptr + pidx, mask=inside, other=0.0)
    Af = tl.load(out_s_ptr + pidx * 4, mask=inside, other=0.0)
    z0 = tl.load(aux_ptr + pidx * 3, mask=inside, other=0.0)
    M1f = tl.load(aux_ptr + pidx * 3 + 1, mask=inside, other=0.0)
    M2f = tl.load(aux_ptr + pidx * 3 + 2, mask=inside, other=0.0)
    gA = tl.load(g_s_ptr + pidx * 4, mask=inside, other=0.0)
    gD = tl.load(g_s_ptr + pidx * 4 + 1, mask=inside, other=0.0)
    gM = tl.load(g_s_ptr + pidx * 4 + 2, mask=inside, other=0.0)
    gL = tl.load(g_s_ptr + pidx * 4 + 3, mask=inside, other=0.0)
    gp = tl.load(g_pay_ptr + pidx[:, None] * P + ch[None, :], mask=inside[:, None] & chm[None, :], other=0.0)
    z0s = tl.where(z0 > 0.0, z0, 1.0)
    B = tl.zeros([BLOCK], dtype=dt)
    hi = tl.max(last, axis=0)
    for jj in range(0, hi - start):
        j = hi - 1 - jj
        r = tl.load(lst_ptr + j).to(tl.int64)
        tu0, tu1, tu2, tv0, tv1, tv2, tw0, tw1, tw2, cx, cy, o = _load_surfel(tab_ptr, r)
        dx, dy, k0, k1, k2, l0, l1, l2, hzs, u, v, use3d, ex, G, alpha, z, sig = _intersect(
            tu0, tu1, tu2, tv0, tv1, tv2, tw0, tw1, tw2, cx, cy, o, px, py, near, ALPHA_MAX_C, ALPHA_MIN_C
        )
        contrib = inside & (j < last) & sig
        T = tl.where(contrib, T / (1.0 - alpha.to(tl.float64)), T)
        Tc = T.to(dt)
        w = tl.where(contrib, alpha * Tc, 0.0)
        pay = tl.load(pay_ptr + r * P + ch, mask=chm, other=0.0)
        fdot = tl.sum(gp * pay[None, :], axis=1)
        zs = tl.where(contrib, z, 1.0)
        mt = cm * (zs - z0s) / (zs * z0s)
        e = fdot + gA + gD * z + gL * (mt * mt * Af - 2.0 * mt * M1f + M2f)
        g_a = tl.where(contrib, Tc * (e - B), 0.0)
        B = tl.where(contrib, alpha * e + (1.0 - alpha) * B, B)
        g_z = tl.where(contrib, w * (gD + gL * 2.0 * (mt * Af - M1f) * cm / (zs * zs)), 0.0)
        g_z += tl.where(contrib & (med_i == j), gM, 0.0)
        # α = min(0.99, o·e^(−ρ/2)); the clamp passes no gradient
        g_a = tl.where(G <= ALPHA_MAX_C, g_a, 0.0)
        g_o = g_a * ex
        g_rho = -0.5 * g_a * G
        # 3D branch: ρ = u² + v², z = Tw·(u, v, 1), (u, v) = (h_x, h_y)/h_z with h = k × l
        g_u = tl.where(use3d, 2.0 * g_rho * u + g_z * tw0, 0.0)
        g_v = tl.where(use3d, 2.0 * g_rho * v + g_z * tw1, 0.0)
        g_hx = g_u / hzs
        g_hy = g_v / hzs
        g_hz = -(g_u * u + g_v * v) / hzs
        g_k0 = l1 * g_hz - l2 * g_hy
        g_k1 = l2 * g_hx - l0 * g_hz
        g_k2 = l0 * g_hy - l1 * g_hx
        g_l0 = g_hy * k2 - g_hz * k1
        g_l1 = g_hz * k0 - g_hx * k2
        g_l2 = g_hx * k1 - g_hy * k0
        g_z3 = tl.where(use3d, g_z, 0.0)
        g_tw0 = dx * g_k0 + dy * g_l0 + g_z3 * u
        g_tw1 = dx * g_k1 + dy * g_l1 + g_z3 * v
        g_tw2 = dx * g_k2 + dy * g_l2 + g_z
        # 2D branch: ρ = 2(dx² + dy²), z = Tw[2]
        g_rho2 = tl.where(use3d, 0.0, 4.0 * g_rho)
        g_dx = g_k0 * tw0 + g_k1 * tw1 + g_k2 * tw2 + g_rho2 * dx
        g_dy = g_l0 * tw0 + g_l1 * tw1 + g_l2 * tw2 + g_rho2 * dy
        if tl.max(contrib.to(tl.int32), axis=0) > 0:
            gb = gtab_ptr + r * 12
            tl.atomic_add(gb, -tl.sum(g_k0, axis=0))
            tl.atomic_add(gb + 1, -tl.sum(g_k1, axis=0))
            tl.atomic_add(gb + 2, -tl.sum(g_k2, axis=0))
            tl.atomic_add(gb + 3, -tl.sum(g_l0, axis=0))
            tl.atomic_add(gb + 4, -tl.sum(g_l1, axis=0))
            tl.atomic_add(gb + 5, -tl.sum(g_l2, axis=0))
            tl.atomic_add(gb + 6, tl.sum(g_tw0, axis=0))
            tl.atomic_add(gb + 7, tl.sum(g_tw1, axis=0))
            tl.atomic_add(gb + 8, tl.sum(g_tw2, axis=0))
            tl.atomic_add(gb + 9, -tl.sum(g_dx, axis=0))
            tl.atomic_add(gb + 10, -tl.sum(g_dy, axis=0))
            tl.atomic_add(gb + 11, tl.sum(g_o, axis=0))
            tl.atomic_add(gpay_ptr + r * P + ch, tl.sum(w[:, None] * gp, axis=0), mask=chm)


def bin_tiles(boxes: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-tile surfel lists from candidate pixel boxes.

    boxes: (Nv, 4) int64 pixel boxes (x0, y0, x1, y1), max exclusive, of surfels already in
    compositing order (empty boxes are skipped). Returns offsets (num_tiles + 1,) int32 and the
    list (L,) int32 of surfel indices, grouped by tile (row-major tile id) and ascending within a tile.
    """
    device = boxes.device
    gx, gy = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    x0, y0, x1, y1 = boxes.unbind(1)
    nonempty = (x1 > x0) & (y1 > y0)
    tx0 = torch.div(x0, TILE, rounding_mode="floor")
    ty0 = torch.div(y0, TILE, rounding_mode="floor")
    tx1 = torch.div(x1 - 1, TILE, rounding_mode="floor") + 1
    ty1 = torch.div(y1 - 1, TILE, rounding_mode="floor") + 1
    bw = torch.where(nonempty, tx1 - tx0, torch.zeros_like(tx0))
    counts = torch.where(nonempty, bw * (ty1 - ty0), torch.zeros_like(tx0))
    total = int(counts.sum())
    num_tiles = gx * gy
    if total == 0:
        empty = torch.zeros(0, dtype=torch.int32, device=device)
        return torch.zeros(num_tiles + 1, dtype=torch.int32, device=device), empty
    sid = torch.repeat_interleave(torch.arange(boxes.shape[0], device=device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    k = torch.arange(total, device=device) - torch.repeat_interleave(first, counts, output_size=total)
    bws = bw[sid]
    oy = torch.div(k, bws, rounding_mode="floor")
    tile = (ty0[sid] + oy) * gx + tx0[sid] + (k - oy * bws)
    tile, order = torch.sort(tile, stable=True)
    lst = sid[order].to(torch.int32)
    per_tile = torch.bincount(tile, minlength=num_tiles)
    offsets = torch.zeros(num_tiles + 1, dtype=torch.long, device=device)
    offsets[1:] = torch.cumsum(per_tile, 0)
    return offsets.to(torch.int32), lst


def _launch_args(width: int, height: int, payload_ch: int, near: float, far: float) -> tuple[tuple, dict]:
    gx = (width + TILE - 1) // TILE
    cm = far * near / (far - near)
    consts = dict(
        ALPHA_MAX_C=ALPHA_MAX, ALPHA_MIN_C=ALPHA_MIN, TILE_C=TILE, BLOCK=_BLOCK, CP=triton.next_power_of_2(payload_ch)
    )
    return (width, height, gx, payload_ch, float(near), float(cm)), consts


def _launch_options() -> dict:
    # the compiled kernels keep separate multiplies and adds (no FMA contraction), like torch's
    # elementwise ops, so that threshold decisions (1/255, branch, termination) match the packed path
    return {} if INTERPRETED else {"num_warps": _NUM_WARPS, "enable_fp_fusion": False}


class _TileComposite(torch.autograd.Function):
    """Forward/backward kernels as one autograd node.

    table: (12, Nv), payload: (P, Nv) (features then camera normals); offsets, lst from
    :func:`bin_tiles`. Returns pay_img (HW, P) Σ w·payload, stats (HW, 4) = (A, Σw·z, median, distortion)
    and count (HW,) int32 contributors per pixel (not differentiable).
    """

    @staticmethod
    def forward(ctx, table, payload, offsets, lst, width, height, near, far):  # type: ignore[override]
        dtype, device = table.dtype, table.device
        tab = table.detach().T.contiguous()
        pay = payload.detach().T.contiguous()
        P = pay.shape[1]
        HW = width * height
        out_pay = torch.zeros(HW, P, dtype=dtype, device=device)
        out_s = torch.zeros(HW, 4, dtype=dtype, device=device)
        aux = torch.zeros(HW, 3, dtype=dtype, device=device)
        tfin = torch.ones(HW, dtype=torch.float64, device=device)
        auxi = torch.zeros(HW, 3, dtype=torch.int32, device=device)
        args, consts = _launch_args(width, height, P, near, far)
        num_tiles = offsets.shape[0] - 1
        if lst.numel() > 0:  # otherwise every tile is empty and the zero images are the result
            _forward_kernel[(num_tiles,)](
                tab, pay, offsets, lst, out_pay, out_s, aux, tfin, auxi, *args,
                T_MIN_C=T_MIN, CHUNK=_CHUNK, **consts, **_launch_options(),
            )
        ctx.save_for_backward(tab, pay, offsets, lst, out_s, aux, tfin, auxi)
        ctx.dims = (width, height, near, far)
        count = auxi[:, 2].clone()
        ctx.mark_non_differentiable(count)
        return out_pay, out_s, count

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_pay, g_s, _g_count):  # type: ignore[override]
        tab, pay, offsets, lst, out_s, aux, tfin, auxi = ctx.saved_tensors
        width, height, near, far = ctx.dims
        P = pay.shape[1]
        g_pay = torch.zeros_like(out_s[:, :1]).expand(-1, P) if g_pay is None else g_pay
        g_s = torch.zeros_like(out_s) if g_s is None else g_s
        g_pay = g_pay.to(tab.dtype).contiguous()
        g_s = g_s.to(tab.dtype).contiguous()
        gtab = torch.zeros_like(tab)
        gpay = torch.zeros_like(pay)
        args, consts = _launch_args(width, height, P, near, far)
        num_tiles = offsets.shape[0] - 1
        if lst.numel() > 0:
            _backward_kernel[(num_tiles,)](
                tab, pay, offsets, lst, out_s, aux, tfin, auxi, g_pay, g_s, gtab, gpay, *args,
                **consts, **_launch_options(),
            )
        return gtab.T, gpay.T, None, None, None, None, None, None


def composite_triton(
    table: torch.Tensor,
    payload: torch.Tensor,
    boxes: torch.Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    progress: Callable[[int, int], None] | None = None,
) -> PackedImages:
    """Render one camera from surfels sorted by centre depth (same inputs as ``composite_packed``).

    table: (12, Nv) rows Tu − c_x·Tw, Tv − c_y·Tw, Tw, low-pass centre c (2), opacity; differentiable.
    payload: (D + 3, Nv) features then camera-frame normals; differentiable.
    boxes: (Nv, 4) int64 candidate pixel boxes (``candidate_pixel_boxes``).
    ``num_pairs`` counts the composited (contributing) pairs, which the kernel knows; the packed
    backend counts every significant pair, including those behind a terminated pixel.
    progress(1, 1) is called once the forward kernel has run.
    """
    if table.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"rasterize_surfels(backend='triton'): unsupported dtype {table.dtype}")
    if not device_supported(table.device):
        raise ValueError(
            "rasterize_surfels(backend='triton'): tensors on "
            f"{table.device} need Triton's interpreter (set TRITON_INTERPRET=1 before sage_core.render._triton_surfels "
            "is imported); compiled kernels need CUDA tensors"
        )
    offsets, lst = bin_tiles(boxes, width, height)
    pay_img, stats, count = _TileComposite.apply(
        table.contiguous(), payload.contiguous(), offsets, lst, width, height, float(near), float(far)
    )
    if progress is not None:
        progress(1, 1)
    D = payload.shape[0] - 3
    return PackedImages(
        features=pay_img[:, :D].T,
        alpha=stats[:, 0],
        depth_sum=stats[:, 1],
        normal=pay_img[:, D:].T,
        median=stats[:, 2],
        distortion=stats[:, 3],
        num_pairs=int(count.sum()),
    )
