"""``sage track`` end to end: bad input refused before anything is written, and synthetic captures
(one photo, a video with a missed detection, a calibrated rig) tracked into captures that ``sage ingest``
reads, with their vertex error against the known truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from track_helpers import astronaut, invoke, models_or_skip, write_png

from sage_core.track.truth import compare_to_truth, input_from_capture

TINY = ["--preset", "tiny", "--device", "cpu", "--threads", "1", "--quiet"]


@pytest.fixture(scope="module")
def model(tiny_capture):
    models_or_skip()
    return tiny_capture.model_path


@pytest.fixture(scope="module")
def embedding(tiny_capture, tmp_path_factory):
    """The tiny head's landmark embedding, calibrated once (the tests below pass it with --landmark-embedding)."""
    import torch

    from sage_core.flame import FlameModel, load_flame_model
    from sage_core.track.embedding import calibrate_embedding, save_embedding
    from sage_core.track.faces import FaceObserver
    from sage_core.track.weights import find_models

    fm = FlameModel(load_flame_model(tiny_capture.model_path))
    with torch.no_grad():
        v = fm().vertices[0]
    emb, _ = calibrate_embedding(v, fm.faces, FaceObserver(find_models(models_or_skip())), size=256, n_yaw=3)
    return save_embedding(tmp_path_factory.mktemp("emb") / "embedding.npz", emb)


def _refused(tmp_path: Path, model: Path, inp: Path, code: int, text: str, *extra: str) -> None:
    out = tmp_path / "out"
    res = invoke(["track", inp, out, "--flame-model", model, *TINY, *extra])
    assert res.exit_code == code, res.output
    assert text in " ".join(res.output.split()), res.output
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())


def test_bad_photos_are_refused(tmp_path, model):
    import cv2

    from skimage import data

    img = astronaut()
    # a real photograph without a face (the detector alone sees one in it turned sideways)
    _refused(tmp_path, model, write_png(tmp_path / "coffee.png", (data.coffee() / 255.0).astype(np.float32)), 2, "no face found")
    _refused(tmp_path, model, write_png(tmp_path / "side.png", np.ascontiguousarray(np.rot90(img))), 2, "rotate it upright")
    _refused(tmp_path, model, write_png(tmp_path / "upside.png", np.ascontiguousarray(img[::-1, ::-1])), 2, "turned 180°")
    face = img[40:220, 130:320]
    _refused(tmp_path, model, write_png(tmp_path / "two.png", np.concatenate([face, face], 1)), 2, "2 faces found")
    canvas = np.ones((96, 96, 3), np.float32)
    canvas[25:70, 24:72] = cv2.resize(face, (48, 45), interpolation=cv2.INTER_AREA)
    _refused(tmp_path, model, write_png(tmp_path / "tiny.png", canvas), 2, "px wide, less than the 40 px needed")
    # cut below the nose: the face is found, but more than half of its landmarks lie beyond the edge
    _refused(tmp_path, model, write_png(tmp_path / "cut.png", np.ascontiguousarray(img[:120])), 2, "the face runs out of the 512x120 image")


def test_bad_files_and_options_are_refused(tmp_path, model):
    bad = tmp_path / "clip.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    _refused(tmp_path, model, bad, 2, "clip.mp4")
    photo = write_png(tmp_path / "me.png", astronaut())
    _refused(tmp_path, model, photo, 3, "regime sv-hr needs several frames", "--regime", "sv-hr")
    _refused(tmp_path, model, photo, 3, "needs calibrated cameras", "--regime", "mv")
    _refused(tmp_path, model, photo, 3, "regime = 'x'", "--regime", "x")
    res = invoke(["track", photo, tmp_path / "o", "--flame-model", tmp_path / "nope.pkl", *TINY])
    assert res.exit_code == 2 and "FLAME model file not found" in res.output
    occupied = tmp_path / "busy"
    occupied.mkdir()
    (occupied / "keep.txt").write_text("mine")
    res = invoke(["track", photo, occupied, "--flame-model", model, *TINY])
    assert res.exit_code == 3 and "--force" in res.output and (occupied / "keep.txt").read_text() == "mine"


def _sub_capture(capture: Path, dst: Path, cameras: tuple[int, ...], timesteps: tuple[int, ...]) -> Path:
    """The frames of ``cameras`` x ``timesteps`` of a synthetic capture, with its truth, as a capture of their own."""
    import shutil

    doc = json.loads((capture / "transforms.json").read_text())
    doc["frames"] = [f for f in doc["frames"] if f["camera_index"] in cameras and f["timestep_index"] in timesteps]
    dst.mkdir()
    (dst / "transforms.json").write_text(json.dumps(doc))
    for f in doc["frames"]:
        for key in ("file_path", "fg_mask_path"):
            if f.get(key):
                (dst / Path(f[key]).parent).mkdir(exist_ok=True)
                shutil.copy(capture / f[key], dst / f[key])
    for folder in ("gt", "flame_param", "model"):
        shutil.copytree(capture / folder, dst / folder)
    return dst


@pytest.mark.slow
def test_one_photo_to_an_ingestible_capture(tmp_path, tiny_capture, model):
    """The frontal image of the tiny capture's first timestep as one photo; the landmark embedding is calibrated."""
    oneshot = _sub_capture(tiny_capture, tmp_path / "sub", (8,), (0,))
    inp, _ = input_from_capture(oneshot, tmp_path / "in")
    out = tmp_path / "cap"
    res = invoke(["track", inp, out, "--flame-model", model, *TINY])
    assert res.exit_code == 0, res.output
    assert "one-shot" in res.output and "sage run" in res.output
    for name in ("images/00000_00.png", "fg_masks/00000_00.png", "flame_param/00000.npz", "canonical_flame_param.npz",
                 "transforms_train.json", "track/report.json", "track/contact_sheet.png", "track/landmark_embedding.npz"):
        assert (out / name).is_file(), name
    report = json.loads((out / "track" / "report.json").read_text())
    assert report["regime"] == "one-shot" and report["calibration"]["kept"] > 200 and report["reprojection_px"]["mean"] < 3
    # no EXIF, no --focal: the focal length is fitted, then held for a second fit (one photo's default),
    # and the fit with the lower landmark error is kept
    cam = report["camera"]
    assert cam["focal_source"] == "fitted" and cam["focal_refit"] is not None
    assert cam["focal_refit"]["focal_px"][0] == pytest.approx(cam["focal_px"], rel=1e-5)
    first_px, second_px = cam["focal_refit"]["landmark_px"]
    assert cam["focal_refit"]["kept"] == ("second" if second_px < first_px else "first")
    assert report["reprojection_px"]["mean"] == pytest.approx(min(first_px, second_px), abs=2e-3)
    from sage_core.data.imageio import read_image

    height = read_image(out / "images" / "00000_00.png").shape[0]
    assert (height < 186) == any("px tall" in w for w in report["warnings"])
    assert report["masks"] == {"keyed": 1, "colour_cut": 0}  # matted on white: keyed, no colour cut
    err = compare_to_truth(out, oneshot)
    assert err["aligned"]["mean_mm"] < 4.0, err["aligned"]
    ws = tmp_path / "ws"
    res = invoke(["ingest", out, ws, "--flame-model", model, "--regime", "one-shot", "--preset", "tiny", "--quiet"])
    assert res.exit_code == 0, res.output
    assert json.loads((ws / "data" / "summary.json").read_text())["counts"]["train"] == 1
    from sage_core.stages.run import eval_splits

    assert eval_splits(ws) == []  # one photo, no held-out frames: `sage run` leaves eval out
    # the mask covers the head and not the background
    m = read_image(out / "fg_masks" / "00000_00.png")[..., 0]
    truth = read_image(oneshot / "fg_masks" / "00000_08.png")[..., 0]
    if m.shape == truth.shape:
        inter, union = ((m > 0.5) & (truth > 0.5)).sum(), ((m > 0.5) | (truth > 0.5)).sum()
        assert inter / union > 0.9


@pytest.mark.slow
def test_one_fit_of_a_fitted_focal_length_when_asked(tmp_path, tiny_capture, model, embedding):
    """--set focal_refit=off: the photo is fitted once, its focal length with everything else, and the
    report says there was no second fit."""
    oneshot = _sub_capture(tiny_capture, tmp_path / "sub", (8,), (0,))
    inp, _ = input_from_capture(oneshot, tmp_path / "in")
    out = tmp_path / "cap"
    res = invoke(["track", inp, out, "--flame-model", model, "--landmark-embedding", embedding, "--set", "focal_refit=off",
                  *TINY])
    assert res.exit_code == 0, res.output
    cam = json.loads((out / "track" / "report.json").read_text())["camera"]
    assert cam["focal_source"] == "fitted" and cam["focal_refit"] is None
    assert compare_to_truth(out, oneshot)["aligned"]["mean_mm"] < 4.0


def test_a_distant_face_in_a_large_photo(tmp_path, model, embedding):
    """The astronaut shrunk to a face about 47 px wide in a 1200x1600 picture: found by the tiled
    search, tracked, written at the crop's own size with a warning that it is small."""
    import cv2

    from sage_core.data.imageio import read_image

    canvas = np.full((1600, 1200, 3), 0.55, np.float32)
    canvas[900:1156, 700:956] = cv2.resize(astronaut(), (256, 256), interpolation=cv2.INTER_AREA)
    out = tmp_path / "cap"
    res = invoke(["track", write_png(tmp_path / "far.png", canvas), out, "--flame-model", model, *TINY,
                  "--landmark-embedding", embedding])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "track" / "report.json").read_text())
    img = read_image(out / "images" / "00000_00.png")
    assert img.shape[0] < 186 and any("px tall" in w for w in report["warnings"])
    assert report["reprojection_px"]["mean"] < 4
    # the crop holds the face: the photo's grey backdrop is not the whole image
    assert (np.abs(img[..., :3] - 0.55).max(-1) > 0.1).mean() > 0.3


@pytest.mark.slow
def _clip(tmp_path: Path, tiny_capture: Path) -> Path:
    """An MP4 of the frontal camera's first 6 timesteps with a blank frame inserted after the third."""
    from sage_core.data.imageio import read_image
    from sage_core.export.video import VideoWriter

    frames = [read_image(tiny_capture / "images" / f"{t:05d}_08.png")[..., :3] for t in range(6)]
    frames.insert(3, np.ones_like(frames[0]))
    clip = tmp_path / "clip.mp4"
    with VideoWriter(clip, fps=5, width=frames[0].shape[1], height=frames[0].shape[0]) as vw:
        for f in frames:
            vw.write(f)
    return clip


def test_video_with_a_missed_frame(tmp_path, tiny_capture, model, embedding):
    """A clip of the frontal camera with one blank frame: that frame is dropped and reported. Fitted
    on 3 keyframes, then tracked in chunks of 2 frames; the head's pivot held or not as the keyframes
    fitted without it decide (steady_pivot=auto)."""
    clip = _clip(tmp_path, tiny_capture)
    out = tmp_path / "cap"
    res = invoke(["track", clip, out, "--flame-model", model, *TINY, "--landmark-embedding", embedding, "--set", "steps=100",
                  "--set", "keyframes=3", "--set", "track_chunk=2", "--set", "track_steps=10"])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "track" / "report.json").read_text())
    assert report["regime"] == "sv-hr" and report["timesteps"] == 6
    assert {"fit_keyframes", "fit_track"} <= set(report["timings_s"]) and "track" in report["losses"]
    assert max(im["reprojection_px"] for im in report["per_image"]) < 8
    assert [d["timestep_id"] for d in report["dropped"]] == ["frame_00003"] and report["dropped"][0]["kind"] == "no-face"
    ids = [f["timestep_id"] for f in json.loads((out / "transforms.json").read_text())["frames"]]
    assert "frame_00003" not in ids and len(ids) == 6
    assert report["calibration"] is None and "from" in report["landmark_embedding"]
    pivot = report["steady_pivot"]
    assert pivot["mode"] == "auto" and pivot["held"] is (pivot["spread"] <= pivot["scale"] == 0.01)
    # no EXIF, no --focal: with the pivot held the fitted focal length is held for a second fit, which
    # keeps the first's decision; with it free the video is fitted once
    refit = report["camera"]["focal_refit"]
    assert (refit is not None) is pivot["held"]
    kept_second = refit is not None and refit["kept"] == "second"
    if refit is not None:
        assert refit["kept"] == ("second" if refit["landmark_px"][1] < refit["landmark_px"][0] or not refit["landmarks_compared"]
                                 else "first")
    prefix = "fit_first_" if kept_second else "fit_"
    assert (f"{prefix}pivot_check" in report["timings_s"]) is pivot["held"]


def test_a_held_pivot_uses_the_wider_pose_table(tmp_path, tiny_capture, model):
    """With the pivot held the calibration continues the pose table out to ``pivot_pose_yaw_deg``
    (the tiny preset's yaw steps of 30° to ±60°) and the capture keeps that table; without it, the
    table ends at ``calib_pose_yaw_deg`` (±30°)."""
    from sage_core.flame import load_flame_model
    from sage_core.track.embedding import load_embedding

    n_faces = load_flame_model(model).n_faces
    clip = _clip(tmp_path, tiny_capture)
    yaws = {}
    for pivot in ("on", "off"):
        out = tmp_path / f"cap_{pivot}"
        res = invoke(["track", clip, out, "--flame-model", model, *TINY, "--set", "steps=60", "--set", "keyframes=0",
                      "--set", "focal_refit=off", "--set", f"steady_pivot={pivot}", "--set", "pivot_pose_yaw_deg=60"])
        assert res.exit_code == 0, res.output
        report = json.loads((out / "track" / "report.json").read_text())
        assert report["steady_pivot"] == {"mode": pivot, "held": pivot == "on"}
        assert ("pivot_pose_views" in report["calibration"]) is (pivot == "on")
        emb = load_embedding(out / "track" / "landmark_embedding.npz", n_faces)
        yaws[pivot] = emb.pose.yaws
    assert yaws["on"].max() == pytest.approx(60.0) and yaws["off"].max() == pytest.approx(30.0)


def test_a_known_or_held_focal_length_fits_a_clip_without_the_pose_table(tmp_path, tiny_capture, model):
    """A clip whose focal length is given (--set focal) is fitted without the pose table (the
    calibration builds none, the capture's embedding has none), unless the whole outline is pulled both
    ways (silhouette_two_sided=all); without a focal length the fitted one is held for a second fit
    (focal_refit=on), kept, which drops the first fit's table and keeps its decision on the head's
    pivot."""
    from sage_core.flame import load_flame_model
    from sage_core.track.embedding import load_embedding

    n_faces = load_flame_model(model).n_faces
    clip = _clip(tmp_path, tiny_capture)
    reports, tables = {}, {}
    for name, extra in (("given", ("--set", "focal=300")), ("refit", ("--set", "focal_refit=on")),
                        ("given_all", ("--set", "focal=300", "--set", "silhouette_two_sided=all"))):
        out = tmp_path / f"cap_{name}"
        res = invoke(["track", clip, out, "--flame-model", model, *TINY, "--set", "steps=60", "--set", "keyframes=0", *extra])
        assert res.exit_code == 0, res.output
        reports[name] = json.loads((out / "track" / "report.json").read_text())
        tables[name] = load_embedding(out / "track" / "landmark_embedding.npz", n_faces).pose is not None
    assert tables == {"given": False, "refit": False, "given_all": True}
    given, refit = reports["given"], reports["refit"]
    assert given["camera"]["focal_source"] != "fitted" and given["calibration"]["pose_views"] == 0
    # the whole outline pulled both ways (asked for) brings the table back with a known focal length
    assert reports["given_all"]["calibration"]["pose_views"] > 0
    assert refit["camera"]["focal_source"] == "fitted" and refit["calibration"]["pose_views"] > 0
    # the first fit followed the detector's lean with the table, the second not: their landmark errors
    # are not compared (and under auto, too, the second fit would be kept)
    assert refit["camera"]["focal_refit"]["kept"] == "second"
    assert refit["camera"]["focal_refit"]["landmarks_compared"] is False
    assert refit["steady_pivot"]["mode"] == "auto" and "spread" in refit["steady_pivot"]
    assert refit["steady_pivot"]["held"] is (refit["steady_pivot"]["spread"] <= 0.01)


def test_a_wider_pose_table_with_other_landmarks_is_not_used(tmp_path, tiny_capture, model, monkeypatch):
    """Should the wider calibration of a held pivot keep other landmarks than the embedding's, the
    capture keeps the narrower table (the embedding's own), still holds the pivot, and says why."""
    import sage_core.track.embedding as embedding_mod
    from sage_core.flame import load_flame_model
    from sage_core.track.embedding import load_embedding

    calls = []

    def differs(a, b):
        calls.append((a, b))
        return False

    monkeypatch.setattr(embedding_mod, "same_landmarks", differs)
    clip = _clip(tmp_path, tiny_capture)
    out = tmp_path / "cap"
    res = invoke(["track", clip, out, "--flame-model", model, *TINY, "--set", "steps=60", "--set", "keyframes=0",
                  "--set", "focal_refit=off", "--set", "steady_pivot=on", "--set", "pivot_pose_yaw_deg=60"])
    assert res.exit_code == 0, res.output
    assert len(calls) == 1
    report = json.loads((out / "track" / "report.json").read_text())
    assert report["steady_pivot"] == {"mode": "on", "held": True}
    assert "pivot_pose_views" not in report["calibration"]
    assert any("wider pose table" in w and "not used" in w for w in report["warnings"]), report["warnings"]
    emb = load_embedding(out / "track" / "landmark_embedding.npz", load_flame_model(model).n_faces)
    assert emb.pose.yaws.max() == pytest.approx(30.0)


@pytest.mark.slow
def test_calibrated_rig(tmp_path, tiny_capture, model, embedding):
    """Three cameras of the tiny multiview capture at two timesteps, with its transforms.json."""
    sub = _sub_capture(tiny_capture, tmp_path / "sub", (6, 8, 10), (0, 1))
    inp, cams = input_from_capture(sub, tmp_path / "in")
    out = tmp_path / "cap"
    res = invoke(["track", inp, out, "--flame-model", model, "--cameras", cams, "--regime", "mv", *TINY, "--landmark-embedding", embedding,
                  "--set", "steps=120", "--set", "refine_steps=10"])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "track" / "report.json").read_text())
    assert report["regime"] == "mv-mf" and report["images"] == 6 and report["camera"]["rig_scale"] == 1.0
    val = json.loads((out / "transforms_val.json").read_text())["frames"]
    assert {f["camera_index"] for f in val} == {8}
    err = compare_to_truth(out, sub)
    assert err["world"]["mean_mm"] < 5.0, err["world"]
    assert set(err["regions"]) == {"face", "neck", "scalp"} and err["regions"]["face"]["world_mm"] < 5.0, err["regions"]


def test_the_closing_panel_says_whether_the_pivot_was_held(tmp_path):
    from sage_core.track.pipeline import TrackResult

    base = dict(out_dir=tmp_path, regime="sv-hr", kind="video", timesteps=6, images=6, splits={"train": 4}, dropped=[],
                reprojection_px=1.0, reprojection_max_px=2.0, focal_px=900.0, focal_source="fitted", masks={"segmented": 6},
                calibration=None, timings={}, wall_time_s=1.0)
    rows = dict(TrackResult(**base, steady_pivot={"mode": "auto", "held": True, "spread": 0.0058, "scale": 0.01}).rows())
    assert rows["head's pivot"] == "held, auto (spread 0.58 % of its distance, held within 1 %)"
    assert dict(TrackResult(**base, steady_pivot={"mode": "on", "held": True}).rows())["head's pivot"] == "held, on"
    assert "head's pivot" not in dict(TrackResult(**base, steady_pivot={"mode": "off", "held": False}).rows())


def test_an_out_that_is_the_current_folder_or_holds_the_input_is_refused(tmp_path, monkeypatch):
    """Before any model is read: the finished capture takes OUT's place as a whole."""
    here = tmp_path / "here"
    (here / "photos").mkdir(parents=True)
    photo = write_png(here / "photos" / "me.png", astronaut()[::4, ::4])
    model = tmp_path / "model.npz"  # never read: the output folder is checked first
    monkeypatch.chdir(here)
    for out in (".", "..", str(here)):
        res = invoke(["track", photo, out, "--flame-model", model, *TINY])
        assert res.exit_code == 3, res.output
        assert f"the output folder {out} is the current folder or holds it" in " ".join(res.output.split())
    res = invoke(["track", "photos/me.png", here, "--flame-model", model, "--force", *TINY])
    assert res.exit_code == 3 and "is the current folder" in " ".join(res.output.split()), res.output
    monkeypatch.chdir(tmp_path)
    res = invoke(["track", "here/photos/me.png", "here", "--flame-model", model, "--force", *TINY])
    assert res.exit_code == 3, res.output
    assert "the output folder here holds the input here/photos/me.png" in " ".join(res.output.split())
    assert sorted(p.name for p in here.rglob("*")) == ["me.png", "photos"]
