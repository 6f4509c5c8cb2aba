"""Multi-resolution hash encoding (instant-ngp / tiny-cuda-nn conventions) in pure torch.

Level l of L uses ``scale_l = N_min * b**l - 1`` with ``b = exp((ln N_max - ln N_min) / (L - 1))``,
``res_l = ceil(scale_l) + 1`` vertices per axis and ``pos = x01 * scale_l + 0.5``. Coarse levels whose
``res_l**3`` fits into ``size_l = min(next_multiple_of_8(res_l**3), T)`` are dense (stride index), the others
hash the integer corner with ``x*1 ^ y*2654435761 ^ z*805459861`` (uint32 wrap emulated in int64). All
levels live in one ``(sum_l size_l, F)`` table. Interpolation gathers the 8 corners and multiplies three
explicit 1-D weights, so second derivatives (eikonal loss) are exact and zero along an axis inside a cell.

Backends (``HashGrid.backend``): ``torch`` is the reference below; ``cpp`` is the native C++/OpenMP
kernel of ``_cpp_hashgrid`` (same rules, exact first and second derivatives); ``auto`` (the default)
uses ``cpp`` for CPU tensors when the extension builds and ``torch`` otherwise (CUDA tensors always
use ``torch``). The normalization and its clamp stay in torch for both.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

_PRIMES = (1, 2654435761, 805459861)
_UINT32 = 0xFFFFFFFF
BACKENDS = ("auto", "torch", "cpp")


def resolve_backend(backend: str, device: torch.device | str) -> str:
    """``auto|torch|cpp`` for tensors on ``device`` -> the backend that runs: ``torch`` or ``cpp``.

    ``auto`` picks ``cpp`` on CPU when the native extension is available (building it on first use)
    and otherwise warns once and picks ``torch``. CUDA tensors always use ``torch``. An explicit
    ``cpp`` on CPU whose extension cannot be built raises ValueError with the reason.
    """
    if backend not in BACKENDS:
        raise ValueError(f"HashGrid: unknown backend {backend!r} (choose from {', '.join(BACKENDS)})")
    if backend == "torch" or torch.device(device).type != "cpu":
        return "torch"
    from . import _cpp_hashgrid

    return _cpp_hashgrid.EXT.choose(backend, "HashGrid")


def _level_scales(n_levels: int, base_res: int, max_res: int) -> list[float]:
    """Per-level ``scale_l = N_min * b**l - 1`` (float64), snapped to integers within 1e-9 relative.

    Without the snap, float64 rounding gives ``16 * b**15 - 1 = 2047.0000000000005`` for N_min 16 and
    N_max 2048, so ``ceil`` would give a top resolution of 2049 instead of 2048.
    """
    if n_levels == 1:
        growth = 1.0
    else:
        growth = math.exp((math.log(max_res) - math.log(base_res)) / (n_levels - 1))
    scales = []
    for level in range(n_levels):
        s = base_res * growth**level - 1.0
        r = round(s)
        if abs(s - r) <= 1e-9 * max(1.0, abs(s)):
            s = float(r)
        scales.append(s)
    return scales


class HashGrid(nn.Module):
    """Multi-resolution hash grid over an axis-aligned box in world units.

    Args:
        bbox_min: (3,) lower corner of the encoded box, world units; points outside are clamped to it.
        bbox_max: (3,) upper corner.
        n_levels: L, number of resolution levels.
        n_features: F, features per level.
        log2_table: log2 of the maximum entries per level, T = 2**log2_table.
        base_res: N_min, coarsest resolution (vertices per axis, tcnn convention).
        max_res: N_max, finest resolution.
        init_range: table entries start as U(-init_range, init_range).
        backend: ``auto`` | ``torch`` | ``cpp`` (see the module docstring); an attribute that may be
            changed later, not part of the state dict.

    Presets: ``tiny`` (CPU) L=8..12, F=2, log2 T=14..16, N_min=16, N_max=256;
    ``default`` (paper, GPU) L=16, F=2, log2 T=19, N_min=16, N_max=2048 (12.2M parameters).

    Progressive training: ``set_active_levels(n)`` multiplies the features of levels >= n by 0.
    """

    def __init__(
        self,
        bbox_min: Sequence[float] | torch.Tensor,
        bbox_max: Sequence[float] | torch.Tensor,
        n_levels: int = 16,
        n_features: int = 2,
        log2_table: int = 19,
        base_res: int = 16,
        max_res: int = 2048,
        init_range: float = 1e-4,
        backend: str = "auto",
    ) -> None:
        super().__init__()
        if n_levels < 1 or n_features < 1:
            raise ValueError("n_levels and n_features must be positive")
        if backend not in BACKENDS:
            raise ValueError(f"HashGrid: unknown backend {backend!r} (choose from {', '.join(BACKENDS)})")
        self.backend = backend
        if max_res < base_res:
            raise ValueError("max_res must be >= base_res")
        self.n_levels = int(n_levels)
        self.n_features = int(n_features)
        self.log2_table = int(log2_table)
        self.base_res = int(base_res)
        self.max_res = int(max_res)
        table_max = 2 ** self.log2_table

        scales = _level_scales(self.n_levels, self.base_res, self.max_res)
        resolutions, sizes, dense, offsets = [], [], [], []
        total = 0
        for s in scales:
            res = int(math.ceil(s)) + 1
            n_dense = res**3
            size = min(((n_dense + 7) // 8) * 8, table_max)
            resolutions.append(res)
            sizes.append(size)
            dense.append(n_dense <= size)
            offsets.append(total)
            total += size
        self.level_scales = scales
        self.level_resolutions = resolutions
        self.level_sizes = sizes

        lo = torch.as_tensor(bbox_min, dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(bbox_max, dtype=torch.float32).reshape(3)
        if bool((hi <= lo).any()):
            raise ValueError("bbox_max must exceed bbox_min on every axis")
        self.register_buffer("bbox_min", lo.clone())
        self.register_buffer("bbox_max", hi.clone())
        self.register_buffer("_scales", torch.tensor(scales, dtype=torch.float64))
        self.register_buffer("_res", torch.tensor(resolutions, dtype=torch.int64))
        self.register_buffer("_sizes", torch.tensor(sizes, dtype=torch.int64))
        self.register_buffer("_dense", torch.tensor(dense, dtype=torch.bool))
        self.register_buffer("_offsets", torch.tensor(offsets, dtype=torch.int64))
        self.register_buffer("_primes", torch.tensor(_PRIMES, dtype=torch.int64))
        layout = [[r, n, o, int(d)] for r, n, o, d in zip(resolutions, sizes, offsets, dense)]
        self.register_buffer("_layout", torch.tensor(layout, dtype=torch.int64), persistent=False)
        self.register_buffer("level_mask", torch.ones(self.n_levels))
        self.table = nn.Parameter(torch.empty(total, self.n_features).uniform_(-init_range, init_range))

    @property
    def output_dim(self) -> int:
        """L * F."""
        return self.n_levels * self.n_features

    @property
    def active_levels(self) -> int:
        """Number of levels currently contributing (progressive masking)."""
        return int(self.level_mask.sum().item())

    def set_active_levels(self, n: int) -> None:
        """Enable the ``n`` coarsest levels and zero the features of the others (1 <= n <= L)."""
        n = max(1, min(int(n), self.n_levels))
        mask = torch.zeros_like(self.level_mask)
        mask[:n] = 1.0
        self.level_mask.copy_(mask)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) -> box coordinates in [0, 1]^3 (clamped)."""
        lo = self.bbox_min.to(x.dtype)
        hi = self.bbox_max.to(x.dtype)
        return ((x - lo) / (hi - lo)).clamp(0.0, 1.0)

    def finest_cell_size(self) -> float:
        """Cell edge of the finest *active* level in world units (the largest over the three axes)."""
        level = self.active_levels - 1
        extent = float((self.bbox_max - self.bbox_min).max().item())
        return extent / self.level_scales[level]

    def level_features(self, x: torch.Tensor) -> torch.Tensor:
        """Interpolated features per level.

        x: (N, 3) world points -> (N, L, F); masked (inactive) levels are 0. Runs the backend that
        ``resolve_backend(self.backend, x.device)`` picks (float16/bfloat16 inputs use torch).
        """
        x01 = self.normalize(x)
        if x01.dtype in (torch.float32, torch.float64) and resolve_backend(self.backend, x01.device) == "cpp":
            from . import _cpp_hashgrid

            scales = self._scales.to(torch.float64)
            mask = self.level_mask.to(torch.float64)
            return _cpp_hashgrid.encode(x01, self.table, self._layout, scales, mask)
        return self._level_features_torch(x01)

    def _level_features_torch(self, x01: torch.Tensor) -> torch.Tensor:
        """The pure-torch reference: x01 (N, 3) box coordinates in [0, 1] -> (N, L, F)."""
        scales = self._scales.to(x01.dtype)
        pos = x01[:, None, :] * scales[None, :, None] + 0.5  # (N, L, 3)
        base = torch.floor(pos)
        t = pos - base  # (N, L, 3); floor has no gradient, t carries d/dx
        base_i = base.to(torch.int64)
        one_minus_t = 1.0 - t
        res = self._res[None, :]
        dense = self._dense[None, :]
        sizes = self._sizes[None, :]
        offsets = self._offsets[None, :]
        table = self.table.to(x01.dtype) if self.table.dtype != x01.dtype else self.table
        out = x01.new_zeros(x01.shape[0], self.n_levels, self.n_features)
        for corner in range(8):
            bits = ((corner >> 0) & 1, (corner >> 1) & 1, (corner >> 2) & 1)
            cx = base_i[..., 0] + bits[0]
            cy = base_i[..., 1] + bits[1]
            cz = base_i[..., 2] + bits[2]
            idx_dense = cx + res * (cy + res * cz)
            idx_hash = ((cx * self._primes[0]) ^ (cy * self._primes[1]) ^ (cz * self._primes[2])) & _UINT32
            idx = torch.where(dense, idx_dense, idx_hash) % sizes + offsets  # (N, L)
            wx = t[..., 0] if bits[0] else one_minus_t[..., 0]
            wy = t[..., 1] if bits[1] else one_minus_t[..., 1]
            wz = t[..., 2] if bits[2] else one_minus_t[..., 2]
            w = wx * wy * wz  # explicit product: exact second derivatives
            out = out + w[..., None] * table[idx]
        return out * self.level_mask.to(out.dtype)[None, :, None]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, 3) world points -> (N, L*F) features, level-major (level l at [l*F:(l+1)*F])."""
        return self.level_features(x).reshape(x.shape[0], self.output_dim)
