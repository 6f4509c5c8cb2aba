"""Native CPU rasterizer (C++/OpenMP): the ``backend="cpp"`` path of ``rasterize_surfels``.

:func:`render_cpp` renders each camera with one autograd node whose forward and backward run in the
extension ``csrc/surfels_cpu.cpp``: projection (splat matrix, low-pass centre, culling, radius, tile
rectangle, candidate box), the centre-depth order, 16×16 tile compositing and the image outputs
(colour with background, expected depth, camera and world normals, normals from depth), and their
exact backward down to means, quaternions, scales, opacities, features, ``means2d`` and background.
``means2d`` comes from a second small node, so that it sits upstream of every output as in the torch
backend and its gradient is hbb1's densification proxy. The rules are the packed backend's; see the
header of the C++ file.

When the camera itself is differentiated, ``rasterize_surfels`` keeps the torch projection and calls
:func:`composite_cpp`, which runs only the compositing in the extension.

The extension is compiled on first use, never at import, by ``sage_core.native_build`` (cached in
``$SAGE_CACHE_DIR`` or ``~/.cache/sage/torch_extensions/<torch version>/`` under a hash of the source,
the build flags and the torch version; concurrent builds serialized by an ``fcntl`` lock).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from ..native_build import cache_dir, native_extension
from ._packed import IMAGE_OUTPUTS, PackedImages

__all__ = [
    "EXT",
    "IMAGE_OUTPUTS",
    "CppRender",
    "available",
    "bin_tiles",
    "cache_dir",
    "composite_cpp",
    "depth_to_normal_cpp",
    "render_cpp",
    "warn_unavailable_once",
]

EXT = native_extension(__file__, "surfels_cpu", probe_op="render_forward", what="rasterizer", fallback="pure-torch backend for rendering")

available, warn_unavailable_once = EXT.available, EXT.warn_unavailable_once


def _ops():  # noqa: ANN202 - a torch.ops namespace
    return EXT.ops("rasterize_surfels(backend='cpp')")


def bin_tiles(boxes: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-tile surfel lists: offsets (num_tiles + 1,) int64 and list (L,) int32, ascending in each tile.

    boxes: (Nv, 4) int64 pixel boxes (x0, y0, x1, y1), max exclusive; empty boxes are skipped.
    """
    offsets, lst = _ops().bin_tiles(boxes.contiguous(), int(width), int(height))
    return offsets, lst


class _Means2d(torch.autograd.Function):
    """Projected surfel centres (K·p_c)[:2] / z_c of N surfels in C cameras (camera constant).

    means: (N, 3); K: (C, 3, 3); w2c: (C, 4, 4). Returns (C, N, 2), or (N, 2) with ``squeeze`` (C = 1).
    """

    @staticmethod
    def forward(ctx, means, K, w2c, squeeze):  # type: ignore[override]
        m = means.detach().contiguous()
        ctx.save_for_backward(m, K, w2c)
        return _ops().means2d_forward(m, K, w2c, bool(squeeze))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        m, K, w2c = ctx.saved_tensors
        g = grad.to(m.dtype).reshape(K.shape[0], m.shape[0], 2).contiguous()
        return _ops().means2d_backward(m, K, w2c, g), None, None, None


class _CppRender(torch.autograd.Function):
    """One camera end to end in the extension, as one autograd node.

    Differentiable inputs: means (N, 3), quats (N, 4), scales (N, 2), opacities (N,), feats (N, D),
    means2d (N, 2), background (D,); K (3, 3) and w2c (4, 4) are constants. Returns the ten
    :data:`IMAGE_OUTPUTS` ((H, W, D), (H, W) or (H, W, 3)), then visible (N,) bool, radii (N,) int32
    and the composited pair count (0-dim int64), which are not differentiable.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, feats, means2d, background, K, w2c, width, height, near, far):  # type: ignore[override]
        ins = [t.detach().contiguous() for t in (means, quats, scales, opacities, feats, means2d, background)]
        res = _ops().render_forward(*ins, K, w2c, width, height, near, far)
        images, (visible, radii, pairs), saved = res[:10], res[10:13], res[13:]
        ctx.save_for_backward(*ins, K, w2c, visible, *saved, images[1], images[2], images[3])
        ctx.dims = (width, height, near, far)
        ctx.set_materialize_grads(False)
        ctx.mark_non_differentiable(visible, radii, pairs)
        return (*images, visible, radii, pairs)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):  # type: ignore[override]
        saved = ctx.saved_tensors
        dtype = saved[0].dtype
        gs = [None if g is None else g.to(dtype) for g in grads[:10]]  # any strides (often expanded)
        nothing = (None,) * 13
        if all(g is None for g in gs):
            return nothing
        out = _ops().render_backward(*saved, *gs, *ctx.dims)
        return tuple(o if need else None for o, need in zip(out, ctx.needs_input_grad[:7])) + nothing[7:]


@dataclass
class CppRender:
    """Result of :func:`render_cpp`; a batch of C cameras adds a leading C everywhere.

    Attributes:
        images: the :data:`IMAGE_OUTPUTS` by name ((H, W, D), (H, W) or (H, W, 3)).
        visible: (N,) bool surfels kept by culling and touching at least one tile.
        radii: (N,) int32 hbb1 screen radius in px (0 where not visible).
        means2d: (N, 2) projected centres in px (densification-proxy gradient).
        num_pairs: (C,) or 0-dim int64 composited (surfel, pixel) pairs.
    """

    images: dict[str, torch.Tensor]
    visible: torch.Tensor
    radii: torch.Tensor
    means2d: torch.Tensor
    num_pairs: torch.Tensor


def render_cpp(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: Sequence[torch.Tensor],
    Ks: torch.Tensor,
    w2cs: torch.Tensor,
    background: torch.Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    batched: bool,
    progress: Callable[[int, int], None] | None = None,
) -> CppRender:
    """Render N surfels into C cameras in the extension (all outputs of ``rasterize_surfels``).

    means: (N, 3); quats: (N, 4) wxyz (normalized here); scales: (N, 2); opacities: (N,);
    features: C tensors (N, D), one per camera (SH already evaluated); Ks: (C, 3, 3), w2cs: (C, 4, 4)
    (not differentiated); background: (D,). All CPU tensors of one dtype, float32 or float64.
    With ``batched`` False (C = 1) the leading camera dimension is dropped. progress(1, 1) is called
    after each camera. Raises RuntimeError when the extension is unavailable.
    """
    C = Ks.shape[0]
    if means.device.type != "cpu":
        raise ValueError(f"rasterize_surfels(backend='cpp'): needs CPU tensors, got {means.device}")
    Kc, Wc = Ks.detach().contiguous(), w2cs.detach().contiguous()
    means2d = _Means2d.apply(means, Kc, Wc, not batched)
    bg = background.contiguous()
    per_cam: list[tuple[torch.Tensor, ...]] = []
    for c in range(C):
        m2 = means2d[c] if batched else means2d
        per_cam.append(
            _CppRender.apply(
                means, quats, scales, opacities, features[c], m2, bg, Kc[c], Wc[c],
                int(width), int(height), float(near), float(far),
            )
        )
        if progress is not None:
            progress(1, 1)

    def pick(k: int) -> torch.Tensor:
        return torch.stack([r[k] for r in per_cam]) if batched else per_cam[0][k]

    return CppRender(
        images={name: pick(k) for k, name in enumerate(IMAGE_OUTPUTS)},
        visible=pick(10),
        radii=pick(11),
        means2d=means2d,
        num_pairs=pick(12),
    )


class _CppComposite(torch.autograd.Function):
    """Compositing only, from a table built in torch, as one autograd node.

    table: (12, Nv), payload: (P, Nv), boxes: (Nv, 4). Returns pay_img (HW, P) Σ w·payload,
    stats (HW, 4) = (A, Σw·z, median, distortion) and the composited pair count (0-dim int64).
    """

    @staticmethod
    def forward(ctx, table, payload, boxes, width, height, near, far):  # type: ignore[override]
        ops = _ops()
        tab = table.detach().T.contiguous()
        pay = payload.detach().T.contiguous()
        bx = boxes.contiguous()
        pay_img, stats, aux, auxi, offsets, lst, cmask, pairs = ops.forward(tab, pay, bx, width, height, near, far)
        ctx.save_for_backward(tab, pay, bx, offsets, lst, aux, auxi, cmask)
        ctx.dims = (width, height, near, far)
        ctx.mark_non_differentiable(pairs)
        return pay_img, stats, pairs

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_pay, g_s, _g_pairs):  # type: ignore[override]
        tab, pay, bx, offsets, lst, aux, auxi, cmask = ctx.saved_tensors
        width, height, near, far = ctx.dims
        HW, P = width * height, pay.shape[1]
        g_pay = torch.zeros(HW, P, dtype=tab.dtype) if g_pay is None else g_pay.to(tab.dtype).contiguous()
        g_s = torch.zeros(HW, 4, dtype=tab.dtype) if g_s is None else g_s.to(tab.dtype).contiguous()
        gtab, gpay = _ops().backward(tab, pay, bx, offsets, lst, aux, auxi, cmask, g_pay, g_s, width, height, near, far)
        return gtab.T, gpay.T, None, None, None, None, None


class _DepthNormal(torch.autograd.Function):
    """Normals from depth in the extension; depth: (H, W), kinv: (3, 3) float64 (not differentiated)."""

    @staticmethod
    def forward(ctx, depth, kinv):  # type: ignore[override]
        ctx.save_for_backward(depth.detach(), kinv)
        return _ops().depth_normal_forward(depth.detach().contiguous(), kinv)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        depth, kinv = ctx.saved_tensors
        return _ops().depth_normal_backward(depth, kinv, grad.contiguous()), None


def depth_to_normal_cpp(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Same as ``surfels.depth_to_normal`` (depth: (H, W), K: (3, 3) -> (H, W, 3)), computed in the
    extension in float64; differentiable w.r.t. depth only (K is treated as a constant)."""
    kinv = torch.linalg.inv(K.detach().double()).contiguous()
    return _DepthNormal.apply(depth, kinv)


def composite_cpp(
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
    boxes: (Nv, 4) int64 candidate pixel boxes (``candidate_pixel_boxes``). CPU tensors, float32 or
    float64. ``num_pairs`` counts the composited pairs (as the triton backend). progress(1, 1) is
    called once the forward has run. Raises RuntimeError when the extension is unavailable.
    """
    if table.device.type != "cpu":
        raise ValueError(f"rasterize_surfels(backend='cpp'): needs CPU tensors, got {table.device}")
    if table.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"rasterize_surfels(backend='cpp'): unsupported dtype {table.dtype}")
    pay_img, stats, pairs = _CppComposite.apply(table, payload, boxes, int(width), int(height), float(near), float(far))
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
        num_pairs=int(pairs),
    )
