"""Native CPU hash encoding (C++/OpenMP): the ``backend="cpp"`` path of ``HashGrid.level_features``.

``encode(x01, table, levels, scales, mask)`` gives the same (N, L, F) features as the torch
reference from box coordinates ``x01`` already normalized and clamped (by ``HashGrid.normalize``, so
the clamp's gradient stays torch's). It is differentiable twice in every input that requires a
gradient, exactly: the backward is itself an autograd function (``_EncodeBackward``) whose backward
returns the second-order terms, so ``autograd.grad(sdf.sum(), x, create_graph=True)`` followed by a
loss on that gradient (eikonal, L_pt, L_align) reaches the table, the MLP and x as with the
reference. Third derivatives are refused (``once_differentiable``).

Kernels: ``csrc/hashgrid_cpu.cpp`` (its header states the rules and the threading). The extension is
built on first use by ``sage_core.native_build``; ``available()`` reports whether it could be.
"""

from __future__ import annotations

from typing import Any

import torch

from ..native_build import native_extension

__all__ = ["EXT", "available", "encode", "warn_unavailable_once"]

EXT = native_extension(__file__, "hashgrid_cpu", probe_op="double_backward", what="hash-grid encoding", fallback="pure-torch encoding")

available, warn_unavailable_once = EXT.available, EXT.warn_unavailable_once


def _ops():  # noqa: ANN202 - a torch.ops namespace
    return EXT.ops("HashGrid(backend='cpp')")


def _needed(ctx: Any, i: int) -> bool:
    """Whether the running backward pass uses the gradient of input ``i`` of this node.

    ``needs_input_grad`` only says the input requires a gradient; ``autograd.grad(sdf.sum(), x)``
    never uses the table's, so the engine's execution plan is asked as well (when this torch has
    ``torch._C._will_engine_execute_node``; otherwise every required gradient is computed).
    """
    if not ctx.needs_input_grad[i]:
        return False
    will_execute = getattr(torch._C, "_will_engine_execute_node", None)
    try:
        node = ctx.next_functions[i][0]
        return node is not None and (will_execute is None or bool(will_execute(node)))
    except (AttributeError, IndexError, RuntimeError):
        return True


class _Encode(torch.autograd.Function):
    """x01 (N, 3), table (T, F) -> features (N, L, F); levels/scales/mask describe the layout."""

    @staticmethod
    def forward(ctx, x01, table, levels, scales, mask):  # type: ignore[override]
        ctx.save_for_backward(x01, table)  # the inputs themselves, so a double backward reaches them
        ctx.layout = (levels, scales, mask)
        return _ops().forward(x01.contiguous(), table.contiguous(), levels, scales, mask)

    @staticmethod
    def backward(ctx, grad_feats):  # type: ignore[override]
        x01, table = ctx.saved_tensors
        need_x, need_table = _needed(ctx, 0), _needed(ctx, 1)
        if not (need_x or need_table):
            return None, None, None, None, None
        gx, gt = _EncodeBackward.apply(grad_feats, x01, table, *ctx.layout, need_x, need_table)
        return (gx if need_x else None), (gt if need_table else None), None, None, None


class _EncodeBackward(torch.autograd.Function):
    """(grad_feats (N, L, F), x01, table) -> (grad_x01 (N, 3), grad_table (T, F)).

    An output that was not asked for is an empty tensor. Its backward takes the gradients of both
    outputs (either may be None) and returns the exact terms for grad_feats, x01 and table.
    """

    @staticmethod
    def forward(ctx, grad_feats, x01, table, levels, scales, mask, need_x, need_table):  # type: ignore[override]
        g = grad_feats.detach().to(x01.dtype).contiguous()
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(g, x01, table)
        ctx.layout = (levels, scales, mask)
        gx, gt = _ops().backward(g, x01.contiguous(), table.contiguous(), levels, scales, mask, need_x, need_table)
        empty = x01.new_empty(0)
        return (gx if gx is not None else empty), (gt if gt is not None else empty)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gg_x, gg_table):  # type: ignore[override]
        g, x01, table = ctx.saved_tensors
        need_g, need_x, need_table = _needed(ctx, 0), _needed(ctx, 1), _needed(ctx, 2)
        gg_x = gg_x.contiguous() if gg_x is not None and gg_x.numel() else None
        gg_table = gg_table.contiguous() if gg_table is not None and gg_table.numel() else None
        if (gg_x is None and gg_table is None) or not (need_g or need_x or need_table):
            return (None,) * 8
        d_g, d_table, d_x = _ops().double_backward(
            g, x01.contiguous(), table.contiguous(), gg_x, gg_table, *ctx.layout, need_g, need_table, need_x
        )
        return d_g, d_x, d_table, None, None, None, None, None


def encode(
    x01: torch.Tensor, table: torch.Tensor, levels: torch.Tensor, scales: torch.Tensor, mask: torch.Tensor
) -> torch.Tensor:
    """Interpolated hash features of every level.

    x01: (N, 3) box coordinates in [0, 1] (float32 or float64, CPU); table: (T, F) of the same dtype;
    levels: (L, 4) int64 rows (res, size, offset, dense); scales: (L,) float64; mask: (L,) float64.
    Returns (N, L, F); levels whose mask is 0 give zeros and no gradient. Raises RuntimeError when the
    extension is unavailable.
    """
    if x01.device.type != "cpu" or table.device.type != "cpu":
        raise ValueError(f"HashGrid(backend='cpp'): needs CPU tensors, got {x01.device} and {table.device}")
    if x01.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"HashGrid(backend='cpp'): unsupported dtype {x01.dtype}")
    if table.dtype != x01.dtype:
        table = table.to(x01.dtype)
    return _Encode.apply(x01, table, levels, scales, mask)
