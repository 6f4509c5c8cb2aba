"""Files that cannot run code when loaded: tensors in safetensors, structure in JSON.

Every binary file sage writes and reads back (avatars, SDF files, checkpoints, the avatar of a
bundle) is a `safetensors <https://github.com/huggingface/safetensors>`_ file: an 8-byte
little-endian header length, a JSON header naming each tensor's dtype, shape and byte range, then
the raw tensor bytes. Nothing in it is executed on load. The header's ``__metadata__`` holds:

* ``sage.kind``: what the file is (``sage-avatar``, ``sage-sdf``, ``sage-checkpoint``,
  ``sage-mouth-prior``);
* ``sage.format``: the kind's format version (an integer, as text);
* ``sage.tree``: the saved object as JSON in which every tensor or numpy array is replaced by a
  reference to a tensor of the file (see :func:`encode`);
* ``sage.sha256``: a hash over the tensors' names, dtypes, shapes and bytes;
* ``sage.digest``: a hash over the kind, the format, the JSON tree and ``sage.sha256``, so the
  structure is covered as well as the tensors. Both are checked on load, so a truncated, damaged or
  edited file is reported as such (files written before ``sage.digest`` existed are checked on
  their tensors only). These are checksums, not signatures: they catch damage and careless edits.
  That loading runs no code does not rest on them but on the format (JSON and raw tensors only).

Older sage versions wrote these files with ``torch.save`` (Python pickle, which can run arbitrary
code). They are refused with :class:`~sage_core.errors.UnsafeFileError`; a user who trusts such a
file converts it once with ``sage convert FILE --trust`` (:func:`convert_trusted`).

The JSON tree: ``None``, bools, ints, floats (exact, ``repr``-based) and strings as themselves;
lists as lists; dicts with string keys (none starting with ``__``) as objects; any other dict as
``{"__dict__": [[key, value], ...]}``; tuples as ``{"__tuple__": [...]}``; a torch tensor as
``{"__tensor__": name}``; a numpy array as ``{"__ndarray__": name}`` (restored as numpy with its
dtype); a numpy scalar as ``{"__np__": dtype, "v": value}``. Tensor names are the path of the
value in the tree joined with ``/`` (e.g. ``state/surfels.mu_loc``).
"""

from __future__ import annotations

import hashlib
import json
import re
import reprlib
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import ConfigError, InputError, UnsafeFileError

if TYPE_CHECKING:
    import torch

AVATAR_KIND = "sage-avatar"
AVATAR_FORMAT = 2
"""Avatar files: format 1 was a torch.save pickle (refused now, ``sage convert FILE --trust``
rewrites it); 2 is a safetensors file that may reference the workspace's FLAME model."""
SDF_KIND = "sage-sdf"
SDF_FILE_FORMAT = 2
"""SDF files (init-mesh): format 1 was a torch.save pickle (refused now); 2 is a safetensors file."""
CHECKPOINT_KIND = "sage-checkpoint"
CHECKPOINT_FORMAT = 2
"""Stage checkpoints: format 1 was a torch.save pickle (refused now); 2 is a safetensors file."""
MOUTH_PRIOR_KIND = "sage-mouth-prior"
MOUTH_PRIOR_FORMAT = 1
"""The pretrained mouth-interior prior (:mod:`sage_core.avatar.mouth_prior`)."""

META_KIND = "sage.kind"
META_FORMAT = "sage.format"
META_TREE = "sage.tree"
META_SHA = "sage.sha256"
META_DIGEST = "sage.digest"
MAX_TREE_DEPTH = 200
"""Deepest nesting of lists and objects accepted in a file's JSON tree."""
MAX_HEADER = 100 * 1024 * 1024

CONVERT_HINT = "`sage convert {path} --trust`"


# --------------------------------------------------------------------------------------------
# Tree encoding
# --------------------------------------------------------------------------------------------


def encode(obj: Any) -> tuple[Any, dict[str, torch.Tensor]]:
    """Split ``obj`` into a JSON-able tree and a name -> tensor dict (see the module doc).

    Raises TypeError naming the path of a value that has no safe representation.
    """
    import torch

    tensors: dict[str, torch.Tensor] = {}

    def name_for(path: tuple[str, ...]) -> str:
        base = "/".join(path) or "value"
        name, i = base, 1
        while name in tensors:
            i += 1
            name = f"{base}#{i}"
        return name

    def enc(x: Any, path: tuple[str, ...]) -> Any:
        if x is None or isinstance(x, (bool, str)):
            return x
        if isinstance(x, np.generic):
            return {"__np__": x.dtype.str, "v": x.item()}
        if isinstance(x, (int, float)):
            return x
        if isinstance(x, torch.Tensor):
            if x.is_sparse or x.is_complex():
                raise TypeError(f"{'/'.join(path)}: sparse or complex tensors cannot be saved")
            name = name_for(path)
            tensors[name] = x.detach().to("cpu").contiguous().clone()
            return {"__tensor__": name}
        if isinstance(x, np.ndarray):
            if x.dtype.kind not in "biuf":
                raise TypeError(f"{'/'.join(path)}: numpy arrays of dtype {x.dtype} cannot be saved")
            name = name_for(path)
            tensors[name] = torch.from_numpy(np.array(x, copy=True, order="C"))
            return {"__ndarray__": name}
        if isinstance(x, tuple):
            return {"__tuple__": [enc(v, (*path, str(i))) for i, v in enumerate(x)]}
        if isinstance(x, list):
            return [enc(v, (*path, str(i))) for i, v in enumerate(x)]
        if isinstance(x, dict):
            if all(isinstance(k, str) and not k.startswith("__") for k in x):
                return {k: enc(v, (*path, k)) for k, v in x.items()}
            return {"__dict__": [[enc(k, (*path, "key")), enc(v, (*path, str(k)))] for k, v in x.items()]}
        raise TypeError(f"{'/'.join(path) or 'value'}: {type(x).__name__} cannot be saved")

    return enc(obj, ()), tensors


def decode(tree: Any, tensors: dict[str, torch.Tensor]) -> Any:
    """Inverse of :func:`encode`. KeyError / ValueError on a malformed tree."""

    def dec(x: Any) -> Any:
        if isinstance(x, list):
            return [dec(v) for v in x]
        if not isinstance(x, dict):
            return x
        if len(x) == 1:
            ((k, v),) = x.items()
            if k == "__tensor__":
                return tensors[v]
            if k == "__ndarray__":
                return tensors[v].numpy()
            if k == "__tuple__":
                return tuple(dec(i) for i in v)
            if k == "__dict__":
                return {_hashable(dec(a)): dec(b) for a, b in v}
        if set(x) == {"__np__", "v"}:
            return np.dtype(x["__np__"]).type(x["v"])
        if any(k.startswith("__") for k in x):
            raise ValueError(f"unknown tree node {sorted(x)}")
        return {k: dec(v) for k, v in x.items()}

    return dec(tree)


def _hashable(k: Any) -> Any:
    return tuple(k) if isinstance(k, list) else k


def tree_digest(kind: str, version: str, tree_json: str, tensors_sha: str) -> str:
    """The ``sage.digest`` of a file: SHA-256 over its kind, format, JSON tree and tensor hash."""
    h = hashlib.sha256()
    for part in (kind, version, tree_json, tensors_sha):
        h.update(part.encode("utf-8"))
        h.update(b"\0")
    return h.hexdigest()


def _json_depth(text: str) -> int:
    """Deepest bracket nesting of a JSON text (brackets inside strings are skipped)."""
    depth = deepest = 0
    in_str = escaped = False
    for ch in text:
        if in_str:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def tensors_sha256(tensors: dict[str, torch.Tensor]) -> str:
    """Hash over every tensor's name, dtype, shape and bytes (sorted by name)."""
    import torch

    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name]
        h.update(f"{name}\0{t.dtype}\0{tuple(t.shape)}\0".encode())
        if t.numel():
            h.update(t.contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------


def to_bytes(obj: Any, kind: str, version: int) -> bytes:
    """The safetensors bytes of ``obj`` (see the module doc)."""
    from safetensors.torch import save

    tree, tensors = encode(obj)
    tree_json = json.dumps(tree, separators=(",", ":"))
    sha = tensors_sha256(tensors)
    meta = {
        META_KIND: kind,
        META_FORMAT: str(int(version)),
        META_TREE: tree_json,
        META_SHA: sha,
        META_DIGEST: tree_digest(kind, str(int(version)), tree_json, sha),
    }
    return save(tensors, metadata=meta)


def save_file(path: str | Path, obj: Any, kind: str, version: int) -> Path:
    """Write ``obj`` as a ``kind`` file of format ``version`` atomically; returns the path."""
    from .atomic import atomic_write_bytes

    p = Path(path)
    atomic_write_bytes(p, to_bytes(obj, kind, version))
    return p


@dataclass
class FileCheck:
    """What :func:`inspect_file` found: ``status`` is "ok", "pickle" (an old torch.save / pickle
    file), "missing" or "corrupt"; ``kind`` and ``version`` come from a readable header."""

    path: Path
    status: str
    kind: str = ""
    version: int = 0
    reason: str = ""


def _looks_like_pickle(head: bytes) -> bool:
    """Whether the first bytes (at least 9) are those of a torch.save file: a zip archive (local
    header) or a raw pickle (PROTO opcode). A safetensors header length whose low bytes read like
    the PROTO opcode (0x80, 2..5) is told apart by the JSON header that follows it."""
    if head.startswith(b"PK\x03\x04"):
        return True
    if len(head) >= 9 and head[8:9] == b"{" and int.from_bytes(head[:8], "little") <= MAX_HEADER:
        return False
    return len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5


def _read_header(data: bytes) -> tuple[dict[str, Any], int]:
    """(header dict, data offset) of safetensors bytes; ValueError when malformed or truncated."""
    if len(data) < 8:
        raise ValueError("file is truncated (no header)")
    (n,) = struct.unpack("<Q", data[:8])
    if n > MAX_HEADER or 8 + n > len(data):
        raise ValueError("file is truncated or not a safetensors file (bad header length)")
    try:
        header = json.loads(data[8 : 8 + n].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"unreadable header ({e})") from None
    except RecursionError:
        raise ValueError("unreadable header (nested too deeply)") from None
    if not isinstance(header, dict):
        raise ValueError("unreadable header (not an object)")
    meta = header.get("__metadata__")
    if meta is not None and not (isinstance(meta, dict) and all(isinstance(v, str) for v in meta.values())):
        raise ValueError("unreadable header (its __metadata__ is not a map of strings)")
    end = 0
    for name, info in header.items():
        if name == "__metadata__":
            continue
        try:
            end = max(end, int(info["data_offsets"][1]))
        except (KeyError, TypeError, ValueError, IndexError):
            raise ValueError(f"unreadable header entry {reprlib.repr(name)}") from None
    if 8 + n + end != len(data):
        raise ValueError(f"file is truncated or padded ({len(data)} bytes, the header describes {8 + n + end})")
    return header, 8 + n


def _format_version(meta: dict[str, str]) -> int:
    """The ``sage.format`` of a header's metadata (0 when absent); ValueError unless it is a
    string of decimal digits."""
    text = meta.get(META_FORMAT, "0")
    if not re.fullmatch(r"[0-9]{1,9}", text):
        raise ValueError(f"unreadable format version {reprlib.repr(text)}")
    return int(text)


def inspect_file(path: str | Path) -> FileCheck:
    """Classify a file without loading its tensors (reads the whole file to check its size)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        return FileCheck(p, "missing", reason="file not found")
    except OSError as e:
        return FileCheck(p, "corrupt", reason=f"cannot read ({e.strerror or e})")
    if _looks_like_pickle(data[:9]):
        return FileCheck(p, "pickle", reason="a pickle file written by an older sage")
    try:
        header, _ = _read_header(data)
    except ValueError as e:
        return FileCheck(p, "corrupt", reason=str(e))
    meta = header.get("__metadata__") or {}
    try:
        version = _format_version(meta)
    except ValueError:
        return FileCheck(p, "corrupt", reason="unreadable format version")
    return FileCheck(p, "ok", kind=str(meta.get(META_KIND, "")), version=version)


def legacy_message(path: Path, what: str) -> str:
    """The refusal of an old pickle-based file (names the file and how to convert it)."""
    return (
        f"{what} in the old pickle format, which can run arbitrary code when loaded, so sage does not read it. "
        f"If you trust where it came from, convert it once with {CONVERT_HINT.format(path=path)}"
    )


def load_file(
    path: str | Path, kind: str, max_version: int, what: str, map_location: Any = None
) -> tuple[Any, int]:
    """Load a ``kind`` file written by :func:`save_file`: returns (object, format version).

    what: how messages name the file ("avatar file", "checkpoint", ...). Raises
    :class:`UnsafeFileError` for an old pickle file (nothing of it is executed) and InputError for a
    missing, damaged, foreign or newer file. map_location: device the tensors are moved to.
    """
    from safetensors.torch import load

    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise InputError(p, f"{what} not found") from None
    except OSError as e:
        raise InputError(p, f"cannot read {what}: {e.strerror or e}") from None
    if _looks_like_pickle(data[:9]):
        raise UnsafeFileError(p, legacy_message(p, what))
    try:
        header, _ = _read_header(data)
    except ValueError as e:
        raise InputError(p, f"damaged {what}: {e}") from None
    meta = header.get("__metadata__") or {}
    if meta.get(META_KIND) != kind:
        raise InputError(p, f"not a sage {what} (kind {reprlib.repr(meta.get(META_KIND))}, expected {kind!r})")
    try:
        version = _format_version(meta)
    except ValueError:
        raise InputError(p, f"damaged {what}: unreadable format version") from None
    if version > max_version:
        raise InputError(p, f"{what} format {version} is newer than this sage supports ({max_version}); update sage")
    try:
        tensors = load(data)
    except Exception as e:  # noqa: BLE001  (safetensors raises its own error types)
        raise InputError(p, f"damaged {what}: {e}") from None
    problem = _checksum_problem(meta, tensors)
    if problem:
        raise InputError(p, f"damaged {what}: {problem}")
    tree_json = meta.get(META_TREE, "null")
    if _json_depth(tree_json) > MAX_TREE_DEPTH:
        raise InputError(p, f"damaged {what}: its structure is nested deeper than {MAX_TREE_DEPTH} levels")
    try:
        tree = json.loads(tree_json)
        obj = decode(tree, tensors)
    except (json.JSONDecodeError, KeyError, ValueError, TypeError, RecursionError) as e:
        raise InputError(p, f"damaged {what}: malformed structure ({type(e).__name__}: {e})") from None
    if map_location is not None:
        obj = _move(obj, map_location)
    return obj, version


def _move(obj: Any, device: Any) -> Any:
    import torch

    if isinstance(obj, torch.Tensor):
        return obj.to(device)
    if isinstance(obj, dict):
        return {k: _move(v, device) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_move(v, device) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_move(v, device) for v in obj)
    return obj


# --------------------------------------------------------------------------------------------
# Converting old pickle files (explicitly trusted)
# --------------------------------------------------------------------------------------------


@dataclass
class Conversion:
    """Result of :func:`convert_trusted`: the file, its kind, whether it was rewritten, and the
    backup of the original (None without one)."""

    path: Path
    kind: str
    converted: bool
    backup: Path | None


def classify_legacy(blob: Any) -> tuple[str, int]:
    """(kind, format) of an object loaded from an old pickle file; ValueError when it is none of
    sage's file kinds."""
    if not isinstance(blob, dict):
        raise ValueError(f"holds a {type(blob).__name__}, not a sage file")
    if blob.get("kind") == AVATAR_KIND:
        return AVATAR_KIND, AVATAR_FORMAT
    if {"format", "step", "state"} <= set(blob):
        return CHECKPOINT_KIND, CHECKPOINT_FORMAT
    if {"format", "args", "state"} <= set(blob):
        return SDF_KIND, SDF_FILE_FORMAT
    raise ValueError("is not a sage avatar, SDF or checkpoint file")


def convert_trusted(path: str | Path, trust: bool, keep_backup: bool = True) -> Conversion:
    """Rewrite an old pickle-based sage file (avatar, SDF, checkpoint) in the safe format, in place.

    Loading a pickle runs whatever code it holds, so this refuses (ConfigError) unless ``trust``.
    The original is kept as ``<name>.pickle-backup`` (``keep_backup``). A file that is already in
    the safe format is left as it is.
    """
    import torch

    p = Path(path)
    chk = inspect_file(p)
    if chk.status == "missing":
        raise InputError(p, "file not found")
    if chk.status == "ok":
        return Conversion(p, chk.kind, False, None)
    if chk.status != "pickle":
        raise InputError(p, f"not a sage file that can be converted ({chk.reason})")
    if not trust:
        raise ConfigError(f"{p}: converting runs the code a pickle file holds; pass --trust if you trust this file's origin")
    try:
        blob = torch.load(p, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001
        raise InputError(p, f"cannot read the pickle file: {e}") from None
    try:
        kind, version = classify_legacy(blob)
    except ValueError as e:
        raise InputError(p, str(e)) from None
    from .atomic import atomic_write_bytes

    data = to_bytes(blob, kind, version)
    backup = None
    if keep_backup:
        backup = p.with_name(p.name + ".pickle-backup")
        atomic_write_bytes(backup, p.read_bytes())
    atomic_write_bytes(p, data)
    return Conversion(p, kind, True, backup)


def verify_file(path: str | Path) -> str | None:
    """Load a safe file fully and check its checksum: None when sound, else the problem."""
    from safetensors.torch import load

    p = Path(path)
    try:
        data = p.read_bytes()
        header, _ = _read_header(data)
        tensors = load(data)
    except Exception as e:  # noqa: BLE001
        return str(e)
    return _checksum_problem(header.get("__metadata__") or {}, tensors)


def _checksum_problem(meta: dict[str, Any], tensors: dict[str, torch.Tensor]) -> str | None:
    """Why a file's tensors or structure do not match its checksums, or None when they do."""
    sha = tensors_sha256(tensors)
    if meta.get(META_SHA) != sha:
        return "its content does not match its checksum"
    if META_DIGEST in meta:
        expected = tree_digest(str(meta.get(META_KIND, "")), str(meta.get(META_FORMAT, "")), str(meta.get(META_TREE, "null")), sha)
        if meta[META_DIGEST] != expected:
            return "its structure does not match its checksum"
    return None
