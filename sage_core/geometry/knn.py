"""Exact k-nearest-neighbour queries between point sets (chunked distance matrices)."""

from __future__ import annotations

import torch

__all__ = ["nearest_indices"]


def nearest_indices(
    queries: torch.Tensor, points: torch.Tensor, k: int, exclude: torch.Tensor | None = None, chunk: int = 2048
) -> torch.Tensor:
    """(Q, k) indices into ``points`` of the k nearest points of each query, nearest first.

    queries: (Q, 3); points: (P, 3); k ≤ P (≤ P − 1 with ``exclude``); exclude: optional (Q,) index of
    a point each query must skip (itself, for neighbours within one set); chunk: queries per distance
    matrix, so memory stays chunk × P. No gradient.
    """
    out = []
    with torch.no_grad():
        for s in range(0, int(queries.shape[0]), chunk):
            d = torch.cdist(queries[s : s + chunk], points)
            if exclude is not None:
                d[torch.arange(d.shape[0], device=d.device), exclude[s : s + chunk]] = float("inf")
            out.append(d.topk(int(k), dim=1, largest=False).indices)
    return torch.cat(out) if out else torch.zeros(0, int(k), dtype=torch.long, device=points.device)
