"""A driving motion for an avatar (export and reenact).

* :func:`load_driving_motion` reads a motion, cuts it to ``--max-frames`` and checks it against the
  avatar (:func:`check_motion_for_avatar`);
* :func:`with_identity` puts the avatar's own shape and static offset into a motion's FLAME inputs.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    import torch

    from ..avatar import Avatar


def with_identity(avatar: Avatar, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A motion's FLAME inputs (batch 1, no identity) with the avatar's own ``shape`` and
    ``static_offset``: the subject keeps its identity whatever drives it (cross-reenactment)."""
    dev = avatar.device
    own = avatar.params.to_torch(dev)
    out = {k: v.to(dev) for k, v in inputs.items() if k not in ("shape", "static_offset")}
    out["shape"] = own["shape"][None]
    if "static_offset" in own:
        out["static_offset"] = own["static_offset"]
    return out


def check_motion_for_avatar(avatar: Avatar, motion: Any) -> None:
    """Validate a :class:`sage_core.export.Motion` against the avatar before rendering anything.

    Checks T >= 1, finite values, that ``expr`` has no non-zero coefficient beyond the model's
    expression components (:func:`sage_core.flame.params.expr_overflow`), and that ``dynamic_offset``
    has between the model's base vertex count and its full vertex count rows (fewer rows are
    zero-padded at the end, as for the teeth).
    Raises InputError naming the motion source.
    """
    from ..flame.params import expr_overflow

    p = motion.params
    if p.n_timesteps < 1:
        raise InputError(motion.source, "the motion holds no frames")
    problem = expr_overflow(p, int(avatar.model_data.n_expr))
    if problem is not None:
        raise InputError(motion.source, problem)
    for key in ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation"):
        a = np.asarray(getattr(p, key))
        if a.shape[0] != p.n_timesteps:
            raise InputError(motion.source, f"'{key}' has {a.shape[0]} rows, the motion has T = {p.n_timesteps} frames")
        if not np.isfinite(a).all():
            raise InputError(motion.source, f"'{key}' holds NaN or Inf")
    if p.dynamic_offset is not None:
        d = np.asarray(p.dynamic_offset)
        n_v = int(np.asarray(avatar.model_data.v_template).shape[0])
        n_base = int(avatar.model_data.n_base_vertices)
        if d.shape[0] != p.n_timesteps:
            raise InputError(motion.source, f"'dynamic_offset' has {d.shape[0]} frames, the motion has T = {p.n_timesteps}")
        if not n_base <= d.shape[1] <= n_v:
            raise InputError(
                motion.source,
                f"'dynamic_offset' has {d.shape[1]} vertices; this avatar's FLAME model has {n_base} "
                f"({n_v} with its appended teeth and mouth interior)",
            )
        if not np.isfinite(d).all():
            raise InputError(motion.source, "'dynamic_offset' holds NaN or Inf")


def load_driving_motion(avatar: Avatar, source: str | Path, max_frames: int | None = None) -> Any:
    """The :class:`sage_core.export.Motion` at ``source`` (npz, flame_param folder or capture), cut
    to its first ``max_frames`` frames and checked against the avatar
    (:func:`check_motion_for_avatar`) before anything renders."""
    from ..export.motion import load_motion

    motion = load_motion(source, n_expr=avatar.params.n_expr)
    if max_frames is not None and max_frames < motion.n_frames:
        motion.params = motion.params.select(list(range(max_frames)))
    check_motion_for_avatar(avatar, motion)
    return motion
