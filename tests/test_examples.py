"""examples/: every config resolves through the real config resolution with the preset its usage
line names, the SUBJECTS example loads, the Python API example runs on a small workspace, and the
examples README describes every file."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"
CONFIGS = sorted((EXAMPLES / "configs").glob("*.yaml")) + sorted((EXAMPLES / "configs").glob("*.json"))


def test_there_are_example_configs_for_each_use():
    names = {p.stem for p in CONFIGS}
    assert {"tiny_cpu", "small_cpu", "monocular", "one_shot"} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_example_config_resolves_for_every_stage(path):
    from sage_core.config import PRESETS, STAGE_CONFIGS, load_config_file, resolve_config, section_name

    text = path.read_text(encoding="utf-8")
    usage = re.search(r"--preset (\w+) --config (\S+)", " ".join(text.replace("\\\n", " ").split()))
    assert usage, f"{path.name} should show its usage: sage run ... --preset P --config {path.relative_to(REPO)}"
    preset, named = usage.groups()
    assert preset in PRESETS and named == path.relative_to(REPO).as_posix()
    data = load_config_file(path)
    assert data, f"{path.name} is empty"
    sections = {section_name(s): s for s in STAGE_CONFIGS}
    assert set(data) <= set(sections), f"{path.name}: unknown sections {set(data) - set(sections)}"
    regime = (data.get("ingest") or {}).get("regime")
    for stage in STAGE_CONFIGS:
        cfg = resolve_config(stage, preset, data, None, file_label=str(path), regime=regime)
        base = resolve_config(stage, preset, None, None, regime=regime)
        if section_name(stage) in data:
            assert cfg != base, f"{path.name}: section {section_name(stage)} changes nothing"


def test_regime_configs_set_their_regime():
    from sage_core.config import load_config_file, resolve_config

    for name, regime in (("monocular", "sv-hr"), ("one_shot", "one-shot")):
        data = load_config_file(EXAMPLES / "configs" / f"{name}.yaml")
        assert resolve_config("ingest", "tiny", data).regime == regime


def test_subjects_example_loads(tmp_path):
    from sage_core.batch.subjects import load_subjects

    src = EXAMPLES / "batch" / "subjects.csv"
    dst = tmp_path / "subjects.csv"
    shutil.copy(src, dst)
    ids = []
    for line in src.read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#") and not line.startswith("id,"):
            cells = line.split(",")
            ids.append(cells[0])
            (tmp_path / cells[1]).mkdir(parents=True)
            model = tmp_path / cells[5]
            model.parent.mkdir(parents=True, exist_ok=True)
            model.write_bytes(b"")
    subjects = load_subjects(dst)
    assert [s.id for s in subjects] == ids == ["multiview", "monocular", "oneshot"]
    assert [s.regime for s in subjects] == ["mv-sf", "sv-hr", "one-shot"]
    assert subjects[1].sets == ("phase1.pose_refine=true", "eval.samples=2")
    # every sage synth line of the comment writes a capture the file names
    synth = re.findall(r"sage synth (\S+)", src.read_text(encoding="utf-8"))
    assert sorted(Path(s).name for s in synth) == sorted(Path(s.capture).name for s in subjects)


def test_examples_readme_describes_every_file():
    text = (EXAMPLES / "README.md").read_text(encoding="utf-8")
    files = [p.relative_to(EXAMPLES).as_posix() for p in EXAMPLES.rglob("*") if p.is_file() and p.name != "README.md"
             and "__pycache__" not in p.parts]
    assert files
    for f in files:
        assert f"`{f}`" in text, f"examples/README.md does not describe {f}"
    assert "examples/" in (REPO / "README.md").read_text(encoding="utf-8")


def test_python_api_example_help():
    res = subprocess.run([sys.executable, str(EXAMPLES / "python_api.py"), "--help"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "workspace" in res.stdout and "--frames" in res.stdout


def test_python_api_example_runs_on_a_small_workspace(tiny_avatar_ws, tmp_path):
    from sage_core.data.imageio import read_image

    out = tmp_path / "frames"
    res = subprocess.run(
        [sys.executable, str(EXAMPLES / "python_api.py"), str(tiny_avatar_ws), "--out", str(out), "--frames", "2"],
        capture_output=True, text=True, timeout=600, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    frames = sorted(out.glob("frame_*.png"))
    normals = sorted(out.glob("normal_*.png"))
    assert len(frames) == 2 and len(normals) == 2
    a, b = (read_image(p) for p in frames)
    assert a.ndim == 3 and a.shape[2] >= 3
    assert float(abs(a - b).max()) > 1 / 255, "the expression should change between the frames"

    # --motion: rows of a FLAME sequence (here 3 rows; --frames 2 renders the first two)
    import numpy as np

    from sage_core.data.dataset import IngestedData

    E = IngestedData.open(tiny_avatar_ws / "data").params.n_expr
    arrays = {k: np.zeros((3, 3), np.float32) for k in ("rotation", "neck_pose", "jaw_pose", "translation")}
    arrays["expr"] = np.linspace(0, 1.5, 3 * E, dtype=np.float32).reshape(3, E)
    arrays["eyes_pose"] = np.zeros((3, 6), np.float32)
    np.savez(tmp_path / "motion.npz", **arrays)
    out2 = tmp_path / "motion_frames"
    res = subprocess.run(
        [sys.executable, str(EXAMPLES / "python_api.py"), str(tiny_avatar_ws), "--out", str(out2), "--frames", "2",
         "--motion", str(tmp_path / "motion.npz")],
        capture_output=True, text=True, timeout=600, env={**__import__("os").environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert len(sorted(out2.glob("frame_*.png"))) == 2
