"""Native CPU SDF network (C++/OpenMP): the ``backend="cpp"`` path of ``SDFNetwork``.

``evaluate(x, table, w0, b0, w1, b1, layout, with_grad, with_encoding, keep, with_feature)`` runs a
one-hidden-layer ``SDFNetwork`` (hash encoding, Linear, Softplus, Linear) and returns sdf (N,), the
spatial gradient d sdf / dx (N, 3) (with ``with_grad``), the feature (N, F_z) (with ``with_feature``)
and the hash encoding (N, L*F) (with ``with_encoding``). It is one autograd node: its backward takes the
upstream gradients of all four outputs (any may be unused) and returns the exact gradients of x, the
hash table and the four MLP tensors, the second-order terms of the gradient output included (the
eikonal, alignment and NeuS losses on the gradient). The backward itself is not differentiable
(``once_differentiable``): a loss on a gradient of these gradients raises. With ``keep`` (the default) the node holds the kernel's
per-point hash features and their derivatives until the backward, which then reads the table only to
scatter its gradient.

Kernels: ``csrc/sdf_cpu.cpp`` (its header states the formulas, the passes and the threading). The
extension is built on first use by ``sage_core.native_build``; ``available()`` reports whether it could be.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from ..native_build import native_extension
from ._cpp_hashgrid import _needed

__all__ = ["EXT", "Layout", "available", "evaluate", "warn_unavailable_once"]

EXT = native_extension(__file__, "sdf_cpu", probe_op="backward", what="SDF network", fallback="autograd SDF network")

available, warn_unavailable_once = EXT.available, EXT.warn_unavailable_once


def _ops():  # noqa: ANN202 - a torch.ops namespace
    return EXT.ops("SDFNetwork(backend='cpp')")


@dataclass(frozen=True)
class Layout:
    """Everything of the network that is not a trainable tensor.

    levels: (L, 4) int64 rows (res, size, offset, dense) of the hash grid; scales: (L,) float64 level
    scales; mask: (L,) float64 level mask (0 = inactive level); box: (3, 3) rows ``lo``, ``hi - lo`` and
    the centre, in the dtype of x; half_extent: the SDF scale h; beta, threshold: of the Softplus.
    """

    levels: torch.Tensor
    scales: torch.Tensor
    mask: torch.Tensor
    box: torch.Tensor
    half_extent: float
    beta: float
    threshold: float

    def args(self) -> tuple[Any, ...]:
        """The layout as the operators' trailing positional arguments."""
        return (self.levels, self.scales, self.mask, self.box, self.half_extent, self.beta, self.threshold)


def _grad_or_none(g: torch.Tensor | None, like: torch.Tensor) -> torch.Tensor | None:
    """An upstream gradient as a contiguous tensor of ``like``'s dtype (None when absent or empty)."""
    if g is None or g.numel() == 0:
        return None
    return g.to(like.dtype).contiguous()


class _SDFEval(torch.autograd.Function):
    """(x, table, w0, b0, w1, b1) -> (sdf, grad, feature, encoding); the layout and flags ride along.

    ``keep``: keep the kernel's per-point hash features (with ``with_grad`` also their first derivatives,
    with ``keep_second`` also the second) for the backward, which then reads the table only to scatter
    its gradient; about 4 * L * F (+ 3 * L * F) values per point. Without it the backward recomputes them.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, x, table, w0, b0, w1, b1, layout, with_grad, with_enc, keep, keep_second, with_feature
    ):
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(x, table, w0, b0, w1, b1)
        ctx.layout = layout
        sdf, grad, feature, enc, kept = _ops().forward(
            x, table, w0, b0, w1, b1, *layout.args(), with_grad, with_enc, keep, keep_second, with_feature
        )
        ctx.kept = (kept if keep else None, with_grad, keep_second)
        return sdf, grad, feature, enc

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_sdf, g_grad, g_feature, g_enc):  # type: ignore[override]
        x, table, w0, b0, w1, b1 = ctx.saved_tensors
        ups = [_grad_or_none(g, x) for g in (g_sdf, g_grad, g_feature, g_enc)]
        through_mlp = any(u is not None for u in ups[:3])  # the encoding alone does not reach the MLP
        need_x, need_table = _needed(ctx, 0), _needed(ctx, 1)
        need_mlp = through_mlp and any(_needed(ctx, i) for i in range(2, 6))
        if not (need_x or need_table or need_mlp) or all(u is None for u in ups):
            return (None,) * 12
        kept, kept_first, kept_second = ctx.kept
        gx, gt, gw0, gb0, gw1, gb1 = _ops().backward(
            x, table, w0, b0, w1, b1, *ctx.layout.args(), kept, kept_first, kept_second, *ups, need_x, need_table,
            need_mlp,
        )
        wanted = [need_x, need_table] + [need_mlp and ctx.needs_input_grad[i] for i in range(2, 6)]
        outs = [g if w else None for g, w in zip((gx, gt, gw0, gb0, gw1, gb1), wanted)]
        return (*outs, None, None, None, None, None, None)


def evaluate(
    x: torch.Tensor,
    table: torch.Tensor,
    w0: torch.Tensor,
    b0: torch.Tensor,
    w1: torch.Tensor,
    b1: torch.Tensor,
    layout: Layout,
    with_grad: bool,
    with_encoding: bool = False,
    keep: bool = True,
    with_feature: bool = True,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """sdf, gradient, feature and encoding of a one-hidden-layer SDF network at x.

    x: (N, 3) world points, float32 or float64 CPU; table: (T, F) hash table; w0: (H, 3 + L*F), b0: (H,),
    w1: (1 + F_z, H), b1: (1 + F_z,) the two Linear layers, all of x's dtype; layout: see ``Layout``.
    Returns sdf (N,) (already multiplied by the half extent), grad (N, 3) (an empty (0,) tensor unless
    ``with_grad``), feature (N, F_z) (empty unless ``with_feature``: then the second layer computes the
    sdf row only, the same values) and the encoding (N, L*F) (empty unless ``with_encoding``).
    Differentiable once in every input that requires a gradient when grad mode is on. ``keep=False``
    makes the backward recompute the hash features instead of holding them (worth it when only the
    encoding's gradient can arrive). Raises RuntimeError when the extension is unavailable.
    """
    if x.device.type != "cpu":
        raise ValueError(f"SDFNetwork(backend='cpp'): needs CPU tensors, got {x.device}")
    if x.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"SDFNetwork(backend='cpp'): unsupported dtype {x.dtype}")
    tensors = [t.contiguous() for t in (x, table, w0, b0, w1, b1)]
    keep = keep and torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    keep_second = keep and bool(with_grad) and x.requires_grad  # a loss on grad can then reach x
    flags = (bool(with_grad), bool(with_encoding), keep, keep_second, bool(with_feature))
    return _SDFEval.apply(*tensors, layout, *flags)
