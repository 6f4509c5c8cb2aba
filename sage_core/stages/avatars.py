"""The avatar of a workspace stage, seen from the stages that use it (eval, reenact, export, run).

* :func:`resolve_avatar_stage` picks the avatar to use: the latest finished of phase2 and phase1,
  refusing a stale one with the workspace's message;
* :func:`load_stage_avatar` loads ``WS/<stage>/avatar.pt`` with the settings it was trained to be
  rendered with (near/far and, for phase 2, the surfel correction from the stage's saved config;
  the background of the ingested data);
* :class:`AvatarRenderer` renders it for a camera and a frame's (or a motion's) FLAME inputs, with
  the canonical state computed once;
* :func:`reference_camera` and :func:`head_center` give the default camera and the head's centre.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..errors import InputError, StageError
from ..export.bundle import RenderSettings

if TYPE_CHECKING:
    from ..avatar import Avatar, PosedSurfels
    from ..data.cameras import Camera
    from ..data.dataset import IngestedData
    from ..workspace import Workspace

AVATAR_STAGES: tuple[str, ...] = ("phase2", "phase1")
"""Stages that write an avatar (``WS/<stage>/avatar.pt``), newest first."""

AVATAR_FILE = "avatar.pt"


def resolve_avatar_stage(ws: Workspace, requested: str, by: str) -> str:
    """The avatar stage ``by`` should use.

    requested: "auto", "phase1" or "phase2". "auto" takes phase2 when it finished, phase2's
    refusal when it is stale (re-run it), otherwise phase1 (missing or interrupted phase2).
    Raises StageError (the workspace's message) when the chosen stage is missing or stale.
    """
    if requested not in ("auto", *AVATAR_STAGES):
        from ..errors import ConfigError

        raise ConfigError(f"--stage must be auto, phase1 or phase2, got {requested!r}")
    if requested != "auto":
        ws.require(requested, by)
        return requested
    for stage in AVATAR_STAGES:
        st = ws.status(stage)
        if st.status == "complete":
            return stage
        if st.status == "stale":
            ws.require(stage, by)  # raises with the stage to re-run
    raise StageError(f"'{by}' needs a trained avatar, but neither phase2 nor phase1 has completed: run `sage phase1 {ws.root}` first")


CORRECTION_KEYS: tuple[str, ...] = ("radius_edges", "max_neighbours", "w_s", "umbilic_tol", "anisotropy_tol", "mode")
"""Fields of the phase-2 config's ``correction`` section that are ``CorrectedPosing`` keyword arguments
(a config saved before the sections existed names them ``correction_<field>`` at the top level)."""


def saved_correction(cfg: dict[str, Any]) -> dict[str, Any] | None:
    """``CorrectedPosing`` keyword arguments from a saved phase-2 config (plain data, nested or of
    the earlier flat form), or None when the correction is off or the config is not phase 2's."""
    section = cfg.get("correction")
    if isinstance(section, dict):
        if section.get("enabled") is not True:
            return None
        out = {k: section[k] for k in CORRECTION_KEYS if k in section}
    elif section is True:
        out = {k: cfg[f"correction_{k}"] for k in CORRECTION_KEYS if f"correction_{k}" in cfg}
    else:
        return None
    # phase-2 avatars trained before the affine mode existed used the curvature mode
    out.setdefault("mode", "curvature")
    return out


def stage_render_settings(stage_dir: Path, data: IngestedData | None) -> RenderSettings:
    """Render settings of an avatar stage: near/far from its saved ``config.json``, the surfel
    correction when that config enables it (phase 2), and the background of the ingested data."""
    near, far = 0.2, 100.0
    correction = None
    cfg_path = stage_dir / "config.json"
    if cfg_path.is_file():
        try:
            cfg = json.loads(cfg_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as e:
            raise InputError(cfg_path, f"cannot read the stage's config: {e}") from None
        near = float(cfg.get("near", near))
        far = float(cfg.get("far", far))
        correction = saved_correction(cfg)
    bg = 1.0
    if data is not None:
        bg = 0.0 if str(data.summary.get("background", "white")) == "black" else 1.0
    return RenderSettings(near=near, far=far, background=bg, correction=correction)


@dataclass
class StageAvatar:
    """An avatar loaded from a workspace stage."""

    stage: str
    path: Path
    fingerprint: str
    avatar: Avatar
    render: RenderSettings


def load_stage_avatar(ws: Workspace, stage: str, data: IngestedData | None, device: str | torch.device = "cpu") -> StageAvatar:
    """Load ``WS/<stage>/avatar.pt`` (the stage must be complete and fresh: StageError otherwise)."""
    from ..avatar import Avatar

    manifest = ws.require(stage, "loading the avatar")
    path = ws.stage_dir(stage) / AVATAR_FILE
    if not path.is_file():
        raise StageError(f"{path}: the stage '{stage}' finished without an avatar file; re-run `sage {stage} {ws.root} --force`")
    avatar = Avatar.load(path, device)
    avatar.eval()
    return StageAvatar(stage, path, str(manifest.get("fingerprint", "")), avatar, stage_render_settings(ws.stage_dir(stage), data))


class AvatarRenderer:
    """Poses and renders one avatar for many frames; the canonical state is computed once.

    With ``settings.correction`` the surfels are posed with the stretch- and curvature-driven
    correction (:class:`sage_core.avatar.corrected.CorrectedPosing`), as phase 2 renders them.
    backend: the ``render_backend`` of the stage that renders (auto, torch, cpp, triton), resolved
    once for the avatar's device (:func:`sage_core.runtime.resolve_render_backend`, ConfigError
    when an explicit backend cannot run there); the result is ``self.backend``.
    """

    def __init__(self, avatar: Avatar, settings: RenderSettings, backend: str = "auto") -> None:
        from ..runtime import resolve_render_backend

        self.avatar = avatar
        self.settings = settings
        self.backend = resolve_render_backend(backend, str(avatar.device))
        self.posing = None
        if settings.correction is not None:
            from ..avatar.corrected import CorrectedPosing

            self.posing = CorrectedPosing(avatar, True, **settings.correction)
        with torch.no_grad():
            self.canonical = avatar.canonical_state(with_sdf=avatar.attributes == "mlp")

    def posed(self, flame_inputs: dict[str, torch.Tensor], view_from: torch.Tensor | None) -> PosedSurfels:
        """World-space surfels of one frame, colours for the camera centre ``view_from`` (3,) (None:
        each surfel seen along its normal)."""
        with torch.no_grad():
            if self.posing is not None:
                p, _ = self.posing.posed(flame_inputs, view_from, canonical=self.canonical)
                return p
            return self.avatar.posed(flame_inputs, view_from, canonical=self.canonical)

    def render(self, camera: Camera, flame_inputs: dict[str, torch.Tensor]) -> torch.Tensor:
        """(H, W, 3) colour (unclamped) of one frame seen by ``camera``, on the settings' background."""
        from ..render import RenderCamera, rasterize_surfels

        dev = self.avatar.device
        cam = RenderCamera.from_camera(camera, dev)
        w2c = cam.w2c
        p = self.posed(flame_inputs, -(w2c[:3, :3].T @ w2c[:3, 3]))
        s = self.settings
        with torch.no_grad():
            out = rasterize_surfels(p.means, p.quats, p.scales, p.opacities, p.colors, cam, s.background,
                                    near=s.near, far=s.far, return_statistics=False, backend=self.backend)  # fmt: skip
        return out.color


def reference_camera(data: IngestedData, camera: int | None = None) -> Camera:
    """A camera of the ingested data: ``camera`` when given (InputError if absent), else the val
    (novel-view) camera, else camera 8 (frontal in NeRSemble), else the first training camera."""
    if camera is not None:
        if camera not in data.cameras:
            raise InputError(data.root / "cameras.json", f"no camera {camera} (cameras: {sorted(data.cameras)})")
        return data.cameras[camera]
    if data.val:
        return data.val[0].camera
    if 8 in data.cameras:
        return data.cameras[8]
    return data.train[0].camera


def head_center(data: IngestedData) -> np.ndarray:
    """(3,) centre of the canonical timestep's posed head box from the ingest summary (world)."""
    box = data.summary.get("head_bbox")
    if not box:
        return np.zeros(3)
    return 0.5 * (np.asarray(box[0], np.float64) + np.asarray(box[1], np.float64))
