"""The training losses against recorded reference values: 20 steps of phase 1 (network and free
surfels, a one-shot capture with pseudo views) and phase 2 (rest and NeuS teachers) must give the
recorded loss terms (bit-identical on the recording machine, within :data:`LOSS_REL` on another
CPU), and the config hashes of the presets must stay as recorded.

The reference (``tests/loss_reference.json``) records, per case, every step's total loss and, per loss
term, the sum of its values over the steps, each as ``float.hex``; a mismatch names the case, the
term and the step. The numbers depend on the training code, the synthetic test captures and the
torch build. When a deliberate change of the training method or of the synthetic captures changes
them, record them anew and say so in the change:

    SAGE_RECORD_LOSS_REFERENCE=1 python -m pytest tests/test_loss_reference.py

The cases use the flat (pre-nesting) key names on purpose: they are accepted as aliases of the nested
fields, and the reference was recorded before the configs were nested.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
import torch

pytestmark = pytest.mark.slow

REFERENCE = Path(__file__).with_name("loss_reference.json")
RECORD = os.environ.get("SAGE_RECORD_LOSS_REFERENCE") == "1"
STEPS = 20

_P1_BASE = {"iterations": STEPS, "n_surfels": 800, "rays_per_step": 48, "neus_samples": 8, "neus_importance": 8, "neus_up_steps": 1,
            "app_hidden": 16, "shape_hidden": 16, "eval_every": 0, "mc_resolution": 32, "smooth_points": 64, "sym_points": 64,
            "light_albedo_pairs": 2048}  # fmt: skip

PHASE1_CASES: dict[str, dict] = {
    # every phase-1 term of the network avatar: the 2DGS terms and the SDF from early steps, exposure,
    # symmetry, pose refinement, the light priors, rebinding, and the polish over the last 5 steps
    "mlp": {**_P1_BASE, "normal_consistency_from": 2, "distortion_from": 3, "sdf_from": 1, "polish_fraction": 0.25,
            "rebind_every": 7, "exposure": "gain", "w_sym_sdf": 0.1, "w_sym_color": 0.05, "pose_refine": True,
            "pose_refine_from": 5, "w_mask": 0.5},
    # free surfels: adaptive density control, GaussianAvatars' local terms, no shading
    "free": {**_P1_BASE, "attributes": "free", "shading": "none", "densify": True, "densify_from": 2, "densify_until": 15,
             "densify_every": 4, "opacity_reset_every": 9, "w_local_position": 0.01, "w_local_scale": 1.0,
             "normal_consistency_from": 4, "distortion_from": 4, "rebind_every": 0, "polish_fraction": 0.0},
}  # fmt: skip
ONESHOT_CASE = {**_P1_BASE, "pseudo_view_prob": 0.5, "pseudo_ring_views": 2, "exposure": "rgb", "w_sym_sdf": 0.1,
                "w_sym_color": 0.05, "normal_consistency_from": 2, "distortion_from": 2, "polish_fraction": 0.1, "rebind_every": 0}  # fmt: skip

_P2_BASE = {"iterations": STEPS, "rays_per_step": 48, "neus_samples": 8, "neus_importance": 8, "neus_up_steps": 1, "eval_phase1": False,
            "teacher_max_views": 4, "curve_steps": 10}  # fmt: skip
PHASE2_CASES: dict[str, dict] = {
    # the rest teacher, every trainable group, the photometric term and steps at rest, wrinkles by distortion
    "rest": {**_P2_BASE, "lr_position": 1e-4, "lr_networks": 1e-4, "w_photometric": 0.5, "photometric_every": 3,
             "rest_fraction": 0.3, "wrinkle_region": "distortion"},
    # the NeuS teacher, the paper's curvature correction, a constant rate
    "neus": {**_P2_BASE, "teacher": "neus", "correction_mode": "curvature", "correction_w_s": 1e-3, "lr_schedule": "constant",
             "lr_shape": 1e-5, "mouth_prior_visibility": "faces"},
}  # fmt: skip

HASH_CASES = [(stage, preset, regime) for stage in ("ingest", "init-mesh", "phase1", "phase2", "eval", "export")
              for preset in ("tiny", "small", "default") for regime in (None, "sv-hr", "one-shot")]  # fmt: skip


def _hex(x: float) -> str:
    return float(x).hex()


def _summary(history: list[dict[str, float]]) -> dict:
    """Each step's total loss and each term's sum over the steps (in step order), as float.hex."""
    sums: dict[str, float] = {}
    for out in history:
        for k, v in out.items():
            if k != "loss":
                sums[k] = sums.get(k, 0.0) + float(v)
    return {"loss": [_hex(o["loss"]) for o in history], "terms": {k: _hex(v) for k, v in sorted(sums.items())}}


def _phase1_history(data, init_dir, flags: dict, pseudo: bool = False) -> list[dict[str, float]]:
    from sage_core.config import resolve_config
    from sage_core.train.phase1 import Phase1Trainer, build_avatar, one_shot_pseudo_views

    cfg = resolve_config("phase1", "tiny", None, flags, regime=data.regime)
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    av = build_avatar(data, init_dir, cfg, "cpu", g)
    views, mirror = one_shot_pseudo_views(data, av, cfg) if pseudo else ([], None)
    tr = Phase1Trainer(av, data, cfg, "cpu", g, pseudo_views=views, mirror_index=mirror)
    return [tr.step() for _ in range(STEPS)]


LOSS_REL = 1e-2
"""Relative tolerance of every recorded value (each step's total, each term's sum). On the machine
that recorded the reference the values are bit-identical; another CPU rounds float32 sums
differently (vector widths, BLAS kernels), in the synthetic test captures and in training, and
twenty steps carry that forward: an Intel Xeon against the AMD EPYC that recorded it deviated by up
to 2.6e-3 (the SDF smoothness and NeuS mask terms of the network case), as did the same Xeon with
torch's vector kernels or OpenBLAS's kernel choice forced. The set of terms is compared exactly; a
change of a term, a weight or a schedule moves its sum by far more than 1 %."""


def _rel(a: str, b: str) -> float:
    x, y = float.fromhex(a), float.fromhex(b)
    return abs(x - y) / max(abs(y), 1e-12)


def _check(case: str, got: dict, ref: dict) -> float:
    """Assert every step's total and every term's sum agree with the reference within
    :data:`LOSS_REL`; returns the largest relative deviation."""
    assert set(got["terms"]) == set(ref["terms"]), (case, sorted(set(got["terms"]) ^ set(ref["terms"])))
    worst = 0.0
    for i, (a, b) in enumerate(zip(got["loss"], ref["loss"])):
        d = _rel(a, b)
        worst = max(worst, d)
        assert d <= LOSS_REL, f"{case}: total loss of step {i} is {float.fromhex(a)!r}, recorded {float.fromhex(b)!r}"
    for k, v in ref["terms"].items():
        d = _rel(got["terms"][k], v)
        worst = max(worst, d)
        assert d <= LOSS_REL, f"{case}: term {k} sums to {float.fromhex(got['terms'][k])!r}, recorded {float.fromhex(v)!r}"
    return worst


@pytest.fixture(scope="module")
def results(tiny_ws, tiny_init_dir, oneshot_ws, tmp_path_factory):
    """Every case run once (one torch thread: the sums of a multi-threaded reduction may differ)."""
    from sage_core.config import resolve_config
    from sage_core.data.dataset import IngestedData
    from sage_core.train.phase2 import Phase2Trainer
    from sage_core.workspace import Workspace

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        out: dict[str, dict] = {}
        data = IngestedData.open(tiny_ws / "data")
        for name, flags in PHASE1_CASES.items():
            out[f"phase1/{name}"] = _summary(_phase1_history(data, tiny_init_dir, flags))
        w = Workspace(oneshot_ws)
        one = IngestedData.open(w.stage_dir("ingest"))
        out["phase1/one-shot"] = _summary(_phase1_history(one, w.stage_dir("init-mesh"), ONESHOT_CASE, pseudo=True))

        # phase 2 starts from a phase-1 avatar of a few steps
        from sage_core.train.phase1 import Phase1Trainer, build_avatar

        p1 = resolve_config("phase1", "tiny", None, {**_P1_BASE, "iterations": 4, "rebind_every": 0})
        torch.manual_seed(0)
        g = torch.Generator().manual_seed(0)
        av = build_avatar(data, tiny_init_dir, p1, "cpu", g)
        tr = Phase1Trainer(av, data, p1, "cpu", g)
        for _ in range(4):
            tr.step()
        path = tmp_path_factory.mktemp("loss_ref") / "avatar.pt"
        av.save(path)
        from sage_core.avatar.model import Avatar

        for name, flags in PHASE2_CASES.items():
            cfg = resolve_config("phase2", "tiny", None, flags)
            torch.manual_seed(0)
            t2 = Phase2Trainer(Avatar.load(path), data, cfg, "cpu", torch.Generator().manual_seed(0), tiny_init_dir)
            out[f"phase2/{name}"] = _summary([t2.step() for _ in range(STEPS)])
    finally:
        torch.set_num_threads(before)
    return out


def _hashes() -> dict[str, str]:
    from sage_core.config import config_hash, resolve_config

    return {f"{s}/{p}/{r or '-'}": config_hash(resolve_config(s, p, regime=r)) for s, p, r in HASH_CASES}


def test_losses_match_the_reference(results):
    if RECORD:
        doc = {"steps": STEPS, "torch": torch.__version__, "cases": results, "config_hashes": _hashes()}
        REFERENCE.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
        pytest.skip(f"recorded {REFERENCE.name}")
    ref = json.loads(REFERENCE.read_text())
    assert set(results) == set(ref["cases"])
    worst = {case: _check(case, got, ref["cases"][case]) for case, got in results.items()}
    print("largest relative deviation per case:", {k: f"{v:.1e}" for k, v in worst.items()})


def test_every_case_exercises_its_terms(results):
    """The cases reach the terms they are meant to cover (a case that silently lost a term would
    still match a reference recorded without it)."""
    terms = {case: set(r["terms"]) for case, r in results.items()}
    assert {"rgb", "mask", "normal_consistency", "distortion", "pt", "align", "depth", "normal", "neus_rgb", "neus_mask", "eikonal",
            "smooth", "sym_sdf", "sym_color", "exposure_prior", "light_prior", "light_albedo", "pose_prior", "rebound"} <= terms["phase1/mlp"]
    assert {"local_position", "local_scale", "densify_cloned", "densify_split", "densify_pruned"} <= terms["phase1/free"]
    assert "light_prior" not in terms["phase1/free"]
    assert {"pseudo_rgb", "pseudo_view", "rgb"} <= terms["phase1/one-shot"]
    assert {"normal_consistency", "distortion", "appearance", "rgb"} <= terms["phase2/rest"]
    assert {"normal_consistency", "distortion", "appearance"} <= terms["phase2/neus"]


def test_config_hashes_match_the_reference():
    """An unchanged config keeps its hash (finished stages of existing workspaces stay up to date)."""
    if RECORD:
        pytest.skip("recording")
    ref = json.loads(REFERENCE.read_text())["config_hashes"]
    assert _hashes() == ref


def test_the_comparison_takes_rounding_and_refuses_a_changed_term():
    ref = {"loss": [_hex(1.5), _hex(1.25)], "terms": {"rgb": _hex(2.0), "smooth": _hex(0.5)}}
    rounded = {"loss": [_hex(1.5 * (1 + 3e-3)), _hex(1.25)], "terms": {"rgb": _hex(2.0 * (1 - 2e-3)), "smooth": _hex(0.5)}}
    assert 2e-3 < _check("case", rounded, ref) < 4e-3
    changed = {"loss": [_hex(1.5), _hex(1.25)], "terms": {"rgb": _hex(2.0), "smooth": _hex(0.5 * 1.05)}}
    with pytest.raises(AssertionError, match="term smooth"):
        _check("case", changed, ref)
    with pytest.raises(AssertionError):
        _check("case", {"loss": ref["loss"], "terms": {"rgb": _hex(2.0)}}, ref)  # a term went missing
