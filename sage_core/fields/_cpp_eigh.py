"""Native CPU eigensolver of symmetric 3x3 matrices (C++/OpenMP): the fast path of ``shape.safe_eigh``.

``torch.linalg.eigh`` on CPU calls LAPACK once per matrix, which costs microseconds per 3x3 matrix
in call overhead alone; ``eigh3`` solves the whole batch in one pass with Jacobi rotations in double
precision (``csrc/eigh3_cpu.cpp``, whose header states the method, the sign rule and the threading).

What agrees with ``torch.linalg.eigh``: only the lower triangle is read; eigenvalues ascending, to
rounding; eigenvectors as orthonormal columns. What may differ: the sign of each eigenvector (here
the entry of largest magnitude is made non-negative, LAPACK fixes no sign), and, for repeated
eigenvalues, the basis chosen in their eigenspace. Non-finite inputs give NaN outputs instead of an
error. There is no backward here: ``shape._SafeEigh`` supplies it.

The extension is built on first use by ``sage_core.native_build``; ``available()`` reports whether it
could be.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..native_build import NativeExtension

__all__ = ["EXT", "available", "eigh3", "supports", "warn_unavailable_once"]

EXT = NativeExtension(
    name="sage_eigh3_cpu",
    source=Path(__file__).parent / "csrc" / "eigh3_cpu.cpp",
    namespace="sage_eigh3_cpu",
    probe_op="eigh3",
    what="3x3 eigensolver",
    fallback="torch.linalg.eigh",
)

available = EXT.available
"""(True, where it was loaded from) once the extension is built and loaded, else (False, reason); the
first call compiles it unless a cached build exists, and the result is remembered for the process."""
warn_unavailable_once = EXT.warn_unavailable_once


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
