"""Native CPU compositing (C++/OpenMP): the ``backend="cpp"`` path of ``rasterize_surfels``.

The projection (splat matrix, low-pass centre, culling, candidate boxes) stays in torch and is shared
with the packed backend; this module replaces the compositing of one camera with the extension in
``csrc/surfels_cpu.cpp`` (16×16 tile binning, a forward per tile and an exact backward that walks
each pixel's contributors back to front). The rules are the packed backend's; see that file's header.

The extension is compiled on first use, never at import, by ``sage_core.native_build`` (cached in
``$SAGE_CACHE_DIR`` or ``~/.cache/sage/torch_extensions/<torch version>/`` under a hash of the source,
the build flags and the torch version; concurrent builds serialized by an ``fcntl`` lock).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch

from ..native_build import NativeExtension, cache_dir
from ._packed import PackedImages

__all__ = ["EXT", "available", "bin_tiles", "cache_dir", "composite_cpp", "depth_to_normal_cpp", "warn_unavailable_once"]

EXT = NativeExtension(
    name="sage_surfels_cpu",
    source=Path(__file__).parent / "csrc" / "surfels_cpu.cpp",
    namespace="sage_surfels_cpu",
    probe_op="forward",
    what="rasterizer",
    fallback="pure-torch backend for rendering",
)

available = EXT.available
"""(True, where it was loaded from) once the extension is built and loaded, else (False, reason); the
first call compiles it unless a cached build exists, and the result is remembered for the process."""
warn_unavailable_once = EXT.warn_unavailable_once


def _ops():  # noqa: ANN202 - a torch.ops namespace
    return EXT.ops("rasterize_surfels(backend='cpp')")


def bin_tiles(boxes: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-tile surfel lists: offsets (num_tiles + 1,) int64 and list (L,) int32, ascending in each tile.

    boxes: (Nv, 4) int64 pixel boxes (x0, y0, x1, y1), max exclusive; empty boxes are skipped.
    """
    offsets, lst = _ops().bin_tiles(boxes.contiguous(), int(width), int(height))
    return offsets, lst


class _CppComposite(torch.autograd.Function):
    """Forward/backward of the extension as one autograd node.

    table: (12, Nv), payload: (P, Nv), boxes: (Nv, 4). Returns pay_img (HW, P) Σ w·payload,
    stats (HW, 4) = (A, Σw·z, median, distortion) and count (HW,) int32 contributors per pixel.
    """

    @staticmethod
    def forward(ctx, table, payload, boxes, width, height, near, far):  # type: ignore[override]
        ops = _ops()
        tab = table.detach().T.contiguous()
        pay = payload.detach().T.contiguous()
        bx = boxes.contiguous()
        pay_img, stats, aux, auxi, offsets, lst = ops.forward(tab, pay, bx, width, height, near, far)
        ctx.save_for_backward(tab, pay, bx, offsets, lst, aux, auxi)
        ctx.dims = (width, height, near, far)
        count = auxi[:, 2].clone()
        ctx.mark_non_differentiable(count)
        return pay_img, stats, count

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_pay, g_s, _g_count):  # type: ignore[override]
        tab, pay, bx, offsets, lst, aux, auxi = ctx.saved_tensors
        width, height, near, far = ctx.dims
        HW, P = width * height, pay.shape[1]
        g_pay = torch.zeros(HW, P, dtype=tab.dtype) if g_pay is None else g_pay.to(tab.dtype).contiguous()
        g_s = torch.zeros(HW, 4, dtype=tab.dtype) if g_s is None else g_s.to(tab.dtype).contiguous()
        gtab, gpay = _ops().backward(tab, pay, bx, offsets, lst, aux, auxi, g_pay, g_s, width, height, near, far)
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
    pay_img, stats, count = _CppComposite.apply(
        table, payload, boxes, int(width), int(height), float(near), float(far)
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
