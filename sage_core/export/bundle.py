"""The avatar bundle: a self-contained, animatable avatar folder (docs/formats.md §7.2).

Layout of a bundle folder (format 3; ``docs/workspace.md`` "Bundle format" describes every array)::

    avatar.safetensors the avatar (Avatar.save: the subject's FLAME parameters, surfels with their
                       bindings, SDF and attribute networks, the canonical mesh and triangle frames
                       derived from FLAME; the FLAME model itself only with ``include_flame_model``),
                       a safetensors file whose header metadata holds the structure as JSON
                       (:mod:`sage_core.serialization`); loading it runs no code
    flame_param.npz    the subject's FLAME parameters with exactly GaussianAvatars' keys and dtypes,
                       all float32: shape (S,), expr (T,E), rotation/neck_pose/jaw_pose/translation
                       (T,3), eyes_pose (T,6), static_offset (1,V,3), dynamic_offset (T,V,3) (zeros
                       when the capture has none); row i is dataset timestep ``timestep_map[i]``
    bundle.json        versioned metadata (see :func:`bundle_metadata`), with an ``arrays`` section
                       listing every array of both files: dtype, shape and meaning

The FLAME model is licensed and is not handed out with a bundle: ``bundle.json`` ("flame" →
"model") names the user's model file and its SHA-256, and records what sage appended to it (the
mouth interior: the lip vertex ids it is placed from, whether it has a cavity and a tongue). :func:`load_bundle`
then needs that model file (``sage reenact --bundle DIR --flame-model PATH``): its bytes are
checked against the SHA-256 before it is parsed, the appended parts are rebuilt, and the result
must have the content hash the avatar file records. ``sage export --include-flame-model`` embeds
the model instead, as format 2 did.

Nothing in it refers back to the workspace: :func:`load_bundle` rebuilds the avatar from the
folder (and the model file) alone and checks it against the metadata (vertex and face counts,
face-table hash). Format-2 bundles (model embedded) load as before; format-1 bundles
(``avatar.pt``) still load when their avatar file was converted with ``sage convert``; an
unconverted one (a pickle) is refused with a message saying how.
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

BUNDLE_FORMAT = 3
BUNDLE_KIND = "sage-avatar-bundle"
BUNDLE_JSON = "bundle.json"
AVATAR_FILE = "avatar.safetensors"
LEGACY_AVATAR_FILE = "avatar.pt"
PARAMS_FILE = "flame_param.npz"
GA_PARAM_KEYS = ("shape", "expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation", "static_offset", "dynamic_offset")
"""The keys of GaussianAvatars' ``flame_param.npz``, all float32."""
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
class FlameSource:
    """Where a bundle's FLAME model comes from when it is not embedded.

    file_name: the user's model file name (e.g. ``flame2023.pkl``); file_sha256: the SHA-256 of its
    bytes (64 hex), or only its first 16 hex digits (``file_sha256_prefix``) when the file was no
    longer at hand at export; base: the model as sage reads that file (with GaussianAvatars-order
    teeth for FLAME's 5023-vertex topology); lips: the lip vertex ids the mouth interior was placed
    from (None: sage appended nothing); cavity: whether the mouth interior has its cavity; tongue:
    whether it has the tongue (references without the key have none).
    """

    file_name: str
    file_sha256: str | None
    file_sha256_prefix: str
    base: Any
    lips: list[int] | None = None
    cavity: bool = True
    tongue: bool = False

    def reference(self) -> dict[str, Any]:
        """The plain-data reference written into ``bundle.json`` and the avatar file."""
        from ..avatar.storage import flame_model_sha256

        return {"included": False, "file": self.file_name, "file_sha256": self.file_sha256,
                "file_sha256_prefix": self.file_sha256_prefix, "base_sha256": flame_model_sha256(self.base),
                "mouth_interior": None if self.lips is None else {"lips": [int(i) for i in self.lips], "cavity": bool(self.cavity),
                                                                  "tongue": bool(self.tongue)}}  # fmt: skip


def rebuild_model(base: Any, ref: dict[str, Any]) -> Any:
    """The avatar's FLAME model from the user's model ``base`` and a bundle's reference: the mouth
    interior appended as sage's init-mesh appended it."""
    mouth = ref.get("mouth_interior")
    if not mouth:
        return base
    from ..flame import add_mouth_interior

    return add_mouth_interior(base, {"lips": np.asarray(mouth["lips"], dtype=np.int64)}, cavity=bool(mouth.get("cavity", True)),
                              tongue=bool(mouth.get("tongue", False)))


def check_model_file(path: Path, ref: dict[str, Any], where: Path) -> None:
    """InputError unless the bytes of ``path`` have the SHA-256 the reference records (checked
    before anything parses the file)."""
    from ..workspace import file_sha256

    if not path.is_file():
        raise InputError(path, "FLAME model file not found")
    digest = file_sha256(path)
    full, prefix = ref.get("file_sha256"), str(ref.get("file_sha256_prefix") or "")
    if (full and digest != full) or (not full and not digest.startswith(prefix)):
        want = full or f"{prefix}…"
        raise InputError(path, f"is not the FLAME model the bundle {where} was built with ({ref.get('file')}, "
                               f"SHA-256 {want}; this file's is {digest})")  # fmt: skip


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
    from .._version import __version__

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
        "avatar_format": {"container": "safetensors", "kind": "sage-avatar", "structure": "header metadata 'sage.tree' (JSON)"},
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
    flame_source: FlameSource | None = None,
) -> Path:
    """Write ``avatar.safetensors``, ``flame_param.npz`` (GaussianAvatars' keys) and (last)
    ``bundle.json`` with the description of every array into ``out_dir``; returns it.

    flame_source: reference the user's FLAME model instead of embedding it (module doc); the model
    rebuilt from it must be the avatar's (ValueError otherwise). None embeds the model."""
    from ..avatar.storage import flame_model_sha256, save_avatar
    from ..workspace import atomic_write_json

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / LEGACY_AVATAR_FILE).unlink(missing_ok=True)
    ref: dict[str, Any] = {"included": True}
    if flame_source is not None:
        ref = flame_source.reference()
        if flame_model_sha256(rebuild_model(flame_source.base, ref)) != flame_model_sha256(avatar.model_data):
            raise ValueError("the avatar's FLAME model cannot be rebuilt from the user's model file; "
                             "export with --include-flame-model")  # fmt: skip
        save_avatar(avatar, out / AVATAR_FILE, external_flame=ref)
    else:
        avatar.save(out / AVATAR_FILE, embed_flame=True)
    write_ga_flame_params(out / PARAMS_FILE, avatar.params, int(np.asarray(avatar.model_data.v_template).shape[0]))
    meta = bundle_metadata(avatar, render, reference_camera=reference_camera, head_center=head_center,
                           up_axis=up_axis, source=source)  # fmt: skip
    meta["flame"]["model"] = ref
    meta["arrays"] = {AVATAR_FILE: describe_avatar_file(out / AVATAR_FILE), PARAMS_FILE: describe_npz(out / PARAMS_FILE)}
    atomic_write_json(out / BUNDLE_JSON, meta)
    return out


def ga_flame_param_arrays(params: Any, n_vertices: int | None = None) -> dict[str, np.ndarray]:
    """GaussianAvatars' ``flame_param.npz`` arrays of a :class:`~sage_core.flame.params.FlameParams`:
    exactly :data:`GA_PARAM_KEYS`, float32, T-leading; static_offset (1,V,3) and dynamic_offset
    (T,V,3), zeros where the parameters carry none (V: ``n_vertices``, default the offsets' own
    vertex count, else 5143)."""
    T = int(np.asarray(params.expr).shape[0])
    out: dict[str, np.ndarray] = {k: np.asarray(getattr(params, k), dtype=np.float32) for k in
                                  ("expr", "rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")}  # fmt: skip
    out["shape"] = np.asarray(params.shape, dtype=np.float32).reshape(-1)
    so = None if params.static_offset is None else np.asarray(params.static_offset, np.float32).reshape(-1, 3)
    do = None if params.dynamic_offset is None else np.asarray(params.dynamic_offset, np.float32).reshape(T, -1, 3)
    V = so.shape[0] if so is not None else do.shape[1] if do is not None else (n_vertices or 5143)
    out["static_offset"] = (so if so is not None else np.zeros((V, 3), np.float32))[None]
    out["dynamic_offset"] = do if do is not None else np.zeros((T, V, 3), np.float32)
    return {k: np.ascontiguousarray(out[k]) for k in GA_PARAM_KEYS}


def write_ga_flame_params(path: str | Path, params: Any, n_vertices: int | None = None) -> Path:
    """Write :func:`ga_flame_param_arrays` as an npz, atomically, with the usual file mode (umask)."""
    import io

    from ..workspace import atomic_write_bytes

    buf = io.BytesIO()
    np.savez(buf, **ga_flame_param_arrays(params, n_vertices))
    p = Path(path)
    atomic_write_bytes(p, buf.getvalue())
    return p


# meaning of the arrays of a bundle (``bundle.json`` "arrays", docs/workspace.md "Bundle format")
_EXACT: dict[str, str] = {
    "flame/v_template": "FLAME template vertices (V,3), metres, FLAME's y-up head frame; rows past n_base_vertices are teeth and mouth interior",
    "flame/faces": "triangle vertex indices (F,3) of the full face table (FLAME, teeth, mouth interior); surfel bindings index it",
    "flame/shapedirs": "identity blendshapes (V,3,S)",
    "flame/exprdirs": "expression blendshapes (V,3,E)",
    "flame/posedirs": "pose corrective blendshapes (V,3,9*(J-1))",
    "flame/j_regressor": "joint regressor (J,V)",
    "flame/lbs_weights": "linear blend skinning weights (V,J)",
    "flame/parents": "kinematic tree (J,), -1 for the root",
    "params/shape": "the subject's identity coefficients (S,)",
    "params/expr": "expression coefficients per row (T,E)",
    "params/rotation": "global head rotation per row (T,3), axis-angle, pivot at joint 0",
    "params/neck_pose": "neck joint rotation per row (T,3), axis-angle",
    "params/jaw_pose": "jaw joint rotation per row (T,3), axis-angle",
    "params/eyes_pose": "two eye joint rotations per row (T,6), axis-angle",
    "params/translation": "translation added after skinning per row (T,3), metres",
    "params/static_offset": "per-vertex canonical offsets (V',3) added to the template",
    "params/dynamic_offset": "per-row per-vertex offsets (T,V',3)",
    "params/timesteps": "dataset timestep of each row (T,)",
    "state/surfels.binding": "triangle (face) id each surfel is bound to (N,)",
    "state/surfels.mu_loc": "surfel centre in its triangle's local frame (N,3): x_c = k_c*R_c*mu_loc + T_c of the bound canonical triangle",
    "state/surfels.q_loc": "surfel rotation in its triangle's frame (N,4), quaternion wxyz (unnormalised)",
    "state/surfels.s_loc": "log in-plane scales relative to the triangle scale k (N,2)",
    "state/surfels.region_id": "region label of each surfel (N,) (0 skin, see sage_core.flame.regions)",
    "state/surfels.face_region": "region label of each triangle (F,)",
    "state/surfels.opacity": "free mode: opacity logit (N,)",
    "state/surfels.opacity_offset": "mlp mode, when trained: logit added to the appearance network's opacity (N,)",
    "state/surfels.sh_dc": "free mode: SH degree-0 colour coefficient (N,1,3)",
    "state/surfels.sh_rest": "free mode: higher SH colour coefficients (N,(d+1)^2-1,3)",
    "state/surfels.wrinkle": "wrinkle shading per surfel (N,2): amplitude and full compression",
    "state/surfels.color_prior": "colour prior per surfel (N,4): RGB and blend weight",
    "state/surfels.unseen_floor": "unseen fill per surfel (N,2): opacity lower bound (0: none) and in-plane scale gain (1: none)",
    "state/canonical_vertices": "canonical mesh vertices (V,3) (derived: FLAME at the canonical timestep, zero global motion)",
    "state/root_joint": "canonical root joint position (3,) (derived)",
    "state/R_c": "canonical triangle frames (F,3,3), columns [a0,-a2,a1] (surfel-flat convention) (derived)",
    "state/T_c": "canonical triangle centroids (F,3) (derived)",
    "state/k_c": "canonical triangle scales (F,) (derived)",
    "state/q_c": "canonical triangle frames as quaternions wxyz (F,4) (derived)",
    "state/base_scale": "per-surfel base size of the shape network (N,) (mlp mode)",
    "state/variance.variance": "NeuS s-variance (scalar)",
}
_PREFIX: tuple[tuple[str, str], ...] = (
    ("flame/vertex_groups/", "vertex ids of an appended part of the model (teeth, mouth interior)"),
    ("state/sdf.", "canonical SDF network: hash-grid encoding (sdf.encoding.*) and MLP (sdf.layers.*), PyTorch state-dict entry"),
    ("state/appearance.", "appearance network f_app (colour, opacity), PyTorch state-dict entry"),
    ("state/shape.", "shape network (rotation, scales) on the SDF grid features (mlp mode), PyTorch state-dict entry"),
    ("state/light.", "world-space SH irradiance of the sh2 shading mode"),
    ("state/", "avatar module state-dict entry"),
)
_GA_MEANING: dict[str, str] = {
    "shape": "identity coefficients (S,) float32",
    "expr": "expression coefficients (T,E) float32",
    "rotation": "global rotation (T,3) float32, axis-angle",
    "neck_pose": "neck rotation (T,3) float32, axis-angle",
    "jaw_pose": "jaw rotation (T,3) float32, axis-angle",
    "eyes_pose": "eye rotations (T,6) float32, axis-angle",
    "translation": "translation (T,3) float32, metres",
    "static_offset": "canonical per-vertex offsets (1,V,3) float32",
    "dynamic_offset": "per-row per-vertex offsets (T,V,3) float32 (zeros when the capture has none)",
}


def array_meaning(name: str) -> str:
    """What an array of ``avatar.safetensors`` holds (by its tensor name)."""
    if name in _EXACT:
        return _EXACT[name]
    for prefix, text in _PREFIX:
        if name.startswith(prefix):
            return text
    return "avatar data"


def describe_avatar_file(path: str | Path) -> dict[str, dict[str, Any]]:
    """{tensor name: {dtype, shape, meaning}} of an avatar safetensors file (header only)."""
    from safetensors import safe_open

    out: dict[str, dict[str, Any]] = {}
    with safe_open(str(path), framework="pt") as f:
        for name in sorted(f.keys()):
            sl = f.get_slice(name)
            out[name] = {"dtype": str(sl.get_dtype()), "shape": list(sl.get_shape()), "meaning": array_meaning(name)}
    return out


def describe_npz(path: str | Path) -> dict[str, dict[str, Any]]:
    """{key: {dtype, shape, meaning}} of the bundle's ``flame_param.npz``."""
    out: dict[str, dict[str, Any]] = {}
    with np.load(path, allow_pickle=False) as z:
        for k in z.files:
            out[k] = {"dtype": str(z[k].dtype), "shape": list(z[k].shape), "meaning": _GA_MEANING.get(k, "")}
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


def load_bundle(root: str | Path, device: str | torch.device = "cpu", flame_model: str | Path | None = None) -> Bundle:
    """Load a bundle folder without any workspace; InputError when it is incomplete or inconsistent.

    flame_model: the user's FLAME model file, needed by a bundle that does not embed it (its bytes
    are checked against the recorded SHA-256 before it is parsed; module doc); ignored otherwise."""
    from ..avatar.model import Avatar
    from ..data.cameras import Camera

    root = Path(root)
    meta = read_bundle_metadata(root)
    name = str(meta["files"].get("avatar", AVATAR_FILE if int(meta.get("format", 1)) >= 2 else LEGACY_AVATAR_FILE))
    if Path(name).is_absolute() or ".." in Path(name).parts:
        raise InputError(root / BUNDLE_JSON, f"the avatar file {name!r} lies outside the bundle")
    avatar_path = root / name
    if not avatar_path.is_file():
        raise InputError(avatar_path, "avatar file of the bundle is missing")
    ref = meta["flame"].get("model") or {"included": True}
    model = None
    if not ref.get("included", True):
        if flame_model is None:
            raise InputError(root, f"this bundle does not carry the licensed FLAME model: give the model file it was built "
                                   f"with ({ref.get('file')}) with --flame-model PATH")  # fmt: skip
        from ..flame import load_flame_model
        from ..avatar.storage import flame_model_sha256

        path = Path(flame_model)
        check_model_file(path, ref, root)
        base = load_flame_model(path)
        if flame_model_sha256(base) != ref.get("base_sha256"):
            raise InputError(path, f"reads as another model than the one the bundle {root} was built with")
        try:
            model = rebuild_model(base, ref)
        except ValueError as e:
            raise InputError(root / BUNDLE_JSON, f"cannot rebuild the mouth interior: {e}") from None
    avatar = Avatar.load(avatar_path, device, flame_model=model)
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
