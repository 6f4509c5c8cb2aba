"""The avatar bundle: a self-contained, animatable avatar folder (formats.md §7.2).

Layout of a bundle folder::

    avatar.pt          the avatar (Avatar.save: FLAME model arrays with the face table, the subject's
                       FLAME parameters, surfels with their bindings, SDF and attribute networks)
    flame_param.npz    the subject's FLAME parameters in the GaussianAvatars key layout (shape (S,),
                       expr (T,E), rotation/neck_pose/jaw_pose/translation (T,3), eyes_pose (T,6),
                       static_offset (1,V,3), dynamic_offset (T,V,3) when present, timesteps (T,))
    bundle.json        metadata (see :func:`bundle_metadata`)

Nothing in it refers back to the workspace: :func:`load_bundle` rebuilds the avatar from the
folder alone and checks it against the metadata (vertex and face counts, face-table hash).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import InputError

if TYPE_CHECKING:
    import torch

    from ..avatar.model import Avatar
    from ..data.cameras import Camera

BUNDLE_FORMAT = 1
BUNDLE_KIND = "sage-avatar-bundle"
BUNDLE_JSON = "bundle.json"
AVATAR_FILE = "avatar.pt"
PARAMS_FILE = "flame_param.npz"
FRAME_CONVENTION = "surfel-flat [a0,-a2,a1]"


@dataclass
class RenderSettings:
    """How the avatar is rendered: near/far planes (m), the background grey level, and the surfel
    correction applied while posing (``None``: none; else the keyword arguments of
    :class:`sage_core.avatar.corrected.CorrectedPosing`, as phase 2 trained with them)."""

    near: float = 0.2
    far: float = 100.0
    background: float = 1.0
    correction: dict[str, Any] | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"near": self.near, "far": self.far, "background": self.background,
                "correction": None if self.correction is None else dict(self.correction)}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> RenderSettings:
        corr = d.get("correction")
        return RenderSettings(float(d.get("near", 0.2)), float(d.get("far", 100.0)), float(d.get("background", 1.0)),
                              dict(corr) if isinstance(corr, dict) else None)  # fmt: skip


@dataclass
class Bundle:
    """A loaded bundle: the avatar, its metadata, render settings, reference camera and head centre."""

    root: Path
    avatar: Avatar
    meta: dict[str, Any]
    render: RenderSettings
    reference_camera: Camera | None
    head_center: np.ndarray | None


def faces_sha256(faces: np.ndarray | torch.Tensor) -> str:
    """sha256 of the (F, 3) face table as little-endian int64 (the face-table id in bundle.json)."""
    if hasattr(faces, "detach"):
        faces = faces.detach().cpu().numpy()
    return hashlib.sha256(np.ascontiguousarray(np.asarray(faces), dtype="<i8").tobytes()).hexdigest()


def bundle_metadata(
    avatar: Avatar,
    render: RenderSettings,
    *,
    reference_camera: Camera | None = None,
    head_center: np.ndarray | None = None,
    up_axis: str = "y",
    source: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The ``bundle.json`` document of an avatar.

    Holds the FLAME version and whether it has a jaw joint, n_shape, n_expr, vertex and face counts,
    the face-table id and hash, the surfel frame convention (``surfel-flat [a0,-a2,a1]``), the
    primitive (2D surfels), attribute mode and SH degree, the up axis, the canonical timestep, the
    row → dataset-timestep map, the render settings, a reference camera and the head centre.
    """
    from .. import __version__

    md = avatar.model_data
    params = avatar.params
    n_joints = int(np.asarray(md.parents).shape[0])
    if avatar.attributes == "free":
        sh_degree, sh_source = int(avatar.surfels.sh_degree), "per-surfel SH, canonical view direction"
    else:
        sh_degree = int(avatar.app_args.get("sh_degree", 0))
        sh_source = "appearance network's view-direction SH encoding, canonical view direction"
    return {
        "format": BUNDLE_FORMAT,
        "kind": BUNDLE_KIND,
        "generator": f"sage {__version__}",
        "files": {"avatar": AVATAR_FILE, "flame_params": PARAMS_FILE},
        "flame": {
            "version": str(md.version),
            "jaw": n_joints >= 3,
            "n_joints": n_joints,
            "n_shape": int(params.n_shape),
            "n_expr": int(params.n_expr),
            "n_vertices": int(np.asarray(md.v_template).shape[0]),
            "n_base_vertices": int(md.n_base_vertices),
            "n_faces": int(np.asarray(md.faces).shape[0]),
            "face_table": str(md.face_table),
            "faces_sha256": faces_sha256(np.asarray(md.faces)),
        },
        "surfels": {
            "count": len(avatar.surfels),
            "primitive": "2d-surfel",
            "dimensions": 2,
            "frame_convention": FRAME_CONVENTION,
            "quaternion_order": "wxyz",
            "attributes": avatar.attributes,
            "sh_degree": sh_degree,
            "sh_source": sh_source,
        },
        "up_axis": up_axis,
        "units": "metres",
        "canonical_timestep": int(avatar.canonical_timestep),
        "timestep_map": [{"row": i, "timestep": int(t)} for i, t in enumerate(np.asarray(params.timesteps))],
        "render": render.to_dict(),
        "reference_camera": None if reference_camera is None else reference_camera.to_dict(),
        "head_center": None if head_center is None else [float(x) for x in np.asarray(head_center).reshape(3)],
        "source": source or {},
    }


def write_bundle(
    avatar: Avatar,
    out_dir: str | Path,
    render: RenderSettings,
    *,
    reference_camera: Camera | None = None,
    head_center: np.ndarray | None = None,
    up_axis: str = "y",
    source: dict[str, Any] | None = None,
) -> Path:
    """Write ``avatar.pt``, ``flame_param.npz`` and (last) ``bundle.json`` into ``out_dir``; returns it."""
    from ..flame.params import save_stacked_npz
    from ..workspace import atomic_write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    avatar.save(out / AVATAR_FILE)
    save_stacked_npz(out / PARAMS_FILE, avatar.params)
    meta = bundle_metadata(avatar, render, reference_camera=reference_camera, head_center=head_center,
                           up_axis=up_axis, source=source)  # fmt: skip
    atomic_write_json(out / BUNDLE_JSON, meta)
    return out


def is_bundle(path: str | Path) -> bool:
    """True when ``path`` is a folder holding ``bundle.json``."""
    return (Path(path) / BUNDLE_JSON).is_file()


def read_bundle_metadata(root: str | Path) -> dict[str, Any]:
    """Read and check ``bundle.json``; InputError naming the file when it is missing or not a bundle."""
    p = Path(root) / BUNDLE_JSON
    if not p.is_file():
        raise InputError(Path(root), f"not an avatar bundle (no {BUNDLE_JSON}; write one with `sage export WS --bundle`)")
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(p, f"cannot read bundle metadata: {e}") from None
    if not isinstance(meta, dict) or meta.get("kind") != BUNDLE_KIND:
        raise InputError(p, f"not a sage avatar bundle (kind is not {BUNDLE_KIND!r})")
    if int(meta.get("format", 0)) > BUNDLE_FORMAT:
        raise InputError(p, f"bundle format {meta.get('format')} is newer than this sage supports ({BUNDLE_FORMAT})")
    for key in ("flame", "surfels", "files"):
        if not isinstance(meta.get(key), dict):
            raise InputError(p, f"bundle metadata lacks the '{key}' section")
    return meta


def load_bundle(root: str | Path, device: str | torch.device = "cpu") -> Bundle:
    """Load a bundle folder without any workspace; InputError when it is incomplete or inconsistent."""
    from ..avatar.model import Avatar
    from ..data.cameras import Camera

    root = Path(root)
    meta = read_bundle_metadata(root)
    avatar_path = root / str(meta["files"].get("avatar", AVATAR_FILE))
    if not avatar_path.is_file():
        raise InputError(avatar_path, "avatar file of the bundle is missing")
    avatar = Avatar.load(avatar_path, device)
    fl = meta["flame"]
    faces = avatar.model_data.faces
    found = {
        "n_vertices": int(np.asarray(avatar.model_data.v_template).shape[0]),
        "n_faces": int(np.asarray(faces).shape[0]),
        "faces_sha256": faces_sha256(np.asarray(faces)),
    }
    for key, value in found.items():
        if key in fl and fl[key] != value:
            raise InputError(avatar_path, f"does not match {BUNDLE_JSON}: {key} is {value}, the metadata says {fl[key]}")
    if int(meta["surfels"].get("count", len(avatar.surfels))) != len(avatar.surfels):
        raise InputError(avatar_path, f"holds {len(avatar.surfels)} surfels, {BUNDLE_JSON} says {meta['surfels']['count']}")
    cam = None
    if meta.get("reference_camera"):
        try:
            cam = Camera.from_dict(meta["reference_camera"])
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(root / BUNDLE_JSON, f"malformed reference camera: {e}") from None
    centre = None if meta.get("head_center") is None else np.asarray(meta["head_center"], np.float64).reshape(3)
    return Bundle(root, avatar, meta, RenderSettings.from_dict(meta.get("render") or {}), cam, centre)
