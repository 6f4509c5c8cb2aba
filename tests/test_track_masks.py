"""The written masks of `sage track`: keyed mattes, the mesh's coverage, the hair reach and the colour cut."""

from __future__ import annotations

import numpy as np

from sage_core.track.masks import (
    background_key,
    colour_cut,
    person_colour_cut,
    person_probability,
    refine_mask,
    wants_colour_cut,
)

H, W = 120, 100


def _scene(seed: int = 0) -> dict[str, np.ndarray]:
    """A head on a two-coloured textured background, with the regions a segmentation confuses.

    face: a skin-coloured ellipse (what the fitted mesh covers); hair: a dark cap above it, off the
    mesh; patch: background beside the neck that a segmentation took for the person.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    img = np.where((x < W / 2)[..., None], np.array([0.25, 0.45, 0.8]), np.array([0.3, 0.7, 0.35])).astype(np.float32)
    img = img + rng.normal(0, 0.03, img.shape).astype(np.float32)
    face = ((x - 50) / 22) ** 2 + ((y - 65) / 30) ** 2 < 1
    hair = (((x - 50) / 28) ** 2 + ((y - 50) / 36) ** 2 < 1) & ~face & (y < 62)
    img[face] = np.array([0.8, 0.6, 0.5]) + rng.normal(0, 0.03, (int(face.sum()), 3))
    img[hair] = np.array([0.2, 0.12, 0.08]) + rng.normal(0, 0.03, (int(hair.sum()), 3))
    patch = (x > 14) & (x < 26) & (y > 80) & (y < 108)
    return {"image": np.clip(img, 0, 1), "face": face, "hair": hair, "patch": patch}


def test_colour_cut_drops_background_the_segmentation_kept_and_keeps_hair():
    s = _scene()
    mask = (s["face"] | s["hair"] | s["patch"]).astype(np.float32)
    keep = colour_cut(s["image"], mask, s["face"], band=6)
    assert keep[s["face"]].all()  # the mesh's pixels stay
    assert keep[s["hair"]].mean() > 0.97  # hair off the mesh, darker than everything around it, stays
    assert keep[s["patch"]].mean() < 0.1  # the background patch goes back
    assert not keep[mask < 0.5].any()  # nothing is added


def test_colour_cut_scales_a_large_image_down_and_back():
    s = _scene(1)
    big = {k: np.repeat(np.repeat(v, 4, 0), 4, 1) for k, v in s.items()}
    mask = (big["face"] | big["hair"] | big["patch"]).astype(np.float32)
    keep = colour_cut(big["image"], mask, big["face"], band=24)
    assert keep.shape == mask.shape
    assert keep[big["patch"]].mean() < 0.15 and keep[big["hair"]].mean() > 0.95 and keep[big["face"]].all()


def test_refine_mask_with_colour_only_removes_off_the_mesh():
    s = _scene()
    person = (s["face"] | s["hair"] | s["patch"]).astype(np.float32)
    coverage = s["face"].astype(np.float32)
    plain = refine_mask(person, coverage, None, face_height=100.0)
    cut = refine_mask(person, coverage, None, face_height=100.0, image=s["image"])
    assert plain[s["patch"]].min() == 1.0
    assert cut[s["patch"]].mean() < 0.1 and (cut[s["face"]] == 1.0).all()
    assert (cut <= plain + 1e-6).all()
    # the neck line multiplies the result, the hair reach drops person pixels far from the mesh
    neck = np.ones((H, W), np.float32)
    neck[100:] = 0
    assert refine_mask(person, coverage, neck, face_height=100.0)[100:].max() == 0.0
    far = refine_mask(person, coverage, None, face_height=20.0, hair_reach=0.1)
    assert far[s["patch"]].max() == 0.0


def test_background_key_and_when_the_colour_cut_runs():
    s = _scene()
    assert background_key(s["image"]) is None  # two colours: no key
    white = np.ones((H, W, 3), np.float32)
    white[s["face"]] = np.array([0.8, 0.6, 0.5])
    key = background_key(white)
    assert key is not None and key[s["face"]].min() > 0.9 and key[~s["face"]].max() < 0.5
    seg = np.zeros((H, W), np.float32)
    seg[s["face"]] = 1.0
    seg[100:, :] = 1.0  # the segmentation invents shoulders below the head; the key far from it drops them
    prob, how = person_probability(white, seg)
    assert how == "keyed" and prob[110:].max() < 0.5 and prob[s["face"]].min() > 0.9
    assert not wants_colour_cut("auto", how) and wants_colour_cut("on", how) and not wants_colour_cut("off", how)
    prob, how = person_probability(s["image"], seg)
    assert how == "segmented" and np.array_equal(prob, seg)
    assert wants_colour_cut("auto", how) and wants_colour_cut("on", how) and not wants_colour_cut("off", how)


def test_person_colour_cut_before_the_fit_keeps_the_face_and_hair():
    """Before the fit no mesh exists: the landmarks' hull is the face the cut keeps."""
    s = _scene()
    person = (s["face"] | s["hair"] | s["patch"]).astype(np.float32)
    ys, xs = np.nonzero(s["face"])
    inner = (np.abs(xs - 50) < 15) & (np.abs(ys - 65) < 20)  # landmarks lie inside the face's outline
    landmarks = np.stack([xs[inner], ys[inner]], 1).astype(np.float64)[::7]
    out = person_colour_cut(s["image"], person, landmarks, face_height=60.0)
    assert out.dtype == np.float32 and out.shape == person.shape
    assert out[s["patch"]].mean() < 0.1
    assert out[s["face"]].mean() > 0.99 and out[s["hair"]].mean() > 0.97
    assert (out <= person).all()
    # landmarks off the person (a bad detection): nothing to anchor on, the map is returned as it is
    off = np.array([[2.0, 2.0], [6.0, 2.0], [4.0, 6.0]])
    assert np.array_equal(person_colour_cut(s["image"], person, off, face_height=60.0), person)


def test_refine_mask_checks_mesh_pixels_the_person_map_left_out():
    """A fitted mesh wider than the head (a jaw beside short hair) covers background: where the person
    map has no person the colour decides; the mesh's pixels inside the person map stay."""
    s = _scene()
    person = (s["face"] | s["hair"]).astype(np.float32)
    wide = s["face"] | s["patch"]  # the mesh reaches over the background patch
    coverage = wide.astype(np.float32)
    cut = refine_mask(person, coverage, None, face_height=100.0, image=s["image"])
    assert cut[s["patch"]].mean() < 0.1
    assert (cut[s["face"]] == 1.0).all() and cut[s["hair"]].mean() > 0.97
    # a keyed matte (no colour check) keeps every pixel the mesh covers, as before
    plain = refine_mask(person, coverage, None, face_height=100.0)
    assert plain[s["patch"]].min() == 1.0
    # mesh pixels the colour cut keeps stay even outside the person map (hair a segmentation missed)
    missed = refine_mask(s["face"].astype(np.float32), (s["face"] | s["hair"]).astype(np.float32), None,
                         face_height=100.0, image=s["image"])
    assert missed[s["hair"]].mean() > 0.9
    # deep inside the mesh a hole of the person map stays filled whatever its colour
    y, x = np.mgrid[0:H, 0:W]
    hole = (np.abs(x - 50) < 4) & (np.abs(y - 68) < 4)
    img = s["image"].copy()
    img[hole] = img[5, 5]
    holed = refine_mask((s["face"] & ~hole).astype(np.float32), s["face"].astype(np.float32), None,
                        face_height=100.0, image=img)
    assert holed[hole].min() == 1.0
