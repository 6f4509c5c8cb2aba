"""The benchmark suite (benchmarks/suite.py): row definitions -> CLI arguments, the results
document (Markdown tables, merging partial runs), the subprocess runner, stage copies between
workspaces, and one end-to-end smoke run of two rows."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

from _suite import ROW_IDS, SIZES, Settings, merge_results, parse_overrides, plan, render_markdown, run_process, smoke_size  # noqa: E402
from _suite.execute import step_command  # noqa: E402
from _suite.report import DASH, render_document  # noqa: E402
from _suite.workspaces import copy_stages  # noqa: E402
from helpers import LPIPS_WEIGHTS  # noqa: E402


def _settings(tmp_path: Path, **kw) -> Settings:
    return Settings(SIZES["tiny"], tmp_path / "out", lpips_weights=Path("/w/lpips.pth"), **kw)


def _steps(tmp_path: Path, rows=ROW_IDS, **kw):
    steps, needs = plan(_settings(tmp_path, **kw), list(rows))
    return {s.key: s for s in steps}, needs, steps


def _flag(argv: list[str], name: str) -> str:
    return argv[argv.index(name) + 1]


def _sets(argv: list[str]) -> list[str]:
    return [argv[i + 1] for i, a in enumerate(argv) if a == "--set"]


# --------------------------------------------------------------------------------------------
# rows -> commands
# --------------------------------------------------------------------------------------------


def test_rows_map_to_the_expected_cli_arguments(tmp_path):
    by_key, needs, _ = _steps(tmp_path)
    p1 = by_key["sage:phase1"].argv
    assert p1[:2] == ["phase1", str(tmp_path / "out/ws/sage")] and _flag(p1, "--attributes") == "mlp"
    assert _flag(p1, "--preset") == "tiny" and _flag(p1, "--seed") == "0"
    assert _flag(by_key["no_mlp:phase1"].argv, "--attributes") == "free"
    assert _flag(by_key["no_correction:phase2"].argv, "--correction") == "off"
    assert "--correction" not in by_key["sage:phase2"].argv
    for rid in ("ga_mvsf", "ga_mvmf", "free_mvsf"):
        a = by_key[f"{rid}:phase1"].argv
        assert _flag(a, "--attributes") == "free"
        assert {"sdf_from=1000000000", "w_normal_consistency=0", "w_distortion=0", "w_mask=0"} <= set(_sets(a))
        assert f"{rid}:phase2" not in by_key
        assert _flag(by_key[f"{rid}:eval:all"].argv, "--stage") == "phase1"
    # GaussianAvatars: per-face init, density control on the size's schedule, no rebinding, its own
    # init-mesh with teeth and no cavity; the free-surfel row keeps SAGE's layout and init-mesh
    for rid in ("ga_mvsf", "ga_mvmf"):
        sets = set(_sets(by_key[f"{rid}:phase1"].argv))
        assert {"init_layout=per_face", "init_opacity=0.1", "densify=true", "rebind_every=0", "w_local_position=0.01", "w_local_scale=1",
                "densify_from=25", "densify_every=100", "densify_until=1500", "opacity_reset_every=500"} <= sets
        assert "mouth_cavity=false" in _sets(by_key[f"{rid}:init-mesh"].argv)
    assert by_key["ga_mvsf:copy"].stages == ("ingest",) and by_key["free_mvsf:copy"].stages == ("ingest", "init-mesh")
    assert not any("densify" in kv or "init_layout" in kv for kv in _sets(by_key["free_mvsf:phase1"].argv))
    assert "free_mvsf:init-mesh" not in by_key
    assert _flag(by_key["ga_mvmf:ingest"].argv, "--regime") == "mv-mf"
    assert _flag(by_key["sage:ingest"].argv, "--regime") == "mv-sf"
    assert _flag(by_key["sv_hr:ingest"].argv, "--regime") == "sv-hr"
    assert _flag(by_key["one_shot:ingest"].argv, "--regime") == "one-shot"
    assert _flag(by_key["synth:monocular"].argv, "--regime") == "monocular"
    # multiview rows train on the tracked capture; sage_exact is SAGE on the exact one
    assert _flag(by_key["synth:multiview"].argv, "--tracking") == "fitted"
    assert _flag(by_key["synth:multiview_exact"].argv, "--tracking") == "exact"
    assert _flag(by_key["synth:multiview_exact"].argv, "--regime") == "multiview"
    assert by_key["synth:multiview_exact"].argv[1] == str(tmp_path / "out/captures/multiview_exact")
    assert _flag(by_key["sage_exact:ingest"].argv, "--regime") == "mv-sf"
    assert "/captures/multiview_exact/" in _flag(by_key["sage_exact:ingest"].argv, "--flame-model")
    assert "synth:multiview_exact" in needs["sage_exact"] and "synth:multiview" not in needs["sage_exact"]
    assert all("synth:multiview_exact" not in needs[r] for r in ROW_IDS if r != "sage_exact")
    assert _flag(by_key["sage_exact:phase1"].argv, "--attributes") == "mlp" and "sage_exact:phase2" in by_key
    assert _flag(by_key["sv_hr:eval:novel"].argv, "--split") == "novel"
    assert _flag(by_key["one_shot:eval:novel"].argv, "--split") == "novel"
    assert "one_shot:reenact" not in by_key
    # w/o phase 2 evaluates the SAGE phase-1 avatar copied from the sage workspace
    ev = by_key["no_phase2:eval:all"].argv
    assert _flag(ev, "--stage") == "phase1" and _flag(ev, "--lpips-weights") == "/w/lpips.pth"
    assert "no_phase2:phase1" not in by_key and "no_phase2:phase2" not in by_key
    assert by_key["no_phase2:copy"].stages == ("ingest", "init-mesh", "phase1")
    assert by_key["no_mlp:copy"].stages == ("ingest", "init-mesh")
    assert "sage:phase1" in needs["no_phase2"] and "sage:phase2" not in needs["no_phase2"]
    # phase 2's own evaluation is cut: the suite evaluates with `sage eval`
    assert "eval_phase1=false" in _sets(by_key["sage:phase2"].argv)


def test_ga_schedule_is_gaussian_avatars_scaled_to_each_preset():
    """GA's fractions of its 600,000 steps (start 1/60, interval 1/300, resets 1/10, to the end); at
    the full size exactly, at the short ones with the intervals floored."""
    from _suite.rows import MIN_DENSIFY_EVERY, MIN_RESET_EVERY, ga_schedule, preset_iterations

    def parsed(items):
        return {k: int(v) for k, v in (kv.split("=") for kv in items)}

    assert parsed(ga_schedule(600_000)) == {"densify_from": 10_000, "densify_every": 2_000, "densify_until": 600_000,
                                            "opacity_reset_every": 60_000}
    assert parsed(SIZES["full"].densify) == {"densify_from": 500, "densify_every": 100, "densify_until": 30_000, "opacity_reset_every": 3_000}
    for name, preset in (("tiny", "tiny"), ("small", "small"), ("full", "default")):
        d, n = parsed(SIZES[name].densify), preset_iterations(preset)
        assert d["densify_until"] == n and d["densify_from"] == round(n / 60)
        assert d["densify_every"] == max(MIN_DENSIFY_EVERY, round(n / 300)) and d["opacity_reset_every"] == max(MIN_RESET_EVERY, round(n / 10))


def test_the_ceiling_row_trains_nothing_and_renders_the_tracked_truth(tmp_path):
    by_key, needs, _ = _steps(tmp_path, rows=("ceiling",))
    assert by_key["ceiling:copy"].stages == ("ingest",) and "sage:ingest" in needs["ceiling"]
    assert not any(k.startswith("ceiling:") and k.split(":")[1] in ("init-mesh", "phase1", "phase2", "reenact") for k in by_key)
    assert not any(k.startswith("sage:") and k != "sage:ingest" for k in by_key)
    step = by_key["ceiling:eval:test"]
    assert step.kind == "ceiling" and step.split == "test" and step.out == tmp_path / "out/ws/ceiling"
    assert step.capture == tmp_path / "out/captures/multiview" and step.lpips_weights == Path("/w/lpips.pth")
    cmd = step_command(step)
    assert cmd.startswith('python -c "from sage_core.evaluate.ceiling import evaluate_ceiling;') and "'test'" in cmd


def test_plan_is_deduplicated_and_ordered(tmp_path):
    by_key, needs, steps = _steps(tmp_path, rows=("no_phase2", "sage", "ga_mvsf"))
    keys = [s.key for s in steps]
    assert len(keys) == len(set(keys))
    assert keys.count("synth:multiview") == 1
    pos = {k: i for i, k in enumerate(keys)}
    for s in steps:
        assert all(pos[d] < pos[s.key] for d in s.deps), s.key
    assert pos["sage:phase1"] < pos["no_phase2:copy"]
    assert set(needs) == {"no_phase2", "sage", "ga_mvsf"}
    assert step_command(by_key["no_phase2:copy"]).startswith("mkdir -p ")
    assert step_command(by_key["sage:phase1"]).startswith("sage phase1 ")
    with pytest.raises(ValueError, match="unknown row"):
        plan(_settings(tmp_path), ["nope"])


def test_overrides_and_smoke_size_reach_the_commands(tmp_path):
    ov = parse_overrides(["phase1:iterations=7", "phase2:iterations=3"])
    assert ov == {"phase1": ("iterations=7",), "phase2": ("iterations=3",)}
    with pytest.raises(ValueError):
        parse_overrides(["iterations=7"])
    by_key, _, _ = _steps(tmp_path, rows=("sage",), overrides=ov)
    assert "iterations=7" in _sets(by_key["sage:phase1"].argv)
    assert "iterations=3" in _sets(by_key["sage:phase2"].argv)
    smoke = smoke_size(SIZES["tiny"])
    st = Settings(smoke, tmp_path)
    steps, _ = plan(st, ["sage"])
    k = {s.key: s for s in steps}
    assert smoke.smoke and _flag(k["synth:multiview"].argv, "--cameras") == "9"
    assert any(s.startswith("iterations=") for s in _sets(k["sage:phase1"].argv))
    assert SIZES["full"].preset == "default" and SIZES["tiny"].preset == "tiny" and SIZES["small"].preset == "small"


def test_every_row_runs_on_each_subject_with_the_chosen_head(tmp_path):
    by_key, needs, steps = _steps(tmp_path, rows=("sage", "one_shot"))
    # subject 0 keeps the plain keys and paths, subject 1 (capture seed 1) is prefixed and suffixed
    a, b = by_key["synth:multiview"].argv, by_key["seed1/synth:multiview"].argv
    assert _flag(a, "--seed") == "0" and _flag(b, "--seed") == "1"
    assert _flag(a, "--appearance") == _flag(b, "--appearance") == "detailed"
    assert b[1] == str(tmp_path / "out/captures/multiview_seed1")
    p1 = by_key["seed1/sage:phase1"].argv
    assert p1[1] == str(tmp_path / "out/ws/sage_seed1") and _flag(p1, "--seed") == "0"  # stages keep the suite's seed
    assert "/captures/multiview_seed1/" in _flag(by_key["seed1/sage:ingest"].argv, "--flame-model")
    assert by_key["seed1/sage:phase1"].deps == ["seed1/sage:init-mesh"] and by_key["seed1/sage:phase1"].subject == 1
    assert by_key["seed1/one_shot:eval:novel"].argv[1] == str(tmp_path / "out/ws/one_shot_seed1")
    assert by_key["seed1/motion:multiview"].out == tmp_path / "out/motions/multiview_seed1_test.npz"
    assert {"sage:phase2", "seed1/sage:phase2"} <= set(needs["sage"]) and "seed1/sage:phase2" not in needs["one_shot"]
    keys = [s.key for s in steps]
    assert keys.index("one_shot:eval:novel") < keys.index("seed1/synth:multiview")  # the first subject's rows first
    # the smooth head of earlier versions, one subject: the plan of earlier versions plus --appearance smooth
    smooth, _, _ = _steps(tmp_path, rows=("sage",), head="smooth", subjects=1)
    assert not any(k.startswith("seed") for k in smooth) and _flag(smooth["synth:multiview"].argv, "--appearance") == "smooth"


def test_the_photo_head_tracks_the_photograph_once_and_skins_every_subject_with_it(tmp_path):
    by_key, needs, steps = _steps(tmp_path, rows=("sage", "one_shot"), head="photo")
    photo = tmp_path / "out/photo/tiny"
    model, track = by_key["photo:model"], by_key["photo:track"]
    # one model of the size's head grid and one track of the photograph, shared by every subject
    assert [s.key for s in steps].count("photo:track") == 1 and [s.key for s in steps][:2] == ["photo:model", "photo:track"]
    assert model.argv[:2] == ["synth", str(photo / "model_head")] and _flag(model.argv, "--preset") == "tiny"
    assert track.argv[:3] == ["track", str(photo / "astronaut.png"), str(photo / "capture")] and track.deps == ["photo:model"]
    assert _flag(track.argv, "--flame-model") == str(photo / "model_head/model/synth_flame.npz")
    for key in ("synth:multiview", "seed1/synth:multiview", "synth:oneshot", "seed1/synth:oneshot"):
        a = by_key[key].argv
        assert _flag(a, "--appearance") == "detailed" and _sets(a) == [f"skin_photo={photo / 'capture'}"], key
        assert by_key[key].deps == ["photo:track"]
    assert needs["sage"].count("photo:track") == 1 and "photo:track" in needs["one_shot"]
    assert "novel" in [k.rsplit(":", 1)[1] for k in by_key if k.startswith("sage:eval:")]  # a detailed head's novel views
    assert step_command(track).startswith("python -c ") and " && sage track " in step_command(track)
    # the other heads have no photo steps and no skin_photo
    assert not any(k.startswith("photo:") for k in _steps(tmp_path, rows=("sage",))[0])


def test_the_photo_head_is_refused_without_the_face_models(tmp_path, monkeypatch, capsys):
    import suite

    empty = tmp_path / "no_models"
    empty.mkdir()
    monkeypatch.setenv("SAGE_MEDIAPIPE_DIR", str(empty))
    with pytest.raises(SystemExit) as exc:
        suite.main(["--size", "tiny", "--out", str(tmp_path / "out"), "--rows", "sage", "--head", "photo", "--docs", str(tmp_path / "docs")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--head photo tracks a photograph with `sage track`" in err and str(empty) in err
    assert not (tmp_path / "out").exists() and not (tmp_path / "docs").exists()  # nothing started


def test_the_photo_steps_track_the_photograph_once(tmp_path):
    from track_helpers import models_or_skip

    from _suite.execute import run_step
    from _suite.rows import photo_steps

    models_or_skip()
    st = Settings(SIZES["tiny"], tmp_path / "out", head="photo")
    model, track = photo_steps(st)
    first = [run_step(s, st, None, False) for s in (model, track)]
    assert [r["rc"] for r in first] == [0, 0] and all(r["ran"] for r in first), first
    assert (st.photo_dir / "astronaut.png").is_file() and (st.photo_dir / "capture" / "track" / "report.json").is_file()
    assert first[1]["command"].startswith("python -c ") and "sage track " in first[1]["command"]
    again = run_step(track, st, first[1], False)  # current: neither the photo nor the track is redone
    assert again["rc"] == 0 and not again["ran"] and again["note"] == "capture already present"


def test_photo_track_is_current_only_for_the_same_photograph_model_and_seed(tmp_path):
    import time

    from _suite.workspaces import track_is_current

    model = tmp_path / "model.npz"
    model.write_bytes(b"m")
    cap = tmp_path / "cap"
    argv = ["track", str(tmp_path / "a.png"), str(cap), "--flame-model", str(model), "--seed", "0", "--quiet"]
    assert not track_is_current(cap, argv)  # nothing tracked yet
    (cap / "track").mkdir(parents=True)
    report = {"input": {"path": str(tmp_path / "a.png")}, "flame_model": str(model), "seed": 0}
    (cap / "track" / "report.json").write_text(json.dumps(report))
    assert track_is_current(cap, argv)
    assert not track_is_current(cap, [*argv[:-3], "--seed", "1", "--quiet"])
    assert not track_is_current(cap, ["track", str(tmp_path / "b.png"), *argv[2:]])
    later = time.time() + 5
    os.utime(model, (later, later))  # the model was rewritten after the track
    assert not track_is_current(cap, argv)


def test_capture_check_follows_the_appearance(tmp_path):
    from _suite.workspaces import capture_is_current

    from sage_core.data.synthetic import preset

    cap = tmp_path / "cap"
    (cap / "gt").mkdir(parents=True)
    cfg = preset("tiny", "oneshot", seed=1, tracking="fitted", appearance="detailed")
    (cap / "gt" / "info.json").write_text(json.dumps({"config": cfg.to_dict()}))
    argv = ["synth", str(cap), "--regime", "oneshot", "--tracking", "fitted", "--preset", "tiny", "--seed", "1", "--quiet"]
    assert capture_is_current(cap, argv) and capture_is_current(cap, [*argv[:-1], "--appearance", "detailed"])
    assert not capture_is_current(cap, [*argv[:-1], "--appearance", "smooth"])
    assert not capture_is_current(cap, [*argv[:-3], "--seed", "2"])
    # the photo head's captures: the skin photo is part of the config (by its folder's name)
    cfg = preset("tiny", "oneshot", seed=1, tracking="fitted", appearance="detailed", skin_photo=str(tmp_path / "photo/capture"))
    (cap / "gt" / "info.json").write_text(json.dumps({"config": cfg.to_dict()}))
    with_photo = [*argv[:-3], "--set", f"skin_photo={tmp_path / 'photo/capture'}", "--seed", "1", "--quiet"]
    assert capture_is_current(cap, with_photo) and not capture_is_current(cap, argv)
    assert not capture_is_current(cap, [*argv[:-3], "--set", "skin_photo=elsewhere", "--seed", "1", "--quiet"])
    assert not capture_is_current(cap, [*argv[:-3], "--set", "no_such_key=1", "--seed", "1", "--quiet"])


def test_subject_numbers_are_averaged_and_counts_summed():
    from _suite.execute import mean_tree

    a = {"test": {"overall": {"psnr": 20.0, "ssim": 0.8, "lpips": None, "count": 4}, "frontal": None},
         "novel": {"view_groups": {"back": {"overall": {"psnr": 12.0, "count": 2}}}}, "images": 4}  # fmt: skip
    b = {"test": {"overall": {"psnr": 22.0, "ssim": 0.9, "lpips": 0.1, "count": 4}, "frontal": {"psnr": 25.0, "count": 1}},
         "novel": {"view_groups": {"back": {"overall": {"psnr": 14.0, "count": 2}}}}, "images": 4}  # fmt: skip
    m = mean_tree([a, b])
    assert m["test"]["overall"] == {"psnr": 21.0, "ssim": pytest.approx(0.85), "lpips": 0.1, "count": 8}
    assert m["test"]["frontal"] == {"psnr": 25.0, "count": 1} and m["images"] == 8
    assert m["novel"]["view_groups"]["back"]["overall"]["psnr"] == 13.0
    assert mean_tree([None, None]) is None


# --------------------------------------------------------------------------------------------
# results document
# --------------------------------------------------------------------------------------------


def _m(psnr, ssim, lpips, count=4):
    return {"psnr": psnr, "ssim": ssim, "lpips": lpips, "count": count}


def _results() -> dict:
    sage = {
        "id": "sage", "label": "SAGE", "input_type": "MV-SF", "has_sdf": True, "errors": [],
        "steps": ["synth:multiview", "sage:phase1"],
        "metrics": {"val": {"overall": _m(31.25, 0.9512, 0.0612)},
                    "test": {"overall": _m(24.5, 0.8811, 0.1011), "frontal": _m(25.75, 0.9022, 0.0833)}},
        "geometry": {"chamfer_mm": 1.234, "chamfer_rel_pct": 0.456, "normal_error_deg": 7.89},
        "stages": {"phase1": {"wall_time_s": 301.0, "iterations_per_s": 4.98, "chamfer_m": 0.002},
                   "phase2": {"wall_time_s": 61.5, "iterations_per_s": 5.5}},
        "reenact": {"render_fps": 12.34}, "peak_rss_mib": 1500.0, "gpu_peak_mib": None,
    }  # fmt: skip
    sage["capture"], sage["capture_tracking"] = "multiview", {"mode": "fitted", "error": {"all": {"mean_mm": 1.8765, "max_mm": 6.5,
                                                                                           "face_mean_mm": 2.25}}}  # fmt: skip
    sage_exact = {**sage, "id": "sage_exact", "label": "SAGE on the exact capture", "capture": "multiview_exact",
                  "capture_tracking": {"mode": "exact"}, "metrics": {"val": {"overall": _m(33.5, 0.97, 0.05)}}}  # fmt: skip
    no_phase2 = {
        "id": "no_phase2", "label": "w/o phase 2", "input_type": "MV-SF", "has_sdf": True, "errors": [],
        "steps": ["synth:multiview", "sage:phase1", "no_phase2:copy"],
        "metrics": {"val": {"overall": _m(31.75, 0.95, 0.06)}, "test": {"overall": _m(22.0, 0.85, 0.12), "frontal": None}},
        "stages": {"phase1": {"wall_time_s": 301.0, "shared": True}},
    }  # fmt: skip
    ga = {
        "id": "ga_mvsf", "label": "GA-style", "input_type": "MV-SF", "has_sdf": False, "errors": ["ga_mvsf:eval:all: exit 3: boom happened"],
        "steps": ["ga_mvsf:phase1"], "metrics": {}, "stages": {},
    }  # fmt: skip
    return {
        "schema": 1, "size": "tiny", "smoke": False, "suite_command": "python benchmarks/suite.py --size tiny --out X",
        "machine": {"cpu": "Test CPU", "cores": 2, "usable_cores": 2, "device": "cpu", "torch": "2.x"},
        "settings": {"preset": "tiny", "seed": 0}, "runs": [],
        "steps": {"synth:multiview": {"command": "sage synth X"}, "sage:phase1": {"command": "sage phase1 WS"},
                  "no_phase2:copy": {"command": "mkdir -p A && cp -a B A/"}, "ga_mvsf:phase1": {"command": "sage phase1 GA"}},
        "rows": {"sage": sage, "sage_exact": sage_exact, "no_phase2": no_phase2, "ga_mvsf": ga},
    }  # fmt: skip


def _table_rows(md: str, heading: str) -> tuple[list[str], dict[str, list[str]]]:
    """Header cells and row cells (keyed by the row id in backticks) of the first table after ``heading``."""
    lines = md.splitlines()
    i = lines.index(heading)
    while not lines[i].startswith("|"):
        i += 1
    header = [c.strip() for c in lines[i].strip("|").split("|")]
    rows = {}
    i += 2
    while i < len(lines) and lines[i].startswith("|"):
        cells = [c.strip() for c in lines[i].strip().strip("|").split(" | ")]
        rid = cells[0].split("`")[1]
        rows[rid] = cells
        i += 1
    return header, rows


def test_markdown_puts_numbers_in_their_columns_and_dashes_for_missing():
    md = render_markdown(_results())
    header, rows = _table_rows(md, "### Novel view and self-reenactment (multiview rows)")
    col = {h: j for j, h in enumerate(header)}
    s = rows["sage"]
    assert s[col["Val PSNR"]] == "31.25" and s[col["Val SSIM"]] == "0.9512" and s[col["Val LPIPS"]] == "0.0612"
    assert s[col["Frontal PSNR"]] == "25.75" and s[col["Frontal LPIPS"]] == "0.0833"
    assert s[col["All PSNR"]] == "24.50" and s[col["All SSIM"]] == "0.8811" and s[col["All LPIPS"]] == "0.1011"
    n = rows["no_phase2"]
    assert n[col["Frontal PSNR"]] == DASH and n[col["All PSNR"]] == "22.00"
    g = rows["ga_mvsf"]
    assert g[col["Val PSNR"]] == DASH and "boom happened" in g[col["Notes"]] and g[col["Notes"]].startswith("error:")
    assert "no_mlp" not in rows  # rows absent from the document are not invented
    assert rows["sage_exact"][col["Val PSNR"]] == "33.50" and rows["sage_exact"][col["All PSNR"]] == DASH
    assert "- Capture `multiview`: tracked, vertex error of the written FLAME parameters mean 1.88 mm, face region 2.25 mm" in md
    assert "- Capture `multiview_exact`: exact" in md
    gh, grows = _table_rows(md, "### Geometry")
    gc = {h: j for j, h in enumerate(gh)}
    assert grows["sage"][gc["Chamfer to GT (mm)"]] == "1.234" and grows["sage"][gc["Normal error (deg)"]] == "7.89"
    assert grows["sage"][gc["Chamfer to FLAME mesh (mm)"]] == "2.000"
    assert all(c == DASH for c in grows["ga_mvsf"][1:])
    ch, crows = _table_rows(md, "### Cost")
    cc = {h: j for j, h in enumerate(ch)}
    assert crows["sage"][cc["phase 1 (s)"]] == "301.0" and crows["no_phase2"][cc["phase 1 (s)"]] == "301.0*"
    assert crows["sage"][cc["phase 1 it/s"]] == "4.98" and crows["sage"][cc["reenact FPS"]] == "12.34"
    assert crows["sage"][cc["peak RSS (MiB)"]] == "1500" and crows["sage"][cc["peak GPU (MiB)"]] == DASH
    # comparison with the paper: differences computed from the JSON, with the paper's beside them
    assert "### Comparison with the paper" in md
    _, comp = _table_rows(md, "Ablations (novel view = val split, self-reenactment = test split, all cameras):")
    assert "-2.50" in comp["no_phase2"][6] and "-4.46" in comp["no_phase2"][6]  # ours 22.00-24.50, paper 22.18-26.64
    assert comp["no_phase2"][7] == "yes"
    assert "- `ga_mvsf`: ga_mvsf:eval:all: exit 3: boom happened" in md
    assert "sage phase1 WS" in md and "mkdir -p A && cp -a B A/" in md
    doc = render_document([{**_results(), "size": "full"}, {**_results(), "size": "small"}, _results()])
    assert doc.index("## Size `tiny`") < doc.index("## Size `small`") < doc.index("## Size `full`")
    doc = render_document([_results()], "## Discussion\n\nOurs against the paper.\n")
    assert doc.rstrip().endswith("Ours against the paper.") and doc.index("## Size `tiny`") < doc.index("## Discussion")


def test_markdown_shows_the_head_the_subjects_and_the_back_views():
    doc = _results()
    doc["head"], doc["subject_seeds"] = "detailed", [0, 1]
    one = {"id": "one_shot", "label": "SAGE", "input_type": "One-shot", "has_sdf": True, "errors": [], "steps": [], "capture": "oneshot",
           "metrics": {"novel": {"overall": _m(18.5, 0.8, 0.2, 20), "view_groups": {"back": {"overall": _m(11.25, 0.6, 0.4, 8)}}}}}  # fmt: skip
    one["subjects"] = [{"seed": 0, "hair": "bob", "metrics": {"novel": {"overall": _m(18.0, 0.8, 0.2, 10)}}},
                       {"seed": 1, "hair": "short", "metrics": {"novel": {"overall": _m(19.0, 0.8, 0.2, 10),
                                                                          "view_groups": {"back": {"overall": _m(11.5, 0.6, 0.4)}}}}}]  # fmt: skip
    doc["rows"]["one_shot"] = one
    md = render_markdown(doc)
    assert "- Synthetic heads: detailed (`sage synth --appearance detailed`), 2 subjects (capture seeds 0, 1)" in md
    header, rows = _table_rows(md, "### Single-view and one-shot regimes")
    col = {h: j for j, h in enumerate(header)}
    assert rows["one_shot"][col["Held-out GT PSNR"]] == "18.50" and rows["one_shot"][col["Back views PSNR"]] == "11.25"
    sh, srows = _table_rows(md, "### Per subject")
    lines = [ln for ln in md.split("### Per subject")[1].split("###")[0].splitlines() if ln.startswith("| SAGE (`one_shot`)")]
    assert len(lines) == 2 and "| 1 | short |" in lines[1] and "11.50" in lines[1] and "19.00" in lines[1]
    # an earlier document (no head recorded) is the smooth head with one subject, and is not merged with a detailed one
    old = _results()
    assert "- Synthetic heads: smooth (`sage synth --appearance smooth`), 1 subject (capture seed 0)" in render_markdown(old)
    assert "### Per subject" not in render_markdown(old)
    assert merge_results(old, doc) is doc
    assert "### Novel views of the training timestep" not in md  # no multiview row has novel views yet
    doc["rows"]["sage"]["metrics"]["novel"] = {"overall": _m(24.0, 0.9, 0.05, 12), "view_groups": {
        "front": {"overall": _m(25.14, 0.951, 0.0399, 6)}, "side": {"overall": _m(21.39, 0.889, 0.0802, 4)},
        "back": {"overall": _m(24.36, 0.881, 0.0685, 2)}}}
    md = render_markdown(doc)
    assert md.startswith("## Size `tiny`, detailed heads")
    header, rows = _table_rows(md, "### Novel views of the training timestep (multiview rows, detailed captures)")
    col = {h: j for j, h in enumerate(header)}
    assert list(rows) == ["sage"] and rows["sage"][col["Off-arc views PSNR"]] == "25.14" and rows["sage"][col["Back views PSNR"]] == "24.36"
    photo = {**doc, "head": "photo"}
    pmd = render_markdown(photo)
    assert pmd.startswith("## Size `tiny`, photo-skinned heads") and "--set skin_photo=OUT/photo/PRESET/capture" in pmd
    assert merge_results(doc, photo) is photo  # another head is never merged
    full = render_document([photo, doc, old])
    # the smooth head first, then the detailed heads, then the photo-skinned ones
    assert full.index("## Size `tiny`\n") < full.index("## Size `tiny`, detailed heads") < full.index("## Size `tiny`, photo-skinned heads")


def test_smoke_results_are_labelled():
    md = render_markdown({**_results(), "smoke": True})
    assert "Smoke test" in md.split("### Novel view")[0]


def test_merge_keeps_rows_that_were_not_rerun():
    old = _results()
    new = {**_results(), "rows": {"sage": {**_results()["rows"]["sage"], "label": "SAGE new"}, "no_mlp": {"id": "no_mlp", "errors": []}},
           "steps": {"x": {"command": "new"}}, "runs": [{"rows": ["sage", "no_mlp"]}]}  # fmt: skip
    old["runs"] = [{"rows": ["sage", "no_phase2", "ga_mvsf"]}]
    m = merge_results(old, new)
    assert set(m["rows"]) == {"sage", "sage_exact", "no_phase2", "ga_mvsf", "no_mlp"}
    assert m["rows"]["sage"]["label"] == "SAGE new" and m["rows"]["ga_mvsf"] == old["rows"]["ga_mvsf"]
    assert "x" in m["steps"] and "sage:phase1" in m["steps"]
    assert [r["rows"] for r in m["runs"]] == [["sage", "no_phase2", "ga_mvsf"], ["sage", "no_mlp"]]
    assert merge_results({**old, "size": "full"}, new) is new
    assert merge_results({**old, "smoke": True}, new) is new
    assert merge_results(None, new) is new


# --------------------------------------------------------------------------------------------
# runner and workspace copies
# --------------------------------------------------------------------------------------------


def test_memory_sampler_reads_the_peak_of_the_running_child(tmp_path):
    """The child holds 160 MiB until the test has sampled it (it waits for a line on its stdin): no
    timing involved."""
    import subprocess

    from _suite.runner import MemorySampler

    code = "import sys; b = bytearray(160 * 2**20); b[::4096] = b'x' * len(b[::4096]); print('ready', flush=True); sys.stdin.readline()"
    p = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert p.stdout.readline().strip() == b"ready"
        sampler = MemorySampler(p.pid, os.fsencode(sys.executable))
        assert MemorySampler(p.pid, b"/not/this/program").sample() is None  # only once it runs its own program
        v = sampler.sample()
        assert v is not None and 150 < v < 400 and sampler.peak == v
        p.stdin.write(b"done\n")
        p.stdin.flush()
    finally:
        p.communicate(timeout=60)
    assert sampler.sample() is None and sampler.peak == v  # gone: the peak stays


def test_run_process_keeps_the_exit_code_and_the_output(tmp_path):
    res = run_process([sys.executable, "-c", "import sys; print('made it'); sys.exit(3)"], tmp_path / "log.txt")
    assert res.rc == 3 and "made it" in res.tail and res.wall_s > 0
    # sampled only if the child lived past the first sample, possibly while it was still starting up
    assert res.peak_rss_mib is None or res.peak_rss_mib > 0
    assert "made it" in (tmp_path / "log.txt").read_text()


def _fake_stage(ws: Path, stage: str, requires: list[str], payload: str) -> dict:
    from sage_core.workspace import Workspace, begin_stage

    w = Workspace(ws)
    w.root.mkdir(parents=True, exist_ok=True)
    with w.lock:
        run = begin_stage(w, stage, {"p": payload}, f"h-{payload}", requires=requires, force=True)
        (run.work_dir / "out.txt").write_text(payload)
        return run.finish()


def test_copied_stages_are_complete_in_the_new_workspace_and_recopied_when_the_source_changes(tmp_path):
    from sage_core.workspace import Workspace

    src, dst = tmp_path / "src", tmp_path / "dst"
    _fake_stage(src, "ingest", [], "a")
    _fake_stage(src, "init-mesh", ["ingest"], "b")
    assert copy_stages(src, dst, ("ingest", "init-mesh")) == ["ingest", "init-mesh"]
    w = Workspace(dst)
    assert w.status("ingest").status == "complete" and w.status("init-mesh").status == "complete"
    assert (dst / "init" / "out.txt").read_text() == "b"
    # a stage run in the copy on top of the copied ones is fresh
    _fake_stage(dst, "phase1", ["init-mesh"], "c")
    assert w.status("phase1").status == "complete"
    assert copy_stages(src, dst, ("ingest", "init-mesh")) == []
    # the source's init-mesh is redone: the copy follows and the copy's phase1 becomes stale
    _fake_stage(src, "init-mesh", ["ingest"], "b2")
    assert copy_stages(src, dst, ("ingest", "init-mesh")) == ["init-mesh"]
    assert (dst / "init" / "out.txt").read_text() == "b2"
    assert w.status("phase1").status == "stale"
    from sage_core.errors import StageError

    with pytest.raises(StageError):
        copy_stages(src, tmp_path / "other", ("phase1",))


def _hold_lock(root, ready, release):
    from sage_core.workspace import Workspace

    with Workspace(root).lock:
        ready.set()
        release.wait(60)


def test_copying_finished_stages_does_not_need_the_source_lock(tmp_path):
    """A row copies its base row's ingest and init-mesh while another suite process trains the base
    row's phase 1 (and so holds its workspace lock)."""
    import multiprocessing as mp

    from sage_core.workspace import Workspace

    src, dst = tmp_path / "src", tmp_path / "dst"
    _fake_stage(src, "ingest", [], "a")
    _fake_stage(src, "init-mesh", ["ingest"], "b")
    ctx = mp.get_context("spawn")
    ready, release = ctx.Event(), ctx.Event()
    holder = ctx.Process(target=_hold_lock, args=(str(src), ready, release))
    holder.start()
    try:
        assert ready.wait(60)
        assert copy_stages(src, dst, ("ingest", "init-mesh")) == ["ingest", "init-mesh"]
    finally:
        release.set()
        holder.join(60)
    assert Workspace(dst).status("init-mesh").status == "complete"


def test_eval_metrics_are_read_only_while_current(tmp_path):
    from _suite.collect import eval_metrics

    from sage_core.workspace import Workspace, atomic_write_json, begin_stage

    ws = tmp_path / "ws"
    _fake_stage(ws, "ingest", [], "a")
    p1 = _fake_stage(ws, "phase1", ["ingest"], "p")
    w = Workspace(ws)
    with w.lock:
        run = begin_stage(w, "eval", {}, "e", requires=["ingest", "phase1"], force=True)
        doc = {"overall": {"psnr": 21.5, "ssim": 0.9, "lpips": None, "psnr_ga": 22.0, "count": 3}, "frontal": None,
               "frontal_camera": 8, "lpips_available": False, "counts": {"images": 3}}  # fmt: skip
        atomic_write_json(run.work_dir / "phase1" / "val" / "metrics.json", doc)
        atomic_write_json(run.work_dir / "results.json", {"phase1/val": {"avatar_stage": "phase1", "avatar_fingerprint": p1["fingerprint"],
                                                                         "files": ["phase1/val"]}})  # fmt: skip
        run.finish()
    m = eval_metrics(ws, "phase1", "val")
    assert m["overall"]["psnr"] == 21.5 and m["overall"]["lpips"] is None and m["frontal"] is None and m["images"] == 3
    with pytest.raises(FileNotFoundError):
        eval_metrics(ws, "phase1", "test")
    _fake_stage(ws, "phase1", ["ingest"], "p2")  # re-trained avatar: the old result no longer counts
    with pytest.raises(FileNotFoundError):
        eval_metrics(ws, "phase1", "val")


# --------------------------------------------------------------------------------------------
# end to end
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_suite_smoke_run_writes_json_and_markdown_and_a_rerun_skips_finished_stages(tmp_path):
    import suite

    docs, out = tmp_path / "docs", tmp_path / "out"
    # one subject keeps the suite's time in bounds; the mean over subjects is tested on its own (mean_tree)
    args = ["--size", "tiny", "--smoke", "--out", str(out), "--rows", "no_phase2,ceiling", "--device", "cpu", "--docs", str(docs),
            "--subjects", "1"]
    assert suite.main(args) == 0
    # detailed heads go to a file of their own, beside the smooth head's (suite_tiny.json)
    assert suite.results_path(docs, "tiny", "smooth").name == "suite_tiny.json" and not (docs / "benchmarks" / "suite_tiny.json").exists()
    doc = json.loads((docs / "benchmarks" / "suite_tiny_detailed.json").read_text())
    assert doc["smoke"] is True and set(doc["rows"]) == {"no_phase2", "ceiling"}
    c = doc["rows"]["ceiling"]
    assert c["errors"] == [] and set(c["metrics"]) == {"test"} and 15 < c["metrics"]["test"]["overall"]["psnr"] < 45
    assert c["metrics"]["test"]["overall"]["count"] == doc["rows"]["no_phase2"]["metrics"]["test"]["overall"]["count"]
    r = doc["rows"]["no_phase2"]
    assert r["errors"] == [], r["errors"]
    # one detailed subject (capture seed 0); the row's metrics are its mean over the subjects
    assert doc["head"] == "detailed" and doc["subject_seeds"] == [0] and [s["seed"] for s in r["subjects"]] == [0]
    assert all(s["appearance"] == "detailed" for s in r["subjects"]) and not (out / "ws" / "no_phase2_seed1").exists()
    assert r["metrics"]["test"]["overall"]["psnr"] == pytest.approx(r["subjects"][0]["metrics"]["test"]["overall"]["psnr"])
    assert r["metrics"]["val"]["overall"]["psnr"] > 5 and r["metrics"]["test"]["overall"]["psnr"] > 5
    assert r["metrics"]["test"]["frontal"]["count"] >= 1
    # the detailed capture's held-out views of the training timestep score the trained row, not the ceiling
    assert {"front", "side", "back"} <= set(r["metrics"]["novel"]["view_groups"]) and r["metrics"]["novel"]["overall"]["psnr"] > 5
    assert "novel" not in c["metrics"]
    # LPIPS where sage finds the weights (as in CI), reported unavailable where it does not
    assert (r["metrics"]["val"]["overall"]["lpips"] is not None) == (LPIPS_WEIGHTS is not None)
    assert r["reenact"]["render_fps"] > 0 and r["peak_rss_mib"] > 100
    assert r["stages"]["phase1"]["shared"] is True and r["stages"]["phase1"]["iterations_per_s"] > 0
    # the capture is tracked: its FLAME mesh differs from the ground truth by the tracking error, so the
    # GT mesh moved to canonical space gives phase 1's Chamfer to its canonical FLAME mesh up to that error
    info = json.loads((out / "captures" / "multiview" / "gt" / "info.json").read_text())
    geo = r["subjects"][0]["geometry"]
    t_can = int(geo["gt_mesh"].split("canonical timestep ")[1].split(",")[0])
    err_mm = info["tracking"]["timesteps"][t_can]["max_mm"]
    assert r["capture_tracking"]["mode"] == "fitted" and 0 < err_mm < 10
    assert abs(geo["chamfer_mm"] - r["stages"]["phase1"]["chamfer_m"] * 1000) <= 1.1 * err_mm + 0.05 * geo["chamfer_mm"]
    assert doc["steps"]["sage:phase1"]["ran"] is True and doc["steps"]["sage:phase1"]["peak_rss_mib"] > 100
    md = (docs / "results.md").read_text()
    assert "Smoke test" in md and "sage phase1 " in md and "### Comparison with the paper" in md
    # a rerun skips every finished stage, keeps the measured memory and merges into the same document
    assert suite.main(args) == 0
    doc2 = json.loads((docs / "benchmarks" / "suite_tiny_detailed.json").read_text())
    assert len(doc2["runs"]) == 2
    assert doc2["steps"]["sage:phase1"]["ran"] is False
    assert doc2["steps"]["sage:phase1"]["peak_rss_mib"] == doc["steps"]["sage:phase1"]["peak_rss_mib"]
    assert doc2["rows"]["no_phase2"]["metrics"]["val"] == r["metrics"]["val"]


def test_the_written_results_name_no_path_of_this_machine(tmp_path):
    """Paths under --out are written relative to it (OUT in commands), the LPIPS weights by name,
    any other absolute path by its last component; the committed documents hold none."""
    from _suite.portable import portable_doc, portable_text

    out, weights = tmp_path / "runs" / "t", tmp_path / "w" / "lpips_alex_v0.1.pth"
    doc = {"settings": {"out": str(out), "lpips_weights": str(weights)},
           "steps": {"sage:eval": {"command": f"sage eval {out}/ws/sage --lpips-weights {weights}", "log": f"{out}/logs/sage__eval.log",
                                   "error": f"exit 2: error: {out}/ws/sage/data: missing | see https://example.org/x"}},
           "rows": {"sage": {"workspace": f"{out}/ws/sage", "errors": [f"copy: {tmp_path}/elsewhere/file.txt: gone"]}},
           "runs": [{"command": f"python benchmarks/suite.py --size tiny --out {out} --docs /somewhere/docs_new"}]}  # fmt: skip
    new = portable_doc(doc, [out], [weights])
    assert new["settings"] == {"out": ".", "lpips_weights": "lpips_alex_v0.1.pth"}
    step = new["steps"]["sage:eval"]
    assert step["command"] == "sage eval OUT/ws/sage --lpips-weights lpips_alex_v0.1.pth" and step["log"] == "logs/sage__eval.log"
    assert step["error"] == "exit 2: error: OUT/ws/sage/data: missing | see https://example.org/x"
    assert new["rows"]["sage"] == {"workspace": "ws/sage", "errors": ["copy: file.txt: gone"]}
    assert new["runs"][0]["command"].endswith("--out OUT --docs docs_new")
    assert portable_text("--variant a=/x/ref::/x/ws::phase1.k=1") == "--variant a=ref::ws::phase1.k=1"
    text = "\n".join(p.read_text(encoding="utf-8") for p in [REPO / "docs" / "results.md", *(REPO / "docs" / "benchmarks").glob("*")])
    import re

    assert not re.search(r"(?<![\w.~/-])/(work|home|tmp|root|mnt|data)/", text)


def test_discussion_links_hold_from_results_md() -> None:
    """The discussion is written in docs/benchmarks/ and copied into docs/results.md: its relative
    links are rebased, and every link of both files points at a file that exists."""
    import re

    from _suite.report import rebase_links

    text = "see [a](x.md), [b](../y.md#s), [c](https://e.org/z), [d](#here), [e](../../pkg/m.py)"
    assert rebase_links(text, "benchmarks") == (
        "see [a](benchmarks/x.md), [b](y.md#s), [c](https://e.org/z), [d](#here), [e](../pkg/m.py)")
    docs = REPO / "docs"
    for page in (docs / "results.md", docs / "benchmarks" / "discussion.md"):
        for target in re.findall(r"\]\(([^)\s#]+)(?:#[^)]*)?\)", page.read_text(encoding="utf-8")):
            if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):
                continue
            assert (page.parent / target).exists(), f"{page.name}: broken link {target}"
