"""A self-contained web page that plays the avatar driven by a FLAME sequence (WebGL2).

The folder holds three files and works offline from disk (``file://``; no network, no CDN):

- ``index.html``: the page (canvas, play/pause, frame slider);
- ``player.js``: sage's own WebGL2 surfel renderer (``sage_core/export/web/player.js``);
- ``avatar.js``: the data, ``window.SAGE_AVATAR = {...}`` with one base64 binary blob (a script, not
  a fetched file, because browsers refuse ``fetch`` from ``file://``).

The surfels are posed on the GPU: the vertex shader reads the frame's mesh vertices from a texture,
builds GaussianAvatars' face frame (R = [a0 | a1 | a2], centroid T, scale k; docs/formats.md §6) of each
surfel's bound triangle and applies ``μ = k·R·μ_loc + T``, ``R(q) = R·R(q_loc)``, ``s = k·s_loc``
to the local attributes of :func:`~sage_core.export.gaussian_avatars.ga_local_gaussians` — the same
posing as ``sage``'s uncorrected surfels. Only the mesh vertices change per frame. Each surfel is
drawn with the surfel rasterizer's own per-pixel maths (:mod:`sage_core.render`): the splat-to-pixel
matrix M in OpenCV pixel coordinates, each pixel's ray–surfel intersection (u, v), the screen-space
low-pass bound ρ = min(u² + v², 2·|x − c|²) around the exact 3σ box centre c, α = min(0.99, o·e^{−ρ/2})
(skipped below 1/255 or before the near plane), over the pixels of the surfel's 16×16 tiles where α
can reach 1/255; the surfels are blended back to front by centre depth (the rasterizer's per-tile
order), sorted whenever the frame or camera changes.

Colours and the phase-2 state: the colours of every frame are sage's own for that frame (the
renderer's posed surfels: expression wrinkle shading, the albedo × world-light shading at the pose,
view-dependent colour for the baking view), stored per frame when they change over the sequence
(``frame_colors``), else once. An avatar rendered with phase 2's surfel correction also gets, per
frame and surfel, the correction's local rotation dq and in-plane scale factors (``frame_correction``):
the page poses ``q = q(R)·q_loc·dq`` and ``s = k·s_loc·factor``, as sage does (the correction does
not move surfel centres).

Binary blob (little-endian, in this order; N surfels, V vertices, T frames):
``tri`` uint32 (N, 3) vertex ids of the bound face; ``mu`` float32 (N, 3) μ_loc; ``rot`` float32
(N, 4) q_loc wxyz; ``scale`` float32 (N, 2) in-plane σ / k; ``rgba`` uint8 (N, 4) colour and
opacity; ``verts`` int16 (T, V, 3) with ``v = q·vert_scale + vert_offset``; with ``frame_colors``
``colors`` uint8 (T, N, 3); with ``frame_correction`` ``dq`` int8 (T, N, 4) (wxyz × 127) and
``log_factor`` int8 (T, N, 2) (ln factor × 64, clamped to ±127).

Page parameters (URL query): ``frame=i`` shows frame i paused; ``camera=ref`` uses the reference
camera of the capture at its exact pixel size (else an orbit camera starts from it); ``ui=0``
hides the controls; ``speed=x`` sets the playback speed. The controls: play/pause (space), a frame
slider, the playback speed, a view reset (key R) and the frames per second the page draws.
``window.sageReady`` turns true once the requested frame is drawn; ``window.sageFps`` holds the
measured drawing rate.
"""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np
import torch

from ..workspace import atomic_write_bytes, atomic_write_text
from .gaussian_avatars import ga_local_gaussians
from .ply import MIN_OPACITY, SH_C0

if TYPE_CHECKING:
    from ..avatar.model import Avatar
    from ..data.cameras import Camera
    from ..flame.params import FlameParams

WEB_FORMAT = 2
LOG_FACTOR_SCALE = 64.0
ASSETS = ("index.html", "player.js")
DATA_FILE = "avatar.js"


@dataclass
class WebPlayerExport:
    """What :func:`write_web_player` wrote."""

    folder: Path
    n_frames: int
    n_surfels: int
    n_bytes: int


def _camera_doc(cam: Camera) -> dict[str, Any]:
    K = np.asarray(cam.K, dtype=np.float64)
    return {"width": int(cam.width), "height": int(cam.height), "fx": float(K[0, 0]), "fy": float(K[1, 1]),
            "cx": float(K[0, 2]), "cy": float(K[1, 2]), "w2c": np.asarray(cam.w2c, dtype=np.float64).reshape(-1).tolist()}  # fmt: skip


def frame_vertices(avatar: Avatar, params: FlameParams, progress: Callable[[int, int, str], None] | None = None) -> np.ndarray:
    """(T, V, 3) float32 posed mesh of every row of ``params`` (the avatar's own shape and static
    offset, the rows' expressions and poses)."""
    out = []
    with torch.no_grad():
        for r in range(params.n_timesteps):
            out.append(avatar.pose_mesh(avatar.params_inputs(params, r)).to("cpu", torch.float32).numpy())
            if progress is not None:
                progress(r + 1, params.n_timesteps, f"frame {r + 1}/{params.n_timesteps}")
    return np.stack(out)


def web_player_data(
    avatar: Avatar,
    params: FlameParams,
    camera: Camera,
    background: float = 1.0,
    fps: float = 25.0,
    view_from: torch.Tensor | None = None,
    title: str = "sage avatar",
    progress: Callable[[int, int, str], None] | None = None,
    renderer: Any = None,
) -> dict[str, Any]:
    """The ``window.SAGE_AVATAR`` document (module doc): metadata and the base64 blob.

    renderer: the :class:`~sage_core.stages.avatars.AvatarRenderer` whose posed surfels give each
    frame's colours and surfel correction (None: the avatar's own posing, no correction)."""
    from ..geometry.rotations import quat_conjugate, quat_multiply, quat_normalize

    if params.n_timesteps < 1:
        raise ValueError("the FLAME sequence has no frames")
    g = ga_local_gaussians(avatar, view_from)
    opac = 1.0 / (1.0 + np.exp(-g["opacity"].astype(np.float64)))
    keep = opac >= MIN_OPACITY
    faces = avatar.faces.cpu().numpy()
    tri = faces[g["binding"][keep]].astype("<u4")
    mu = g["xyz"][keep].astype("<f4")
    rot = g["rot"][keep].astype("<f4")
    scale = np.exp(g["scale"][keep][:, :2].astype(np.float64)).astype("<f4")
    corrected = getattr(renderer, "posing", None) is not None
    verts_l, cols_l, dq_l, lf_l = [], [], [], []
    keep_t = torch.as_tensor(keep, device=avatar.device)
    with torch.no_grad():
        cs = avatar.canonical_state(with_sdf=avatar.attributes == "mlp") if renderer is None else None
        for r in range(params.n_timesteps):
            inputs = avatar.params_inputs(params, r)
            plain = avatar.posed(inputs, view_from, canonical=renderer.canonical if renderer is not None else cs)
            posed = renderer.posed(inputs, view_from) if renderer is not None else plain
            verts_l.append(plain.vertices.to("cpu", torch.float64).numpy())
            cols_l.append(posed.colors[keep_t].clamp(0.0, 1.0).to("cpu", torch.float64).numpy())
            if corrected:
                dq = quat_multiply(quat_conjugate(quat_normalize(plain.quats)), quat_normalize(posed.quats))[keep_t]
                dq = dq * torch.where(dq[:, :1] < 0, -1.0, 1.0)  # w >= 0: the shorter of the two equal rotations
                dq_l.append(dq.to("cpu", torch.float64).numpy())
                lf_l.append(torch.log(posed.scales / plain.scales)[keep_t].to("cpu", torch.float64).numpy())
            if progress is not None:
                progress(r + 1, params.n_timesteps, f"frame {r + 1}/{params.n_timesteps}")
    verts = np.stack(verts_l)
    cols = np.round(np.stack(cols_l) * 255.0).astype(np.uint8)  # (T, N, 3)
    frame_colors = bool((cols != cols[:1]).any())
    rgba = np.concatenate([cols[0], np.round(opac[keep][:, None] * 255.0).astype(np.uint8)], 1)
    lo, hi = verts.reshape(-1, 3).min(0), verts.reshape(-1, 3).max(0)
    offset = 0.5 * (lo + hi)
    vscale = np.maximum(hi - lo, 1e-9) / 65000.0
    q = np.clip(np.round((verts - offset) / vscale), -32767, 32767).astype("<i2")
    parts = [tri, mu, rot, scale, rgba, q]
    if frame_colors:
        parts.append(cols)
    if corrected:
        parts.append(np.clip(np.round(np.stack(dq_l) * 127.0), -127, 127).astype(np.int8))
        parts.append(np.clip(np.round(np.stack(lf_l) * LOG_FACTOR_SCALE), -127, 127).astype(np.int8))
    blob = b"".join(np.ascontiguousarray(a).tobytes() for a in parts)
    centre = verts[0].mean(0)
    return {
        "format": WEB_FORMAT,
        "title": title,
        "n_surfels": int(tri.shape[0]),
        "n_vertices": int(verts.shape[1]),
        "n_frames": int(verts.shape[0]),
        "fps": float(fps),
        "timesteps": [int(t) for t in params.timesteps],
        "vert_scale": vscale.tolist(),
        "vert_offset": offset.tolist(),
        "frame_colors": frame_colors,
        "frame_correction": corrected,
        "log_factor_scale": LOG_FACTOR_SCALE,
        "background": [float(background)] * 3,
        "near": float(getattr(getattr(renderer, "settings", None), "near", 0.2)),
        "head_center": centre.tolist(),
        "camera": _camera_doc(camera),
        "data": base64.b64encode(blob).decode("ascii"),
    }


def write_web_player(
    avatar: Avatar,
    renderer: Any,
    params: FlameParams,
    folder: str | Path,
    camera: Camera,
    *,
    fps: float = 25.0,
    view_from: torch.Tensor | None = None,
    title: str = "sage avatar",
    progress: Callable[[int, int, str], None] | None = None,
) -> WebPlayerExport:
    """Write ``index.html``, ``player.js`` and ``avatar.js`` into ``folder`` (module doc).

    renderer: the :class:`~sage_core.stages.avatars.AvatarRenderer` whose settings give the
    background and whose posed surfels give each frame's colours and correction; params: the FLAME
    rows to play; camera: the reference camera of the page.
    """
    folder = Path(folder)
    background = float(getattr(getattr(renderer, "settings", None), "background", 1.0))
    doc = web_player_data(avatar, params, camera, background, fps, view_from, title, progress, renderer=renderer)
    data = "window.SAGE_AVATAR = " + json.dumps(doc, separators=(",", ":")) + ";\n"
    atomic_write_text(folder / DATA_FILE, data)
    total = len(data)
    pkg = resources.files("sage_core.export") / "web"
    for name in ASSETS:
        raw = (pkg / name).read_bytes()
        if name == "index.html":
            raw = raw.replace(b"{{TITLE}}", _html_escape(title).encode("utf-8"))
        atomic_write_bytes(folder / name, raw)
        total += len(raw)
    return WebPlayerExport(folder, int(doc["n_frames"]), int(doc["n_surfels"]), total)


def _html_escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")
