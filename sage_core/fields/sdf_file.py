"""The SDF file ``init/sdf.pt``: the :class:`SDFNetwork` constructor kwargs and its state dict in a
safetensors file (:mod:`sage_core.serialization`; loading it cannot run code)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from ..errors import InputError
from ..serialization import SDF_FILE_FORMAT, SDF_KIND
from .sdf import SDFNetwork



def save_sdf(path: str | Path, args: dict[str, Any], net: SDFNetwork) -> Path:
    """Write an SDF file atomically: ``{"format", "args": constructor kwargs, "state": state dict}``
    as a safetensors file (loading it cannot run code)."""
    from ..serialization import save_file

    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    return save_file(path, {"format": SDF_FILE_FORMAT, "args": args, "state": state}, SDF_KIND, SDF_FILE_FORMAT)


def read_sdf_file(path: str | Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """(constructor kwargs, CPU state dict) of an SDF file; InputError (UnsafeFileError for an old
    pickle file, which is not loaded) when it is not a readable sage SDF file."""
    from ..serialization import load_file

    p = Path(path)
    blob, _ = load_file(p, SDF_KIND, SDF_FILE_FORMAT, "SDF file")
    if not isinstance(blob, dict) or not isinstance(blob.get("args"), dict) or not isinstance(blob.get("state"), dict):
        raise InputError(p, "not a sage SDF file")
    return blob["args"], blob["state"]


def load_sdf(path: str | Path, device: str | torch.device = "cpu") -> SDFNetwork:
    """Load ``sdf.pt`` written by this stage."""
    p = Path(path)
    args, state = read_sdf_file(p)
    try:
        net = SDFNetwork(**args).to(device)
        net.load_state_dict(state)
    except (TypeError, ValueError, RuntimeError) as e:
        raise InputError(p, f"malformed SDF file: {e}") from None
    return net


__all__ = ["SDF_FILE_FORMAT", "SDF_KIND", "load_sdf", "read_sdf_file", "save_sdf"]
