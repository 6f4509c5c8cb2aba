"""Accumulating stages (eval, export): several results live side by side in one stage folder.

Each result has an entry in ``<stage folder>/results.json`` naming its avatar stage, that stage's
fingerprint and its files; a re-run keeps (:func:`carry_results`) the entries whose avatar is
unchanged (:func:`fresh_results`) and adds the new ones, keyed by :func:`result_key`.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ..workspace import Workspace

RESULTS_INDEX = "results.json"


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
