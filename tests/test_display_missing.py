"""A metric that was not measured (None or NaN: e.g. val PSNR of an SV-HR or one-shot workspace,
which has no val split) shows as a dash in the CLI panels, progress line, `sage info`, the batch
summary and the benchmark Markdown tables, never as "nan"."""

from __future__ import annotations

import io
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from rich.console import Console

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from _suite import report  # noqa: E402

from sage_cli import _common  # noqa: E402
from sage_cli._common import MISSING, fmt_metric  # noqa: E402

NAN = float("nan")


@pytest.mark.parametrize("v", [None, NAN, np.float32("nan"), np.nan, "12.5", True, [1.0], {}])
def test_absent_values_are_the_dash(v):
    assert fmt_metric(v) == MISSING == "\u2014"
    assert fmt_metric(v, ".2f") == MISSING


@pytest.mark.parametrize(
    ("v", "spec", "text"),
    [(31.23456, ".2f", "31.23"), (0.91234, ".4f", "0.9123"), (12345.678, ".4g", "1.235e+04"), (3, ".2f", "3.00"),
     (np.float32(0.5), ".3f", "0.500"), (np.int64(7), "d", "7"), (math.inf, ".2f", "inf"), (0.0, ".1f", "0.0")],
)  # fmt: skip
def test_measured_values_are_formatted(v, spec, text):
    assert fmt_metric(v, spec) == text


def test_progress_line_and_panel_values():
    assert _common._fmt_stat("val_psnr", NAN) == "val_psnr \u2014"
    assert _common._fmt_stat("psnr", 21.4567) == "psnr 21.46"
    assert _common._fmt_stat("step", 3) == "step 3"
    assert _common._fmt_value(NAN) == MISSING and _common._fmt_value(0.25) == "0.25"
    assert _common._fmt_value([1.5, NAN]) == "1.5, \u2014"


def test_summary_panel_shows_the_dash(monkeypatch):
    con = Console(width=120, record=True, file=io.StringIO())
    monkeypatch.setattr(_common, "console", con)
    _common.summary_panel("sage phase1", [("val PSNR", NAN), ("train PSNR", 24.5)])
    text = con.export_text()
    assert "val PSNR" in text and MISSING in text and "24.5" in text and "nan" not in text


def test_info_metrics_of_a_single_camera_phase1():
    from sage_cli.commands.info import _metrics

    text = _metrics("phase1", {"metrics": {"val_psnr": NAN, "train_psnr": 24.125, "chamfer_rel": 0.0123, "regime": "sv-hr"}})
    assert text.splitlines() == ["val_psnr \u2014", "train_psnr 24.12", "chamfer_rel 0.0123"]


def test_eval_tables_and_panel_values():
    from sage_cli.commands.eval_cmd import _fmt, _means, metrics_rows

    m = {"count": 4, "psnr": 25.0, "psnr_ga": NAN, "ssim": 0.9, "lpips": None}
    doc = {"per_camera": {"8": m, "10": m}, "overall": m}
    rows = metrics_rows(doc)
    assert [r[0] for r in rows] == ["camera 8", "camera 10", "all"]
    assert rows[-1] == ("all", "4", "25.00", MISSING, "0.9000", MISSING)
    assert _means(m) == f"25.00 dB / 0.9000 / {MISSING}"
    assert _fmt("unavailable", 2) == "unavailable"


def test_phase2_panel_means():
    from sage_cli.commands.phase2 import _fmt_means

    assert _fmt_means(None) == MISSING and _fmt_means({}) == MISSING
    assert _fmt_means({"psnr": NAN, "ssim": 0.8, "lpips": None}) == f"{MISSING} dB / 0.8000 / LPIPS {MISSING}"
    assert _fmt_means({"psnr": 22.0, "ssim": 0.8, "lpips": 0.1}) == "22.00 dB / 0.8000 / LPIPS 0.1000"


def test_batch_tables():
    from sage_cli.commands.batch_cmd import _table
    from sage_core.batch import SubjectOutcome, summary_markdown

    o = SubjectOutcome("s1", "finished", "/ws", 12.0, {"val_psnr": NAN, "val_ssim": None, "test_psnr": 23.456, "test_ssim": 0.9})
    md = summary_markdown([o])
    assert f"| s1 | finished |  | 12.0 | {MISSING} | {MISSING} | 23.46 | 0.9000 | {MISSING} | {MISSING} |" in md and "nan" not in md
    con = Console(width=160, record=True, file=io.StringIO())
    con.print(_table({"s1": {"state": "finished", "psnr": NAN}, "s2": {"state": "running", "psnr": 20.5}}))
    text = con.export_text()
    assert "nan" not in text and MISSING in text and "20.50" in text


def test_benchmark_tables_treat_nan_as_missing():
    assert report.fmt(NAN, 2) == report.DASH == MISSING and report.fmt(1.0, 1) == "1.0"
    assert report._delta(NAN, 30.0) is None and report._delta(31.0, None) is None
    assert report._delta(31.5, 30.0) == pytest.approx(1.5)
    row = lambda rid, val, test: {  # noqa: E731
        "id": rid, "label": rid, "input_type": "MV-SF",
        "metrics": {"val": {"overall": {"psnr": val, "ssim": NAN, "lpips": None}}, "test": {"overall": {"psnr": test, "ssim": 0.9, "lpips": None}}},
    }  # fmt: skip
    results = {"rows": {"sage": row("sage", NAN, 25.0), "no_mlp": row("no_mlp", 30.0, 24.0)}}
    comparison = report._comparison(results)
    text = "\n".join(comparison + report._rendering_table(list(results["rows"].values())))
    assert re.search(r"\bnan\b", text, re.IGNORECASE) is None
    cells = [c.strip() for c in next(line for line in comparison if line.startswith("| no_mlp")).split("|")]
    assert cells[3] == "30.00" and cells[5] == "24.00"
    assert cells[6] == f"+0.16 / {MISSING}"  # Δ val: ours is missing (SAGE's val PSNR is NaN)
    assert cells[7] == "-1.92 / -1.00" and cells[8] == "yes"


def test_phase1_panel_of_a_one_shot_workspace_says_it_has_no_test_or_val_frames(monkeypatch, tmp_path):
    from types import SimpleNamespace

    from sage_cli.commands import phase1 as p1

    con = Console(width=140, record=True, file=io.StringIO())
    monkeypatch.setattr(_common, "console", con)
    m = {"attributes": "mlp", "n_surfels": 6000, "val_psnr": NAN, "val_ssim": NAN, "val_images": 0, "train_psnr": 22.28,
         "train_ssim": 0.9487, "test_psnr": NAN, "test_ssim": NAN, "test_images": 0, "regime": "one-shot", "chamfer_m": 0.001,
         "chamfer_rel": 0.003, "normal_error_deg": 9.5, "iterations_per_s": 5.0}  # fmt: skip
    p1.show(SimpleNamespace(manifest={"metrics": m, "wall_time_s": 276.1}), tmp_path)
    text = con.export_text()
    assert "no test frames" in text and "no val frames" in text and "22.28 dB" in text and "nan" not in text.lower()
