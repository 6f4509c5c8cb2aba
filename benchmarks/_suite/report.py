"""The results document: machine description, merging partial runs, and the Markdown tables of
``docs/results.md`` (generated from ``docs/benchmarks/suite_<size>[_detailed].json`` only)."""

from __future__ import annotations

import os
import platform
import posixpath
import re
from typing import Any

from .rows import ROW_IDS, ROWS

TRAINED_IDS: tuple[str, ...] = tuple(i for i in ROW_IDS if not ROWS[i].ceiling)
"""Rows that train an avatar (the geometry and cost tables list only these)."""

SCHEMA = 1
DASH = "—"

PAPER_ABLATION: dict[str, dict[str, tuple[float, float, float] | None]] = {
    "sage": {"val": (33.79, 0.963, 0.071), "test_all": (26.64, 0.907, 0.093)},
    "no_mlp": {"val": (33.95, 0.961, 0.071), "test_all": (24.72, 0.857, 0.142)},
    "no_phase2": {"val": (34.14, 0.962, 0.067), "test_all": (22.18, 0.800, 0.132)},
    "no_correction": {"val": None, "test_all": (25.42, 0.905, 0.101)},
}
"""SAGE paper, ablation table: novel view and self-reenactment (PSNR, SSIM, LPIPS); "w/o
correction" novel view is reported as "same as full"."""

PAPER_MAIN: dict[str, dict[str, tuple[float, float, float]]] = {
    "ga_mvmf": {"test_frontal": (25.94, 0.922, 0.079), "test_all": (25.32, 0.903, 0.084)},
    "ga_mvsf": {"test_frontal": (17.75, 0.825, 0.200), "test_all": (17.23, 0.823, 0.215)},
    "sage": {"test_frontal": (25.41, 0.896, 0.085), "test_all": (24.27, 0.879, 0.094)},
    "sv_hr": {"test_frontal": (23.90, 0.90, 0.089), "test_all": (22.76, 0.881, 0.102)},
    "one_shot": {"test_frontal": (21.04, 0.821, 0.125), "test_all": (18.57, 0.785, 0.169)},
}
"""SAGE paper, main table (NeRSemble, novel expressions, frontal and all views): GA MV-MF / MV-SF,
Ours MV-SF / SV-HR / One-shot."""


# --------------------------------------------------------------------------------------------
# Machine and merging
# --------------------------------------------------------------------------------------------


def machine_info(device: str) -> dict[str, Any]:
    """CPU model, cores, memory, OS, Python and torch versions, and the device the stages use."""
    import torch

    cpu = platform.processor() or platform.machine()
    mem_gib = None
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
        with open("/proc/meminfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    mem_gib = round(int(line.split()[1]) / 2**20, 1)
                    break
    except OSError:
        pass
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        usable = os.cpu_count()
    resolved = ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device
    info: dict[str, Any] = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "usable_cores": usable,
        "memory_gib": mem_gib,
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "device": resolved,
    }
    if resolved.startswith("cuda") and torch.cuda.is_available():
        idx = int(resolved.split(":")[1]) if ":" in resolved else 0
        info["gpu"] = torch.cuda.get_device_name(idx)
        info["gpu_memory_gib"] = round(torch.cuda.get_device_properties(idx).total_memory / 2**30, 1)
    return info


def _head(doc: dict[str, Any]) -> tuple[str, list[int]]:
    """(head, subject seeds) of a results document (earlier documents: the smooth head, one subject)."""
    return doc.get("head", "smooth"), list(doc.get("subject_seeds") or [(doc.get("settings") or {}).get("seed", 0)])


def merge_results(old: dict[str, Any] | None, new: dict[str, Any]) -> dict[str, Any]:
    """A document with ``new``'s rows, steps and runs over ``old``'s: rows and steps of the same
    id are replaced, the others kept (a ``--rows`` run updates part of the suite). Documents of
    another size, schema, head or subjects, or a smoke run with a real one, are not merged: ``new``
    is returned."""
    if not old or any(old.get(k) != new.get(k) for k in ("size", "schema", "smoke")) or _head(old) != _head(new):
        return new
    out = dict(new)
    out["rows"] = {**(old.get("rows") or {}), **(new.get("rows") or {})}
    out["steps"] = {**(old.get("steps") or {}), **(new.get("steps") or {})}
    out["runs"] = [*(old.get("runs") or []), *(new.get("runs") or [])]
    return out


# --------------------------------------------------------------------------------------------
# Markdown
# --------------------------------------------------------------------------------------------


def present(v: Any) -> bool:
    """Whether ``v`` is a measured number (None, NaN, a bool or a non-number is not)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v


def fmt(v: Any, digits: int) -> str:
    """A number with ``digits`` decimals, or the dash for a missing value."""
    return f"{v:.{digits}f}" if present(v) else DASH


def _triple(m: dict[str, Any] | None) -> list[str]:
    if not m:
        return [DASH, DASH, DASH]
    return [fmt(m.get("psnr"), 2), fmt(m.get("ssim"), 4), fmt(m.get("lpips"), 4)]


def _metric(row: dict[str, Any], split: str, which: str) -> dict[str, Any] | None:
    return ((row.get("metrics") or {}).get(split) or {}).get(which)


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|"]
    out += ["| " + " | ".join(c.replace("|", "\\|").replace("\n", " ") for c in r) + " |" for r in rows]
    return out


def _notes(row: dict[str, Any], limit: int = 160) -> str:
    errs = row.get("errors") or []
    if not errs:
        return ""
    text = "; ".join(str(e) for e in errs)
    return "error: " + (text if len(text) <= limit else text[: limit - 1] + "…")


def _rows(results: dict[str, Any], ids: tuple[str, ...]) -> list[dict[str, Any]]:
    rows = results.get("rows") or {}
    return [rows[i] for i in ids if i in rows]


def _name(row: dict[str, Any]) -> str:
    return f"{row.get('label', row.get('id'))} (`{row.get('id')}`)"


def _rendering_table(rows: list[dict[str, Any]]) -> list[str]:
    header = ["Row", "Input", "Val PSNR", "Val SSIM", "Val LPIPS", "Frontal PSNR", "Frontal SSIM", "Frontal LPIPS",
              "All PSNR", "All SSIM", "All LPIPS", "Notes"]  # fmt: skip
    body = []
    for r in rows:
        body.append([_name(r), str(r.get("input_type", DASH)), *_triple(_metric(r, "val", "overall")),
                     *_triple(_metric(r, "test", "frontal")), *_triple(_metric(r, "test", "overall")), _notes(r)])  # fmt: skip
    return _table(header, body)


def _capture_lines(rows: list[dict[str, Any]]) -> list[str]:
    """One line per capture the rows train on: exact, or tracked with its tracking error."""
    out, seen = [], set()
    for r in rows:
        cap, tr = r.get("capture"), r.get("capture_tracking")
        if cap in seen or not tr:
            continue
        seen.add(cap)
        err = (tr.get("error") or {}).get("all") or {}
        if tr.get("mode") == "exact":
            out.append(f"- Capture `{cap}`: exact (the FLAME parameters are the ground truth).")
        else:
            out.append(f"- Capture `{cap}`: tracked, vertex error of the written FLAME parameters mean {fmt(err.get('mean_mm'), 2)} mm, "
                       f"face region {fmt(err.get('face_mean_mm'), 2)} mm, max {fmt(err.get('max_mm'), 2)} mm.")  # fmt: skip
    return out + [""] if out else []


def _group(row: dict[str, Any], group: str) -> dict[str, Any] | None:
    return ((((row.get("metrics") or {}).get("novel") or {}).get("view_groups") or {}).get(group) or {}).get("overall")


def _regime_table(rows: list[dict[str, Any]]) -> list[str]:
    header = ["Row", "Input", "Held-out GT PSNR", "SSIM", "LPIPS", "Back views PSNR", "SSIM", "LPIPS", "Test (all) PSNR", "SSIM",
              "LPIPS", "Notes"]  # fmt: skip
    body = [[_name(r), str(r.get("input_type", DASH)), *_triple(_metric(r, "novel", "overall")), *_triple(_group(r, "back")),
             *_triple(_metric(r, "test", "overall")), _notes(r)] for r in rows]  # fmt: skip
    return _table(header, body)


def _novel_view_table(rows: list[dict[str, Any]]) -> list[str]:
    """Multiview rows on their capture's held-out views of the training timestep (``gt/novel``)."""
    header = ["Row", "Val PSNR", "LPIPS", "Off-arc views PSNR", "SSIM", "LPIPS", "Side views PSNR", "LPIPS", "Back views PSNR", "LPIPS"]
    body = []
    for r in rows:
        if not _metric(r, "novel", "overall"):
            continue
        val, front, side, back = _metric(r, "val", "overall") or {}, _group(r, "front") or {}, _group(r, "side") or {}, _group(r, "back") or {}
        body.append([_name(r), fmt(val.get("psnr"), 2), fmt(val.get("lpips"), 4), *_triple(front), fmt(side.get("psnr"), 2),
                     fmt(side.get("lpips"), 4), fmt(back.get("psnr"), 2), fmt(back.get("lpips"), 4)])  # fmt: skip
    return _table(header, body) if body else []


def _subject_table(rows: list[dict[str, Any]]) -> list[str]:
    """One line per row and subject: novel view, self-reenactment (all cameras) and held-out GT."""
    header = ["Row", "Subject seed", "Hair", "Val PSNR", "All PSNR", "All LPIPS", "Held-out GT PSNR", "Held-out GT LPIPS", "Back views PSNR"]
    body = []
    for r in rows:
        for sub in r.get("subjects") or []:
            m = {"metrics": sub.get("metrics")}
            body.append([_name(r), str(sub.get("seed", DASH)), str(sub.get("hair") or DASH), fmt((_metric(m, "val", "overall") or {}).get("psnr"), 2),
                         fmt((_metric(m, "test", "overall") or {}).get("psnr"), 2), fmt((_metric(m, "test", "overall") or {}).get("lpips"), 4),
                         fmt((_metric(m, "novel", "overall") or {}).get("psnr"), 2), fmt((_metric(m, "novel", "overall") or {}).get("lpips"), 4),
                         fmt((_group(m, "back") or {}).get("psnr"), 2)])  # fmt: skip
    return _table(header, body)


def _geometry_table(rows: list[dict[str, Any]]) -> list[str]:
    header = ["Row", "Chamfer to GT (mm)", "Chamfer (% head diagonal)", "Normal error (deg)", "Chamfer to FLAME mesh (mm)"]
    body = []
    for r in rows:
        g = r.get("geometry") or {}
        p1 = (r.get("stages") or {}).get("phase1") or {}
        if not r.get("has_sdf"):
            body.append([_name(r), DASH, DASH, DASH, DASH])
            continue
        ch = p1.get("chamfer_m")
        body.append([_name(r), fmt(g.get("chamfer_mm"), 3), fmt(g.get("chamfer_rel_pct"), 3), fmt(g.get("normal_error_deg"), 2),
                     fmt(ch * 1000.0 if isinstance(ch, (int, float)) else None, 3)])  # fmt: skip
    return _table(header, body)


def _cost_table(rows: list[dict[str, Any]]) -> list[str]:
    header = ["Row", "surfels", "ingest (s)", "init-mesh (s)", "phase 1 (s)", "phase 2 (s)", "eval (s)", "reenact (s)", "peak RSS (MiB)",
              "peak GPU (MiB)", "phase 1 it/s", "phase 2 it/s", "reenact FPS"]  # fmt: skip
    body = []
    for r in rows:
        st = r.get("stages") or {}

        def wall(name: str) -> str:
            s = st.get(name)
            if not s:
                return DASH
            v = fmt(s.get("wall_time_s"), 1)
            return f"{v}*" if s.get("shared") and v != DASH else v

        ev = [s.get("wall_time_s") for k, s in st.items() if k.startswith("eval:") and s.get("wall_time_s") is not None]
        re = (st.get("reenact") or {}).get("wall_time_s")
        fps = (r.get("reenact") or {}).get("render_fps")
        body.append([_name(r), fmt((st.get("phase1") or {}).get("n_surfels"), 0), wall("ingest"), wall("init-mesh"), wall("phase1"), wall("phase2"), fmt(sum(ev) if ev else None, 1),
                     fmt(re, 1), fmt(r.get("peak_rss_mib"), 0), fmt(r.get("gpu_peak_mib"), 0),
                     fmt((st.get("phase1") or {}).get("iterations_per_s"), 2), fmt((st.get("phase2") or {}).get("iterations_per_s"), 2),
                     fmt(fps, 2)])  # fmt: skip
    return _table(header, body)


def _delta(a: Any, b: Any) -> float | None:
    """``a - b``, or None where either is missing (None, NaN or not a number)."""
    return float(a) - float(b) if present(a) and present(b) else None


def _sgn(v: float | None, digits: int = 2) -> str:
    return DASH if v is None else f"{v:+.{digits}f}"


def _paper(t: tuple[float, float, float]) -> str:
    return f"{t[0]:.2f} / {t[1]:.3f} / {t[2]:.3f}"


def _comparison(results: dict[str, Any]) -> list[str]:
    """Paper values beside ours, and the differences each ablation or baseline makes to SAGE,
    with whether their sign agrees with the paper's. Nothing beyond the numbers."""
    rows = results.get("rows") or {}
    out = ["Paper numbers: NeRSemble subjects at 550×802 (ablation table and main table of the paper). Ours: the",
           "synthetic capture of this run. Absolute values are not comparable across the two data sets; the",
           "differences to the SAGE row are.", ""]  # fmt: skip
    header = ["Row", "Paper val PSNR", "Ours val PSNR", "Paper test-all PSNR", "Ours test-all PSNR",
              "Δ val PSNR vs SAGE (paper / ours)", "Δ test-all PSNR vs SAGE (paper / ours)", "Same sign of Δ test-all"]  # fmt: skip
    body = []
    sage = rows.get("sage") or {}
    s_val = (_metric(sage, "val", "overall") or {}).get("psnr")
    s_all = (_metric(sage, "test", "overall") or {}).get("psnr")
    for rid in ("sage", "no_mlp", "no_phase2", "no_correction"):
        r = rows.get(rid)
        if r is None:
            continue
        p = PAPER_ABLATION[rid]
        o_val = (_metric(r, "val", "overall") or {}).get("psnr")
        o_all = (_metric(r, "test", "overall") or {}).get("psnr")
        pv = p["val"][0] if p["val"] else None
        pa = p["test_all"][0] if p["test_all"] else None
        dpv = _delta(pv, PAPER_ABLATION["sage"]["val"][0]) if rid != "sage" and pv is not None else None  # type: ignore[index]
        dpa = _delta(pa, PAPER_ABLATION["sage"]["test_all"][0]) if rid != "sage" else None  # type: ignore[index]
        dov = _delta(o_val, s_val) if rid != "sage" else None
        doa = _delta(o_all, s_all) if rid != "sage" else None
        same = DASH
        if dpa is not None and doa is not None:
            same = "yes" if (dpa > 0) == (doa > 0) else "no"
        body.append([_name(r), fmt(pv, 2) if pv is not None else ("same as full" if rid == "no_correction" else DASH), fmt(o_val, 2),
                     fmt(pa, 2), fmt(o_all, 2), f"{_sgn(dpv)} / {_sgn(dov)}" if rid != "sage" else DASH,
                     f"{_sgn(dpa)} / {_sgn(doa)}" if rid != "sage" else DASH, same])  # fmt: skip
    if body:
        out += ["Ablations (novel view = val split, self-reenactment = test split, all cameras):", ""]
        out += _table(header, body)
        out.append("")
    header2 = ["Row", "Input", "Paper frontal PSNR / SSIM / LPIPS", "Ours frontal", "Paper all PSNR / SSIM / LPIPS", "Ours all"]
    body2 = []
    for rid in ("ga_mvmf", "ga_mvsf", "sage", "sv_hr", "one_shot"):
        r = rows.get(rid)
        if r is None:
            continue
        p = PAPER_MAIN[rid]
        split = "test" if rid not in ("sv_hr", "one_shot") else "novel"
        ours_f = _triple(_metric(r, split, "frontal"))
        ours_a = _triple(_metric(r, split, "overall"))
        body2.append([_name(r), str(r.get("input_type")), _paper(p["test_frontal"]), " / ".join(ours_f),
                      _paper(p["test_all"]), " / ".join(ours_a)])  # fmt: skip
    if body2:
        out += ["Main table rows (novel expressions; SV-HR and one-shot rows: ours on the held-out ground truth `gt/novel`):", ""]
        out += _table(header2, body2)
        out.append("")
        ga_mf, ga_sf, sg = rows.get("ga_mvmf"), rows.get("ga_mvsf"), rows.get("sage")
        if sg and ga_sf:
            d = _delta((_metric(sg, "test", "overall") or {}).get("psnr"), (_metric(ga_sf, "test", "overall") or {}).get("psnr"))
            if d is not None:
                out.append(f"- SAGE MV-SF minus GA-style MV-SF, self-reenactment PSNR (all cameras): ours {d:+.2f} dB, paper "
                           f"{PAPER_MAIN['sage']['test_all'][0] - PAPER_MAIN['ga_mvsf']['test_all'][0]:+.2f} dB.")  # fmt: skip
        if sg and ga_mf:
            d = _delta((_metric(sg, "test", "overall") or {}).get("psnr"), (_metric(ga_mf, "test", "overall") or {}).get("psnr"))
            if d is not None:
                out.append(f"- SAGE MV-SF minus GA-style MV-MF, self-reenactment PSNR (all cameras): ours {d:+.2f} dB, paper "
                           f"{PAPER_MAIN['sage']['test_all'][0] - PAPER_MAIN['ga_mvmf']['test_all'][0]:+.2f} dB.")  # fmt: skip
        ceil = (_metric(rows["ceiling"], "test", "overall") or {}).get("psnr") if "ceiling" in rows else None
        below = [(_name(rows[rid]), _delta((_metric(rows[rid], "test", "overall") or {}).get("psnr"), ceil))
                 for rid in ("sage", "ga_mvsf", "ga_mvmf") if rid in rows]  # fmt: skip
        below = [(n, d) for n, d in below if d is not None]
        if below:
            out.append(f"- Against the tracking ceiling ({fmt(ceil, 2)} dB, self-reenactment PSNR, all cameras): "
                       + ", ".join(f"{n} {d:+.2f} dB" for n, d in below) + ".")
        out.append("")
    return out


def render_markdown(results: dict[str, Any]) -> str:
    """The Markdown section of one suite results document (one size)."""
    size = results.get("size", "?")
    m = results.get("machine") or {}
    st = results.get("settings") or {}
    head, _ = _head(results)
    lines = [f"## Size `{size}`" + {"smooth": "", "photo": ", photo-skinned heads"}.get(head, f", {head} heads"), ""]
    if results.get("smoke"):
        lines += ["**Smoke test: a few steps per stage on a reduced capture. These numbers check the machinery and say",
                  "nothing about the method.**", ""]  # fmt: skip
    lines += [
        f"- Suite command (latest run): `{results.get('suite_command', DASH)}`",
        f"- Machine: {m.get('cpu', DASH)}, {m.get('usable_cores', DASH)} usable of {m.get('cores', DASH)} cores, "
        f"{m.get('memory_gib', DASH)} GiB RAM, {m.get('os', DASH)}; Python {m.get('python', DASH)}, torch {m.get('torch', DASH)}; "
        f"device `{m.get('device', DASH)}`" + (f" ({m['gpu']}, {m.get('gpu_memory_gib')} GiB)" if m.get("gpu") else ""),
        f"- Preset `{st.get('preset', DASH)}`, seed {st.get('seed', DASH)}, LPIPS weights: {st.get('lpips_weights') or 'none (LPIPS unavailable)'}"
        + (f"; overrides: {st.get('overrides')}" if st.get("overrides") else ""),
        "- Paths are relative to the suite's `--out` folder, written `OUT` in the commands; the LPIPS weights are named by their file.",
    ]
    head, seeds = _head(results)
    how = (f"`sage synth --appearance {head}`" if head != "photo" else
           "detailed, with a photograph's face as the skin: `sage synth --appearance detailed --set skin_photo=OUT/photo/PRESET/capture`, "
           "the capture `sage track` made of scikit-image's astronaut photograph")
    lines.append(f"- Synthetic heads: {head} ({how}), {len(seeds)} subject{'s' if len(seeds) > 1 else ''} "
                 f"(capture seed{'s' if len(seeds) > 1 else ''} {', '.join(str(x) for x in seeds)})"
                 + ("; every number is the mean over the subjects (per subject below)" if len(seeds) > 1 else ""))
    for run in results.get("runs") or []:
        lines.append(f"- Run {run.get('started_at', DASH)} → {run.get('finished_at', DASH)} ({fmt(run.get('wall_s'), 0)} s), rows "
                     f"{', '.join(run.get('rows') or [])}; load average at start / end: {run.get('load_start', DASH)} / {run.get('load_end', DASH)}"
                     + (f"; `{run['command']}`" if run.get("command") else ""))  # fmt: skip
    lines.append("")
    lines += ["### Novel view and self-reenactment (multiview rows)", "",
              "Val = novel view (the held-out frontal camera at the training timesteps); Frontal / All = self-reenactment",
              "on the test split (held-out novel expressions) seen by the frontal camera / all cameras. PSNR is the",
              "standard per-image value (docs/formats.md §8), SSIM 11×11 Gaussian, LPIPS AlexNet v0.1 on [−1, 1].", ""]  # fmt: skip
    mv_ids = ("ceiling", "sage", "sage_exact", "no_mlp", "no_phase2", "no_correction", "no_wrinkles", "no_relocation", "no_light", "ga_mvsf", "ga_mvmf", "free_mvsf")
    lines += _capture_lines(_rows(results, mv_ids))
    lines += _rendering_table(_rows(results, mv_ids))
    novel_table = _novel_view_table(_rows(results, mv_ids))
    if novel_table:
        lines += ["", "### Novel views of the training timestep (multiview rows, detailed captures)", "",
                  "Val = the one held-out camera of the arc (frontal). Off-arc views = `gt/novel`'s cameras midway between two",
                  "training cameras, 22° above or 16° below the arc (view group `front`); side and back = its views around the",
                  "head, which no training camera sees (beyond 75° and 135° from the face). All at the training timestep with",
                  "its training FLAME parameters: only the viewpoint is new.", ""]  # fmt: skip
        lines += novel_table
    regime_rows = _rows(results, ("sv_hr", "one_shot"))
    if regime_rows:
        lines += ["", "### Single-view and one-shot regimes", "",
                  "Held-out GT = `sage eval WS --split novel` against the capture's `gt/novel/` views and expressions (all of them);",
                  "back views = its views behind the head (view group `back`, beyond 135° from the face; detailed captures).", ""]  # fmt: skip
        lines += _capture_lines(regime_rows)
        lines += _regime_table(regime_rows)
    if any(len(r.get("subjects") or []) > 1 for r in _rows(results, ROW_IDS)):
        lines += ["", "### Per subject", "",
                  "The rows' numbers on each synthetic subject (the tables above show their mean). Back views = the held-out",
                  "views behind the head (`gt/novel` view group `back`).", ""]  # fmt: skip
        lines += _subject_table(_rows(results, ROW_IDS))
    lines += ["", "### Geometry", "",
              "SDF zero level set of phase 1 (frozen in phase 2) against the ground-truth mesh of the canonical timestep",
              "moved into canonical space; Chamfer = mean of both directions' closest-point distances; normal error =",
              "mean angle between closest faces' normals, both directions. The last column is phase 1's own Chamfer to",
              "the canonical FLAME mesh. GA-style rows have no SDF. On a tracked capture the GT mesh is moved with the",
              "capture's tracked pose, so that timestep's tracking error is part of the distance.", ""]  # fmt: skip
    lines += _geometry_table(_rows(results, TRAINED_IDS))
    lines += ["", "### Cost", "",
              "Wall times of ingest, init-mesh, phase 1 and phase 2 from the stage manifests (* = stage shared with the",
              "row it was copied from); surfels: the phase-1 avatar's count (GaussianAvatars rows: after densification);",
              "eval and reenact: subprocess wall time. Peak RSS: the largest resident set of the",
              "row's stage processes (`VmHWM`); peak GPU: the largest nvidia-smi sample. Reenact FPS: render-only",
              "frames per second of `sage reenact` on the test-split clip.", ""]  # fmt: skip
    lines += _cost_table(_rows(results, TRAINED_IDS))
    lines += ["", "### Comparison with the paper", ""]
    lines += _comparison(results)
    errs = [(r["id"], e) for r in _rows(results, ROW_IDS) for e in (r.get("errors") or [])]
    if errs:
        lines += ["### Errors", ""]
        lines += [f"- `{rid}`: {e}" for rid, e in errs]
        lines.append("")
    lines += ["### Commands", "", "Every row, reproducible step by step (shared steps appear under the first row that needs them):", ""]
    steps = results.get("steps") or {}
    seen: set[str] = set()
    for r in _rows(results, ROW_IDS):
        keys = list(dict.fromkeys(k for k in r.get("steps") or [] if k not in seen))
        seen.update(keys)
        lines += [f"`{r['id']}`:", "", "```bash"]
        lines += [(steps.get(k) or {}).get("command", f"# {k}: not recorded") for k in keys] or ["# (all steps shared with rows above)"]
        lines += ["```", ""]
    return "\n".join(lines).rstrip() + "\n"


def render_document(docs: list[dict[str, Any]], discussion: str | None = None) -> str:
    """``docs/results.md``: every size's section, smallest first, then the hand-written ``discussion``
    (markdown) when given."""
    order = {"tiny": 0, "small": 1, "full": 2}
    parts = ["# Benchmark results", "",
             "Generated by `python benchmarks/suite.py` from `docs/benchmarks/suite_<size>.json` (smooth head),",
             "`suite_<size>_detailed.json` (detailed heads) and `suite_<size>_photo.json` (detailed heads with a photograph's",
             "face, `--head photo`); rerunning the suite",
             "regenerates this file. Rows: the tracking ceiling (the capture's ground truth drawn on its tracked FLAME",
             "fit, no training), SAGE (MV-SF, one training timestep), its ablations (w/o attribute MLPs, w/o phase 2,",
             "w/o correction, w/o wrinkle shading, w/o the world light), GaussianAvatars (per-face surfels with density",
             "control, photometric loss only, no SDF, no phase 2) on one timestep (MV-SF) and all training timesteps",
             "(MV-MF), free surfels on SAGE's layout, and SAGE in the single-view head-rotation (SV-HR) and one-shot",
             "regimes. All rows of a size share the seed and train on tracked captures (`sage synth --tracking fitted`:",
             "FLAME parameters fitted to a ground truth the written model cannot fully express, plus pose noise;",
             "docs/synthetic.md), except `sage_exact`, SAGE MV-SF on the exact multiview capture (`--tracking exact`:",
             "the parameters are the truth). Each size's section names its synthetic heads: detailed (pixel-scale skin and",
             "hair detail, hair volume off the scalp; every row on two subjects, numbers averaged), the same with a real",
             "photograph's face as the skin, or the smooth head of earlier versions.", ""]  # fmt: skip
    heads = {"smooth": 0, "detailed": 1, "photo": 2}
    for d in sorted(docs, key=lambda d: (order.get(str(d.get("size")), 9), heads.get(_head(d)[0], 9))):
        parts.append(render_markdown(d))
    if discussion:
        parts += ["", rebase_links(discussion.strip(), "benchmarks")]
    return "\n".join(parts).rstrip() + "\n"


_LINK = re.compile(r"(\]\()([^)\s]+)(\))")


def rebase_links(markdown: str, folder: str) -> str:
    """Relative link targets of ``markdown`` written from ``folder`` (relative to docs/), rewritten
    to hold from docs/ itself: the discussion lives in docs/benchmarks/ and is copied into
    docs/results.md. Absolute, scheme and anchor-only targets are left alone."""

    def fix(m: re.Match[str]) -> str:
        target = m.group(2)
        if target.startswith(("#", "/")) or re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
            return m.group(0)
        return m.group(1) + posixpath.normpath(posixpath.join(folder, target)) + m.group(3)

    return _LINK.sub(fix, markdown)


__all__ = ["SCHEMA", "machine_info", "merge_results", "rebase_links", "render_markdown", "render_document"]
