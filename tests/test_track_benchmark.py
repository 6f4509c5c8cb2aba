"""benchmarks/track.py's seed runs of the monocular clip: folders per seed and settings, the record in
track.json (replacing a run of the same label and focal length) and its table."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import track as bench  # noqa: E402


def _errors(aligned: float) -> dict:
    e = {"mean_mm": aligned, "max_mm": 3 * aligned, "worst_timestep_mean_mm": 2 * aligned}
    return {"aligned": {**e, "scale": 1.0}, "camera": {**e, "mean_mm": 10 * aligned}, "world": e,
            "rigid_per_timestep": {**e, "mean_mm": aligned / 2}, "focal_rel_error": -0.1 * aligned}


def test_settings_tag_names_a_folder_per_set_of_settings_in_any_order():
    assert bench._settings_tag([]) == ""
    a = bench._settings_tag(["steady_pivot=true", "calib_pose_yaw_deg=60"])
    assert a == bench._settings_tag(["calib_pose_yaw_deg=60", "steady_pivot=true"])
    assert a != bench._settings_tag(["steady_pivot=true"]) and a.startswith("_") and len(a) == 9


def test_clip_seed_runs_are_recorded_per_label_and_focal_length(tmp_path, monkeypatch):
    calls = []

    def fake_case(work, regime, synth_preset, track_preset, threads, known_focal=False, seed=None, sets=None):
        calls.append((regime, known_focal, seed, list(sets or [])))
        return {"regime": regime, "known_focal": known_focal, "seed": seed, "sets": list(sets or []),
                "timesteps": 11, "errors": _errors(1.0 + seed), "command": f"sage track ... --seed {seed}"}

    monkeypatch.setattr(bench, "track_case", fake_case)
    mean = {"aligned_mm": 9.0, "rigid_per_timestep_mm": 4.0, "camera_mm": 90.0, "focal_rel_error": -0.2}
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "track.json").write_text(json.dumps({
        "command": "c", "machine": {"cpus": 2, "torch": "t", "load_average": [0, 0, 0], "date_utc": "d"}, "threads": 1,
        "load_after": [0, 0, 0], "cases": [],
        "clip_runs": [{"label": "pivot", "known_focal": k, "sets": [], "seeds": [], "cases": [], "mean": mean}
                      for k in (True, False)]}))
    bench.main(["--only-clip-seeds", "0,2", "--known-focal", "--clip-label", "pivot", "--clip-set", "steady_pivot=true",
                "--out", str(tmp_path / "work"), "--docs", str(docs), "--synth-preset", "small"])
    assert calls == [("monocular", True, 0, ["steady_pivot=true"]), ("monocular", True, 2, ["steady_pivot=true"])]
    doc = json.loads((docs / "track.json").read_text())
    runs = doc["clip_runs"]
    # the earlier run of the same label and focal length is replaced; the fitted-focal one is kept
    assert [(r["label"], r["known_focal"]) for r in runs] == [("pivot", False), ("pivot", True)]
    new = runs[1]
    assert new["seeds"] == [0, 2] and new["sets"] == ["steady_pivot=true"]
    assert new["mean"]["aligned_mm"] == 2.0 and new["mean"]["rigid_per_timestep_mm"] == 1.0
    assert new["mean"]["camera_mm"] == 20.0 and abs(new["mean"]["focal_rel_error"] + 0.2) < 1e-9
    assert "--only-clip-seeds 0,2" in new["benchmark_command"]
    md = (docs / "track.md").read_text()
    assert "The monocular clip (a folder of 11 frames) tracked at several seeds" in md
    assert "| pivot: `steady_pivot=true` | given | 1.00 (0), 3.00 (2) | 2.00 | 1.00 | 20.00 | -20.0% |" in md


def test_rescore_reads_each_case_from_the_folder_it_was_tracked_into(tmp_path, monkeypatch):
    """--rescore: a known-focal case and a clip's seed run are scored from their own folders (the focal
    mode, seed and settings are part of the name), and the clip run's means follow the new errors."""
    import sage_core.track.truth as truth

    seen = []

    def fake_compare(out, cap):
        seen.append((Path(out).name, Path(cap).name))
        return _errors(4.0 if "seed1" in Path(out).name else 2.0)

    monkeypatch.setattr(truth, "compare_to_truth", fake_compare)
    case = {"regime": "monocular", "track_regime": "sv-hr", "synth_preset": "small", "track_preset": "default",
            "images": 11, "image_size": [256, 372], "wall_s": 50.0, "reprojection_px": 2.5, "capture_tracking_error": None}
    clip = [{**case, "known_focal": True, "seed": s, "sets": ["steady_pivot=true"], "timesteps": 11, "errors": _errors(9.0)}
            for s in (0, 1)]
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "track.json").write_text(json.dumps({
        "command": "c", "machine": {"cpus": 2, "torch": "t", "load_average": [0, 0, 0], "date_utc": "d"}, "threads": 1,
        "load_after": [0, 0, 0], "cases": [{**case, "known_focal": True, "errors": _errors(9.0)}],
        "clip_runs": [{"label": "pivot", "known_focal": True, "sets": ["steady_pivot=true"], "seeds": [0, 1],
                       "cases": clip, "mean": {}}]}))
    bench.main(["--rescore", "--out", str(tmp_path / "work"), "--docs", str(docs)])
    tag = bench._settings_tag(["steady_pivot=true"])
    assert seen == [("tracked_monocular_small_default_focal", "cap_monocular_small"),
                    (f"tracked_monocular_small_default_focal_seed0{tag}", "cap_monocular_small"),
                    (f"tracked_monocular_small_default_focal_seed1{tag}", "cap_monocular_small")]
    doc = json.loads((docs / "track.json").read_text())
    assert doc["clip_runs"][0]["mean"]["aligned_mm"] == 3.0 and doc["cases"][0]["errors"]["aligned"]["mean_mm"] == 2.0


def test_a_full_run_keeps_what_it_did_not_measure(tmp_path, monkeypatch):
    """A run of the regimes replaces the cases and keeps the clip's seed runs (and superseded ones), the
    backgrounds, the video runs, the avatar variants and the notes of earlier runs (each with its own
    command)."""
    def fake_case(work, regime, synth_preset, track_preset, threads, known_focal=False, seed=None, sets=None):
        return {"regime": regime, "track_regime": "one-shot", "synth_preset": synth_preset, "track_preset": track_preset,
                "known_focal": known_focal, "seed": seed, "sets": [], "images": 1, "image_size": [256, 372], "timesteps": 1,
                "wall_s": 1.0, "reprojection_px": 1.0, "errors": {**_errors(2.0), "regions": None}, "command": "sage track ...",
                "capture_tracking_error": None}

    monkeypatch.setattr(bench, "track_case", fake_case)
    docs = tmp_path / "docs"
    docs.mkdir()
    kept = {"clip_runs": [{"label": "pivot", "known_focal": True, "sets": [], "seeds": [0], "cases": [],
                           "mean": {"aligned_mm": 9.0, "rigid_per_timestep_mm": 4.0, "camera_mm": 90.0, "focal_rel_error": 0.0},
                           "machine": {"date_utc": "d"}}],
            "backgrounds": [], "video_runs": [], "notes": {"cases": "earlier notes"},
            "clip_runs_superseded": [{"label": "older"}], "avatar_variants": [_avatar("oneshot", 19.0, label="refit")]}
    (docs / "track.json").write_text(json.dumps({
        "command": "c", "machine": {"cpus": 2, "torch": "t", "load_average": [0, 0, 0], "date_utc": "d"}, "threads": 1,
        "load_after": [0, 0, 0], "cases": [{"regime": "old"}], **kept}))
    bench.main(["--regimes", "oneshot", "--out", str(tmp_path / "work"), "--docs", str(docs), "--synth-preset", "small"])
    doc = json.loads((docs / "track.json").read_text())
    assert [c["regime"] for c in doc["cases"]] == ["oneshot"]
    for key, value in kept.items():
        assert doc[key] == value, key


def test_an_avatar_its_run_trained_again_is_not_reported_as_reused(tmp_path, monkeypatch):
    """An avatar counts as reused only when its run left the finished phase 2 as it was; a run that
    retrained it (a changed default) reports its own wall time."""
    work = tmp_path
    cap = work / "cap"
    (cap / "gt").mkdir(parents=True)
    (cap / "gt" / "info.json").write_text(json.dumps({"config": {"train_timesteps": 2}, "counts": {"timesteps": 3}}))
    tracked = work / "tracked_monocular_small_default_uncropped"
    tracked.mkdir()
    (tracked / "transforms.json").write_text(json.dumps({"frames": [{"timestep_index": 0, "timestep_id": "0"}]}))
    monkeypatch.setattr(bench, "_capture", lambda w, r, p: cap)
    monkeypatch.setattr(bench, "_input", lambda w, r, p, c: (work / "in", None))
    retrain = {"own": False, "tracked": True}

    def fake_sage(args, threads):
        ws = Path(args[2])
        name = "own" if "_own_" in ws.name else "tracked"
        for stage, done in (("phase1", "t0"), ("phase2", "t1")):
            m = ws / stage / "manifest.json"
            if retrain[name] or not m.is_file():
                m.parent.mkdir(parents=True, exist_ok=True)
                m.write_text(json.dumps({"finished_at": done + ("b" if m.is_file() else ""), "wall_time_s": 5.0}))
        metrics = ws / "eval" / "phase2" / "test" / "metrics.json"
        metrics.parent.mkdir(parents=True, exist_ok=True)
        metrics.write_text(json.dumps({"images": [{"timestep": 0, "camera": 0, "psnr": 20.0, "ssim": 0.8, "lpips": 0.2}]}))
        return 42.0, ""

    monkeypatch.setattr(bench, "_sage", fake_sage)
    first = bench.avatar_case(work, "monocular", "small", "default", "tiny", [], 1)
    assert not any(r.get("reused") for r in first["runs"].values()) and first["runs"]["own"]["wall_s"] == 42.0
    again = bench.avatar_case(work, "monocular", "small", "default", "tiny", [], 1)
    assert again["runs"]["own"].get("reused") is True and again["runs"]["own"]["wall_s"] == 10.0
    assert "reused" not in again["runs"]["tracked"] and again["runs"]["tracked"]["wall_s"] == 42.0


def test_a_clip_seed_run_keeps_what_another_run_wrote_meanwhile(tmp_path, monkeypatch):
    """The results file is read after the clip's seeds are tracked: an entry another run of the benchmark
    wrote in the meantime (here an avatar comparison) survives."""
    docs = tmp_path / "docs"
    docs.mkdir()
    path = docs / "track.json"
    path.write_text(json.dumps({
        "command": "c", "machine": {"cpus": 2, "torch": "t", "load_average": [0, 0, 0], "date_utc": "d"}, "threads": 1,
        "load_after": [0, 0, 0], "cases": []}))

    def fake_case(work, regime, synth_preset, track_preset, threads, known_focal=False, seed=None, sets=None):
        doc = json.loads(path.read_text())  # another benchmark process finishes while the seeds are tracked
        doc["backgrounds"] = [{"background": "coffee", "written_while": seed}]
        path.write_text(json.dumps(doc))
        return {"regime": regime, "known_focal": known_focal, "seed": seed, "sets": [], "timesteps": 11,
                "errors": _errors(1.0), "command": "sage track ..."}

    monkeypatch.setattr(bench, "track_case", fake_case)
    monkeypatch.setattr(bench, "_write", lambda docs_dir, doc: (docs_dir / "track.json").write_text(json.dumps(doc)))
    bench.main(["--only-clip-seeds", "0", "--clip-label", "x", "--out", str(tmp_path / "work"), "--docs", str(docs),
                "--synth-preset", "small"])
    doc = json.loads(path.read_text())
    assert doc["backgrounds"] == [{"background": "coffee", "written_while": 0}]
    assert [r["label"] for r in doc["clip_runs"]] == ["x"]


def _avatar(regime: str, psnr: float, **extra) -> dict:
    common = {"psnr": psnr, "ssim": 0.8, "lpips": 0.2}
    return {"regime": regime, "track_regime": "sv-hr", "known_focal": False, "avatar_preset": "tiny", "avatar_sets": [],
            "common_images": 4, "runs": {"own": {"common": common, "wall_s": 1.0}, "tracked": {"common": common, "wall_s": 1.0}},
            "psnr_difference_db": 0.0, **extra}


def test_avatar_variants_are_recorded_per_label_beside_the_main_rows(tmp_path, monkeypatch):
    """--only-avatars --avatar-label L --avatar-track-set K=V: the tracking gets the settings, the comparison
    goes into avatar_variants (replacing L's earlier row of that regime, keeping other labels), the main
    avatar rows stay; --avatar-track-set without a label is refused."""
    calls = []

    def fake_avatar(work, regime, synth_preset, track_preset, avatar_preset, avatar_sets, threads, known_focal=False,
                    track_sets=None):
        calls.append((regime, known_focal, list(track_sets or [])))
        return _avatar(regime, 21.0, track_sets=list(track_sets or []))

    monkeypatch.setattr(bench, "avatar_case", fake_avatar)
    docs = tmp_path / "docs"
    docs.mkdir()
    main_rows = [_avatar("monocular", 20.0)]
    (docs / "track.json").write_text(json.dumps({
        "command": "c", "machine": {"cpus": 2, "torch": "t", "load_average": [0, 0, 0], "date_utc": "d"}, "threads": 1,
        "load_after": [0, 0, 0], "cases": [], "avatars": main_rows,
        "avatar_variants": [_avatar("monocular", 19.0, label="refit"), _avatar("monocular", 18.0, label="other")]}))
    bench.main(["--only-avatars", "--regimes", "monocular", "--avatar-label", "refit", "--avatar-track-set", "focal_refit=on",
                "--out", str(tmp_path / "work"), "--docs", str(docs), "--synth-preset", "small"])
    assert calls == [("monocular", False, ["focal_refit=on"])]
    doc = json.loads((docs / "track.json").read_text())
    assert doc["avatars"] == main_rows
    assert [(v["label"], v["runs"]["tracked"]["common"]["psnr"]) for v in doc["avatar_variants"]] == [("other", 18.0), ("refit", 21.0)]
    md = (docs / "track.md").read_text()
    assert "| refit | monocular | `focal_refit=on` | 21.00 / 0.8000 / 0.2000 | +0.00 |" in md
    import pytest

    with pytest.raises(SystemExit):
        bench.main(["--only-avatars", "--avatar-track-set", "focal_refit=on", "--out", str(tmp_path / "work"),
                    "--docs", str(docs)])


def test_an_avatar_variant_tracks_into_its_own_folders(tmp_path, monkeypatch):
    """avatar_case with track_sets passes them to `sage track` and keeps that capture and its avatar in
    folders tagged by the settings; the own-parameter avatar is shared."""
    work = tmp_path
    cap = work / "cap"
    (cap / "gt").mkdir(parents=True)
    (cap / "gt" / "info.json").write_text(json.dumps({"config": {"train_timesteps": 2}, "counts": {"timesteps": 3}}))
    monkeypatch.setattr(bench, "_capture", lambda w, r, p: cap)
    monkeypatch.setattr(bench, "_input", lambda w, r, p, c: (work / "in", None))
    seen = []

    def fake_sage(args, threads):
        seen.append(list(args))
        out = Path(args[2])
        if args[0] == "track":
            out.mkdir(parents=True)
            (out / "transforms.json").write_text(json.dumps({"frames": [{"timestep_index": 0, "timestep_id": "0"}]}))
            return 1.0, ""
        metrics = out / "eval" / "phase2" / "test" / "metrics.json"
        metrics.parent.mkdir(parents=True, exist_ok=True)
        metrics.write_text(json.dumps({"images": [{"timestep": 0, "camera": 0, "psnr": 20.0, "ssim": 0.8, "lpips": 0.2}]}))
        return 2.0, ""

    monkeypatch.setattr(bench, "_sage", fake_sage)
    res = bench.avatar_case(work, "monocular", "small", "default", "tiny", [], 1, track_sets=["focal_refit=on"])
    tag = bench._settings_tag(["focal_refit=on"])
    track = next(a for a in seen if a[0] == "track")
    assert track[2].endswith(f"tracked_monocular_small_default_uncropped{tag}") and "focal_refit=on" in track
    runs = [a for a in seen if a[0] == "run"]
    assert Path(runs[0][2]).name == "avatar_monocular_small_own_tiny"
    assert Path(runs[1][2]).name == f"avatar_monocular_small_tracked{tag}_tiny" and Path(runs[1][1]) == Path(track[2])
    assert res["track_sets"] == ["focal_refit=on"]


def test_the_video_table_says_which_head_each_video_shows():
    """Video rows name their appearance: with hair (detailed) or the bare head of earlier runs (smooth,
    also rows recorded before the appearance was)."""
    def run(label: str, **video) -> dict:
        v = {"video": "v.mp4", "seconds": 20, "frames": 600, "sway_mm": 0.0, "timesteps": 600, "dropped": 0, "wall_s": 300.0,
             "timings_s": {"fit": 200.0}, "reprojection_px": 1.5, "errors": _errors(4.0), **video}
        return {"label": label, "run": {}, "video": v}

    md = bench.markdown({"command": "c", "machine": {"cpus": 2, "torch": "t", "load_average": [0, 0, 0], "date_utc": "d"},
                         "threads": 1, "load_after": [0, 0, 0], "cases": [],
                         "video_runs": [run("a", appearance="detailed"), run("b", appearance="smooth"), run("c")]})
    first = md[:md.index("Where the error lies")]
    rows = [line for line in first.splitlines() if line.startswith("| 20 s")]
    assert [r.split(" | ")[0] for r in rows] == ["| 20 s (600 frames, with hair)"] + ["| 20 s (600 frames, bare head)"] * 2


def test_the_video_shape_table_splits_the_error_by_region_and_turn():
    """Runs that measured it get a row with each frame moved alone, the regions and the turns; older runs
    (no per-frame measure) are left out of that table."""
    err = _errors(4.0)
    err["regions"] = {"face": {"camera_mm": 9.0, "aligned_mm": 3.84, "rigid_mm": 2.41},
                      "scalp": {"camera_mm": 9.0, "aligned_mm": 5.11, "rigid_mm": 3.0}}
    err["by_turn"] = {"within 15°": {"frames": 120, "aligned_mm": 4.36}, "beyond 45°": {"frames": 200, "aligned_mm": 4.32}}
    old = _errors(5.0)
    del old["rigid_per_timestep"]

    def run(label: str, errors: dict) -> dict:
        v = {"video": "v.mp4", "seconds": 20, "frames": 600, "sway_mm": 0.0, "timesteps": 600, "dropped": 0, "wall_s": 300.0,
             "timings_s": {}, "reprojection_px": 1.5, "errors": errors, "appearance": "detailed"}
        return {"label": label, "run": {}, "video": v}

    md = bench.markdown({"command": "c", "machine": {"cpus": 2, "torch": "t", "load_average": [0, 0, 0], "date_utc": "d"},
                         "threads": 1, "load_after": [0, 0, 0], "cases": [], "video_runs": [run("new", err), run("old", old)]})
    second = md[md.index("Where the error lies"):].splitlines()
    rows = [line for line in second if line.startswith("| 20 s")]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert cells[1:] == ["new", "4.00", "2.00", "3.84 / 2.41", "—", "5.11 / 3.00", "4.36 (120)", "—", "4.32 (200)"]


def test_landmark_follow_truth_points_project_and_keep_the_visible_ones():
    """The benchmark's truth: embedding points on a mesh projected with the camera; points on triangles
    facing away or outside the image do not count."""
    import landmark_follow as lf

    # two triangles at z = 0 facing +z (towards a camera at z = 1 looking down -z) and one facing away
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.5, 0, 0], [0.6, 0, 0], [0.5, 0.1, 0]], float)
    tri = np.array([[0, 1, 2], [3, 4, 5], [0, 2, 1]])
    bary = np.full((3, 3), 1 / 3)
    from sage_core.data.cameras import Camera

    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, :3] = np.diag([1.0, -1.0, -1.0])  # OpenCV camera at z = 1 looking down -z
    w2c[2, 3] = 1.0
    uv, ok = lf.truth_points(v, tri, bary, Camera(K, w2c, 100, 100))
    assert uv[0] == pytest.approx([50 + 100 * 0.1 / 3, 50 - 100 * 0.1 / 3])
    assert ok.tolist() == [True, False, False]  # the second lies beyond the image's edge, the third faces away
