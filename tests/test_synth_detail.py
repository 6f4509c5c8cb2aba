"""Detailed synthetic heads (``appearance="detailed"``): the smooth head stays as earlier versions wrote it, the
detail is glued to the skin and prefiltered, the hair volume is rigid with the skull and part of the
truth only, held-out views go all around the head."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

from sage_core.data.cameras import Camera, look_at
from sage_core.data.imageio import read_image
from sage_core.data.synthetic import make_capture, preset, write_capture
from sage_core.data.synthetic.capture import canonical_vertices, make_subject
from sage_core.data.synthetic.config import (
    MULTIVIEW_AROUND_DEFAULT,
    NOVEL_AROUND_DEFAULT,
    SynthConfig,
    parse_sets,
)
from sage_core.data.synthetic.detail import _dots, _spots, attenuation
from sage_core.errors import ConfigError

COARSE = {"head_rows": 40, "head_cols": 48, "eye_rows": 6, "eye_cols": 8}
SMALL = {"n_cameras": 3, "width": 40, "height": 58, "train_timesteps": 1, "test_timesteps": 2, **COARSE}

SMOOTH_CASES = {
    "multiview_exact": ("multiview", dict(n_cameras=3, width=48, height=70, train_timesteps=1, test_timesteps=1),
                        "aff726c15635949a7375687d26194f7061adcd7ac41e57b687bedc389b10adc2"),
    "multiview_fitted": ("multiview", dict(tracking="fitted", n_cameras=3, width=40, height=58, train_timesteps=1, test_timesteps=2, **COARSE),
                         "c044583f49a954b2188d6c34bf9fda776c7745c78384cf8efc25054e28461091"),
    "monocular_fitted": ("monocular", dict(tracking="fitted", width=40, height=58, train_timesteps=2, test_timesteps=1, novel_views=2,
                                           novel_expressions=1, **COARSE),
                         "5b8b5d8071fbdd47a445c0b406588c42fc03a0622139e08e1bfc6ec28dc935d1"),
    "oneshot_exact": ("oneshot", dict(width=40, height=58, novel_views=3, novel_expressions=1, seed=3, **COARSE),
                      "de2409a0b16e4225f655a4cb7fe0aabca2845b64f83e263b4124b98b0f002a4e"),
}  # fmt: skip
"""Smooth captures as the generator wrote them before the detailed appearance existed: regime, config
fields, and the SHA-256 over the relative paths and bytes of every file, as written on the machine
that recorded them. Floating-point results differ in their last bits between CPUs (vector widths,
BLAS kernels), so another machine compares the files' contents within rounding instead
(:func:`_fingerprint` against ``smooth_capture_reference.json``, recorded from the same generator)."""

SMOOTH_REFERENCE = Path(__file__).with_name("smooth_capture_reference.json")
RECORD_SMOOTH = os.environ.get("SAGE_RECORD_SMOOTH_REFERENCE") == "1"
BLOCK_LEVELS = 0.05
"""Largest change of an image's 4 x 4 block means, in 8-bit levels: rounding flips a few pixels by one
level (a block holds over a hundred), any change of the picture moves whole blocks."""
REL = 1e-6
"""Relative tolerance of the sums over arrays and numbers (float64 rounding is about 1e-16)."""


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(q for q in root.rglob("*") if q.is_file()):
        h.update(str(p.relative_to(root)).encode())
        h.update(b"\0")
        h.update(p.read_bytes())
    return h.hexdigest()


def _stats(a: np.ndarray) -> dict:
    """An array's shape and its sums (float64): plain, of squares, and weighted by position."""
    a = np.asarray(a)
    f = a.astype(np.float64).ravel()
    w = np.linspace(-1.0, 1.0, f.size) if f.size else f
    return {"shape": list(a.shape), "sums": [float(f.sum()), float((f * f).sum()), float((f * w).sum())]}


def _split_json(x) -> tuple[object, list[float]]:
    """A JSON document as its skeleton (numbers replaced by 0: structure and strings) and its
    numbers in a fixed order (dict keys sorted)."""
    if isinstance(x, bool) or x is None or isinstance(x, str):
        return x, []
    if isinstance(x, (int, float)):
        return 0, [float(x)]
    if isinstance(x, dict):
        parts = {k: _split_json(x[k]) for k in sorted(x)}
        return {k: v[0] for k, v in parts.items()}, [n for v in parts.values() for n in v[1]]
    items = [_split_json(v) for v in x]
    return [v[0] for v in items], [n for v in items for n in v[1]]


def _fingerprint(root: Path) -> dict:
    """Per file of a capture, its content in a form that rounding does not change: images as 4 x 4
    block means per channel (8-bit levels); arrays (npz, pkl, ply) and JSON numbers as :func:`_stats`;
    JSON structure and strings, mesh faces and anything else by SHA-256."""
    import imageio.v3 as iio
    import trimesh

    from sage_core.flame.model_io import load_flame_model
    from sage_core.flame.regions import load_masks

    out: dict = {}
    for p in sorted(q for q in root.rglob("*") if q.is_file()):
        rel = str(p.relative_to(root))
        if p.suffix == ".png":
            a = iio.imread(p).astype(np.float64)
            a = a[..., None] if a.ndim == 2 else a
            H, W = a.shape[:2]
            blocks = [a[i * H // 4:(i + 1) * H // 4, j * W // 4:(j + 1) * W // 4].mean(axis=(0, 1)).tolist() for i in range(4) for j in range(4)]
            out[rel] = {"shape": list(a.shape), "blocks": blocks}
        elif p.suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                out[rel] = {k: _stats(z[k]) if z[k].dtype.kind in "biuf" else z[k].tolist() for k in sorted(z.files)}
        elif p.suffix == ".json":
            skeleton, numbers = _split_json(json.loads(p.read_text(encoding="utf-8")))
            out[rel] = {"numbers": _stats(np.array(numbers)),
                        "skeleton": hashlib.sha256(json.dumps(skeleton, sort_keys=True).encode()).hexdigest()}
        elif p.suffix == ".ply":
            m = trimesh.load(p, process=False)
            out[rel] = {"vertices": _stats(m.vertices), "faces": hashlib.sha256(np.ascontiguousarray(m.faces, np.int64).tobytes()).hexdigest()}
        elif p.name == "FLAME_masks.pkl":
            out[rel] = {k: hashlib.sha256(np.asarray(v, np.int64).tobytes()).hexdigest() for k, v in sorted(load_masks(p).items())}
        elif p.suffix == ".pkl":
            data = load_flame_model(p, add_teeth=False)
            out[rel] = {k: _stats(v) for k, v in sorted(vars(data).items()) if isinstance(v, np.ndarray)}
        else:
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _close(got, ref, where: str) -> None:
    """Assert two fingerprints agree within rounding (module constants)."""
    if isinstance(ref, dict):
        assert isinstance(got, dict) and sorted(got) == sorted(ref), f"{where}: keys {sorted(got)} against {sorted(ref)}"
        for k in ref:
            if k == "blocks":
                d = np.abs(np.asarray(got[k]) - np.asarray(ref[k])).max()
                assert d <= BLOCK_LEVELS, f"{where}: an image block changed by {d:.3f} levels"
            elif k == "sums":  # within REL of the array's norm (the root of its sum of squares) or the value
                norm = max(1.0, abs(ref[k][1]) ** 0.5)
                for g, r in zip(got[k], ref[k]):
                    assert abs(g - r) <= REL * max(norm, abs(r)), f"{where}: {g!r} against {r!r}"
            else:
                _close(got[k], ref[k], f"{where}/{k}")
    else:
        assert got == ref, f"{where}: {got!r} against {ref!r}"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SMOOTH_CASES))
def test_smooth_captures_are_the_captures_of_earlier_versions(name: str, tmp_path: Path) -> None:
    regime, kw, digest = SMOOTH_CASES[name]
    out = write_capture(tmp_path / name, preset("tiny", regime, appearance="smooth", **kw))
    fp = _fingerprint(out)
    if RECORD_SMOOTH:
        ref = json.loads(SMOOTH_REFERENCE.read_text()) if SMOOTH_REFERENCE.is_file() else {}
        ref[name] = fp
        SMOOTH_REFERENCE.write_text(json.dumps(ref, indent=1, sort_keys=True) + "\n")
    if _digest(out) == digest:
        return  # the very bytes of earlier versions
    _close(fp, json.loads(SMOOTH_REFERENCE.read_text())[name], name)


def test_the_capture_comparison_sees_a_changed_picture(tmp_path: Path) -> None:
    import imageio.v3 as iio

    root = tmp_path / "cap"
    (root / "images").mkdir(parents=True)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (40, 32, 3)).astype(np.uint8)
    iio.imwrite(root / "images" / "a.png", img)
    np.savez(root / "p.npz", x=np.linspace(0, 1, 50))
    (root / "t.json").write_text(json.dumps({"fl_x": 100.5, "frames": [{"file_path": "images/a.png", "m": [1.0, 2.0]}]}))
    ref = _fingerprint(root)
    flipped = img.copy()
    flipped[5, 7, 0] ^= 1  # one pixel by one level: rounding
    iio.imwrite(root / "images" / "a.png", flipped)
    _close(_fingerprint(root), ref, "cap")
    brighter = np.clip(img.astype(int) + 2, 0, 255).astype(np.uint8)  # the picture changed
    iio.imwrite(root / "images" / "a.png", brighter)
    with pytest.raises(AssertionError, match="levels"):
        _close(_fingerprint(root), ref, "cap")
    iio.imwrite(root / "images" / "a.png", img)
    np.savez(root / "p.npz", x=np.linspace(0, 1, 50) * (1 + 1e-4))
    with pytest.raises(AssertionError, match="p.npz/x"):
        _close(_fingerprint(root), ref, "cap")
    np.savez(root / "p.npz", x=np.linspace(0, 1, 50))
    (root / "t.json").write_text(json.dumps({"fl_x": 100.5, "frames": [{"file_path": "images/b.png", "m": [1.0, 2.0]}]}))
    with pytest.raises(AssertionError, match="t.json/skeleton"):
        _close(_fingerprint(root), ref, "cap")


def test_config_keeps_old_captures_readable_and_presets_add_views_around() -> None:
    old = preset("tiny", "oneshot").to_dict()
    assert "appearance" not in old and "novel_around" not in old
    assert SynthConfig.from_dict(old).appearance == "smooth" and SynthConfig.from_dict(old).novel_around == 0
    det = preset("tiny", "oneshot", appearance="detailed")
    assert det.novel_around == NOVEL_AROUND_DEFAULT and det.to_dict()["appearance"] == "detailed"
    assert SynthConfig.from_dict(det.to_dict()) == det
    assert preset("tiny", "monocular", appearance="detailed", novel_around=0).novel_around == 0
    mv = preset("small", "multiview", appearance="detailed")
    assert mv.novel_multiview and mv.novel_around == MULTIVIEW_AROUND_DEFAULT and mv.to_dict()["novel_multiview"] is True
    assert not preset("small", "multiview", appearance="detailed", novel_multiview=False).novel_multiview
    assert "novel_multiview" not in preset("small", "multiview").to_dict()  # smooth: as earlier versions wrote it
    assert parse_sets(["novel_multiview=false"]) == {"novel_multiview": False}
    with pytest.raises(ConfigError, match="bool"):
        parse_sets(["novel_multiview=maybe"])
    assert parse_sets(["appearance=smooth", "novel_around=3"]) == {"appearance": "smooth", "novel_around": 3}
    with pytest.raises(ConfigError, match="appearance"):
        preset("tiny", appearance="photoreal")
    with pytest.raises(ConfigError, match="novel_around"):
        preset("tiny", "oneshot", novel_around=-1)


@pytest.fixture(scope="module")
def detailed(tmp_path_factory) -> Path:
    return make_capture(tmp_path_factory.mktemp("detailed") / "cap", preset("tiny", tracking="fitted", appearance="detailed", seed=0, **SMALL))


def test_detailed_capture_writes_the_hair_volume_beside_the_head(detailed: Path) -> None:
    import trimesh

    from sage_core.flame import load_flame_model

    info = json.loads((detailed / "gt" / "info.json").read_text())
    detail = info["identity"]["appearance"]["detail"]
    assert info["config"]["appearance"] == "detailed" and info["hair"]["style"] == detail["hair_style"] == "bob"
    n_t = info["counts"]["timesteps"]
    head = trimesh.load(detailed / "gt" / "meshes" / "00000.ply", process=False)
    hair = [trimesh.load(detailed / "gt" / "hair" / f"{t:05d}.ply", process=False) for t in range(n_t)]
    canon = trimesh.load(detailed / "gt" / "hair" / "canonical.ply", process=False)
    # the written model has the head only; the hair is extra truth geometry
    assert load_flame_model(detailed / "model" / "synth_flame.npz").n_vertices == len(head.vertices) == info["counts"]["vertices"]
    assert len(canon.vertices) == len(hair[0].vertices) > 100
    # the bob hangs below the scalp's hairline, outside the head
    assert float(np.asarray(canon.vertices)[:, 1].min()) < -0.04
    # rigid: pairwise distances of hair vertices are the same in every timestep
    ref = np.asarray(canon.vertices)
    idx = np.random.default_rng(0).choice(len(ref), 200, replace=False)
    d0 = np.linalg.norm(ref[idx, None] - ref[None, idx], axis=-1)
    for h in hair:
        v = np.asarray(h.vertices, np.float64)
        np.testing.assert_allclose(np.linalg.norm(v[idx, None] - v[None, idx], axis=-1), d0, atol=2e-6)


def test_hair_volume_is_in_the_images_and_masks(detailed: Path) -> None:
    """Rendering the same frame without the hair volume loses coverage (the bob hangs beside the face)."""
    from sage_core.data.cameras import camera_from_nerf_frame
    from sage_core.data.synthetic.appearance import render_head

    cfg = SynthConfig.from_dict(json.loads((detailed / "gt" / "info.json").read_text())["config"])
    subj = make_subject(cfg)
    fr = json.loads((detailed / "transforms_test.json").read_text())["frames"][0]
    cam = camera_from_nerf_frame(fr)
    import trimesh

    verts = np.asarray(trimesh.load(detailed / "gt" / "meshes" / f"{fr['timestep_index']:05d}.ply", process=False).vertices, np.float64)
    mask = read_image(detailed / fr["fg_mask_path"])[..., 0]
    with_hair = subj.render(verts, cam, None, cfg.supersample)
    without = render_head(subj.head, verts, cam, subj.app, supersample=cfg.supersample)
    assert with_hair.alpha.sum() > 1.05 * without.alpha.sum()
    assert np.abs(mask - with_hair.alpha).mean() < 0.02


def test_same_seed_same_bytes_and_seeds_vary_the_subject(tmp_path: Path) -> None:
    cfg = preset("tiny", appearance="detailed", **{**SMALL, "n_cameras": 2, "test_timesteps": 1})
    a, b = write_capture(tmp_path / "a", cfg), write_capture(tmp_path / "b", cfg)
    assert _digest(a) == _digest(b)
    styles = [make_subject(cfg.with_overrides(seed=s)).app.detail for s in range(6)]
    assert len({s.hair_style for s in styles}) >= 3
    assert any(s.freckles > 0 for s in styles) and any(s.freckles == 0 for s in styles)
    assert any(s.stubble > 0 for s in styles) and any(s.stubble == 0 for s in styles)
    # the smooth subject of the same seed keeps its identity and colours
    smooth, det = make_subject(cfg.with_overrides(appearance="smooth")), make_subject(cfg)
    np.testing.assert_array_equal(smooth.shape, det.shape)
    assert (smooth.app.skin, smooth.app.hair) == (det.app.skin, det.app.hair) and smooth.app.detail is None


def _frontal(width: int, px_per_mm: float) -> Camera:
    height = width * 11 // 8
    fl = px_per_mm * 1000.0 * 0.92
    K = np.array([[fl, 0.0, width / 2], [0.0, fl, height / 2], [0.0, 0.0, 1.0]])
    target = np.array([0.0, 0.02, 0.0])
    return Camera(K, look_at(target + np.array([0.0, 0.0, 1.0]), target), width, height)


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    g = lambda yy, xx: img[np.clip(yy, 0, img.shape[0] - 1), np.clip(xx, 0, img.shape[1] - 1)]  # noqa: E731
    return (g(y0, x0) * (1 - fx) + g(y0, x0 + 1) * fx) * (1 - fy) + (g(y0 + 1, x0) * (1 - fx) + g(y0 + 1, x0 + 1) * fx) * fy


def test_detail_is_glued_to_the_skin() -> None:
    """Moving the head (not the camera) moves the texture with it: the colour at the projection of a
    cheek vertex is the same before and after (a texture in world space would slide across the skin)."""
    cfg = preset("tiny", appearance="detailed", seed=2, **COARSE)
    subj = make_subject(cfg)
    v = canonical_vertices(subj)
    move = np.array([0.006, -0.004, 0.0])
    cam = _frontal(200, 1.6)
    a = subj.render(v, cam, None, 2).rgb.astype(np.float64)
    b = subj.render(v + move, cam, None, 2).rgb.astype(np.float64)
    t = subj.head.v_template
    cheek = np.flatnonzero((subj.head.part == 0) & (np.abs(np.abs(t[:, 0]) - 0.035) < 0.012) & (np.abs(t[:, 1] + 0.005) < 0.012) & (t[:, 2] > 0.05))
    ua, _ = cam.project(v[cheek])
    ub, _ = cam.project(v[cheek] + move)
    ca, cb = _bilinear(a, ua), _bilinear(b, ub)
    texture = float(np.abs(ca - ca.mean(0)).mean())
    assert texture > 0.01  # there is detail to follow
    glued = float(np.abs(ca - cb).mean())
    # what a texture fixed in the image would give: the moved render sampled where the vertices were
    fixed = float(np.abs(_bilinear(b, ua) - ca).mean())
    assert glued < 0.35 * texture and glued < 0.4 * fixed, (glued, fixed, texture)


def test_prefiltering_keeps_the_mean_and_removes_what_the_pixel_cannot_hold() -> None:
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.05, 0.05, (40000, 3))
    for fp, keep in ((0.0, True), (0.002, False)):
        f = np.full(len(p), fp)
        dots = _dots(p, 1900.0, 5, f)
        spots = _spots(p, 7, f, 0.0034, np.full(len(p), 0.8), 0.0004, 0.0008)
        if keep:
            sharp_dots, sharp_spots = dots, spots
            assert dots.std() > 0.1 and spots.max() > 0.5
        else:  # a 2 mm footprint: pores vanish into their mean, spots widen and fade keeping their integral
            assert dots.std() < 1e-6 and abs(dots.mean() - sharp_dots.mean()) < 0.01
            assert spots.max() < 0.25 and abs(spots.mean() - sharp_spots.mean()) < 0.25 * sharp_spots.mean()
    assert attenuation(1000.0, np.array([0.0]))[0] == 1.0 and attenuation(1000.0, np.array([0.001]))[0] < 1e-8


def test_tiny_renders_are_band_limited_not_aliased_noise() -> None:
    """At the tiny preset's scale (0.44 px/mm) the render matches a 4× finer render averaged down to
    the same pixels: the detail that survives is the detail a finer camera sees, not sampling noise."""
    cfg = preset("tiny", appearance="detailed", seed=1, **COARSE)
    subj = make_subject(cfg)
    v = canonical_vertices(subj)
    lo = subj.render(v, _frontal(64, 0.44), None, 2)
    hi = subj.render(v, _frontal(256, 1.76), None, 2)
    hi_down = hi.rgb.reshape(lo.rgb.shape[0], 4, lo.rgb.shape[1], 4, 3).mean(axis=(1, 3))
    inside = (lo.alpha > 0.99) & (hi.alpha.reshape(lo.alpha.shape[0], 4, lo.alpha.shape[1], 4).min(axis=(1, 3)) > 0.99)
    err = np.abs(lo.rgb - hi_down)[inside].mean()
    texture = np.abs(hi_down[inside] - hi_down[inside].mean(0)).mean()
    assert err < 0.02 and err < 0.25 * texture, (err, texture)


def test_views_around_the_head_are_grouped(tmp_path: Path) -> None:
    cfg = preset("tiny", "oneshot", appearance="detailed", novel_views=3, novel_expressions=1, novel_around=4, width=40, height=58, **COARSE)
    out = write_capture(tmp_path / "one", cfg)
    info = json.loads((out / "gt" / "info.json").read_text())
    groups = info["novel"]["view_groups"]
    assert info["novel"]["cameras"] == 7
    # the arc in front (-60°, 0°, 60°), then around: 90° and 270° at the sides, 150° and 210° behind
    assert groups == {"front": [0, 1, 2], "side": [3, 6], "back": [4, 5]}
    val = json.loads((out / "gt" / "novel" / "transforms_val.json").read_text())
    test = json.loads((out / "gt" / "novel" / "transforms_test.json").read_text())
    assert val["camera_indices"] == list(range(7)) and test["camera_indices"] == [0, 1, 2]
    from sage_core.data.cameras import camera_from_nerf_frame

    for fr in val["frames"]:
        c = camera_from_nerf_frame(fr).center
        if fr["camera_index"] in groups["back"]:
            assert c[2] < -0.5 * np.hypot(c[0], c[2])
        img = read_image(out / "gt" / "novel" / fr["file_path"])
        assert (img[..., :3] < 0.99).any(axis=-1).mean() > 0.1  # the head is in view, not cut away


def test_multiview_novel_views_show_the_training_timestep_from_new_directions(detailed: Path, tmp_path: Path) -> None:
    """gt/novel of a detailed multiview capture: the first training timestep with its written
    parameters, seen from cameras no training camera is close to (off the arc and around the head);
    the capture itself is what it is without them."""
    from sage_core.data.cameras import camera_from_nerf_frame

    info = json.loads((detailed / "gt" / "info.json").read_text())
    novel = detailed / "gt" / "novel"
    assert info["novel"]["training_timestep"] == 0 and not (novel / "transforms_test.json").exists()
    assert (novel / "flame_param" / "00000.npz").read_bytes() == (detailed / "flame_param" / "00000.npz").read_bytes()
    val = json.loads((novel / "transforms_val.json").read_text())["frames"]
    train = json.loads((detailed / "transforms_train.json").read_text())["frames"]
    assert {f["timestep_index"] for f in val} == {0} and set(info["novel"]["view_groups"]) == {"front", "side", "back"}

    def direction(fr: dict) -> np.ndarray:
        c = camera_from_nerf_frame(fr).center
        return c / np.linalg.norm(c)

    seen = np.stack([direction(f) for f in train])
    for fr in val:
        nearest = np.degrees(np.arccos(np.clip(seen @ direction(fr), -1, 1)).min())
        assert nearest > 8.0, (fr["camera_index"], nearest)
    cfg = SynthConfig.from_dict(info["config"])
    plain = write_capture(tmp_path / "plain", cfg.with_overrides(novel_multiview=False, novel_around=0))
    for p in sorted(q for q in plain.rglob("*") if q.is_file() and q.name != "info.json"):
        assert p.read_bytes() == (detailed / p.relative_to(plain)).read_bytes(), p


def test_ceiling_reproduces_an_exact_detailed_capture(tmp_path: Path) -> None:
    from sage_core.data.cameras import camera_from_nerf_frame
    from sage_core.data.synthetic.ceiling import FLAME_KEYS, TrackedTruth

    cap = make_capture(tmp_path / "cap", preset("tiny", appearance="detailed", seed=3, **{**SMALL, "n_cameras": 2, "test_timesteps": 1}))
    truth = TrackedTruth.open(cap)
    for fr in json.loads((cap / "transforms.json").read_text())["frames"]:
        with np.load(cap / fr["flame_param_path"]) as z:
            params = {k: z[k] for k in FLAME_KEYS}
        img = read_image(cap / fr["file_path"])[..., :3]
        mse = float(((truth.render(params, camera_from_nerf_frame(fr)) - img) ** 2).mean())
        assert 10 * np.log10(1.0 / max(mse, 1e-12)) > 45.0, fr["file_path"]
