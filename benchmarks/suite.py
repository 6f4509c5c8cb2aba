"""The SAGE benchmark suite: one command that builds a synthetic multiview benchmark capture,
trains and evaluates every row on the same data and seed, and writes the results.

Usage:
    python benchmarks/suite.py --size tiny|small|full --out DIR [--rows a,b,...] [--device auto]
                               [--seed 0] [--head detailed|smooth|photo] [--subjects 2] [--lpips-weights PATH]

Rows (ids): ceiling, sage, sage_exact, no_mlp, no_phase2, no_correction, no_wrinkles, no_relocation, no_light, ga_mvsf, ga_mvmf, free_mvsf,
sv_hr, one_shot (``ceiling`` trains nothing: the capture's ground truth on its tracked FLAME fit).
Each size runs every stage with the preset of its name: ``tiny`` (128x186 captures, minutes per row
on a CPU), ``small`` (256x372, 20k surfels; a CPU in hours) and ``full`` (the default presets,
550x802, a GPU).
The captures are tracked (``sage synth --tracking fitted``: FLAME parameters fitted to a ground
truth the written model cannot fully express, plus pose noise); ``sage_exact`` trains SAGE MV-SF
on the exact multiview capture (``--tracking exact``) so both are visible. The synthetic heads are
detailed (``sage synth --appearance detailed``: pixel-scale skin and hair detail, hair volume off the
scalp) and every row runs on ``--subjects`` subjects (capture seeds ``--seed``, ``--seed``+1, …);
the tables show the mean over the subjects, and a per-subject table. ``--head smooth --subjects 1``
reproduces the captures and numbers of earlier versions (the smooth head, one subject). ``--head
photo`` gives the detailed heads a real face: scikit-image's astronaut photograph, tracked by ``sage
track`` with a model of the size's head grid, becomes their face's skin (``sage synth --set
skin_photo``; it needs the MediaPipe face models of ``sage track``).
Every stage runs through the real ``sage`` CLI in a subprocess, one workspace per row under
``DIR/ws/<row>``; rows copy the finished stages they share with the SAGE row (``cp -a`` of the
stage folders keeps their manifests, so the workspace accepts them as complete). A rerun skips
every stage that is already complete with the same settings. Results go to
``docs/benchmarks/suite_<size>.json`` (``suite_<size>_<head>.json`` for the detailed and photo heads; rows of an
earlier run that were not rerun are kept) and
``docs/results.md`` is regenerated from every ``suite_*.json``; both name no path of this machine
(paths relative to ``--out``, written ``OUT`` in commands; the LPIPS weights by file name:
:mod:`_suite.portable`).

Hidden options for checking the machinery: ``--smoke`` (a few steps per stage on a reduced
capture, labelled as not representative) and ``--override STAGE:key=value`` (added to every run
of that stage), ``--docs DIR`` (where the JSON and results.md go; default the repository's
``docs/``, or ``DIR/docs`` with ``--smoke`` so a smoke run never replaces the real results).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

def build_parser() -> argparse.ArgumentParser:
    from _suite.rows import HEADS, ROW_IDS, SIZES

    ap = argparse.ArgumentParser(prog="python benchmarks/suite.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", required=True, choices=sorted(SIZES), help="tiny (tiny presets, 128x186, CPU), small (small presets, 256x372, CPU) or full (default presets, 550x802, GPU).")
    ap.add_argument("--out", required=True, type=Path, help="Folder for the captures, the row workspaces and the logs.")
    ap.add_argument("--rows", default=",".join(ROW_IDS), help=f"Comma-separated subset of: {', '.join(ROW_IDS)} (default: all).")
    ap.add_argument("--device", default="auto", help="Device of every stage: auto, cpu or cuda[:N].")
    ap.add_argument("--seed", type=int, default=0, help="Seed of every stage and of the first subject's captures (further subjects: seed+1, ...).")
    ap.add_argument("--head", default="detailed", choices=HEADS,
                    help="Synthetic heads: detailed (pixel-scale skin and hair detail, hair volume), smooth (earlier versions' head) or photo "
                         "(the detailed heads with a real photograph's face as their skin; needs the face models of `sage track`).")  # fmt: skip
    ap.add_argument("--subjects", type=int, default=2, help="Synthetic subjects (different seeds) every row runs on; the tables show their mean.")
    ap.add_argument("--lpips-weights", type=Path, default=None, help="LPIPS AlexNet v0.1 weights (default: where sage finds them: $SAGE_LPIPS_WEIGHTS, then ~/.cache/sage/lpips_alex_v0.1.pth; LPIPS is reported unavailable without them).")
    ap.add_argument("--smoke", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--override", action="append", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--docs", type=Path, default=None, help=argparse.SUPPRESS)
    return ap


def _load(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError):
        return None


DISCUSSION_FILE = "discussion.md"
"""Hand-written discussion of the measured results against the paper, appended to results.md."""


def results_path(docs_dir: Path, size: str, head: str) -> Path:
    """``docs_dir/benchmarks/suite_<size>.json`` for the smooth head (the file earlier versions wrote),
    ``suite_<size>_<head>.json`` for another, so that a run on one head never replaces the other's."""
    return docs_dir / "benchmarks" / (f"suite_{size}.json" if head == "smooth" else f"suite_{size}_{head}.json")


def write_docs(doc: dict, docs_dir: Path) -> tuple[Path, Path]:
    """Merge ``doc`` into its results file (:func:`results_path`) and regenerate
    ``docs_dir/results.md`` from every ``suite_*.json`` there (and ``benchmarks/discussion.md``,
    the hand-written comparison with the paper, when present). Returns both paths."""
    from _suite.report import merge_results, render_document

    from sage_core.workspace import atomic_write_json, atomic_write_text

    json_path = results_path(docs_dir, doc["size"], doc.get("head", "smooth"))
    merged = merge_results(_load(json_path), doc)
    atomic_write_json(json_path, merged)
    docs = [d for d in (_load(p) for p in sorted((docs_dir / "benchmarks").glob("suite_*.json"))) if d]
    md_path = docs_dir / "results.md"
    discussion = docs_dir / "benchmarks" / DISCUSSION_FILE
    text = discussion.read_text(encoding="utf-8") if discussion.is_file() else None
    atomic_write_text(md_path, render_document(docs, text))
    return json_path, md_path


def main(argv: list[str] | None = None) -> int:
    from _suite.execute import collect_row, execute
    from _suite.portable import portable_doc
    from _suite.report import SCHEMA, machine_info
    from _suite.rows import ROWS, SIZES, Settings, parse_overrides, plan, smoke_size

    from sage_core.workspace import now_iso, resolve_device

    ap = build_parser()
    args = ap.parse_args(argv)
    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in ROWS]
    if bad or not rows:
        ap.error(f"unknown row(s): {', '.join(bad) or '(none given)'}")
    try:
        overrides = parse_overrides(args.override)
        resolve_device(args.device)
    except Exception as e:  # noqa: BLE001
        ap.error(str(e))
    from sage_core.evaluate.lpips import find_lpips_weights

    try:
        lpips = find_lpips_weights(args.lpips_weights)
    except Exception as e:  # noqa: BLE001
        ap.error(str(e))
    if args.subjects < 1:
        ap.error("--subjects must be at least 1")
    if args.head == "photo":
        from sage_core.track.weights import models_available

        missing = models_available()
        if missing:
            ap.error(f"--head photo tracks a photograph with `sage track`: {missing}")
    size = SIZES[args.size]
    if args.smoke:
        size = smoke_size(size)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    settings = Settings(size, out, args.device, args.seed, lpips.resolve() if lpips else None, overrides, head=args.head,
                        subjects=args.subjects)
    steps, needs = plan(settings, rows)

    docs_dir = args.docs if args.docs is not None else (out / "docs" if size.smoke else REPO / "docs")
    json_path = results_path(docs_dir, size.name, settings.head)
    previous = _load(json_path) or {}
    same = (previous.get("size") == size.name and bool(previous.get("smoke")) == size.smoke
            and previous.get("head", "smooth") == settings.head and previous.get("subject_seeds", [args.seed]) == settings.subject_seeds)
    prev_steps = (previous.get("steps") or {}) if same else {}
    machine = machine_info(args.device)
    poll_gpu = str(machine.get("device", "")).startswith("cuda")

    def log(msg: str) -> None:
        print(msg, flush=True)

    started, t0, load0 = now_iso(), time.time(), os.getloadavg()
    log(f"suite {size.name}{' (smoke)' if size.smoke else ''}: {len(rows)} rows, {len(steps)} steps, out {out}")
    try:
        records = execute(steps, settings, prev_steps, log, poll_gpu=poll_gpu)
    except KeyboardInterrupt:
        log("interrupted: nothing written (finished stages stay in the workspaces; rerun to continue)")
        return 130
    row_docs = {rid: collect_row(ROWS[rid], settings, needs[rid], records) for rid in rows}
    suite_cmd = " ".join(["python", "benchmarks/suite.py", *(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))])
    doc = {
        "schema": SCHEMA,
        "size": size.name,
        "smoke": size.smoke,
        "head": settings.head,
        "subject_seeds": settings.subject_seeds,
        "suite_command": suite_cmd,
        "generated_at": now_iso(),
        "machine": machine,
        "settings": {"preset": size.preset, "synth_preset": size.synth_preset, "seed": args.seed, "head": settings.head,
                     "subject_seeds": settings.subject_seeds, "device": args.device,
                     "lpips_weights": str(settings.lpips_weights) if settings.lpips_weights else None,
                     "overrides": {k: list(v) for k, v in overrides.items()}, "out": str(out)},  # fmt: skip
        "runs": [{"started_at": started, "finished_at": now_iso(), "wall_s": round(time.time() - t0, 1), "rows": rows, "command": suite_cmd,
                  "load_start": [round(x, 2) for x in load0], "load_end": [round(x, 2) for x in os.getloadavg()]}],  # fmt: skip
        "steps": records,
        "rows": row_docs,
    }
    jp, mp = write_docs(portable_doc(doc, [out], [settings.lpips_weights] if settings.lpips_weights else []), docs_dir)
    failed = [rid for rid, r in row_docs.items() if r["errors"]]
    log(f"wrote {jp} and {mp} ({time.time() - t0:.0f} s)")
    if failed:
        log(f"rows with errors: {', '.join(failed)} (see the Errors section of {mp})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
