"""The tracking ceiling of a synthetic capture: its ground-truth appearance on the posed written model.

An avatar is driven by the capture's FLAME parameters, so on a tracked capture (``--tracking
fitted``) even a perfect avatar draws the head where the *written* model, posed with those
parameters, puts it, not where the truth is. :class:`TrackedTruth` renders exactly that perfect
avatar: the capture's own procedural albedo, Lambert shading, highlights and compression creases
(the darkening of :func:`~.appearance.crease_weights`, from the written mesh's own compression) on
the written model posed with given parameters, through the same mesh renderer that wrote the
images. Compared with the ground truth it measures what the tracking alone costs; on an exact
capture it reproduces the ground-truth images. A detailed subject's hair volume follows the
written model's skull rigidly, as it follows the truth's in the images.

It is a reference for benchmarks, not a bound in the strict sense: an avatar that blurs where the
tracked silhouette is uncertain can score a higher PSNR on some images.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ...errors import ConfigError, InputError
from ..cameras import Camera
from .appearance import crease_weights
from .capture import _Subject, make_subject, neck_line_mask
from .config import SynthConfig
from .model_files import flame_model

if TYPE_CHECKING:
    from ...flame import FlameModel

FLAME_KEYS: tuple[str, ...] = ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")
"""Per-frame FLAME parameters the ceiling poses the written model with."""

_MATCH_TOL = 1e-5
"""Largest relative difference between the rebuilt subject and the capture's files (float32 files)."""


@dataclass
class TrackedTruth:
    """The ground truth of a ``sage synth`` capture, rendered on any pose of its written model.

    capture: the capture folder; config: its synthesis config (from ``gt/info.json``); subject:
    the head, identity and appearance rebuilt from that config; written: the written FLAME-format
    model (float64 ``sage_core.flame.FlameModel``; the full head's on an exact capture).
    """

    capture: Path
    config: SynthConfig
    subject: _Subject
    written: FlameModel

    @classmethod
    def open(cls, capture_dir: str | Path) -> TrackedTruth:
        """Rebuild the subject of the capture in ``capture_dir`` and check it against the capture's
        files (canonical mesh, written model, appearance). Raises InputError when the folder is not
        a ``sage synth`` capture or was written by a generator whose subject differs."""
        root = Path(capture_dir)
        info_path = root / "gt" / "info.json"
        try:
            info = json.loads(info_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(info_path, "not found: the tracking ceiling needs a capture written by `sage synth`") from None
        except (OSError, ValueError) as e:
            raise InputError(info_path, f"unreadable: {e}") from None
        if info.get("generator") != "sage synth" or "config" not in info:
            raise InputError(info_path, "not a `sage synth` capture (no generator config)")
        try:
            cfg = SynthConfig.from_dict(info["config"])
        except (TypeError, ValueError, KeyError) as e:
            raise InputError(info_path, f"its synthesis config is not readable by this version: {e}") from None
        photo = None
        if cfg.skin_photo is not None:  # the capture keeps its photo skin
            from .photo_skin import PHOTO_SKIN_FILE, read_photo_skin

            try:
                photo = read_photo_skin(root / "gt" / PHOTO_SKIN_FILE)
            except (OSError, ValueError, KeyError, ConfigError) as e:
                raise InputError(root / "gt" / PHOTO_SKIN_FILE, f"unreadable: {e}") from None
        subject = make_subject(cfg, photo)
        written = subject.tracked.written if subject.tracked is not None else flame_model(subject.head)
        truth = cls(root, cfg, subject, written)
        truth._check(info)
        return truth

    def _check(self, info: dict[str, Any]) -> None:
        import trimesh

        from .capture import canonical_vertices

        subj = self.subject
        if info.get("identity", {}).get("appearance") != json.loads(json.dumps(subj.app.to_dict())):
            raise InputError(self.capture / "gt" / "info.json", "its appearance differs from the one this version rebuilds from the config")
        path = self.capture / "gt" / "canonical.ply"
        try:
            canon = np.asarray(trimesh.load(path, process=False).vertices, np.float64)
        except (OSError, ValueError) as e:
            raise InputError(path, f"unreadable: {e}") from None
        ref = canonical_vertices(subj)
        scale = float(np.abs(ref).max())
        if canon.shape != ref.shape or float(np.abs(canon - ref).max()) > _MATCH_TOL * scale:
            raise InputError(path, "the canonical mesh differs from the one this version rebuilds from the capture's config")

    def pose(self, params: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """The written model posed with one frame's ``params`` (:data:`FLAME_KEYS`, each (k,) or
        (1, k); the identity and static offset are the capture's). Returns posed vertices (V, 3) and
        crease weights (V,) of that pose (compression relative to the neutral face)."""
        import torch

        model = self.written
        t = lambda a: torch.as_tensor(np.asarray(a, np.float64).reshape(1, -1), dtype=torch.float64)  # noqa: E731
        shape = torch.as_tensor(self.subject.shape, dtype=torch.float64)
        off = torch.as_tensor(self.subject.static_offset, dtype=torch.float64)
        p = {k: t(params[k]) for k in FLAME_KEYS}
        with torch.no_grad():
            out = model(shape=shape, static_offset=off, **p)
            neutral = model(shape=shape, static_offset=off).v_shaped[0].numpy()
        faces = self.subject.head.faces
        return out.vertices[0].numpy(), crease_weights(out.v_shaped[0].numpy(), neutral, faces)

    def render(self, params: dict[str, np.ndarray], camera: Camera) -> np.ndarray:
        """(H, W, 3) float32 image in [0, 1] on white: the ground-truth appearance on the written
        model posed with ``params``, seen by ``camera`` (any intrinsics: resized cameras too), cut at
        the neck line like the capture's images."""
        verts, crease = self.pose(params)
        subj = self.subject
        r = subj.render(verts, camera, crease, self.config.supersample)
        neck = neck_line_mask(subj.head, verts, camera)[..., None]
        return (r.rgb * neck + (1.0 - neck)).astype(np.float32)
