"""Careless and hostile inputs found by probing the commands: each case exits non-zero with a
message that names the file and the problem, writes nothing, and never ends in a traceback
(docs/workspace.md "Guarantees", docs/cli.md). The pickle payload corpus is in
tests/test_unpickle_security.py; interruption and resume in tests/test_reliability.py."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from sage_cli.app import app

REPO = Path(__file__).resolve().parents[1]
ENV = {"COLUMNS": "400", "SAGE_LPIPS_WEIGHTS": "", "OMP_NUM_THREADS": "1"}


def invoke(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args], env=ENV)


def text(res) -> str:
    return " ".join(res.output.split())


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    """A very small synthetic capture (4 cameras, 48×70, one train and one test timestep)."""
    from sage_core.data.synthetic import make_capture, preset

    cap = tmp_path_factory.mktemp("hostile") / "cap"
    make_capture(cap, preset("tiny", n_cameras=4, width=48, height=70, train_timesteps=1, test_timesteps=1))
    return cap


def _copy(folder: Path, tmp_path: Path, name: str = "cap") -> Path:
    dst = tmp_path / name
    shutil.copytree(folder, dst, symlinks=True)
    return dst


def _ingest(cap: Path, ws: Path, *extra: str):
    return invoke("ingest", cap, ws, "--flame-model", cap / "model" / "synth_flame.npz", "--preset", "tiny", "--quiet", *extra)


# --------------------------------------------------------------------------------------------
# expression columns are never dropped silently
# --------------------------------------------------------------------------------------------


def _widen_expr(path: Path, extra: np.ndarray) -> None:
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["expr"] = np.concatenate([arrays["expr"], extra.astype(arrays["expr"].dtype)], axis=1)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def test_ingest_refuses_nonzero_expression_columns_beyond_the_model(small_capture, tmp_path):
    cap = _copy(small_capture, tmp_path)
    files = sorted((cap / "flame_param").glob("*.npz"))
    for f in files:
        _widen_expr(f, np.full((1, 5), 0.4) if f == files[-1] else np.zeros((1, 5)))
    target = files[-1]
    res = _ingest(cap, tmp_path / "ws")
    assert res.exit_code == 2, text(res)
    assert str(target) in text(res) and "expression components" in text(res)
    assert not (tmp_path / "ws" / "data").exists()
    # extra columns that are all zero change nothing and are accepted
    cap2 = _copy(small_capture, tmp_path, "cap2")
    for f in (cap2 / "flame_param").glob("*.npz"):
        _widen_expr(f, np.zeros((1, 5)))
    res = _ingest(cap2, tmp_path / "ws2")
    assert res.exit_code == 0, text(res)


def test_a_motion_with_nonzero_expression_columns_beyond_the_avatar_is_refused(tmp_path):
    from sage_core.errors import InputError
    from sage_core.export.motion import load_motion

    T, E = 4, 12
    arrays = {"expr": np.zeros((T, E + 3), np.float32), "rotation": np.zeros((T, 3), np.float32),
              "neck_pose": np.zeros((T, 3), np.float32), "jaw_pose": np.zeros((T, 3), np.float32),
              "eyes_pose": np.zeros((T, 6), np.float32), "translation": np.zeros((T, 3), np.float32)}  # fmt: skip
    ok = tmp_path / "ok.npz"
    np.savez(ok, **arrays)
    assert load_motion(ok, n_expr=E).params.expr.shape == (T, E)  # zero columns are dropped
    arrays["expr"][2, E + 1] = 0.7
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(InputError, match=r"bad\.npz.*expression components"):
        load_motion(bad, n_expr=E)
    assert load_motion(bad).params.expr.shape == (T, E + 3)  # kept as stored without an avatar


# --------------------------------------------------------------------------------------------
# everything is validated before any work
# --------------------------------------------------------------------------------------------


def test_bad_seed_and_bad_stage_configs_are_refused_before_any_work(small_capture, init_mesh_ws, tmp_path):
    ws = _copy(init_mesh_ws, tmp_path, "ws")
    res = invoke("phase1", ws, "--preset", "tiny", "--seed", "-1", "--quiet")
    assert res.exit_code == 3 and "--seed" in text(res), text(res)
    assert not (ws / "phase1").exists() and not (ws / ".work" / "phase1").exists()

    out = tmp_path / "run_ws"
    res = invoke("run", small_capture, out, "--flame-model", small_capture / "model" / "synth_flame.npz", "--preset", "tiny",
                 "--quiet", "--set", "phase1.iterations=-3")
    assert res.exit_code == 3 and "iterations = -3" in text(res), text(res)
    assert not out.exists()
    res = invoke("run", small_capture, out, "--flame-model", small_capture / "model" / "synth_flame.npz", "--preset", "tiny",
                 "--quiet", "--seed", "-1")
    assert res.exit_code == 3 and not out.exists(), text(res)

    subjects = tmp_path / "subjects.csv"
    subjects.write_text(f"id,capture,flame_model\na,{small_capture},{small_capture / 'model' / 'synth_flame.npz'}\n")
    res = invoke("batch", subjects, tmp_path / "root", "--preset", "tiny", "--quiet", "--set", "phase1.iterations=-3")
    assert res.exit_code == 3 and "iterations = -3" in text(res), text(res)
    assert not (tmp_path / "root").exists()


# --------------------------------------------------------------------------------------------
# clear exits instead of tracebacks
# --------------------------------------------------------------------------------------------


def test_broken_npz_files_are_named_without_tracebacks(small_capture, tmp_path):
    from sage_core.errors import InputError
    from sage_core.flame import load_flame_model
    from sage_core.flame.params import load_param_npz

    model = small_capture / "model" / "synth_flame.npz"
    with np.load(model) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["v_template"] = np.array([object()] * 3, dtype=object)
    objects = tmp_path / "objects.npz"
    np.savez(objects, **arrays)
    with pytest.raises(InputError, match=r"objects\.npz: array 'v_template' holds Python objects"):
        load_flame_model(objects)

    text_file = tmp_path / "params.npz"
    text_file.write_text("expr 0 0 0\n")
    with pytest.raises(InputError, match="not an npz archive") as ei:
        load_param_npz(text_file)
    assert "allow_pickle" not in str(ei.value)

    with pytest.raises(InputError, match="is a folder, expected a FLAME model file"):
        load_flame_model(tmp_path)
    with pytest.raises(InputError, match="not a regular file"):
        load_flame_model(Path("/dev/null"))


def test_a_model_file_too_large_for_memory_is_named_not_blamed_on_the_image_height(small_capture, tmp_path, monkeypatch):
    import sage_core.flame.model_io as model_io
    from test_flame_io import _sparse_pickle

    model = tmp_path / "huge_sparse.pkl"
    model.write_bytes(_sparse_pickle(200_000, 200_000))  # a J_regressor of 298 GiB once dense
    res = invoke("ingest", small_capture, tmp_path / "ws", "--flame-model", model, "--preset", "tiny", "--quiet")
    assert res.exit_code == 2, text(res)
    assert f"{model}: not a readable FLAME pickle: sparse matrix of shape 200000x200000 is too large" in text(res)
    assert "image height" not in text(res) and not (tmp_path / "ws" / "data").exists()

    def out_of_memory(path):
        raise MemoryError()

    genuine = small_capture / "model" / "synth_flame.npz"
    monkeypatch.setattr(model_io, "_from_npz", out_of_memory)
    res = invoke("ingest", small_capture, tmp_path / "ws2", "--flame-model", genuine, "--preset", "tiny", "--quiet")
    assert res.exit_code == 2, text(res)
    assert f"{genuine}: the FLAME model's arrays do not fit in memory" in text(res)
    assert "image height" not in text(res) and not (tmp_path / "ws2" / "data").exists()


def test_cli_names_folders_and_devices_given_as_files(small_capture, tmp_path):
    res = invoke("ingest", small_capture, tmp_path / "ws", "--flame-model", tmp_path, "--preset", "tiny", "--quiet")
    assert res.exit_code == 2 and "is a folder, expected a FLAME model file" in text(res), text(res)
    res = invoke("ingest", small_capture, tmp_path / "ws", "--flame-model", "/dev/zero", "--preset", "tiny", "--quiet")
    assert res.exit_code == 2 and "not a regular file" in text(res), text(res)
    res = invoke("config", "phase1", "--config", tmp_path)
    assert res.exit_code == 2 and "is a folder, expected a config file" in text(res), text(res)
    assert not (tmp_path / "ws").exists()


def test_an_avatar_file_nested_200000_deep_is_damaged_not_a_recursion_error(tmp_path):
    import torch

    from sage_core.errors import InputError
    from sage_core.serialization import AVATAR_FORMAT, AVATAR_KIND, load_file, save_file

    from safetensors.torch import load, save

    from sage_core.serialization import META_DIGEST, META_SHA, META_TREE, _read_header, tree_digest

    path = save_file(tmp_path / "avatar.pt", {"kind": AVATAR_KIND, "x": torch.zeros(2)}, AVATAR_KIND, AVATAR_FORMAT)
    data = path.read_bytes()
    meta = dict(_read_header(data)[0]["__metadata__"])
    meta[META_TREE] = meta[META_TREE][:-1] + ',"args":' + "[" * 200_000 + "]" * 200_000 + "}"
    meta[META_DIGEST] = tree_digest(meta["sage.kind"], meta["sage.format"], meta[META_TREE], meta[META_SHA])
    path.write_bytes(save(load(data), metadata=meta))
    with pytest.raises(InputError, match="nested deeper than"):
        load_file(path, AVATAR_KIND, AVATAR_FORMAT, "avatar file")


def _rewrite_header(path: Path, header_text) -> None:
    """Replace the JSON header of a safetensors file by ``header_text(header dict)``, data kept."""
    import struct

    from sage_core.serialization import _read_header

    data = path.read_bytes()
    header, start = _read_header(data)
    text = header_text(header).encode("utf-8")
    path.write_bytes(struct.pack("<Q", len(text)) + text + data[start:])


@pytest.mark.parametrize("case,problem", [
    ("deep", "unreadable header (nested too deeply)"),
    ("metadata list", "unreadable header (its __metadata__ is not a map of strings)"),
    ("format list", "unreadable header (its __metadata__ is not a map of strings)"),
    ("format text", "unreadable format version"),
])
def test_a_hostile_safetensors_header_is_damaged_not_a_traceback(tmp_path, case, problem):
    import torch

    from sage_core.errors import InputError
    from sage_core.serialization import AVATAR_FORMAT, AVATAR_KIND, inspect_file, load_file, save_file

    path = save_file(tmp_path / "avatar.pt", {"kind": AVATAR_KIND, "x": torch.zeros(2)}, AVATAR_KIND, AVATAR_FORMAT)

    def edit(header: dict) -> str:
        if case == "deep":
            return json.dumps(header)[:-1] + ', "nest": ' + "[" * 100_000 + "]" * 100_000 + "}"
        if case == "metadata list":
            header["__metadata__"] = [1, 2]
        else:
            header["__metadata__"]["sage.format"] = [AVATAR_FORMAT] if case == "format list" else f"{AVATAR_FORMAT}x"
        return json.dumps(header)

    _rewrite_header(path, edit)
    with pytest.raises(InputError) as ei:
        load_file(path, AVATAR_KIND, AVATAR_FORMAT, "avatar file")
    assert ei.value.path == path and problem in ei.value.problem
    check = inspect_file(path)
    assert check.status == "corrupt" and problem.split(" (")[0] in check.reason


def test_a_full_disk_names_the_file_being_written(small_capture, tmp_path, monkeypatch):
    real_fsync = os.fsync

    def full(fd: int) -> None:
        if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")).startswith(".cameras."):
            raise OSError(errno.ENOSPC, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", full)
    res = _ingest(small_capture, tmp_path / "ws")
    assert res.exit_code == 2, text(res)
    assert "No space left on device" in text(res) and "cameras.json" in text(res)
    assert not (tmp_path / "ws" / "data").exists()


_INTERRUPT_TWICE = textwrap.dedent(
    """
    import os, signal, sys, threading, time
    import sage_core.workspace as w
    real = w.save_checkpoint
    def save(directory, step, state, keep=2):
        out = real(directory, step, state, keep)
        if step == 2:
            def twice():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
                os.kill(os.getpid(), signal.SIGINT)
            threading.Thread(target=twice).start()
            time.sleep(5)
        return out
    w.save_checkpoint = save
    from sage_cli.app import main
    sys.argv = ["sage", *sys.argv[1:]]
    main()
    """
)
P1_ARGS = ["--preset", "tiny", "--device", "cpu", "--threads", "1", "--iterations", "8", "--surfels", "300",
           "--set", "checkpoint_every=2", "--set", "rays_per_step=32", "--set", "neus_samples=8", "--set", "neus_importance=8",
           "--set", "neus_up_steps=1", "--set", "rebind_every=0", "--set", "eval_every=0", "--set", "mc_resolution=32",
           "--set", "app_hidden=16", "--set", "shape_hidden=16"]  # fmt: skip


def test_two_interrupts_50_ms_apart_end_cleanly_and_info_says_interrupted(init_mesh_ws, tmp_path):
    ws = _copy(init_mesh_ws, tmp_path, "ws")
    env = {**os.environ, **ENV}
    res = subprocess.run([sys.executable, "-c", _INTERRUPT_TWICE, "phase1", str(ws), *P1_ARGS], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert res.returncode == 130, res.stderr[-3000:]
    assert "Traceback" not in res.stderr and "interrupted" in res.stderr, res.stderr[-3000:]
    info = text(invoke("info", ws))
    assert "interrupted" in info and "failed" not in info, info
    assert not (ws / ".work" / "phase1" / "FAILED").exists() and not (ws / ".work" / "phase1" / "RUNNING").exists()


# --------------------------------------------------------------------------------------------
# documented exits, symlinks, status
# --------------------------------------------------------------------------------------------


def test_a_deleted_workspace_model_exits_4_naming_the_stage(cmd_avatar_ws, tmp_path):
    ws = _copy(cmd_avatar_ws, tmp_path, "ws")
    (ws / "init" / "flame_model.npz").unlink()
    res = invoke("export", ws, "--ply", "--quiet")
    assert res.exit_code == 4, text(res)
    assert "init-mesh" in text(res) and "flame_model.npz" in text(res)
    info = text(invoke("info", ws))
    assert "incomplete" in info and "init-mesh" in info


def test_capture_symlinks_pointing_outside_are_refused_unless_asked(small_capture, tmp_path):
    cap = _copy(small_capture, tmp_path)
    elsewhere = tmp_path / "elsewhere"
    shutil.move(cap / "images", elsewhere)
    (cap / "images").symlink_to(elsewhere, target_is_directory=True)
    res = _ingest(cap, tmp_path / "ws")
    assert res.exit_code == 2 and "symbolic link" in text(res), text(res)
    assert not (tmp_path / "ws" / "data").exists()
    res = _ingest(cap, tmp_path / "ws", "--set", "follow_symlinks=true")
    assert res.exit_code == 0, text(res)

    cap2 = _copy(small_capture, tmp_path, "cap2")
    one = sorted((cap2 / "images").iterdir())[0]
    outside = tmp_path / "outside.png"
    shutil.move(one, outside)
    one.symlink_to(outside)
    res = _ingest(cap2, tmp_path / "ws2")
    assert res.exit_code == 2 and one.name in text(res) and "symbolic link" in text(res), text(res)


def test_status_running_and_interrupted_follow_the_live_process(init_mesh_ws, tmp_path):
    from sage_core.workspace import Workspace

    ws = _copy(init_mesh_ws, tmp_path, "ws")
    work = ws / ".work" / "phase1"
    work.mkdir(parents=True)
    (work / "RUNNING").write_text(json.dumps({"pid": os.getpid(), "host": os.uname().nodename, "since": "2026-01-01T00:00:00Z"}))
    st = Workspace(ws).status("phase1")
    assert st.status == "running" and f"pid {os.getpid()}" in st.reason
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
    (work / "RUNNING").write_text(json.dumps({"pid": int(dead), "host": os.uname().nodename, "since": "2026-01-01T00:00:00Z"}))
    assert Workspace(ws).status("phase1").status == "interrupted"


def test_info_verify_finds_outputs_changed_after_completion(init_mesh_ws, tmp_path):
    ws = _copy(init_mesh_ws, tmp_path, "ws")
    res = invoke("info", ws, "--verify")
    assert res.exit_code == 0 and "verified" in text(res), text(res)
    target = ws / "data" / "cameras.json"
    data = bytearray(target.read_bytes())
    data[-2] = ord(" ") if data[-2] != ord(" ") else ord("\n")  # same size, other bytes
    target.write_bytes(bytes(data))
    res = invoke("info", ws, "--verify")
    assert res.exit_code == 4, text(res)
    assert "changed" in text(res) and "cameras.json" in text(res)
    assert "complete" in text(invoke("info", ws))  # without --verify only sizes are checked


# --------------------------------------------------------------------------------------------
# bundle.json fields of the wrong type
# --------------------------------------------------------------------------------------------


def _bundle_meta() -> dict:
    """The fields of a format-3 bundle.json that loading a bundle reads, with valid values."""
    return {
        "kind": "sage-avatar-bundle", "format": 3,
        "files": {"avatar": "avatar.safetensors", "flame_params": "flame_param.npz"},
        "flame": {"n_vertices": 4434, "model": {"included": False, "file": "m.npz", "file_sha256": "0" * 64,
                                                "file_sha256_prefix": "0" * 16, "base_sha256": "1" * 64,
                                                "mouth_interior": {"lips": [1, 2, 3], "cavity": True, "tongue": True}}},
        "surfels": {"count": 600},
        "render": {"near": 0.2, "far": 3.0, "background": 1.0, "correction": None},
        "reference_camera": {"K": [[400.0, 0.0, 64.0], [0.0, 400.0, 90.0], [0.0, 0.0, 1.0]],
                             "w2c": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0]],
                             "width": 128, "height": 186, "index": 8, "name": "222200296"},
        "head_center": [0.0, -0.02, 0.0],
    }


def _set_path(d: dict, path: str, value) -> None:
    *parents, last = path.split("/")
    for key in parents:
        d = d[key]
    d[last] = value


@pytest.mark.parametrize("field,value,problem", [
    ("format", "x", "'format' is 'x', expected a whole number"),
    ("surfels/count", "many", "'surfels' → 'count' is 'many', expected a whole number"),
    ("head_center", [1, 2], "'head_center' is [1, 2], expected three finite numbers"),
    ("render/near", "x", "'render' → 'near' is 'x', expected a finite number"),
    ("render/far", 10**400, "'render' → 'far' is"),
    ("flame/model", [1], "'flame' → 'model' is not an object"),
    ("flame/model/included", "no", "'included' is not true or false"),
    ("flame/model/mouth_interior/lips", ["a"], "'lips' is not a list of vertex ids"),
    ("files/avatar", ["avatar.safetensors"], "'files' → 'avatar' is ['avatar.safetensors'], expected a file name"),
    ("reference_camera/K", [[1, 2], [3, 4]], "'reference_camera' → 'K' is not a 3x3 list of finite numbers"),
    ("reference_camera/width", "wide", "'reference_camera' → 'width' is 'wide'"),
])
def test_bundle_metadata_fields_of_the_wrong_type_are_named(tmp_path, field, value, problem):
    from sage_core.errors import InputError
    from sage_core.export.bundle import read_bundle_metadata

    bundle = tmp_path / "bundle"
    bundle.mkdir()
    meta = _bundle_meta()
    (bundle / "bundle.json").write_text(json.dumps(meta))
    assert read_bundle_metadata(bundle)["surfels"]["count"] == 600  # the valid document reads
    _set_path(meta, field, value)
    (bundle / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(InputError) as ei:
        read_bundle_metadata(bundle)
    assert ei.value.path == bundle / "bundle.json"
    assert ei.value.problem.startswith("malformed bundle metadata: ") and problem in ei.value.problem


def test_reenact_names_a_malformed_or_too_deep_bundle_json(tmp_path):
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    meta = _bundle_meta()
    meta["render"]["background"] = None
    (bundle / "bundle.json").write_text(json.dumps(meta))
    motion = tmp_path / "motion.npz"
    np.savez(motion, expr=np.zeros((1, 10), np.float32))
    res = invoke("reenact", "--bundle", bundle, "--flame-seq", motion, "--out", tmp_path / "out", "--device", "cpu", "--quiet")
    assert res.exit_code == 2, text(res)
    assert f"{bundle / 'bundle.json'}: malformed bundle metadata: 'render' → 'background' is None" in text(res)
    (bundle / "bundle.json").write_text('{"kind": "sage-avatar-bundle", "a": ' + "[" * 100_000 + "]" * 100_000 + "}")
    res = invoke("reenact", "--bundle", bundle, "--flame-seq", motion, "--out", tmp_path / "out", "--device", "cpu", "--quiet")
    assert res.exit_code == 2, text(res)
    assert f"{bundle / 'bundle.json'}: cannot read bundle metadata: nested too deeply" in text(res)
    assert not (tmp_path / "out").exists()
