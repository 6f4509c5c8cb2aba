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
import math
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


def _brief(value: Any) -> str:
    """A metadata value for a message, shortened."""
    import reprlib

    return reprlib.repr(value)


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    """Whether ``v`` is a JSON number that is a finite float (an integer of 400 digits is not)."""
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


def _matrix_problem(v: Any, shape: tuple[int, int]) -> bool:
    """Whether ``v`` is not a nested list of finite numbers of ``shape``."""
    return not (isinstance(v, list) and len(v) == shape[0]
                and all(isinstance(r, list) and len(r) == shape[1] and all(_is_number(x) for x in r) for r in v))


def _camera_problem(cam: Any) -> str | None:
    """What is wrong with a ``reference_camera`` section (None: nothing; absent counts as fine)."""
    if cam is None or cam == {}:
        return None
    if not isinstance(cam, dict):
        return "'reference_camera' is not an object"
    if _matrix_problem(cam.get("K"), (3, 3)):
        return "'reference_camera' → 'K' is not a 3x3 list of finite numbers"
    if _matrix_problem(cam.get("w2c"), (4, 4)):
        return "'reference_camera' → 'w2c' is not a 4x4 list of finite numbers"
    for key in ("width", "height"):
        if not (_is_int(cam.get(key)) and 0 < cam[key] <= 1 << 16):
            return f"'reference_camera' → '{key}' is {_brief(cam.get(key))}, expected a positive whole number"
    if not _is_int(cam.get("index", -1)) or not isinstance(cam.get("name", ""), str):
        return "'reference_camera' → 'index' must be a whole number and 'name' a string"
    return None


def _model_problem(ref: Any) -> str | None:
    """What is wrong with the ``flame`` → ``model`` reference (None: nothing; absent counts as fine)."""
    if ref is None:
        return None
    if not isinstance(ref, dict):
        return "'flame' → 'model' is not an object"
    if not isinstance(ref.get("included", True), bool):
        return "'flame' → 'model' → 'included' is not true or false"
    for key in ("file", "file_sha256", "file_sha256_prefix", "base_sha256"):
        if ref.get(key) is not None and not isinstance(ref[key], str):
            return f"'flame' → 'model' → '{key}' is {_brief(ref[key])}, expected a string"
    mouth = ref.get("mouth_interior")
    if mouth is None:
        return None
    if not isinstance(mouth, dict):
        return "'flame' → 'model' → 'mouth_interior' is not an object"
    lips = mouth.get("lips")
    if not (isinstance(lips, list) and lips and all(_is_int(i) and 0 <= i < 1 << 31 for i in lips)):
        return "'flame' → 'model' → 'mouth_interior' → 'lips' is not a list of vertex ids"
    if not all(isinstance(mouth.get(k, False), bool) for k in ("cavity", "tongue")):
        return "'flame' → 'model' → 'mouth_interior' → 'cavity' and 'tongue' must be true or false"
    return None


def _render_problem(render: Any) -> str | None:
    """What is wrong with the ``render`` section (None: nothing; absent counts as fine)."""
    if render is None:
        return None
    if not isinstance(render, dict):
        return "'render' is not an object"
    for key in ("near", "far", "background"):
        if key in render and not _is_number(render[key]):
            return f"'render' → '{key}' is {_brief(render[key])}, expected a finite number"
    if render.get("correction") is not None and not isinstance(render["correction"], dict):
        return "'render' → 'correction' is not an object"
    return None


def _metadata_problem(meta: dict[str, Any]) -> str | None:
    """The first field of a bundle's metadata that :func:`load_bundle` could not use, or None."""
    if not _is_int(meta.get("format", 0)) or meta.get("format", 0) < 0:
        return f"'format' is {_brief(meta.get('format'))}, expected a whole number"
    for key in ("flame", "surfels", "files"):
        if not isinstance(meta.get(key), dict):
            return f"bundle metadata lacks the '{key}' section"
    for key, value in meta["files"].items():
        if not isinstance(value, str):
            return f"'files' → '{key}' is {_brief(value)}, expected a file name"
    count = meta["surfels"].get("count")
    if count is not None and not (_is_int(count) and count >= 0):
        return f"'surfels' → 'count' is {_brief(count)}, expected a whole number"
    centre = meta.get("head_center")
    if centre is not None and not (isinstance(centre, list) and len(centre) == 3 and all(_is_number(x) for x in centre)):
        return f"'head_center' is {_brief(centre)}, expected three finite numbers"
    return _model_problem(meta["flame"].get("model")) or _render_problem(meta.get("render")) \
        or _camera_problem(meta.get("reference_camera"))


def read_bundle_metadata(root: str | Path) -> dict[str, Any]:
    """Read and check ``bundle.json``; InputError naming the file when it is missing, not a bundle,
    or holds a field of the wrong type (:func:`_metadata_problem`)."""
    p = Path(root) / BUNDLE_JSON
    if not p.is_file():
        raise InputError(Path(root), f"not an avatar bundle (no {BUNDLE_JSON}; write one with `sage export WS --bundle`)")
    try:
        meta = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(p, f"cannot read bundle metadata: {e}") from None
    except (RecursionError, ValueError) as e:  # nesting past the parser's depth; an integer of too many digits
        raise InputError(p, "cannot read bundle metadata: " + ("nested too deeply" if isinstance(e, RecursionError) else str(e))) from None
    if not isinstance(meta, dict) or meta.get("kind") != BUNDLE_KIND:
        raise InputError(p, f"not a sage avatar bundle (kind is not {BUNDLE_KIND!r})")
    problem = _metadata_problem(meta)
    if problem is not None:
        raise InputError(p, f"malformed bundle metadata: {problem}")
    if meta.get("format", 0) > BUNDLE_FORMAT:
        raise InputError(p, f"bundle format {meta.get('format')} is newer than this sage supports ({BUNDLE_FORMAT})")
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
