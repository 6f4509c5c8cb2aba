"""The flat public API behind ``import sage_core as sage`` (the names :mod:`sage_core` exports lazily).

Load a trained avatar, pose it with FLAME parameters and render it for a camera::

    import sage_core as sage

    avatar = sage.load_avatar("WS")                      # a workspace, a bundle folder or an avatar file
    camera = sage.reference_camera("WS")                 # a sage.Camera (OpenCV, pixels)
    out = sage.render_avatar(avatar, camera, expr=[1.0, -0.5], jaw_pose=[0.2, 0, 0])
    sage.write_image("frame.png", out.image.cpu().numpy())

Shapes: images are float32 in [0, 1], ``image`` (H, W, 3), ``alpha`` (H, W), ``depth`` (H, W)
metres along the camera's z axis, ``normal`` (H, W, 3) unit world normals; posed surfels are
:class:`~sage_core.avatar.PosedSurfels` (means (N, 3), quats (N, 4) wxyz, scales (N, 2), opacities (N,),
colors (N, 3), vertices (V, 3)). FLAME parameters: ``expr`` (E,), ``rotation``, ``neck_pose``,
``jaw_pose``, ``translation`` (3,) axis-angle radians / metres, ``eyes_pose`` (6,).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from .errors import InputError

if TYPE_CHECKING:
    from .avatar.corrected import CorrectedPosing
    from .avatar.model import Avatar
    from .data.cameras import Camera
    from .flame.params import FlameParams
    from .render import RenderCamera


@dataclass
class RenderOutput:
    """One rendered frame.

    Attributes:
        image: (H, W, 3) colour composited on the background (unclamped; in [0, 1] for an unshaded
            avatar).
        alpha: (H, W) accumulated opacity in [0, 1].
        depth: (H, W) expected depth along the camera's z axis in metres, 0 where alpha is 0.
        normal: (H, W, 3) unit world-space normal (facing the camera), 0 where alpha is 0.
    """

    image: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor


def _settings(avatar: Avatar) -> Any:
    from .export.bundle import RenderSettings

    s = getattr(avatar, "render_settings", None)
    return s if s is not None else RenderSettings()


def load_avatar(path: str | Path, *, stage: str = "auto", device: str | torch.device = "cpu",
                flame_model: str | Path | None = None) -> Avatar:
    """Load a trained avatar, ready to pose and render (in eval mode).

    path: a workspace (the avatar of ``stage``: "auto" takes phase 2 when it finished, else phase 1;
    "phase1" or "phase2"), an exported bundle folder (``sage export WS --bundle``) or an avatar file
    (``WS/phase1/avatar.pt``). The avatar's ``render_settings`` (near/far planes, background and, for
    phase 2, the surfel correction) are those the stage trained with; :func:`render_avatar` uses them.
    flame_model: the FLAME model file a bundle names when it does not carry the model.
    InputError / StageError name the path when nothing loadable is there.
    """
    from .avatar.model import Avatar
    from .export.bundle import RenderSettings, is_bundle, load_bundle

    p = Path(path)
    if p.is_file():
        avatar = Avatar.load(p, device)
        settings = RenderSettings()
    elif is_bundle(p):
        b = load_bundle(p, device, flame_model=flame_model)
        avatar, settings = b.avatar, b.render
    elif p.is_dir():
        from .data.dataset import IngestedData
        from .stages.avatars import load_stage_avatar, resolve_avatar_stage
        from .workspace import Workspace

        ws = Workspace(p)
        chosen = resolve_avatar_stage(ws, stage, "load_avatar")
        data = IngestedData.open(ws.stage_dir("ingest"))
        loaded = load_stage_avatar(ws, chosen, data, device)
        avatar, settings = loaded.avatar, loaded.render
    else:
        raise InputError(p, "no workspace, bundle or avatar file here")
    avatar.eval()
    avatar.render_settings = settings
    return avatar


def load_cameras(path: str | Path) -> dict[int, Camera]:
    """The cameras of a workspace (its ingested ``data/cameras.json``, at the ingested resolution) or
    of a bundle (its reference camera): {camera index: :class:`~sage_core.data.cameras.Camera`}."""
    from .export.bundle import is_bundle, read_bundle_metadata

    p = Path(path)
    if is_bundle(p):
        from .data.cameras import Camera

        meta = read_bundle_metadata(p)
        if not meta.get("reference_camera"):
            raise InputError(p, "this bundle carries no camera")
        cam = Camera.from_dict(meta["reference_camera"])
        return {cam.index: cam}
    from .data.dataset import IngestedData

    return dict(IngestedData.open(p / "data").cameras)


def reference_camera(path: str | Path, camera: int | None = None) -> Camera:
    """The camera ``sage reenact`` renders with by default: for a workspace ``camera`` when given,
    else the novel-view camera, else camera 8, else the first training camera; for a bundle its
    reference camera."""
    from .export.bundle import is_bundle

    p = Path(path)
    if is_bundle(p):
        cams = load_cameras(p)
        if camera is not None and camera not in cams:
            raise InputError(p, f"the bundle carries only camera {next(iter(cams))}")
        return next(iter(cams.values()))
    from .data.dataset import IngestedData
    from .stages.avatars import reference_camera as pick

    return pick(IngestedData.open(p / "data"), camera)


def load_flame_params(path: str | Path, *, n_expr: int | None = None) -> FlameParams:
    """FLAME parameters of a motion: an ``.npz`` sequence (GaussianAvatars ``flame_param`` keys or
    sage's stacked file), a folder of per-frame ``.npz`` files, or a capture folder. Row i is frame i;
    pose row i with ``avatar.pose(params, i)`` or ``render_avatar(avatar, camera, params, row=i)``.
    n_expr: the avatar's expression count (``avatar.params.n_expr``) to pad/check ``expr`` against."""
    from .export.motion import load_motion

    return load_motion(path, n_expr=n_expr).params


_CORRECTIONS: weakref.WeakKeyDictionary[Any, CorrectedPosing] = weakref.WeakKeyDictionary()


def _corrected_posing(avatar: Avatar, correction: dict[str, Any]) -> CorrectedPosing:
    """The avatar's surfel correction (built once per avatar: neighbour sets and curvature cache)."""
    from .avatar.corrected import CorrectedPosing

    posing = _CORRECTIONS.get(avatar)
    if posing is None:
        posing = CorrectedPosing(avatar, True, **correction)
        _CORRECTIONS[avatar] = posing
    return posing


def _render_camera(camera: Camera | RenderCamera, device: torch.device) -> RenderCamera:
    from .render import RenderCamera

    if isinstance(camera, RenderCamera):
        if camera.batched:
            raise ValueError("render_avatar takes one camera; call it once per camera of a batch")
        return camera.to(device)
    return RenderCamera.from_camera(camera, device)


def render_avatar(
    avatar: Avatar,
    camera: Camera | RenderCamera,
    flame: FlameParams | dict[str, Any] | int | None = None,
    row: int = 0,
    *,
    background: float | None = None,
    backend: str = "auto",
    **overrides: Any,
) -> RenderOutput:
    """Render one frame of an avatar for one camera, without gradients.

    flame, row, overrides: the frame's FLAME parameters as :meth:`Avatar.flame_inputs` takes them
    (None: the canonical frame; a dataset timestep; a :class:`FlameParams` row; a dict of FLAME
    arguments) with per-parameter overrides such as ``expr=[...]`` or ``jaw_pose=[0.2, 0, 0]``.
    camera: a :class:`~sage_core.data.cameras.Camera` or an unbatched ``RenderCamera``.
    background: grey level behind the avatar (default: the avatar's ``render_settings``, white).
    backend: the surfel rasterizer ("auto", "torch", "cpp", "triton"; see ``docs/``).
    The near/far planes and the surfel correction (phase 2) come from ``avatar.render_settings``.
    Returns a :class:`RenderOutput` with image (H, W, 3), alpha (H, W), depth (H, W), normal (H, W, 3).
    """
    from .runtime import resolve_render_backend

    s = _settings(avatar)
    dev = avatar.device
    cam = _render_camera(camera, dev)
    inputs = avatar.flame_inputs(flame, row, **overrides)
    bg = s.background if background is None else float(background)
    kw = {"near": s.near, "far": s.far, "return_statistics": False, "backend": resolve_render_backend(backend, str(dev))}
    with torch.no_grad():
        if s.correction is None:
            out, _ = avatar.render(cam, inputs, bg, **kw)
        else:
            from .avatar.rendering import camera_centre
            from .render import rasterize_surfels

            p, _ = _corrected_posing(avatar, s.correction).posed(inputs, camera_centre(cam, avatar.canonical_vertices))
            out = rasterize_surfels(p.means, p.quats, p.scales, p.opacities, p.colors, cam, bg, **kw)
    alpha = out.alpha
    n = out.normal_world
    normal = torch.where(alpha[..., None] > 0, n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12), torch.zeros_like(n))
    return RenderOutput(out.color, alpha, out.depth, normal)
