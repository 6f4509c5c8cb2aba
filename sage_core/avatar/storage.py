"""Saving and loading an :class:`~sage_core.avatar.model.Avatar` file (``docs/workspace.md``).

An avatar file is a safetensors file (:mod:`sage_core.serialization`, format :data:`AVATAR_FORMAT`,
kind :data:`AVATAR_KIND`) holding the constructor data (:func:`avatar_args`), the subject's FLAME
parameters, the state dict without the FLAME buffers, the exposure gains, and either the FLAME model
arrays (``flame``, self-contained) or a reference to the workspace's ``init/flame_model.npz`` with
the SHA-256 of its bytes and its content hash (``flame_ref``: ``file``, ``file_sha256``,
``sha256`` = :func:`flame_model_sha256`), found again on loading in one of the
:data:`FLAME_REF_SEARCH_DEPTH` folders above the file. Loading runs no code from the file: the
referenced model is read only as the project's npz, and only after its bytes match
``file_sha256`` (references written before that field existed are checked by content after the
strict npz read).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from ..errors import InputError, StageError
from ..flame.model_data import FlameModelData
from ..flame.params import FlameParams
from ..serialization import AVATAR_FORMAT, AVATAR_KIND
from ..workspace import file_sha256
from .rendering import exposure_gains_plain
from .surfels import SurfelSet

if TYPE_CHECKING:
    from .model import Avatar

FLAME_REF_SEARCH_DEPTH = 4
"""How many folders above an avatar file :meth:`Avatar.load` looks for the FLAME model it references."""


def plain(obj: Any) -> Any:
    """Dataclasses and dicts as nested dicts (numpy arrays copied), for the file's structure."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {k: plain(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return obj.copy()
    return obj


def avatar_args(avatar: Avatar) -> dict[str, Any]:
    """The constructor data of an avatar as plain data (the file's ``args``)."""
    return {
        "canonical_timestep": avatar.canonical_timestep,
        "sdf_args": plain(avatar.sdf_args),
        "attributes": avatar.attributes,
        "app_args": plain(avatar.app_args),
        "shape_args": plain(avatar.shape_args),
        "n_surfels": len(avatar.surfels),
        "sh_degree": avatar.surfels.sh_degree,
        "shading": avatar.shading,
        "wrinkle_basis": avatar.wrinkle_basis,
    }


def flame_model_sha256(md: FlameModelData) -> str:
    """Content hash of a FLAME model: every field's name, dtype, shape and bytes, in field order."""
    import hashlib

    h = hashlib.sha256()
    for f in dataclasses.fields(md):
        v = getattr(md, f.name)
        items = sorted(v.items()) if isinstance(v, dict) else [("", v)]
        for key, x in items:
            h.update(f"{f.name}\0{key}\0".encode())
            if isinstance(x, np.ndarray):
                a = np.ascontiguousarray(x)
                h.update(f"{a.dtype.str}{a.shape}".encode())
                h.update(a.tobytes())
            else:
                h.update(repr(x).encode())
    return h.hexdigest()


def flame_reference(avatar: Avatar, path: Path) -> dict[str, Any] | None:
    """``{"file", "sha256"}`` referencing the workspace FLAME model when ``path`` lies in the
    workspace the avatar was built from (``WS/init/flame_model.npz``), else None."""
    src = avatar.flame_source
    if src is None or src.parent.name != "init" or not src.is_file():
        return None
    root = src.parent.parent
    if not (root / "data").is_dir():
        return None
    try:
        path.resolve().relative_to(root)
    except ValueError:
        return None
    return {"file": src.relative_to(root).as_posix(), "file_sha256": file_sha256(src),
            "sha256": flame_model_sha256(avatar.model_data)}



def save_avatar(avatar: Avatar, path: str | Path, *, embed_flame: bool | None = None,
                external_flame: dict[str, Any] | None = None) -> Path:
    """Write the avatar file atomically (the arguments of :meth:`Avatar.save`); returns its path.

    external_flame: store this plain-data description of the FLAME model (``flame_external``,
    holding at least ``sha256`` = :func:`flame_model_sha256` of the avatar's model) instead of the
    model: the file then loads only with the model given (an avatar bundle that does not hand out
    the licensed model, :mod:`sage_core.export.bundle`)."""
    from .._version import __version__
    from ..serialization import save_file

    p = Path(path)
    state = {k: v.detach().cpu() for k, v in avatar.state_dict().items() if not k.startswith("flame.")}
    blob: dict[str, Any] = {
        "format": AVATAR_FORMAT,
        "kind": AVATAR_KIND,
        "version": __version__,
        "args": avatar_args(avatar),
        "params": plain(avatar.params),
        "state": state,
    }
    ref = None if embed_flame or external_flame is not None else flame_reference(avatar, p)
    if external_flame is not None:
        blob["flame_external"] = {**external_flame, "sha256": flame_model_sha256(avatar.model_data)}
    elif ref is None:
        blob["flame"] = plain(avatar.model_data)
    else:
        blob["flame_ref"] = ref
    if avatar.exposure_gains:
        blob["exposure_gains"] = exposure_gains_plain(avatar.exposure_gains)
    return save_file(p, blob, AVATAR_KIND, AVATAR_FORMAT)


def load_avatar_file(cls: type[Avatar], path: str | Path, device: str | torch.device = "cpu",
                     flame_model: FlameModelData | None = None) -> Avatar:
    """Read a file written by :func:`save_avatar` into a new ``cls`` (the arguments of
    :meth:`Avatar.load`). flame_model: the model of a file written with ``external_flame`` (its
    content hash must be the recorded one; InputError without it or on a mismatch)."""
    from ..serialization import load_file

    p = Path(path)
    blob, _ = load_file(p, AVATAR_KIND, AVATAR_FORMAT, "avatar file")
    if not isinstance(blob, dict) or blob.get("kind") != AVATAR_KIND:
        raise InputError(p, "not a sage avatar file")
    source: Path | None = None
    try:
        args = blob["args"]
        if "flame_external" in blob:
            if flame_model is None:
                raise InputError(p, "does not carry its FLAME model; give the model it was built with")
            if flame_model_sha256(flame_model) != blob["flame_external"].get("sha256"):
                raise InputError(p, "the FLAME model given is not the one this avatar was built with")
            model_data = flame_model
        elif "flame_ref" in blob:
            model_data, source = resolve_flame_ref(p, blob["flame_ref"])
        else:
            model_data = FlameModelData(**blob["flame"])
        params = FlameParams(**blob["params"])
        state = blob["state"]
        surf_state = {k[len("surfels."):]: v for k, v in state.items() if k.startswith("surfels.")}
        surfels = SurfelSet.from_state_dict(surf_state)
        obj = cls(
            model_data, params, args["canonical_timestep"], surfels, args["sdf_args"], args["attributes"],
            args["app_args"], args["shape_args"] or None, base_scale=state["base_scale"],
            shading=args.get("shading", "none"), wrinkle_basis=args.get("wrinkle_basis", "posed"),
        )  # fmt: skip
        missing, unexpected = obj.load_state_dict(state, strict=False)
        obj.set_exposure_gains({(e["timestep"], e["camera"]): e["gain"] for e in blob.get("exposure_gains", [])})
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as e:
        raise InputError(p, f"malformed avatar file: {e}") from None
    bad = [k for k in missing if not k.startswith("flame.")]
    if bad or unexpected:
        raise InputError(p, f"avatar state does not match: missing {bad[:5]}, unexpected {list(unexpected)[:5]}")
    obj.flame_source = source
    return obj.to(device)


def resolve_flame_ref(path: Path, ref: dict[str, Any]) -> tuple[FlameModelData, Path]:
    """Find and check the FLAME model an avatar file references: ``ref["file"]`` relative to one of
    the folders above the avatar file (its workspace). The file's bytes are checked against
    ``ref["file_sha256"]`` before anything parses it, it is read only as the project's npz, and its
    content against ``ref["sha256"]``. A missing model inside a workspace is a StageError naming
    the stage that writes it."""
    from ..flame import load_flame_model

    if not isinstance(ref, dict) or not isinstance(ref.get("file"), str):
        raise InputError(path, "malformed FLAME model reference")
    rel = ref["file"]
    if Path(rel).is_absolute() or ".." in Path(rel).parts or Path(rel).suffix != ".npz":
        raise InputError(path, f"references the FLAME model {rel!r}, which is not a workspace npz file")
    for anc in list(path.resolve().parents)[:FLAME_REF_SEARCH_DEPTH]:
        cand = anc / rel
        if cand.is_file():
            expected = ref.get("file_sha256")
            if expected is not None and file_sha256(cand) != expected:
                raise InputError(path, f"the FLAME model it references ({cand}) changed since the avatar was saved; "
                                       "re-run the stage that wrote the avatar")
            md = load_flame_model(cand, npz_only=True)
            if flame_model_sha256(md) != ref.get("sha256"):
                raise InputError(path, f"the FLAME model it references ({cand}) changed since the avatar was saved; "
                                       "re-run the stage that wrote the avatar")
            return md, cand
    for anc in list(path.resolve().parents)[:FLAME_REF_SEARCH_DEPTH]:
        stage_folder = (anc / rel).parent
        if stage_folder.name == "init" and (anc / "data").is_dir() and stage_folder.is_dir():
            raise StageError(f"{path}: the workspace's FLAME model {rel} is missing: "
                             f"re-run `sage init-mesh {anc} --force`")
    raise InputError(path, f"references the workspace FLAME model {rel}, which is not found in the folders above it; "
                           "keep avatar files inside their workspace, or export a self-contained bundle "
                           "(`sage export WS --bundle`)")
