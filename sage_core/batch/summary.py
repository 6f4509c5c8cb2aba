"""Per-subject live status files, the "finished" test, and the batch summary (JSON + markdown).

Each running subject writes ``ROOT/<id>/.batch_status.json`` (state, stage, done/total, message,
psnr, start time, and on success the batch ``run_key`` it finished with); the batch process only
reads these files to draw its table. A subject counts as finished when every stage its run needs
is complete in the workspace manifests (not stale) and its status file records the same run key
(so changed batch options re-run it; the stages themselves still skip what is unchanged).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterable

from ..workspace import Workspace, atomic_write_json, atomic_write_text, now_iso, read_json

STATUS_NAME = ".batch_status.json"
SUMMARY_JSON = "batch_summary.json"
SUMMARY_MD = "batch_summary.md"
METRIC_KEYS: tuple[str, ...] = ("val_psnr", "val_ssim", "val_lpips", "test_psnr", "test_ssim", "test_lpips",
                                 "novel_psnr", "novel_ssim", "novel_lpips")
"""Metrics of a subject in the summary: the eval of its avatar on the workspace's val (novel view) and
test (self-reenactment) frames, and on the capture's held-out ground truth (``novel``, ``gt/novel``:
the only held-out measure of a one-shot subject)."""


def status_path(ws: str | Path) -> Path:
    """``WS/.batch_status.json``."""
    return Path(ws) / STATUS_NAME


def read_status(ws: str | Path) -> dict[str, Any]:
    """The subject's status dict, or {} when absent or unreadable (it may be mid-replace)."""
    p = status_path(ws)
    try:
        data = read_json(p)
    except (OSError, json.JSONDecodeError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def write_status(ws: str | Path, **fields: Any) -> dict[str, Any]:
    """Merge ``fields`` into the status file (atomic write) and return the new dict."""
    st = read_status(ws)
    st.update(fields)
    st["updated_at"] = time.time()
    Path(ws).mkdir(parents=True, exist_ok=True)
    atomic_write_json(status_path(ws), st)
    return st


def subject_finished(ws: str | Path, stages: Iterable[str], run_key: str) -> bool:
    """True when every stage in ``stages`` is complete (and fresh) and the status file records ``run_key``."""
    root = Path(ws)
    if not root.is_dir():
        return False
    if read_status(root).get("run_key") != run_key:
        return False
    w = Workspace(root)
    return all(w.status(s).status == "complete" for s in stages)


def subject_metrics(ws: str | Path) -> dict[str, Any]:
    """Evaluation metrics of the subject's avatar from the eval manifest: val/test/novel PSNR, SSIM, LPIPS.

    The avatar stage is phase2 when it is complete, else phase1; keys are :data:`METRIC_KEYS`
    (None where not measured) plus ``avatar_stage``.
    """
    w = Workspace(ws)
    av = "phase2" if w.status("phase2").status == "complete" else "phase1"
    m = (w.manifest("eval") or {}).get("metrics") or {}
    out: dict[str, Any] = {"avatar_stage": av}
    for key in METRIC_KEYS:
        split, name = key.split("_")
        v = m.get(f"{av}/{split} {name}")
        out[key] = float(v) if isinstance(v, (int, float)) else None
    return out


def stages_wall_time(ws: str | Path, stages: Iterable[str]) -> float:
    """Sum of the manifests' ``wall_time_s`` over ``stages`` (0 for missing ones)."""
    w = Workspace(ws)
    return float(sum(float((w.manifest(s) or {}).get("wall_time_s") or 0.0) for s in stages))


@dataclass
class SubjectOutcome:
    """One subject's line in the summary.

    status: "finished" (ran now), "skipped" (already finished), "failed", "interrupted" or "not
    run" (the batch was interrupted before it started). stage: the stage that failed or was
    interrupted (None otherwise).
    """

    id: str
    status: str
    ws: str
    wall_time_s: float = 0.0
    metrics: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    returncode: int | None = None
    attempts: int = 0
    device: str | None = None
    log: str | None = None
    stage: str | None = None


def write_summary(root: str | Path, outcomes: list[SubjectOutcome], meta: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``ROOT/batch_summary.json`` and ``ROOT/batch_summary.md`` atomically; returns both paths."""
    root = Path(root)
    counts: dict[str, int] = {}
    for o in outcomes:
        counts[o.status] = counts.get(o.status, 0) + 1
    doc = {"written_at": now_iso(), **meta, "counts": counts, "subjects": [asdict(o) for o in outcomes]}
    jp, mp = root / SUMMARY_JSON, root / SUMMARY_MD
    atomic_write_json(jp, doc)
    atomic_write_text(mp, summary_markdown(outcomes, counts))
    return jp, mp


def summary_markdown(outcomes: list[SubjectOutcome], counts: dict[str, int] | None = None) -> str:
    """A markdown table: subject, status, the stage that failed, wall time, PSNR and SSIM on val
    (novel view), test (self-reenactment) and gt/novel (held-out views and expressions), error."""

    def num(v: Any, d: int) -> str:
        return f"{v:.{d}f}" if isinstance(v, (int, float)) and not isinstance(v, bool) and v == v else "—"

    lines = [
        "| subject | status | failed stage | wall time (s) | val PSNR | val SSIM | test PSNR | test SSIM | novel PSNR | novel SSIM | error |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for o in outcomes:
        m = o.metrics
        err = (o.error or "").replace("|", "\\|").replace("\n", " ")
        lines.append(
            f"| {o.id} | {o.status} | {o.stage or ''} | {o.wall_time_s:.1f} | {num(m.get('val_psnr'), 2)} | {num(m.get('val_ssim'), 4)} "
            f"| {num(m.get('test_psnr'), 2)} | {num(m.get('test_ssim'), 4)} | {num(m.get('novel_psnr'), 2)} "
            f"| {num(m.get('novel_ssim'), 4)} | {err} |"
        )
    if counts:
        lines += ["", ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))]
    return "\n".join(lines) + "\n"
