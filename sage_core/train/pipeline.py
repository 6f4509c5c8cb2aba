"""The avatar stages of a workspace, seen from the stages that use them (eval, reenact, export, run).

* :func:`resolve_avatar_stage` picks the avatar to use: the latest finished of phase2 and phase1,
  refusing a stale one with the workspace's message;
* :func:`load_stage_avatar` loads ``WS/<stage>/avatar.pt`` with the settings it was trained to be
  rendered with (near/far and, for phase 2, the surfel correction from the stage's saved config;
  the background of the ingested data);
* :class:`AvatarRenderer` renders it for a camera and a frame's (or a motion's) FLAME inputs, with
  the canonical state computed once;
* :func:`load_driving_motion` reads a motion and checks it against the avatar;
* :func:`with_identity` puts the avatar's own shape and static offset into a motion's FLAME inputs;
* :func:`carry_results` keeps the results of earlier runs of an accumulating stage (eval, export)
  whose inputs are unchanged.
"""

from __future__ import annotations

import hashlib
import json
import shutil
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
RESULTS_INDEX = "results.json"


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


CORRECTION_KEYS: dict[str, str] = {
    "correction_radius_edges": "radius_edges",
    "correction_max_neighbours": "max_neighbours",
    "correction_w_s": "w_s",
    "correction_umbilic_tol": "umbilic_tol",
    "correction_anisotropy_tol": "anisotropy_tol",
}
"""Stage-config fields of the surfel correction -> ``CorrectedPosing`` keyword arguments."""


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
        if cfg.get("correction") is True:
            correction = {kw: cfg[key] for key, kw in CORRECTION_KEYS.items() if key in cfg}
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


# --------------------------------------------------------------------------------------------
# Accumulating stages (eval, export): several results live side by side in one stage folder
# --------------------------------------------------------------------------------------------


def result_key(**parts: Any) -> str:
    """Stable hash (16 hex chars) of plain-data parts identifying one result and its inputs."""
    blob = json.dumps(parts, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def read_results(stage_dir: Path) -> dict[str, Any]:
    """The results index ``<stage folder>/results.json`` ({} when absent or unreadable)."""
    p = stage_dir / RESULTS_INDEX
    if not p.is_file():
        return {}
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return {}
    return doc if isinstance(doc, dict) else {}


def fresh_results(ws: Workspace, stage: str) -> dict[str, Any]:
    """Entries of a complete accumulating stage's index whose avatar stage is still complete with
    the fingerprint recorded in the entry (``entry["avatar_stage"]``, ``entry["avatar_fingerprint"]``)
    and whose files still exist; {} when the stage folder is not complete."""
    m = ws.manifest(stage)
    if m is None or m.get("status") != "complete":
        return {}
    root = ws.stage_dir(stage)
    out: dict[str, Any] = {}
    for name, entry in read_results(root).items():
        try:
            av_stage = entry["avatar_stage"]
            st = ws.status(av_stage)
            ok = st.status == "complete" and st.manifest is not None and st.manifest.get("fingerprint") == entry["avatar_fingerprint"]
            ok = ok and all((root / rel).exists() for rel in entry.get("files", []))
        except Exception:  # noqa: BLE001 - a malformed entry is simply not carried
            ok = False
        if ok:
            out[name] = entry
    return out


def carry_results(ws: Workspace, stage: str, work_dir: Path, keep: dict[str, Any]) -> None:
    """Copy the files of the kept entries of ``WS/<stage>/`` into the stage's work folder."""
    root = ws.stage_dir(stage)
    for entry in keep.values():
        for rel in entry.get("files", []):
            src, dst = root / rel, work_dir / rel
            if dst.exists():
                continue
            dst.parent.mkdir(parents=True, exist_ok=True)
            if src.is_dir():
                shutil.copytree(src, dst)
            elif src.is_file():
                shutil.copy2(src, dst)
