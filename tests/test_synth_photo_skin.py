"""A photograph as the face's skin of a detailed synthetic subject (``skin_photo``): which vertices
the photo gives, the capture that keeps it, the ceiling that rebuilds it, and the refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sage_core.data.imageio import read_image
from sage_core.data.synthetic import make_capture, preset
from sage_core.data.synthetic.capture import canonical_vertices, make_subject
from sage_core.data.synthetic.head import PART_SKIN
from sage_core.data.synthetic.motion import arc_cameras
from sage_core.data.synthetic.photo_skin import PhotoSkin, photo_weights, read_photo_skin
from sage_core.errors import ConfigError

COARSE = {"head_rows": 40, "head_cols": 48, "eye_rows": 6, "eye_cols": 8}
SMALL = {"n_cameras": 3, "width": 40, "height": 58, "train_timesteps": 1, "test_timesteps": 1, **COARSE}


@pytest.fixture(scope="module")
def photo(tmp_path_factory) -> Path:
    """A one-image capture of another subject (seed 5) standing in for a tracked photograph."""
    return make_capture(tmp_path_factory.mktemp("photo") / "one", preset("tiny", "oneshot", appearance="detailed", seed=5,
                                                                          width=96, height=140, novel_views=1, novel_expressions=1,
                                                                          novel_around=0, **COARSE))


def test_bilinear_sampling_of_the_photo():
    img = np.zeros((2, 3, 3))
    img[:, :, 0] = [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]
    skin = PhotoSkin(img, np.zeros((0, 2)), np.zeros(0), np.zeros(3), "x")
    got = skin.sample(np.array([[0.5, 0.5], [1.0, 0.5], [1.5, 1.0], [9.0, 9.0]]))[:, 0]
    assert np.allclose(got, [0.0, 0.5, 2.5, 5.0])  # pixel centre, between two, between four, clamped


def test_photo_weights_take_the_face_the_camera_sees():
    cfg = preset("tiny", appearance="detailed", **COARSE)
    subj = make_subject(cfg)
    head = subj.head
    v = canonical_vertices(subj)
    face = head.part == PART_SKIN
    cam = arc_cameras(np.random.default_rng(0), 16, 200, 290, 1.0, 0.42)[8]  # the frontal camera of the arc
    uv, w = photo_weights(v, head.faces, cam, face)
    assert w.min() >= 0.0 and w.max() <= 1.0 and (w > 0.999).sum() > 50
    toward = (v - v.mean(0)) @ (cam.center - v.mean(0))
    assert w[toward < 0].max() == 0.0  # nothing behind the head's centre plane
    assert w[~face].max() == 0.0
    seen = w > 0
    assert (uv[seen] >= 0).all() and (uv[seen, 0] <= cam.width).all() and (uv[seen, 1] <= cam.height).all()


def test_a_photo_capture_becomes_the_face_skin(photo, tmp_path):
    from sage_core.data.cameras import camera_from_nerf_frame
    from sage_core.data.synthetic.ceiling import FLAME_KEYS, TrackedTruth

    kw = {**SMALL, "seed": 3}
    plain = make_capture(tmp_path / "plain", preset("tiny", appearance="detailed", **kw))
    cap = make_capture(tmp_path / "cap", preset("tiny", appearance="detailed", skin_photo=str(photo),
                                                skin_photo_model=str(photo / "model" / "synth_flame.npz"), **kw))
    skin = read_photo_skin(cap / "gt" / "skin_photo.npz")
    assert skin.source == "one" and (skin.weight > 0.999).sum() > 20
    info = json.loads((cap / "gt" / "info.json").read_text())
    assert info["config"]["skin_photo"] == "one" and info["config"]["skin_photo_model"] == "synth_flame.npz"
    assert info["identity"]["appearance"]["skin_photo"] == "one"
    assert np.allclose(info["identity"]["appearance"]["skin"], skin.median_rgb)
    # the face changes, the background does not
    frames = json.loads((cap / "transforms.json").read_text())["frames"]
    a = read_image(cap / frames[0]["file_path"])[..., :3]
    b = read_image(plain / frames[0]["file_path"])[..., :3]
    alpha = read_image(cap / frames[0]["fg_mask_path"])[..., 0]
    assert np.abs(a - b)[alpha > 0.99].mean() > 0.01 and np.abs(a - b)[alpha == 0].max() < 1e-6
    # the tracking ceiling rebuilds the subject from the capture alone (photo skin included)
    truth = TrackedTruth.open(cap)
    for fr in frames[:2]:
        with np.load(cap / fr["flame_param_path"]) as z:
            params = {k: z[k] for k in FLAME_KEYS}
        img = read_image(cap / fr["file_path"])[..., :3]
        mse = float(((truth.render(params, camera_from_nerf_frame(fr)) - img) ** 2).mean())
        assert 10 * np.log10(1.0 / max(mse, 1e-12)) > 45.0, fr["file_path"]


def test_photo_skin_refusals(photo, tmp_path):
    with pytest.raises(ConfigError, match="detailed"):
        preset("tiny", appearance="smooth", skin_photo=str(photo), **SMALL).validate()
    with pytest.raises(ConfigError, match="without skin_photo"):
        preset("tiny", appearance="detailed", skin_photo_model="m.npz", **SMALL).validate()
    with pytest.raises(ConfigError, match="not a capture folder"):
        make_subject(preset("tiny", appearance="detailed", skin_photo=str(tmp_path), **SMALL))
    # a model of another head grid
    with pytest.raises(ConfigError, match="vertices"):
        make_subject(preset("tiny", appearance="detailed", skin_photo=str(photo),
                            skin_photo_model=str(photo / "model" / "synth_flame.npz")))
    with pytest.raises(ConfigError, match="not found"):
        make_subject(preset("tiny", appearance="detailed", skin_photo=str(photo), skin_photo_model=str(tmp_path / "none.npz"), **SMALL))


def test_ring_distance_counts_edges_to_the_outside():
    from sage_core.data.synthetic.photo_skin import ring_distance

    # a strip of triangles over vertices 0..9 (i, i+1, i+2): vertex i neighbours i±1 and i±2
    faces = np.array([[i, i + 1, i + 2] for i in range(8)])
    inside = np.ones(10, bool)
    inside[0] = False
    d = ring_distance(inside, faces, 3)
    assert d.tolist() == [0, 1, 1, 2, 2, 3, 3, 3, 3, 3]


def test_expression_creases_darken_the_photo_skin(photo):
    kw = {**SMALL, "seed": 3}
    model = str(photo / "model" / "synth_flame.npz")
    with_photo = make_subject(preset("tiny", appearance="detailed", skin_photo=str(photo), skin_photo_model=model, **kw))
    plain = make_subject(preset("tiny", appearance="detailed", **kw))
    v = canonical_vertices(plain)
    cam = arc_cameras(np.random.default_rng(0), 16, 80, 116, 1.0, 0.42)[8]
    none, full = np.zeros(v.shape[0]), np.ones(v.shape[0])
    flat = with_photo.render(v, cam, none, 1).rgb
    creased = with_photo.render(v, cam, full, 1).rgb
    plain_flat, plain_creased = plain.render(v, cam, none, 1).rgb, plain.render(v, cam, full, 1).rgb
    region = np.abs(flat - plain_flat).max(-1) > 0.02  # where the photo shows
    assert region.sum() > 50
    darkening = creased[region].mean() / flat[region].mean()
    darkening_plain = plain_creased[region].mean() / plain_flat[region].mean()
    assert darkening_plain < 0.95 and abs(darkening - darkening_plain) < 0.03
