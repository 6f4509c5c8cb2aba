"""Shared pytest configuration: the ``cuda`` marker skips without a CUDA device; the workspaces the
tests share, each built once per session (plain helpers are in tests/helpers.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from helpers import NOVEL_EXPRESSIONS, NOVEL_VIEWS

REPO = Path(__file__).resolve().parents[1]


def pytest_collection_modifyitems(config, items):
    try:
        import torch

        has_cuda = torch.cuda.is_available()
    except ImportError:  # pragma: no cover
        has_cuda = False
    if has_cuda:
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory):
    """A tiny synthetic multiview capture (built once per test session)."""
    from sage_core.data.synthetic import make_capture
    from sage_core.data.synthetic.config import preset

    return make_capture(tmp_path_factory.mktemp("capture") / "cap", preset("tiny"))


@pytest.fixture(scope="session")
def tiny_ws(tiny_capture, tmp_path_factory):
    """A workspace with the tiny capture ingested (mv-sf), shared read-only by tests."""
    from typer.testing import CliRunner

    from sage_cli.app import app

    ws = tmp_path_factory.mktemp("ws") / "ws"
    res = CliRunner().invoke(
        app, ["ingest", str(tiny_capture), str(ws), "--flame-model", str(tiny_capture.model_path), "--preset", "tiny", "--quiet", "--device", "cpu"]
    )
    assert res.exit_code == 0, res.output
    return ws


@pytest.fixture
def one_thread():
    """Small ops: one torch thread is faster than two on a busy 2-core machine."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def tiny_init_dir(tiny_ws, tmp_path_factory):
    """init-mesh outputs (quick SDF pretraining) of ``tiny_ws``, built once and shared read-only."""
    import torch

    from sage_core.config import resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.train.init_mesh import run_init_mesh

    flags = {"pretrain.steps": 20, "pretrain.bank_size": 4000, "pretrain.batch_size": 1024, "mc_resolution": 32,
             "pretrain.eval_samples": 2000}  # fmt: skip
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    out = tmp_path_factory.mktemp("tiny_init")
    run_init_mesh(IngestedData.open(tiny_ws / "data"), out, resolve_config("init-mesh", "tiny", None, flags), seed=0)
    torch.set_num_threads(before)
    return out


@pytest.fixture(scope="session")
def init_mesh_ws(tiny_ws, tiny_init_dir, tmp_path_factory):
    """tiny_ws with the shared init-mesh outputs promoted as its init-mesh stage (copy before use)."""
    import shutil

    from sage_core.workspace import Workspace, begin_stage

    ws = tmp_path_factory.mktemp("rel") / "ws"
    shutil.copytree(tiny_ws, ws)
    w = Workspace(ws)
    with w.lock:
        run = begin_stage(w, "init-mesh", {"copied": True}, "copied-init", requires=["ingest"])
        for f in tiny_init_dir.iterdir():
            if f.is_file():
                shutil.copy2(f, run.work_dir / f.name)
        run.finish()
    return ws


@pytest.fixture(scope="session")
def tiny_avatar_ws(tiny_ws, tiny_init_dir, tmp_path_factory):
    """A workspace with complete ingest, init-mesh (the quick ``tiny_init_dir``) and phase1 stages;
    the phase-1 avatar is an untrained 300-surfel one moved off its initial state. Shared read-only."""
    import shutil

    import torch

    from sage_core.avatar.model import Avatar
    from sage_core.config import config_hash, resolve_config, to_dict
    from sage_core.data.dataset import IngestedData
    from sage_core.workspace import Workspace, begin_stage

    ws = tmp_path_factory.mktemp("avatar_ws") / "ws"
    shutil.copytree(tiny_ws, ws)
    w = Workspace(ws)
    data = IngestedData.open(w.stage_dir("ingest"))
    with w.lock:
        icfg = resolve_config("init-mesh", "tiny")
        run = begin_stage(w, "init-mesh", to_dict(icfg), config_hash(icfg), requires=["ingest"])
        assert run is not None
        shutil.copytree(tiny_init_dir, run.work_dir, dirs_exist_ok=True)
        run.finish()
        pcfg = resolve_config("phase1", "tiny", None, {"n_surfels": 300})
        run = begin_stage(w, "phase1", to_dict(pcfg), config_hash(pcfg), requires=["init-mesh"])
        assert run is not None
        g = torch.Generator().manual_seed(0)
        av = Avatar.build(w.stage_dir("init-mesh"), data, 300, "mlp", app_args={"hidden": 16}, shape_args={"hidden": 16}, generator=g)
        with torch.no_grad():
            av.surfels.mu_loc.add_(0.05 * torch.randn(av.surfels.mu_loc.shape, generator=g))
        av.save(run.work_dir / "avatar.pt")
        run.finish()
    return ws


CMD_AVATAR_SURFELS = 600
CMD_TEST_CAMERAS = (8,)
QUICK_INIT_MESH = {"pretrain.steps": 20, "pretrain.bank_size": 4000, "pretrain.batch_size": 1024, "mc_resolution": 32,
                   "pretrain.eval_samples": 2000}  # fmt: skip
"""init-mesh flags of the shared workspaces: a short SDF pretraining on a coarse grid."""


@pytest.fixture(scope="session")
def cmd_avatar_ws(tiny_ws, tmp_path_factory):
    """The avatar workspace of the command tests (eval, export, reenact, viewers, profiling): the tiny
    ingested capture with its test split cut to camera 8, a quick init-mesh and an untrained
    600-surfel phase-1 avatar moved off its initial state, recorded as complete stages. Built once
    per session; tests copy it before changing it."""
    import json
    import shutil

    import torch

    from sage_core.config import config_hash, resolve_config, to_dict
    from sage_core.data.dataset import IngestedData
    from sage_core.train.init_mesh import run_init_mesh
    from sage_core.train.phase1 import build_avatar
    from sage_core.workspace import Workspace, begin_stage

    ws = tmp_path_factory.mktemp("cmd_avatar_ws") / "ws"
    shutil.copytree(tiny_ws, ws)
    # fewer test images keep the command tests fast: the frontal camera of every test timestep
    frames_path = ws / "data" / "frames.json"
    doc = json.loads(frames_path.read_text())
    doc["frames"] = [f for f in doc["frames"] if f["role"] != "test" or int(f["camera_index"]) in CMD_TEST_CAMERAS]
    frames_path.write_text(json.dumps(doc))
    w = Workspace(ws)
    data = IngestedData.open(w.stage_dir("ingest"))
    icfg = resolve_config("init-mesh", "tiny", None, QUICK_INIT_MESH)
    with w.lock:
        run = begin_stage(w, "init-mesh", to_dict(icfg), config_hash(icfg), requires=["ingest"])
        assert run is not None
        run_init_mesh(data, run.work_dir, icfg, seed=0)
        run.finish()
        pcfg = resolve_config("phase1", "tiny", None, {"n_surfels": CMD_AVATAR_SURFELS, "app_hidden": 16, "shape_hidden": 16})
        run = begin_stage(w, "phase1", to_dict(pcfg), config_hash(pcfg), requires=["init-mesh"])
        assert run is not None
        g = torch.Generator().manual_seed(0)
        av = build_avatar(data, w.stage_dir("init-mesh"), pcfg, "cpu", g)
        with torch.no_grad():  # move off the initial state so that the tests are not about it
            av.surfels.mu_loc.add_(0.05 * torch.randn(av.surfels.mu_loc.shape, generator=g))
        av.save(run.work_dir / "avatar.pt")
        run.finish()
    return ws


@pytest.fixture(scope="session")
def oneshot_ws(tmp_path_factory):
    """A one-shot workspace: a tiny synthetic ``--regime oneshot`` capture (``helpers.NOVEL_VIEWS``
    held-out cameras, ``helpers.NOVEL_EXPRESSIONS`` held-out expression; the capture is the folder
    ``cap`` beside the workspace) ingested as ``one-shot``, with a quick init-mesh. Built once per
    session, shared read-only."""
    from sage_core.config import config_hash, resolve_config, to_dict
    from sage_core.data.capture import read_capture
    from sage_core.data.dataset import IngestedData
    from sage_core.data.ingest import ingest
    from sage_core.data.synthetic import make_capture
    from sage_core.data.synthetic.config import preset
    from sage_core.train.init_mesh import run_init_mesh
    from sage_core.workspace import Workspace, begin_stage

    root = tmp_path_factory.mktemp("oneshot")
    ws = root / "ws"
    cap = make_capture(root / "cap", preset("tiny", "oneshot", novel_views=NOVEL_VIEWS, novel_expressions=NOVEL_EXPRESSIONS,
                                             supersample=1))
    w = Workspace(ws)
    ws.mkdir(parents=True)
    with w.lock:
        run = begin_stage(w, "ingest", {"regime": "one-shot"}, "h11b-oneshot")
        assert run is not None
        ingest(read_capture(cap), cap.model_path, run.work_dir, regime="one-shot")
        run.finish()
        data = IngestedData.open(w.stage_dir("ingest"))
        icfg = resolve_config("init-mesh", "tiny", None, QUICK_INIT_MESH)
        run = begin_stage(w, "init-mesh", to_dict(icfg), config_hash(icfg), requires=["ingest"])
        assert run is not None
        run_init_mesh(data, run.work_dir, icfg, seed=0)
        run.finish()
    return ws
