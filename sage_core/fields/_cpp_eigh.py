"""Native CPU eigensolver of symmetric 3x3 matrices (C++/OpenMP): the fast path of ``shape.safe_eigh``.

``torch.linalg.eigh`` on CPU calls LAPACK once per matrix, which costs microseconds per 3x3 matrix
in call overhead alone; ``eigh3`` solves the whole batch in one pass with Jacobi rotations in double
precision (``csrc/eigh3_cpu.cpp``, whose header states the method, the sign rule and the threading).

What agrees with ``torch.linalg.eigh``: only the lower triangle is read; eigenvalues ascending, to
rounding; eigenvectors as orthonormal columns. What may differ: the sign of each eigenvector (here
the entry of largest magnitude is made non-negative, LAPACK fixes no sign), and, for repeated
eigenvalues, the basis chosen in their eigenspace. Non-finite inputs give NaN outputs instead of an
error. ``eigh3`` has no autograd of its own: ``shape._SafeEigh`` supplies the gap-clamped backward,
which for these solutions runs as ``eigh3_backward`` (the torch formula's operations in its order, so
the same values bit for bit).

The extension is built on first use by ``sage_core.native_build``; ``available()`` reports whether it
could be.
"""

from __future__ import annotations


import torch

from ..native_build import native_extension

__all__ = ["EXT", "available", "eigh3", "eigh3_backward", "supports", "warn_unavailable_once"]

EXT = native_extension(__file__, "eigh3_cpu", probe_op="eigh3", what="3x3 eigensolver", fallback="torch.linalg.eigh")

available, warn_unavailable_once = EXT.available, EXT.warn_unavailable_once


def supports(a: torch.Tensor) -> str | None:
    """Why ``eigh3`` cannot take ``a``, or None when it can: a CPU float32/float64 (..., 3, 3) tensor."""
    if a.device.type != "cpu":
        return f"a is on {a.device}"
    if a.dtype not in (torch.float32, torch.float64):
        return f"dtype {a.dtype}"
    if a.dim() < 2 or a.shape[-2:] != (3, 3):
        return f"shape {tuple(a.shape)} (needs (..., 3, 3))"
    return None


def eigh3(a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Eigen-decomposition of a batch of symmetric 3x3 matrices (lower triangle read), no gradient.

    a: (..., 3, 3) float32 or float64 on the CPU. Returns eigenvalues (..., 3) ascending and
    eigenvectors (..., 3, 3) as columns, in a's dtype. Raises ValueError for other tensors and
    RuntimeError when the extension is unavailable.
    """
    why = supports(a)
    if why is not None:
        raise ValueError(f"eigh3: {why}")
    ops = EXT.ops("eigh3")
    batch = a.shape[:-2]
    evals, evecs = ops.eigh3(a.detach().reshape(-1, 3, 3).contiguous())
    return evals.reshape(*batch, 3), evecs.reshape(*batch, 3, 3)


def eigh3_backward(
    evals: torch.Tensor, evecs: torch.Tensor, g_evals: torch.Tensor | None, g_evecs: torch.Tensor | None, gap: float
) -> torch.Tensor:
    """The gap-clamped backward of ``shape.safe_eigh`` (``shape.eigh_backward_torch`` is the reference).

    evals (..., 3), evecs (..., 3, 3): an ``eigh3`` solution; g_evals (..., 3), g_evecs (..., 3, 3): the
    upstream gradients (either may be None); gap: the smallest |eigenvalue gap| of the 1/gap factors.
    Returns the gradient of the symmetric input (..., 3, 3), in evecs' dtype.
    """
    why = supports(evecs)
    if why is not None:
        raise ValueError(f"eigh3_backward: {why}")
    batch = evecs.shape[:-2]

    def flat(t: torch.Tensor | None, *shape: int) -> torch.Tensor | None:
        return None if t is None else t.to(evecs.dtype).reshape(-1, *shape).contiguous()

    ga = EXT.ops("eigh3").eigh3_backward(flat(evals, 3), flat(evecs, 3, 3), flat(g_evals, 3), flat(g_evecs, 3, 3), float(gap))
    return ga.reshape(*batch, 3, 3)
