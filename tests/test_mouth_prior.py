"""The mouth interior: the synthetic truth's teeth and tongue, sage's tongue rig, the shipped
mouth prior, its mapping onto a mouth mesh and the fitting script's format."""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from sage_core.avatar.mouth_prior import GRID_SHAPE, PARTS, PRIOR_FILE, MouthPrior, load_mouth_prior, save_mouth_prior, surfel_prior_colors
from sage_core.errors import InputError
from sage_core.flame import FlameModel, Regions, add_mouth_interior

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


@pytest.fixture(scope="module")
def synth_mouth_model():
    """The tiny synthetic head's written model with sage's mouth interior (cavity, teeth, tongue)."""
    from sage_core.data.synthetic.head import build_head
    from sage_core.data.synthetic.model_files import flame_model_data

    head = build_head(56, 72)
    masks = {k: np.asarray(v) for k, v in head.masks.items()}
    model = add_mouth_interior(flame_model_data(head), masks, tongue=True)
    return model, Regions(masks, model.faces, model.n_vertices, model.vertex_groups)


def test_shipped_prior_loads_with_its_layout_and_provenance():
    assert PRIOR_FILE.is_file() and PRIOR_FILE.stat().st_size < 1_000_000
    prior = load_mouth_prior()
    assert prior.color.shape == (len(PARTS), *GRID_SHAPE, 3) and prior.weight.shape == (len(PARTS), *GRID_SHAPE)
    assert float(prior.color.min()) >= 0 and float(prior.color.max()) <= 1
    assert all(float(prior.weight[p].sum()) > 0 for p in range(len(PARTS)))  # every part was seen
    prov = prior.provenance
    assert prov["script"] == "benchmarks/train_mouth_prior.py" and prov["samples"] > 0
    assert min(prov["seeds"]) >= 1000  # never the benchmark subjects (seeds 0 and 1)
    # teeth are lighter than the cavity where both were observed
    lum = prior.color.mean(-1)
    seen = prior.weight > 1
    assert lum[2][seen[2]].mean() > lum[0][seen[0]].mean() + 0.1


def test_prior_file_rejects_foreign_or_damaged_files(tmp_path):
    p = tmp_path / "p.safetensors"
    prior = MouthPrior(np.full((4, 2, 2, 2, 3), 0.5, np.float32), np.ones((4, 2, 2, 2), np.float32), provenance={"x": 1})
    save_mouth_prior(p, prior)
    back = load_mouth_prior(p)
    np.testing.assert_array_equal(back.color, prior.color)
    assert back.provenance == {"x": 1}
    data = bytearray(p.read_bytes())
    data[-3] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(InputError):
        load_mouth_prior(p)
    with pytest.raises(ValueError):
        MouthPrior(np.zeros((3, 2, 2, 2, 3), np.float32), np.zeros((3, 2, 2, 2), np.float32))


def test_safetensors_header_length_that_reads_like_a_pickle_opcode_is_not_taken_for_one():
    import pickle

    from sage_core.serialization import _looks_like_pickle

    # a header of 0x0580 bytes starts the file with 80 05, like a protocol-5 pickle
    assert not _looks_like_pickle(b"\x80\x05\x00\x00\x00\x00\x00\x00{")
    assert _looks_like_pickle(pickle.dumps({"a": 1}, protocol=5)[:9])
    assert _looks_like_pickle(pickle.dumps([1, 2, 3], protocol=2)[:9])


def test_lookup_is_trilinear_and_clamped():
    c = np.zeros((4, 2, 2, 2, 3), np.float32)
    c[1, 1] = 1.0  # the lower cavity grid: 1 on the lateral +side, 0 on the -side
    prior = MouthPrior(c, np.ones((4, 2, 2, 2), np.float32))
    lo, hi = prior.lo.astype(float), prior.hi.astype(float)
    mid = 0.5 * (lo + hi)
    pts = np.array([mid, [hi[0] + 5, mid[1], mid[2]], [lo[0] - 5, mid[1], mid[2]]])
    out = prior.lookup(pts, np.array([1, 1, 1]))
    np.testing.assert_allclose(out[:, 0], [0.5, 1.0, 0.0], atol=1e-6)
    assert float(np.abs(prior.lookup(pts, np.array([0, 0, 0]))).max()) == 0.0


def test_prior_maps_onto_a_mouth_mesh_by_position_alone(synth_mouth_model):
    model, regions = synth_mouth_model
    prior = load_mouth_prior()
    v = model.v_template
    f = np.asarray(model.faces)
    centroids = v[f].mean(1)
    binding = np.arange(f.shape[0])
    cols, on = surfel_prior_colors(v, centroids, binding, model, regions, prior)
    mouth = regions.face_mask("mouth_interior") | regions.face_mask("teeth")
    np.testing.assert_array_equal(on, mouth)
    assert float(np.abs(cols[~on]).max()) == 0.0 and float(cols[on].min()) >= 0 and float(cols[on].max()) <= 1
    # subject-independent: the same mouth moved and scaled gets the same colours
    s, t = 1.15, np.array([0.01, -0.02, 0.03])
    cols2, on2 = surfel_prior_colors(v * s + t, centroids * s + t, binding, model, regions, prior)
    np.testing.assert_array_equal(on2, on)
    np.testing.assert_allclose(cols2, cols, atol=1e-5)


def test_tongue_and_lower_teeth_move_with_the_jaw(synth_mouth_model):
    model, _ = synth_mouth_model
    assert "mouth_tongue" in model.vertex_groups and model.face_table.endswith("+sage-tongue-v1")
    fl = FlameModel(model).double()
    with torch.no_grad():
        rest = fl().vertices[0].numpy()
        open_ = fl(jaw_pose=torch.tensor([[0.3, 0.0, 0.0]], dtype=torch.float64)).vertices[0].numpy()
    g = model.vertex_groups
    for name in ("mouth_tongue", "teeth_lower", "mouth_lower"):
        ids = g[name]
        d = np.linalg.norm(open_[ids] - rest[ids], axis=1)
        assert d.min() > 1e-3, name  # every vertex moves with the jaw...
        # ... rigidly: pairwise distances are kept
        a, b = rest[ids], open_[ids]
        np.testing.assert_allclose(np.linalg.norm(a[:, None] - a[None], axis=-1), np.linalg.norm(b[:, None] - b[None], axis=-1), atol=1e-9)
    for name in ("teeth_upper", "mouth_upper"):
        np.testing.assert_allclose(open_[g[name]], rest[g[name]], atol=1e-12)
    # the tongue lies on the cavity floor: below the slit, inside the lower cavity's extent
    t, low = rest[g["mouth_tongue"]], rest[g["mouth_lower"]]
    assert t[:, 1].max() < rest[g["mouth_upper"]][:, 1].min() + 1e-9
    assert (t.min(0)[[0, 2]] >= low.min(0)[[0, 2]] - 1e-9).all() and (t.max(0)[[0, 2]] <= low.max(0)[[0, 2]] + 1e-9).all()


def test_synthetic_truth_shows_its_mouth_on_open_jaw_frames_only():
    from sage_core.data.synthetic.capture import _pose, make_subject
    from sage_core.data.synthetic.config import preset
    from sage_core.data.synthetic.motion import Frame
    from train_mouth_prior import _mouth_camera

    subj = make_subject(replace(preset("tiny", "multiview", seed=5), appearance="detailed", tracking="exact"))
    assert subj.mouth is not None and subj.mouth.n_vertices > 0
    closed, opened = Frame(), Frame(jaw_pose=np.array([0.3, 0.0, 0.0]))
    posed = _pose(subj, [closed, opened])
    centre = subj.canonical[subj.head.slit_pairs.reshape(-1)].mean(0)
    for k, expect in ((0, False), (1, True)):
        v = posed.vertices[k]
        cam = _mouth_camera(centre + np.array([0.0, -0.01 * k, 0.0]), 0.0, 0.0, 48, 36)
        with_mouth = subj.render(v, cam, None, 1)
        mouth, subj.mouth = subj.mouth, None
        without = subj.render(v, cam, None, 1)
        subj.mouth = mouth
        diff = np.abs(with_mouth.rgb - without.rgb).max(-1)
        assert bool((diff > 0.05).sum() > 10) == expect, k
        np.testing.assert_array_equal(with_mouth.alpha, without.alpha)  # inside the head: the mask is the same
    # the mouth style varies with the seed
    from sage_core.data.synthetic.mouth import sample_mouth_style

    assert sample_mouth_style(np.random.default_rng([6, 8])) != subj.mouth.style


@pytest.mark.slow
def test_fitting_script_reproduces_the_shipped_format(tmp_path):
    import train_mouth_prior

    out = tmp_path / "prior.safetensors"
    assert train_mouth_prior.main(["--out", str(out), "--seeds", "1000", "--jaw", "0.25", "--yaw", "0", "--pitch", "0",
                                   "--size", "32x24", "--grid", "4,3,4"]) == 0  # fmt: skip
    prior = load_mouth_prior(out)
    assert prior.color.shape == (len(PARTS), 4, 3, 4, 3) and prior.provenance["seeds"] == [1000]
    assert set(prior.provenance) == set(load_mouth_prior().provenance)
    assert float(prior.weight.sum()) > 0
    again = tmp_path / "again.safetensors"
    train_mouth_prior.main(["--out", str(again), "--seeds", "1000", "--jaw", "0.25", "--yaw", "0", "--pitch", "0",
                            "--size", "32x24", "--grid", "4,3,4"])  # fmt: skip
    np.testing.assert_array_equal(load_mouth_prior(again).color, prior.color)  # deterministic
    assert train_mouth_prior.main(["--out", str(again), "--seeds", "0,1000"]) == 2  # the benchmark's seeds are refused
