"""Reliability corpus: hostile files, broken captures and workspaces, changed inputs, and processes
killed mid-training or mid-promotion.

Every case checks the exit code, that the message names the file and the problem, and that nothing
was half-written or lost (see docs/workspace.md "Guarantees").
"""

from __future__ import annotations

import errno
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from sage_cli.app import app

REPO = Path(__file__).resolve().parents[1]
ENV = {"COLUMNS": "400", "SAGE_LPIPS_WEIGHTS": "", "OMP_NUM_THREADS": "1"}
INIT_FLAGS = ["--set", "pretrain.steps=20", "--set", "pretrain.bank_size=4000", "--set", "pretrain.batch_size=1024",
              "--set", "mc_resolution=32", "--set", "pretrain.eval_samples=2000"]  # fmt: skip
P1_ARGS = ["--preset", "tiny", "--device", "cpu", "--quiet", "--threads", "1", "--iterations", "6", "--surfels", "300",
           "--set", "checkpoint_every=2", "--set", "rays_per_step=32", "--set", "neus_samples=8", "--set", "neus_importance=8",
           "--set", "neus_up_steps=1", "--set", "rebind_every=0", "--set", "eval_every=0", "--set", "mc_resolution=32",
           "--set", "app_hidden=16", "--set", "shape_hidden=16"]  # fmt: skip
P2_ARGS = ["--preset", "tiny", "--device", "cpu", "--quiet", "--threads", "1", "--iterations", "4", "--correction", "off",
           "--set", "checkpoint_every=2", "--set", "rays_per_step=32", "--set", "neus_samples=8", "--set", "neus_importance=8",
           "--set", "neus_up_steps=1", "--set", "eval_phase1=false", "--set", "eval_frames=1"]  # fmt: skip


def invoke(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args], env=ENV)


def text(res) -> str:
    out = res.output
    try:
        out += res.stderr
    except (ValueError, AttributeError):
        pass
    return " ".join(out.split())


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes (to prove nothing changed)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------------------------
# hostile payloads: nothing runs, the message names the file and how to convert a trusted one
# --------------------------------------------------------------------------------------------


class _Payload:
    """Unpickling this runs ``touch marker``."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _payload_files(tmp_path: Path) -> tuple[Path, dict[str, Path]]:
    marker = tmp_path / "PWNED"
    p = _Payload(marker)
    files = {
        "avatar": tmp_path / "avatar.pt",
        "sdf": tmp_path / "sdf.pt",
        "checkpoint": tmp_path / "checkpoints" / "ckpt_00000010.pt",
        "raw": tmp_path / "raw.pt",
    }
    files["checkpoint"].parent.mkdir()
    torch.save({"kind": "sage-avatar", "format": 1, "args": p}, files["avatar"])
    torch.save({"format": 1, "args": {}, "state": p}, files["sdf"])
    torch.save({"format": 1, "step": 10, "state": {"trainer": p}}, files["checkpoint"])
    with open(files["raw"], "wb") as fh:
        pickle.dump({"kind": p}, fh)
    return marker, files


def test_payloads_of_every_file_kind_never_run(tmp_path):
    from sage_core.avatar.model import Avatar
    from sage_core.errors import StageError, UnsafeFileError
    from sage_core.fields.sdf_file import load_sdf, read_sdf_file
    from sage_core.workspace import latest_checkpoint, load_checkpoint

    marker, files = _payload_files(tmp_path)
    # the payload works: a plain unpickle would have run it
    for name, path in files.items():
        with pytest.raises(UnsafeFileError, match=r"old pickle format.*sage convert .*--trust") as ei:
            Avatar.load(path)
        assert str(path) in str(ei.value), name
    for loader in (load_sdf, read_sdf_file):
        with pytest.raises(UnsafeFileError, match=r"SDF file in the old pickle format.*sage convert"):
            loader(files["sdf"])
    ck = latest_checkpoint(files["checkpoint"].parent)
    assert ck == files["checkpoint"]  # returned (not skipped as damaged), so that it is refused loudly
    with pytest.raises(StageError, match=r"ckpt_00000010.pt: checkpoint in the old pickle format.*sage convert"):
        load_checkpoint(ck)
    assert not marker.exists()
    # control: the same file does run its payload under an unsafe load
    torch.load(files["sdf"], weights_only=False)
    assert marker.exists()


def test_payload_bundle_is_refused_by_reenact_and_convert_needs_trust(tmp_path, tiny_capture):
    marker, files = _payload_files(tmp_path)
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    shutil.copy(files["avatar"], bundle / "avatar.pt")
    meta = {"kind": "sage-avatar-bundle", "format": 1, "files": {"avatar": "avatar.pt"}, "flame": {}, "surfels": {}}
    (bundle / "bundle.json").write_text(json.dumps(meta))
    res = invoke("reenact", "--bundle", bundle, "--flame-seq", tiny_capture, "--out", tmp_path / "out", "--device", "cpu", "--quiet")
    msg = text(res)
    assert res.exit_code == 2, msg
    assert str(bundle / "avatar.pt") in msg and "old pickle format" in msg and "sage convert" in msg
    assert not (tmp_path / "out").exists()
    res = invoke("convert", bundle / "avatar.pt")
    assert res.exit_code == 3 and "--trust" in text(res)
    assert not marker.exists()


def test_convert_trusted_old_avatar_round_trips(tmp_path, tiny_init_dir, tiny_ws):
    """A genuine old (pickle) avatar file is refused, converted with --trust, then loads the same."""
    from sage_core.avatar.model import AVATAR_KIND, Avatar
    from sage_core.config import resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.errors import UnsafeFileError
    from sage_core.serialization import load_file
    from sage_core.train.phase1 import build_avatar

    cfg = resolve_config("phase1", "tiny", None, {"n_surfels": 200, "app_hidden": 16, "shape_hidden": 16})
    av = build_avatar(IngestedData.open(tiny_ws / "data"), tiny_init_dir, cfg, "cpu", torch.Generator().manual_seed(0))
    new = av.save(tmp_path / "new.pt")
    blob, _ = load_file(new, AVATAR_KIND, 99, "avatar file")
    blob["format"] = 1
    old = tmp_path / "old.pt"
    torch.save(blob, old)  # what sage wrote before
    with pytest.raises(UnsafeFileError):
        Avatar.load(old)
    res = invoke("convert", old, "--trust")
    assert res.exit_code == 0 and "converted (sage-avatar)" in text(res), text(res)
    assert (tmp_path / "old.pt.pickle-backup").is_file()
    back = Avatar.load(old)
    for k, v in av.state_dict().items():
        assert torch.equal(v, back.state_dict()[k]), k
    res = invoke("convert", old, "--trust")
    assert res.exit_code == 0 and "already in the safe format" in text(res)
    # a folder (an old bundle, a workspace) is searched for old pickle files; the others are left alone
    folder = tmp_path / "old_bundle"
    folder.mkdir()
    torch.save(blob, folder / "avatar.pt")
    shutil.copy(new, folder / "other.pt")
    res = invoke("convert", folder, "--trust", "--no-backup")
    assert res.exit_code == 0 and "avatar.pt: converted (sage-avatar)" in text(res) and "other.pt" not in text(res), text(res)
    assert sorted(p.name for p in folder.iterdir()) == ["avatar.pt", "other.pt"]
    Avatar.load(folder / "avatar.pt")


# --------------------------------------------------------------------------------------------
# broken workspaces
# --------------------------------------------------------------------------------------------


def _copy(ws: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "ws"
    shutil.copytree(ws, dst)
    return dst


def test_workspace_path_is_a_file_or_under_a_file(tmp_path, tiny_capture):
    f = tmp_path / "notes.txt"
    f.write_text("mine")
    res = invoke("init-mesh", f, "--preset", "tiny", "--device", "cpu", "--quiet")
    assert res.exit_code == 2 and str(f) in text(res), text(res)
    ingest = ("--flame-model", tiny_capture.model_path, "--preset", "tiny", "--quiet", "--device", "cpu")
    res = invoke("ingest", tiny_capture, f, *ingest)
    assert res.exit_code == 2 and f"{f}: is a file, not a workspace folder" in text(res), text(res)
    res = invoke("ingest", tiny_capture, f / "ws", *ingest)
    assert res.exit_code == 2 and f"{f} is a file, not a folder" in text(res), text(res)
    assert f.read_text() == "mine"


def test_read_only_workspace_is_refused_before_training(init_mesh_ws, tmp_path, monkeypatch):
    ws = _copy(init_mesh_ws, tmp_path)
    before = snapshot(ws / "init")
    if os.geteuid() == 0:  # root writes anywhere: stand in for the kernel's refusal
        import sage_core.workspace as wsmod

        def refuse(folder):
            raise PermissionError(errno.EACCES, "Permission denied", str(folder))

        monkeypatch.setattr(wsmod, "_probe_write", refuse)
    else:
        for d in (ws, ws / ".work"):
            d.mkdir(exist_ok=True)
            d.chmod(0o555)
    try:
        res = invoke("phase1", ws, *P1_ARGS)
    finally:
        for d in (ws, ws / ".work"):
            d.chmod(0o755)
    msg = text(res)
    assert res.exit_code == 2 and f"{ws}: the workspace is not writable (Permission denied)" in msg, msg
    assert not (ws / ".work" / "phase1").exists() and not (ws / "phase1").exists()
    assert snapshot(ws / "init") == before


def test_manifest_that_is_json_but_not_an_object(init_mesh_ws, tmp_path):
    ws = _copy(init_mesh_ws, tmp_path)
    (ws / "init" / "manifest.json").write_text("[]\n")
    res = invoke("info", ws)
    assert res.exit_code == 0
    assert "corrupt" in text(res) and "is not a JSON object" in text(res)
    res = invoke("phase1", ws, *P1_ARGS)
    msg = text(res)
    assert res.exit_code == 4 and "needs stage 'init-mesh', which is corrupt" in msg and "not a JSON object" in msg, msg
    assert not (ws / "phase1").exists()


def test_deleted_output_makes_the_stage_incomplete(init_mesh_ws, tmp_path):
    from sage_core.workspace import Workspace, begin_stage, read_json

    ws = _copy(init_mesh_ws, tmp_path)
    (ws / "init" / "flame_model.npz").unlink()
    w = Workspace(ws)
    st = w.status("init-mesh")
    assert st.status == "incomplete" and "flame_model.npz is missing" in st.reason
    res = invoke("phase1", ws, *P1_ARGS)
    assert res.exit_code == 4 and "which is incomplete (output flame_model.npz is missing)" in text(res), text(res)
    # the same config and inputs no longer count as complete: init-mesh runs again instead of skipping
    m = read_json(ws / "init" / "manifest.json")
    with w.lock:
        run = begin_stage(w, "init-mesh", read_json(ws / "init" / "config.json"), m["config_hash"], requires=["ingest"])
    assert run is not None
    assert "incomplete" in text(invoke("info", ws))


# --------------------------------------------------------------------------------------------
# changed inputs
# --------------------------------------------------------------------------------------------


def test_changed_image_or_retracked_params_make_ingest_and_later_stages_stale(tiny_capture, tmp_path):
    from sage_core.data.imageio import read_image, write_image
    from sage_core.workspace import HASH_CACHE, Workspace, begin_stage

    cap = tmp_path / "cap"
    shutil.copytree(tiny_capture, cap)
    model = cap / tiny_capture.model_path.relative_to(tiny_capture)
    ws = tmp_path / "ws"
    args = ("ingest", cap, ws, "--flame-model", model, "--preset", "tiny", "--quiet", "--device", "cpu")
    assert invoke(*args).exit_code == 0
    w = Workspace(ws)
    with w.lock:  # a downstream stage that read this ingest
        run = begin_stage(w, "init-mesh", {"x": 1}, "x", requires=["ingest"])
        (run.work_dir / "out.txt").write_text("x")
        run.finish()
    res = invoke(*args)
    assert res.exit_code == 0 and "skipping" in text(res)
    cache = json.loads((ws / HASH_CACHE).read_text())  # re-runs hash only files whose size or mtime changed
    assert len(cache) >= 80 and all(len(v) == 3 for v in cache.values())
    # replace one training image's content (same name, same size)
    img_path = sorted((cap / "images").glob("*.png"))[0]
    img = read_image(img_path)
    write_image(img_path, np.clip(1.0 - img, 0, 1))
    res = invoke(*args)
    assert res.exit_code == 0 and "skipping" not in text(res), text(res)
    st = w.status("init-mesh")
    assert st.status == "stale" and "ingest" in st.reason
    # re-tracking: one timestep's FLAME parameters change
    npz = sorted((cap / "flame_param").glob("*.npz"))[0]
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["expr"] = arrays["expr"] + np.float32(0.01)
    np.savez(npz, **arrays)
    fp = w.manifest("ingest")["fingerprint"]
    res = invoke(*args)
    assert res.exit_code == 0 and "skipping" not in text(res)
    assert w.manifest("ingest")["fingerprint"] != fp


def test_broken_capture_leaves_no_workspace_and_keeps_an_existing_one(tiny_capture, tiny_ws, tmp_path):
    cap = tmp_path / "cap"
    shutil.copytree(tiny_capture, cap)
    model = cap / tiny_capture.model_path.relative_to(tiny_capture)
    img = sorted((cap / "images").glob("*.png"))[0]
    img.write_bytes(img.read_bytes()[:60])  # truncated PNG
    new_ws = tmp_path / "new_ws"
    res = invoke("ingest", cap, new_ws, "--flame-model", model, "--preset", "tiny", "--quiet", "--device", "cpu")
    assert res.exit_code == 2 and img.name in text(res), text(res)
    assert not new_ws.exists()
    ws = tmp_path / "ws"
    shutil.copytree(tiny_ws, ws)
    before = snapshot(ws / "data")
    res = invoke("ingest", cap, ws, "--flame-model", model, "--preset", "tiny", "--quiet", "--device", "cpu")
    assert res.exit_code == 2 and img.name in text(res)
    assert snapshot(ws / "data") == before and not (ws / ".work" / "data").exists()
    # a FLAME parameter file that is not an npz
    shutil.copy2(tiny_capture / "images" / img.name, img)
    npz = sorted((cap / "flame_param").glob("*.npz"))[0]
    npz.write_bytes(b"not an npz")
    res = invoke("ingest", cap, ws, "--flame-model", model, "--preset", "tiny", "--quiet", "--device", "cpu")
    assert res.exit_code == 2 and npz.name in text(res), text(res)
    assert snapshot(ws / "data") == before


# --------------------------------------------------------------------------------------------
# kill and resume
# --------------------------------------------------------------------------------------------

_KILLER = textwrap.dedent(
    """
    import os, signal, shutil, sys
    import sage_core.workspace as w
    point, arg = sys.argv[1], sys.argv[2]
    die = lambda: os.kill(os.getpid(), signal.SIGKILL)
    if point == "checkpoint":
        real_save = w.save_checkpoint
        def save(directory, step, state, keep=2):
            out = real_save(directory, step, state, keep)
            if int(step) == int(arg):
                die()
            return out
        w.save_checkpoint = save
    elif point == "promote":  # between moving the old output aside and renaming the new one into place
        real_replace = os.replace
        def replace(src, dst):
            if os.path.basename(str(dst)) == arg and os.path.basename(os.path.dirname(str(src))) == ".work":
                die()
            return real_replace(src, dst)
        os.replace = replace
    elif point == "cleanup":  # promoted, checkpoints not yet removed
        real_rmtree = shutil.rmtree
        def rmtree(path, *a, **k):
            if str(path).endswith(os.path.join(arg, "checkpoints")):
                die()
            return real_rmtree(path, *a, **k)
        shutil.rmtree = rmtree
    from sage_cli.app import app
    sys.argv = ["sage", *sys.argv[3:]]
    app()
    """
)


def _run_killed(ws: Path, stage: str, args: list[str], *, kill_after_checkpoint: int | None = None,
                kill_at: str | None = None, extra: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    point, arg = ("checkpoint", str(kill_after_checkpoint)) if kill_after_checkpoint is not None else (kill_at, stage)
    folder = {"phase1": "phase1", "phase2": "phase2"}[stage]
    if point in ("promote", "cleanup"):
        arg = folder
    env = {**os.environ, **ENV}
    cmd = [sys.executable, "-c", _KILLER, point, arg, stage, str(ws), *args, *extra]
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


def _avatar_state(path: Path) -> dict[str, torch.Tensor]:
    from sage_core.avatar.model import Avatar

    return {k: v for k, v in Avatar.load(path).state_dict().items() if not k.startswith("flame.")}


def _assert_same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.fixture(scope="module")
def phase1_reference(init_mesh_ws, tmp_path_factory):
    """An uninterrupted phase-1 run (the workspace and its avatar state)."""
    ws = tmp_path_factory.mktemp("ref1") / "ws"
    shutil.copytree(init_mesh_ws, ws)
    res = invoke("phase1", ws, *P1_ARGS)
    assert res.exit_code == 0, text(res)
    return ws, _avatar_state(ws / "phase1" / "avatar.pt")


def test_phase1_killed_mid_training_and_mid_promotion_resumes_bit_identically(init_mesh_ws, phase1_reference, tmp_path):
    ref_ws, ref = phase1_reference
    ws = _copy(init_mesh_ws, tmp_path)
    # 1. SIGKILL right after the step-4 checkpoint
    res = _run_killed(ws, "phase1", P1_ARGS, kill_after_checkpoint=4)
    assert res.returncode == -signal.SIGKILL, res.stderr[-2000:]
    assert not (ws / "phase1").exists()
    assert sorted(p.name for p in (ws / ".work" / "phase1" / "checkpoints").glob("ckpt_*.pt")) == ["ckpt_00000002.pt", "ckpt_00000004.pt"]
    # ... and the newest checkpoint is damaged (truncated): the resume falls back to step 2, says so
    newest = ws / ".work" / "phase1" / "checkpoints" / "ckpt_00000004.pt"
    newest.write_bytes(newest.read_bytes()[: newest.stat().st_size // 2])
    res = invoke("phase1", ws, *P1_ARGS)
    assert res.exit_code == 0 and "resuming" in text(res), text(res)
    log = "\n".join(p.read_text() for p in (ws / "logs").glob("phase1-*.log"))
    assert "ckpt_00000004.pt is damaged" in log and "resuming from ckpt_00000002.pt instead" in log
    _assert_same(_avatar_state(ws / "phase1" / "avatar.pt"), ref)
    assert json.loads((ws / "phase1" / "manifest.json").read_text())["resumed"] is True
    first = snapshot(ws / "phase1")
    # 2. a forced re-run killed between moving the old output aside and renaming the new one in
    res = _run_killed(ws, "phase1", P1_ARGS, kill_at="promote", extra=("--force",))
    assert res.returncode == -signal.SIGKILL, res.stderr[-2000:]
    assert not (ws / "phase1").exists()  # the old output is aside, the new run waits in .work
    assert (ws / ".work" / "phase1" / "manifest.json").is_file()
    assert "interrupted" in text(invoke("info", ws))
    res = invoke("phase1", ws, *P1_ARGS)  # completes the move, nothing is trained again
    assert res.exit_code == 0 and "skipping" in text(res), text(res)
    _assert_same(_avatar_state(ws / "phase1" / "avatar.pt"), ref)
    assert not (ws / ".work" / "phase1").exists() and not list((ws / ".work").glob(".old-*"))
    # 3. killed after the rename, before its checkpoints were removed
    res = _run_killed(ws, "phase1", P1_ARGS, kill_at="cleanup", extra=("--force",))
    assert res.returncode == -signal.SIGKILL, res.stderr[-2000:]
    assert (ws / "phase1" / "checkpoints").is_dir() and (ws / "phase1" / "manifest.json").is_file()
    res = invoke("phase1", ws, *P1_ARGS)
    assert res.exit_code == 0 and "skipping" in text(res)
    assert not (ws / "phase1" / "checkpoints").exists() and not (ws / "phase1" / "RUN").exists()
    _assert_same(_avatar_state(ws / "phase1" / "avatar.pt"), ref)
    assert set(snapshot(ws / "phase1")) == set(first)


def test_phase2_killed_mid_training_and_mid_promotion_resumes(phase1_reference, tmp_path):
    ref_ws, _ = phase1_reference
    a = _copy(ref_ws, tmp_path / "a")
    res = invoke("phase2", a, *P2_ARGS)
    assert res.exit_code == 0, text(res)
    ref = _avatar_state(a / "phase2" / "avatar.pt")
    b = _copy(ref_ws, tmp_path / "b")
    res = _run_killed(b, "phase2", P2_ARGS, kill_after_checkpoint=2)
    assert res.returncode == -signal.SIGKILL, res.stderr[-2000:]
    assert not (b / "phase2").exists() and (b / ".work" / "phase2" / "checkpoints" / "ckpt_00000002.pt").is_file()
    res = _run_killed(b, "phase2", P2_ARGS, kill_at="promote")
    assert res.returncode == -signal.SIGKILL, res.stderr[-2000:]
    res = invoke("phase2", b, *P2_ARGS)
    assert res.exit_code == 0 and "skipping" in text(res), text(res)
    # phase 2 resumes to float rounding, as its in-memory resume does (test_phase2.test_exact_resume):
    # the checkpoint file itself restores the trainer state bit for bit (test_workspace)
    got = _avatar_state(b / "phase2" / "avatar.pt")
    assert got.keys() == ref.keys()
    for k in ref:
        torch.testing.assert_close(got[k], ref[k], atol=1e-6, rtol=1e-5)
    m = json.loads((b / "phase2" / "manifest.json").read_text())
    assert m["resumed"] is True and m["status"] == "complete"


# --------------------------------------------------------------------------------------------
# the bundle: documented, pickle-free, GaussianAvatars' parameter file; one FLAME copy per workspace
# --------------------------------------------------------------------------------------------


def test_bundle_is_pickle_free_documented_and_ga_compatible(phase1_reference, tmp_path):
    from safetensors import safe_open

    from sage_core.avatar.model import Avatar
    from sage_core.export.bundle import GA_PARAM_KEYS, RenderSettings, load_bundle, write_bundle
    from sage_core.serialization import inspect_file

    ws, ref = phase1_reference
    ws_avatar = ws / "phase1" / "avatar.pt"
    with safe_open(str(ws_avatar), "pt") as f:  # the workspace avatar stores no FLAME basis
        assert not [k for k in f.keys() if k.startswith("flame/")]
    av = Avatar.load(ws_avatar)
    out = write_bundle(av, tmp_path / "bundle", RenderSettings())
    assert sorted(p.name for p in out.iterdir()) == ["avatar.safetensors", "bundle.json", "flame_param.npz"]
    assert inspect_file(out / "avatar.safetensors").status == "ok"
    assert (out / "avatar.safetensors").stat().st_size > 2 * ws_avatar.stat().st_size  # the bundle carries the basis
    umask = os.umask(0)
    os.umask(umask)
    assert (out / "flame_param.npz").stat().st_mode & 0o777 == 0o666 & ~umask
    with np.load(out / "flame_param.npz", allow_pickle=False) as z:
        assert sorted(z.files) == sorted(GA_PARAM_KEYS)
        assert all(z[k].dtype == np.float32 for k in z.files)
        T = z["expr"].shape[0]
        assert z["dynamic_offset"].shape[0] == T and z["static_offset"].shape[0] == 1
        assert z["dynamic_offset"].shape[1:] == z["static_offset"].shape[1:]
        np.testing.assert_array_equal(z["expr"], np.asarray(av.params.expr, np.float32))
    meta = json.loads((out / "bundle.json").read_text())
    assert meta["format"] == 3 and meta["flame"]["model"] == {"included": True} and meta["files"]["avatar"] == "avatar.safetensors"
    with safe_open(str(out / "avatar.safetensors"), "pt") as f:
        names = set(f.keys())
        described = meta["arrays"]["avatar.safetensors"]
        assert set(described) == names
        for n in names:
            assert described[n]["shape"] == list(f.get_slice(n).get_shape()) and described[n]["meaning"] != "avatar data", n
    assert set(meta["arrays"]["flame_param.npz"]) == set(GA_PARAM_KEYS)
    b = load_bundle(out)
    _assert_same({k: v for k, v in b.avatar.state_dict().items() if not k.startswith("flame.")}, ref)
    # moved out of its workspace, a workspace avatar file says what it misses
    from sage_core.errors import InputError

    lone = tmp_path / "lone" / "avatar.pt"
    lone.parent.mkdir()
    shutil.copy(ws_avatar, lone)
    with pytest.raises(InputError, match=r"references the workspace FLAME model init/flame_model.npz.*sage export WS --bundle"):
        Avatar.load(lone)
