"""Phase 1's start from the pretrained mouth-interior prior (free per-surfel attributes).

With ``attributes=free`` every surfel has its own colour. The mouth-interior surfels (bound to the
``mouth_interior`` and ``teeth`` regions of ``init_dir/regions.json``) start from the pretrained
prior's albedo at their canonical centre (:mod:`sage_core.avatar.mouth_prior`) instead of grey: the
training views then refine what they see and what they never see keeps the prior. With the
appearance network (``attributes=mlp``) there is no per-surfel colour to start from; phase 2 gives
the unseen mouth surfels the prior as their colour prior (:mod:`sage_core.train.phase2`).
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from ..avatar.model import Avatar
from ..avatar.surfels import SH_C0
from ..errors import InputError


def seed_free_mouth_colors(avatar: Avatar, init_dir: str | Path) -> int:
    """Set the DC colour of the mouth-interior surfels of a free-attribute ``avatar`` to the prior's
    albedo (higher SH bands untouched). Returns how many surfels were set (0 without regions or mouth)."""
    from ..avatar.mouth_prior import avatar_prior_colors
    from ..flame.regions import Regions

    path = Path(init_dir) / "regions.json"
    if avatar.attributes != "free" or not path.is_file():
        return 0
    try:
        regions = Regions.from_dict(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(path, f"malformed regions: {e}") from None
    if not (regions.has("mouth_interior") or regions.has("teeth")) or not regions.has("lips"):
        return 0
    try:
        cols, on = avatar_prior_colors(avatar, regions)
    except ValueError as e:
        raise InputError(path, f"cannot place the mouth prior: {e}") from None
    with torch.no_grad():
        dc = avatar.surfels.sh_dc
        dc[on] = ((cols[on].to(dc) - 0.5) / SH_C0)[:, None, :]
    return int(on.sum())
