"""Canonical space (docs/method.md §2): the FLAME mesh of the canonical timestep with its
expression, jaw, eyes and neck pose, but zero global rotation and translation."""

from __future__ import annotations

from typing import Any

import torch

from .lbs import FlameModel
from .params import FlameParams


def canonical_inputs(params: FlameParams, timestep: int, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> dict[str, Any]:
    """``FlameModel.forward`` keyword arguments for the canonical mesh of ``timestep``.

    Shape, static offset, and the timestep's expression, jaw, eyes, neck pose and dynamic offset
    are kept; global rotation and translation are zero. Every tensor has batch size 1.
    """
    row = params.row_of(timestep)
    p = params.to_torch(device, dtype)
    out: dict[str, Any] = {
        "shape": p["shape"][None],
        "expr": p["expr"][row : row + 1],
        "neck_pose": p["neck_pose"][row : row + 1],
        "jaw_pose": p["jaw_pose"][row : row + 1],
        "eyes_pose": p["eyes_pose"][row : row + 1],
        "rotation": torch.zeros(1, 3, device=device, dtype=dtype),
        "translation": torch.zeros(1, 3, device=device, dtype=dtype),
    }
    if "static_offset" in p:
        out["static_offset"] = p["static_offset"]
    if "dynamic_offset" in p:
        out["dynamic_offset"] = p["dynamic_offset"][row : row + 1]
    return out


def frame_inputs(params: FlameParams, rows: list[int] | torch.Tensor, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> dict[str, Any]:
    """``FlameModel.forward`` keyword arguments for rows ``rows`` of ``params`` (batch = len(rows))."""
    idx = torch.as_tensor(rows, dtype=torch.long)
    p = params.to_torch(device, dtype)
    out: dict[str, Any] = {k: p[k][idx] for k in ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")}
    out["shape"] = p["shape"][None].expand(len(idx), -1)
    if "static_offset" in p:
        out["static_offset"] = p["static_offset"]
    if "dynamic_offset" in p:
        out["dynamic_offset"] = p["dynamic_offset"][idx]
    return out


@torch.no_grad()
def canonical_vertices(model: FlameModel, params: FlameParams, timestep: int) -> torch.Tensor:
    """(V, 3) canonical vertices of ``timestep`` on the model's device and dtype."""
    buf = next(iter(model.buffers()))
    out = model(**canonical_inputs(params, timestep, buf.device, buf.dtype))
    return out.vertices[0]
