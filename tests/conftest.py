"""Shared pytest configuration: the ``cuda`` marker skips without a CUDA device."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _lpips_weights() -> Path | None:
    """The LPIPS AlexNet weights where sage itself finds them ($SAGE_LPIPS_WEIGHTS, then
    ~/.cache/sage/lpips_alex_v0.1.pth), else None: tests that need them skip."""
    from sage_core.evaluate.lpips import find_lpips_weights

    try:
        return find_lpips_weights()
    except Exception:  # a named but missing file: treat as absent here, the CLI tests cover the error
        return None


LPIPS_WEIGHTS = _lpips_weights()
LPIPS_SKIP_REASON = "LPIPS weights not found: set SAGE_LPIPS_WEIGHTS or place lpips_alex_v0.1.pth in ~/.cache/sage/"


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
