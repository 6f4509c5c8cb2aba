"""The fit's pieces: FLAME on a vertex subset, barycentrics of fixed pixels against the mesh
rasterizer, signed distances, outline vertices, the landmark embedding (file and calibration), and a
fit that recovers pose, expression and identity from ideal landmarks."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from track_helpers import models_or_skip

from sage_core.data.capture import read_capture
from sage_core.errors import InputError
from sage_core.flame import FlameModel, load_flame_model
from sage_core.render.mesh_raster import rasterize_mesh
from sage_core.track.config import resolve_track_config
from sage_core.track.embedding import (LandmarkEmbedding, PoseTable, calibrate_embedding, calibration_angles, load_embedding,
                                       save_embedding)
from sage_core.track.fitting import FitCamera, FitImage, FitProblem, Fitter
from sage_core.track.flame_subset import FlameSubset
from sage_core.track.losses import pixel_barycentrics, project, signed_distance, triangle_plane_frame


@pytest.fixture(scope="module")
def head(tiny_capture):
    model = load_flame_model(tiny_capture.model_path)
    return model, read_capture(tiny_capture, check_images=False)


def test_subset_equals_the_model(head):
    model, _ = head
    fm = FlameModel(model, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    ids = torch.randint(0, model.n_vertices, (40,), generator=g)
    kw = dict(shape=torch.randn(300, generator=g, dtype=torch.float64), expr=torch.randn(3, 100, generator=g, dtype=torch.float64),
              rotation=0.3 * torch.randn(3, 3, generator=g, dtype=torch.float64), neck_pose=0.2 * torch.randn(3, 3, generator=g, dtype=torch.float64),
              jaw_pose=0.2 * torch.randn(3, 3, generator=g, dtype=torch.float64), eyes_pose=0.1 * torch.randn(3, 6, generator=g, dtype=torch.float64),
              translation=torch.randn(3, 3, generator=g, dtype=torch.float64),
              static_offset=0.01 * torch.randn(model.n_vertices, 3, generator=g, dtype=torch.float64))
    assert torch.allclose(FlameSubset(fm, ids)(**kw), fm(**kw).vertices[:, ids], atol=1e-12)


def _mesh_view(head):
    model, cap = head
    fm = FlameModel(model)
    cam = cap.cameras[8]
    v = fm(**cap.params.select([0]).to_torch()).vertices[0]
    K = torch.as_tensor(cam.K, dtype=torch.float32)
    w2c = torch.as_tensor(cam.w2c, dtype=torch.float32)
    return fm, v, K, w2c, cam


def test_pixel_barycentrics_match_the_rasterizer(head):
    fm, v, K, w2c, cam = _mesh_view(head)
    r = rasterize_mesh(v, fm.faces, K, w2c, cam.width, cam.height)
    ys, xs = torch.nonzero(r.face_id[0] >= 0, as_tuple=True)
    f = r.face_id[0][ys, xs]
    uv, z = project(v[None], K[None], w2c[None])
    tri = fm.faces[f]
    px = torch.stack([xs, ys], -1).float() + 0.5
    b = pixel_barycentrics(uv[0][tri], z[0][tri], px)
    assert torch.allclose(b, r.bary[0][ys, xs], atol=2e-3)
    vv = v.clone().requires_grad_(True)
    uv2, z2 = project(vv[None], K[None], w2c[None])
    pixel_barycentrics(uv2[0][tri], z2[0][tri], px)[:, 0].sum().backward()
    assert torch.isfinite(vv.grad).all() and vv.grad.abs().sum() > 0


def test_signed_distance_of_a_disc():
    yy, xx = np.mgrid[0:64, 0:64] + 0.5
    r = np.hypot(xx - 32, yy - 32)
    sdt = signed_distance(r < 20)
    inner = (r > 5) & (r < 28)
    assert np.abs(sdt[inner] - (r[inner] - 20)).max() < 1.0
    assert sdt[32, 32] < -18 and sdt[2, 2] > 20


def test_outline_vertices_lie_on_the_rendered_outline(head):
    from scipy.ndimage import distance_transform_edt

    fm, v, K, w2c, cam = _mesh_view(head)
    fit = Fitter(fm, LandmarkEmbedding(np.array([1, 2, 3]), np.array([0, 1, 2]), np.full((3, 3), 1 / 3)),
                 FitProblem([FitCamera(cam.K, cam.w2c, cam.width, cam.height)], [], 1), resolve_track_config("tiny"))
    r = rasterize_mesh(v, fm.faces, K, w2c, cam.width, cam.height)
    uv, z = project(v[None], K[None], w2c[None])
    ids = fit.outline_vertices(v, uv[0], z[0], r.depth[0], w2c)
    assert ids.numel() > 50
    fg = r.mask[0].numpy()
    to_bg = distance_transform_edt(fg)
    p = uv[0][ids].numpy()
    d = to_bg[np.clip(p[:, 1].astype(int), 0, cam.height - 1), np.clip(p[:, 0].astype(int), 0, cam.width - 1)]
    assert np.all(d <= 3.0)


def _silhouette_term(head, person: np.ndarray, **problem: object) -> float:
    """The silhouette term of the capture's first mesh seen by camera 8 against the person mask
    ``person`` (face height 100 px), the fit's outline found at that mesh; ``problem``: FitProblem fields."""
    fm, v, K, w2c, cam = _mesh_view(head)
    emb = LandmarkEmbedding(np.array([1, 2, 3]), np.array([0, 1, 2]), np.full((3, 3), 1 / 3))
    image = FitImage(0, 0, None, 100.0, np.zeros((*person.shape, 3), np.float32), person.astype(np.float32))
    fit = Fitter(fm, emb, FitProblem([FitCamera(cam.K, cam.w2c, cam.width, cam.height)], [image], 1, **problem),
                 resolve_track_config("tiny"))
    r = rasterize_mesh(v, fm.faces, K, w2c, cam.width, cam.height)
    uv, z = project(v[None], K[None], w2c[None])
    fit.outline = fit.outline_vertices(v, uv[0], z[0], r.depth[0], w2c)[None]
    fit.sub_lookup = torch.arange(fm.n_vertices)
    with torch.no_grad():
        return float(fit.silhouette_term(v[None]))


def _coverage(head) -> np.ndarray:
    """(H, W) bool: the pixels the capture's first mesh covers in camera 8."""
    fm, v, K, w2c, cam = _mesh_view(head)
    return rasterize_mesh(v, fm.faces, K, w2c, cam.width, cam.height).mask[0].numpy()


def test_silhouette_pulls_inward_only_vertices_just_inwards(head):
    """A person mask wider than the mesh (hair around the head) pulls every outline vertex outwards,
    except those marked inward-only; a narrower one pulls all of them inwards alike."""
    from scipy.ndimage import binary_dilation, binary_erosion

    cover = _coverage(head)
    n = head[0].v_template.shape[0]
    terms = {}
    for name, person in (("wide", binary_dilation(cover, iterations=4)), ("narrow", binary_erosion(cover, iterations=4))):
        for inward in (None, np.ones(n, bool)):
            terms[name, inward is not None] = _silhouette_term(head, person, silhouette_inward=inward)
    assert terms["wide", False] > 1.0 and terms["wide", True] == 0.0
    assert terms["narrow", True] == pytest.approx(terms["narrow", False]) and terms["narrow", False] > 1.0


def test_silhouette_outward_pull_stops_at_its_limit(head):
    """With ``silhouette_outward_max`` an outline lying deeper inside the person mask than the limit
    (hair or a collar beside the face) is not pulled outwards, one lying within it still is; a mask
    narrower than the mesh pulls inwards whatever the limit."""
    from scipy.ndimage import binary_dilation, binary_erosion

    cover = _coverage(head)
    masks = {"wide 3 px": binary_dilation(cover, iterations=3), "wide 12 px": binary_dilation(cover, iterations=12),
             "narrow 12 px": binary_erosion(cover, iterations=12)}
    terms = {(name, limit): _silhouette_term(head, person, silhouette_outward_max=limit)
             for name, person in masks.items() for limit in (None, 0.05)}  # face height 100 px: the limit is 5 px
    assert terms["wide 3 px", 0.05] == pytest.approx(terms["wide 3 px", None]) and terms["wide 3 px", None] > 1.0
    assert terms["wide 12 px", None] > terms["wide 3 px", None] and terms["wide 12 px", 0.05] == 0.0
    assert terms["narrow 12 px", 0.05] == pytest.approx(terms["narrow 12 px", None]) and terms["narrow 12 px", None] > 1.0


def test_hair_stage_grows_the_hair_volume_alone(head, tiny_capture):
    """With the face-only silhouette the scalp is only pulled inwards, so a person mask wider than the
    head (hair) leaves the scalp offsets where they are; the hair stage pulls them out to it, and moves
    nothing else."""
    from scipy.ndimage import binary_dilation

    from sage_core.flame import load_masks
    from sage_core.track.fitting import TRANS_UNIT
    from sage_core.track.mesh_utils import hair_region

    fm, v, K, w2c, cam = _mesh_view(head)
    groups = {k: np.asarray(x) for k, x in load_masks(tiny_capture / "model" / "FLAME_masks.pkl").items()}
    face = np.zeros(fm.n_vertices, bool)
    for k in ("face", "neck"):
        face[groups[k]] = True
    cover = rasterize_mesh(v, fm.faces, K, w2c, cam.width, cam.height).mask[0].numpy()
    person = binary_dilation(cover, iterations=4).astype(np.float32)
    image = FitImage(0, 0, None, 100.0, np.zeros((*cover.shape, 3), np.float32), person)
    problem = FitProblem([FitCamera(cam.K, cam.w2c, cam.width, cam.height)], [image], 1, hair=hair_region(groups, fm.n_vertices),
                         silhouette_inward=~face, silhouette_outward_max=0.05, hair_stage=True)
    p = head[1].params.select([0])
    grown = {}
    for hair_stage in (False, True):
        fit = Fitter(fm, LandmarkEmbedding(np.array([1, 2, 3]), np.array([0, 1, 2]), np.full((3, 3), 1 / 3)), problem,
                     resolve_track_config("tiny"))
        with torch.no_grad():  # the fit's parameters at the capture's own (its mesh is v)
            fit.params["shape"].copy_(torch.as_tensor(p.shape[: fit.n_shape]))
            fit.params["expr"].copy_(torch.as_tensor(p.expr[:, : fit.n_expr]))
            for n in ("rotation", "neck_pose", "jaw_pose", "eyes_pose"):
                fit.params[n].copy_(torch.as_tensor(getattr(p, n)))
            fit.params["translation"].copy_(torch.as_tensor(p.translation) / TRANS_UNIT)
        before = {n: x.detach().clone() for n, x in fit.params.items()}
        fit._optimise(["offset"], 30, "hair" if hair_stage else "shape")
        grown[hair_stage] = float(fit.params["offset"].mean())
        for n, x in fit.params.items():
            if n != "offset":
                assert torch.equal(x, before[n]), n
    assert grown[False] <= 0.0 < 0.05 < grown[True]  # offsets in cm: the hair stage grows the scalp by half a millimetre or more
    assert resolve_track_config("tiny").hair_fit == "on"  # every face-only fit ends with it by default


def test_the_second_fit_is_kept_by_its_landmark_error():
    """focal_refit=auto keeps the second fit only when its landmarks lie closer (or the two fits' errors
    are not comparable); on keeps it always. The
    landmark error of a fit is the mean over its images with landmarks."""
    from types import SimpleNamespace

    from sage_core.track.pipeline import landmark_error, refit_kept

    assert refit_kept("auto", 3.1, 1.8) and not refit_kept("auto", 1.7, 2.3) and not refit_kept("auto", 2.0, 2.0)
    assert refit_kept("on", 1.7, 2.3)
    # a sequence's first fit with the pose table, its second without: not compared, the second kept
    assert refit_kept("auto", 1.7, 2.3, comparable=False) and not refit_kept("auto", 1.7, 2.3, comparable=True)
    assert landmark_error(SimpleNamespace(reprojection_px=np.array([1.0, np.nan, 3.0]))) == pytest.approx(2.0)
    assert landmark_error(SimpleNamespace(reprojection_px=np.array([np.nan]))) == float("inf")


def test_face_only_silhouette_rule():
    """auto pulls only the face and neck both ways unless a focal length is fitted; face and all are
    taken as given."""
    from sage_core.track.pipeline import face_only_silhouette

    assert face_only_silhouette("auto", focal_fitted=False) and not face_only_silhouette("auto", focal_fitted=True)
    assert face_only_silhouette("face", focal_fitted=True) and not face_only_silhouette("all", focal_fitted=False)


def test_focal_refit_rule():
    """auto (the default) holds a fitted focal length for a second fit for one photo, and for a sequence
    only when its pivot was held; on always; off and a known focal length never."""
    from sage_core.track.pipeline import focal_refit_rule
    from sage_core.track.config import TrackConfig

    assert focal_refit_rule("auto", True, sequence=False, pivot_held=False)
    assert focal_refit_rule("auto", True, sequence=True, pivot_held=True)
    assert not focal_refit_rule("auto", True, sequence=True, pivot_held=False)
    assert focal_refit_rule("on", True, sequence=True, pivot_held=False)
    assert not focal_refit_rule("on", False, sequence=False, pivot_held=False)
    assert not focal_refit_rule("auto", False, sequence=True, pivot_held=True)
    assert not focal_refit_rule("off", True, sequence=False, pivot_held=True)
    assert TrackConfig().focal_refit == "auto"


def test_embedding_file_round_trip_and_errors(tmp_path, head):
    model, _ = head
    emb = LandmarkEmbedding(np.arange(40), np.arange(40) * 3, np.tile([0.2, 0.3, 0.5], (40, 1)), np.linspace(0, 0.004, 40))
    path = save_embedding(tmp_path / "e.npz", emb)
    back = load_embedding(path, model.n_faces)
    assert np.array_equal(back.landmark_ids, emb.landmark_ids) and np.allclose(back.bary, emb.bary) and np.allclose(back.spread, emb.spread)
    with pytest.raises(InputError, match="another mesh"):
        load_embedding(path, 50)
    np.savez(tmp_path / "bad.npz", lmk_face_idx=np.zeros(40, int), lmk_b_coords=np.ones((40, 3)), landmark_indices=np.arange(40))
    with pytest.raises(InputError, match="sum to 1"):
        load_embedding(tmp_path / "bad.npz", model.n_faces)
    np.savez(tmp_path / "keys.npz", faces=np.zeros(3))
    with pytest.raises(InputError, match="lacks key"):
        load_embedding(tmp_path / "keys.npz", model.n_faces)


def _linear_table(K: int, a: float = 0.01, b: float = -0.02) -> PoseTable:
    """A pose table whose offsets are (a · yaw, b · pitch) metres (radians), the same for every landmark."""
    yaws, pitches = calibration_angles(30, 12, 5, 45, 24)
    gy, gp = np.meshgrid(np.deg2rad(yaws), np.deg2rad(pitches))  # (P, Y)
    off = np.stack([a * gy, b * gp], -1)[:, :, None, :].repeat(K, 2)
    return PoseTable(yaws, pitches, off)


def test_calibration_grid_and_pose_table_file(tmp_path, head):
    """The grid continues the calibration's steps outwards; a pose table survives the file, and a
    broken one is refused naming the file."""
    model, _ = head
    yaws, pitches = calibration_angles(30, 12, 5, 45, 24)
    assert yaws.tolist() == [-45, -30, -15, 0, 15, 30, 45] and pitches.tolist() == [-24, -12, 0, 12, 24]
    assert [a.tolist() for a in calibration_angles(30, 12, 3, 0, 0)] == [[-30, 0, 30], [-12, 0, 12]]
    emb = LandmarkEmbedding(np.arange(40), np.arange(40) * 3, np.tile([0.2, 0.3, 0.5], (40, 1)), pose=_linear_table(40))
    back = load_embedding(save_embedding(tmp_path / "e.npz", emb), model.n_faces)
    assert np.allclose(back.pose.offsets, emb.pose.offsets) and np.array_equal(back.pose.yaws, emb.pose.yaws)
    arrays = dict(np.load(tmp_path / "e.npz"))
    np.savez(tmp_path / "short.npz", **{**arrays, "pose_offsets": arrays["pose_offsets"][:, :, :39]})
    with pytest.raises(InputError, match="short.npz.*pose_offsets has shape"):
        load_embedding(tmp_path / "short.npz", model.n_faces)
    del arrays["pose_yaws"]
    np.savez(tmp_path / "part.npz", **arrays)
    with pytest.raises(InputError, match="needs all three"):
        load_embedding(tmp_path / "part.npz", model.n_faces)


def test_pose_table_follows_a_smooth_lean_and_ignores_jumps():
    """Back-projections that slide with the pitch (3 cm per radian along the triangle's in-plane
    perpendicular), one view missing and one detection jumped 4 cm away: the table is the lean
    everywhere, the missing view included."""
    from sage_core.track.embedding import _pose_table

    v = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])  # triangle in z = 0: e1 = x, e2 = y
    faces = np.array([[0, 1, 2]])
    yaws, pitches = calibration_angles(30, 12, 5, 45, 24)
    grid = [(pi, yi) for pi in range(len(pitches)) for yi in range(len(yaws))]
    b = np.array([0.2, 0.3, 0.5])
    p0 = b @ v
    samples = [[]]
    for vi, (pi, yi) in enumerate(grid):
        if (pi, yi) == (4, 6):
            continue  # not seen there
        jump = np.array([0.04, 0.0, 0.0]) if (pi, yi) == (1, 1) else 0.0
        samples[0].append((vi, 0, b, p0 + np.array([0.0, 0.03 * np.deg2rad(pitches[pi]), 0.0]) + jump))
    table = _pose_table(samples, [0], [0], [b], v, faces, yaws, pitches, grid, limit=0.02)
    want = 0.03 * np.deg2rad(pitches)[:, None].repeat(len(yaws), 1)
    assert np.allclose(table.offsets[:, :, 0, 1], want, atol=1e-9) and np.allclose(table.offsets[:, :, 0, 0], 0.0, atol=1e-9)


def test_fit_looks_the_pose_table_up_at_each_images_pose(head):
    """A table linear in yaw and pitch, looked up for the head pitched 10° and turned 20°: the offsets
    are the table's at the pose the camera sees (bilinear is exact for a plane), and they move the
    landmarks in their triangles' planes by that much."""
    fm, v, K, w2c, cam = _mesh_view(head)
    rng = np.random.default_rng(1)
    n = 30
    emb = LandmarkEmbedding(np.arange(n), rng.choice(fm.faces.shape[0], n, replace=False), rng.dirichlet(np.ones(3), n),
                            pose=_linear_table(n))
    fit = Fitter(fm, emb, FitProblem([FitCamera(cam.K, cam.w2c, cam.width, cam.height)], [], 1), resolve_track_config("tiny"))
    with torch.no_grad():
        fit.params["rotation"][0] = torch.tensor([np.deg2rad(10.0), np.deg2rad(20.0), 0.0], dtype=fit.dtype)
        verts = fm(rotation=fit.params["rotation"].detach()).vertices
        tri = verts[:, fit.tri]
        centre = torch.as_tensor(cam.center, dtype=fit.dtype)[None]
        off = fit.pose_offsets(torch.tensor([0]), tri, centre)
        R = fit.params["rotation"][0]
        from sage_core.track.fitting import axis_angle_to_matrix

        face = (tri * fit.bary[:, :, None]).sum(-2).mean(1)[0]
        d = axis_angle_to_matrix(R[None])[0].T @ (centre[0] - face)
        d = d / d.norm()
        yaw, pitch = float(torch.atan2(d[0], d[2])), float(torch.asin(d[1]))
        assert abs(np.rad2deg(pitch)) > 5 and abs(np.rad2deg(yaw)) > 10
        assert torch.allclose(off[0], torch.tensor([0.01 * yaw, -0.02 * pitch], dtype=off.dtype).expand(n, 2), atol=1e-9)
        moved = fit.landmark_points(tri, off) - fit.landmark_points(tri, None)
        assert torch.allclose(moved.norm(dim=-1), off.norm(dim=-1), atol=1e-9)
    fixed = Fitter(fm, replace(emb, pose=None), FitProblem([FitCamera(cam.K, cam.w2c, cam.width, cam.height)], [], 1),
                   resolve_track_config("tiny"))
    assert fixed.pose_offsets(torch.tensor([0]), tri, centre) is None


def test_landmark_pose_rule():
    """auto: one camera that sees the head turn (a video, several frames) whose fit pulls the whole
    outline both ways (a fitted focal length, or silhouette_two_sided=all); on and off as given."""
    from sage_core.track.pipeline import landmark_pose_rule

    assert landmark_pose_rule("auto", "video", 40, True) and landmark_pose_rule("auto", "images", 2, True)
    assert not landmark_pose_rule("auto", "video", 40, False) and not landmark_pose_rule("auto", "images", 2, False)
    assert not landmark_pose_rule("auto", "image", 1, True) and not landmark_pose_rule("auto", "multiview", 6, True)
    assert not landmark_pose_rule("auto", "images", 1, True)
    assert landmark_pose_rule("on", "multiview", 6, False) and not landmark_pose_rule("off", "video", 40, True)


@pytest.mark.parametrize("beyond_edge", [False, True])
def test_fit_recovers_the_head_from_ideal_landmarks(head, one_thread, beyond_edge):
    """Landmarks on 160 random triangles of the head, projected from the true meshes (without hair
    volume) of two timesteps into four cameras: the landmark stages alone bring every vertex within a
    millimetre of the truth. ``beyond_edge``: in every other image 40 of the points are put beyond the
    image's edge, far from where they belong (a face partly out of the frame, whose landmarks there
    the model guesses): they are left out, and the fit is as good."""
    model, cap = head
    fm = FlameModel(model)
    rng = np.random.default_rng(0)
    tris = rng.choice(model.n_faces, 160, replace=False)
    b = rng.dirichlet(np.ones(3), 160)
    emb = LandmarkEmbedding(np.arange(160), tris, b)
    cams = [cap.cameras[c] for c in (5, 7, 9, 11)]
    truth = cap.params.select([0, 1])
    truth.static_offset = None  # the hair volume is the silhouettes' job
    with torch.no_grad():
        verts = fm(**truth.to_torch()).vertices
    images = []
    for t in range(2):
        pts = emb.points(verts[t], fm.faces).numpy()
        for ci, cam in enumerate(cams):
            uv, _ = cam.project(pts)
            full = np.zeros((468, 2))
            full[:160] = uv
            if beyond_edge and ci % 2:
                full[:40, 0] = cam.width + 5 + 40 * rng.random(40)
            images.append(FitImage(t, ci, full, float(np.ptp(uv, 0).max())))
    problem = FitProblem([FitCamera(c.K, c.w2c, c.width, c.height) for c in cams], images, 2)
    # the priors are there for biased detections; exact landmarks need only faint ones
    cfg = resolve_track_config("tiny", None, {"rigid_steps": 60, "steps": 250, "refine_steps": 0, "w_shape": 1e-5,
                                              "w_expr": 1e-5, "w_pose": 1e-3})
    fit = Fitter(fm, emb, problem, cfg)
    assert int((fit.obs_in == 0).sum()) == (160 if beyond_edge else 0)
    res = fit.run()
    with torch.no_grad():
        got = fit.full_vertices()
    err = (got - verts).norm(dim=-1).mean(1) * 1000
    assert float(err.max()) < 1.0, err
    assert np.nanmax(res.reprojection_px) < 0.5


def test_calibrated_embedding_of_the_synthetic_head(head):
    from sage_core.track.faces import FaceObserver
    from sage_core.track.weights import find_models

    observer = FaceObserver(find_models(models_or_skip()))
    model, _ = head
    fm = FlameModel(model)
    with torch.no_grad():
        v = fm().vertices[0]
    emb, rep = calibrate_embedding(v, fm.faces, observer, size=256, n_yaw=3, pose_pitch_deg=24)
    assert rep.views_with_face == rep.views == 9 and rep.pose_views == 15
    # the pose table's extra views (pitch ±24) leave the embedding itself as the 9 views make it
    fixed, rep_fixed = calibrate_embedding(v, fm.faces, observer, size=256, n_yaw=3, pose_table=False)
    assert fixed.pose is None and rep_fixed.pose_views == 0
    assert np.array_equal(fixed.faces, emb.faces) and np.array_equal(fixed.bary, emb.bary)
    # the detector leans: its points move over the face between the frontal view and the pitched ones
    off = emb.pose.offsets
    assert off.shape == (5, 3, len(emb), 2) and np.all(np.isfinite(off))
    assert np.abs(off[4, 1] - off[2, 1]).mean() > 1e-3 and np.abs(off[0, 1] - off[2, 1]).mean() > 1e-3
    assert rep.kept > 300 and rep.median_spread_mm < 6
    pts = emb.points(v, fm.faces).numpy()
    k = {int(i): n for n, i in enumerate(emb.landmark_ids)}
    tip = v[int(torch.argmax(v[:, 2]))].numpy()
    assert 1 in k and np.linalg.norm(pts[k[1]] - tip) < 0.012  # face-mesh point 1: the tip of the nose
    assert 33 in k and 263 in k and pts[k[33], 0] < pts[k[263], 0]  # right eye's outer corner at -x (the head's right)


def _turning_sequence(head, n: int, drift: tuple[float, float, float] = (0.0, 0.0, 0.0)):
    """Landmarks on 160 random triangles of the tiny head turning from -40 to 40 degrees of yaw over
    ``n`` frames (with a nod and a jaw opening and closing), seen by one camera, and the true meshes.
    ``drift``: the head also moves this far (metres, world axes) from the first frame to the last."""
    model, cap = head
    fm = FlameModel(model)
    rng = np.random.default_rng(1)
    tris = rng.choice(model.n_faces, 160, replace=False)
    emb = LandmarkEmbedding(np.arange(160), tris, rng.dirichlet(np.ones(3), 160))
    s = np.linspace(0, 1, n)
    rot = np.stack([0.15 * np.sin(2 * np.pi * s), np.deg2rad(-40 + 80 * s), np.zeros(n)], 1)
    jaw = np.stack([0.12 * np.sin(np.pi * s) ** 2, np.zeros(n), np.zeros(n)], 1)
    truth = cap.params.select([0] * n)
    truth.static_offset = None
    truth.rotation = rot.astype(np.float32)
    truth.jaw_pose = jaw.astype(np.float32)
    truth.translation = (truth.translation + (s - 0.5)[:, None] * np.asarray(drift)[None]).astype(np.float32)
    with torch.no_grad():
        verts = fm(**truth.to_torch()).vertices
    cam = cap.cameras[8]
    images = []
    for t in range(n):
        uv, _ = cam.project(emb.points(verts[t], fm.faces).numpy())
        full = np.zeros((468, 2))
        full[:160] = uv
        images.append(FitImage(t, 0, full, float(np.ptp(uv, 0).max())))
    problem = FitProblem([FitCamera(cam.K, cam.w2c, cam.width, cam.height)], images, n, smooth=True, camera_relative=True)
    return fm, emb, problem, verts


def test_keyframes_then_chunks_track_a_sequence_without_seams(head, one_thread):
    """A 24-frame head turn: 5 keyframes with the full schedule, then chunks of 5 frames with the
    shared parameters frozen. Every frame lies on its landmarks, its mesh near the truth (one camera:
    after one similarity for the whole sequence), and the head's motion across the chunk seams is as
    smooth as inside the chunks."""
    from sage_core.track.truth import similarity_fit

    n = 24
    fm, emb, problem, verts = _turning_sequence(head, n)
    cfg = resolve_track_config("tiny", None, {"rigid_steps": 60, "steps": 200, "refine_steps": 0, "w_shape": 1e-5,
                                              "w_expr": 1e-5, "w_pose": 1e-3, "keyframes": 5, "track_chunk": 5,
                                              "track_steps": 30, "w_smooth": 0.5})
    fit = Fitter(fm, emb, problem, cfg)
    res = fit.run()
    assert res.keyframes == [0, 6, 12, 17, 23] and set(res.timings) == {"keyframes", "track"}
    assert "keyframes_shape" in res.losses and "track" in res.losses
    assert np.nanmax(res.reprojection_px) < 0.5, res.reprojection_px
    with torch.no_grad():
        got = fit.full_vertices().double().numpy()
    true = verts.double().numpy()
    R, t, s = similarity_fit(got.reshape(-1, 3), true.reshape(-1, 3))
    err = np.linalg.norm(s * got @ R.T + t - true, axis=-1).mean(1) * 1000
    assert err.mean() < 2.0 and err.max() < 4.0, err
    # frame-to-frame motion of the vertices against the truth's: across the seams (4->5, 9->10, ...) as
    # inside the chunks
    dev = np.linalg.norm(np.diff(got, axis=0) - np.diff(true, axis=0), axis=-1).mean(1) * 1000
    seams = np.arange(4, n - 1, 5)
    inner = np.setdiff1d(np.arange(n - 1), seams)
    assert dev[seams].max() < 2 * dev[inner].max(), (dev[seams], dev[inner])


def test_keyframes_zero_or_short_sequences_fit_every_frame_jointly(head, one_thread):
    """keyframes=0, no more timesteps than keyframes, or timesteps in no order (a folder of photos, a
    rig: ``smooth`` off): the three stages on all frames at once."""
    from dataclasses import replace

    fm, emb, problem, _ = _turning_sequence(head, 6)
    for flags, prob in (({"keyframes": 0}, problem), ({"keyframes": 6}, problem), ({"keyframes": 3}, replace(problem, smooth=False))):
        cfg = resolve_track_config("tiny", None, {"rigid_steps": 5, "steps": 5, "refine_steps": 0, **flags})
        res = Fitter(fm, emb, prob, cfg).run()
        assert res.keyframes == list(range(6)) and set(res.timings) == {"joint"}
        assert "track" not in res.losses


def test_rotations_interpolate_along_the_shortest_rotation():
    """Between two keyframes a rotation moves along the geodesic at constant angular speed: the
    midpoint is half the angle from both ends; about one axis it equals the linear mix; eyes_pose's
    two rotations are interpolated each on its own."""
    from sage_core.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
    from sage_core.track.fitting import interpolate_rotations

    def angle(Ra, Rb):
        return matrix_to_axis_angle(Ra.transpose(-1, -2) @ Rb).norm(dim=-1)

    a = torch.tensor([[0.0, 1.0, 0.0, 0.1, 0.0, 0.0]], dtype=torch.float64)
    b = torch.tensor([[0.8, 0.0, 0.3, 0.5, 0.0, 0.0]], dtype=torch.float64)
    Ra, Rb = axis_angle_to_matrix(a.reshape(-1, 3)), axis_angle_to_matrix(b.reshape(-1, 3))
    total = angle(Ra, Rb)
    for w in (0.0, 0.25, 0.5, 1.0):
        m = axis_angle_to_matrix(interpolate_rotations(a, b, torch.tensor([[w]], dtype=torch.float64)).reshape(-1, 3))
        assert torch.allclose(angle(Ra, m), w * total, atol=1e-6) and torch.allclose(angle(m, Rb), (1 - w) * total, atol=1e-6)
    mid = interpolate_rotations(a, b, torch.tensor([[0.5]], dtype=torch.float64))
    assert torch.allclose(mid[0, 3:], torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64), atol=1e-7)  # one axis: linear
    lin = (a[0, :3] + b[0, :3]) / 2
    assert not torch.allclose(mid[0, :3], lin, atol=1e-3)  # two axes: not the coefficient mix


def test_problem_subset_and_keyframe_smoothing_gaps(head):
    fm, emb, problem, _ = _turning_sequence(head, 10)
    sub = problem.subset(np.array([0, 4, 9]))
    assert sub.n_timesteps == 3 and [im.timestep for im in sub.images] == [0, 1, 2]
    assert np.array_equal(sub.times, [0, 4, 9]) and sub.images[1].landmarks is problem.images[4].landmarks
    assert [im.timestep for im in problem.images] == list(range(10))  # the original is untouched
    assert np.array_equal(sub.subset(np.array([1, 2])).times, [4, 9])
    # a difference over a gap of g frames weighs 1/g² of one between neighbours
    from sage_core.track.fitting import PER_TIMESTEP

    cfg = resolve_track_config("tiny")
    fit = Fitter(fm, emb, sub, cfg)
    with torch.no_grad():
        fit.params["rotation"][1, 1] = 1.0
        assert float(fit.smoothness()) == pytest.approx((1 / 16 + 1 / 25) / 2, rel=1e-5)
        # a chunk's fixed neighbour joins at a gap of 1 frame
        fit.smooth_before = {k: fit.params[k][:1].clone() for k in PER_TIMESTEP}
        fit.smooth_before["jaw_pose"] = fit.smooth_before["jaw_pose"] + 0.5
        assert float(fit.smoothness()) == pytest.approx((0.25 * 3 + 1 / 16 + 1 / 25) / 3, rel=1e-5)


@pytest.mark.parametrize("flags", [{"keyframes": -1}, {"track_chunk": 0}, {"track_steps": -5}, {"track_outline_period": 0},
                                   {"outline_period": 0}, {"keyframes": 2.5}, {"silhouette_two_sided": "hair"},
                                   {"follow_landmarks": "always"}, {"max_outside": 0}, {"max_outside": 1.5}])
def test_sequence_options_are_validated(flags):
    from sage_core.errors import ConfigError

    with pytest.raises(ConfigError):
        resolve_track_config("default", None, flags)


def test_steady_depth_rule():
    """Only when asked for, and only for a video or a folder of several frames, never for one image or a rig."""
    from sage_core.track.pipeline import steady_depth_rule

    assert steady_depth_rule(True, "video", 40) and steady_depth_rule(True, "images", 2)
    assert not steady_depth_rule(True, "images", 1) and not steady_depth_rule(True, "image", 1)
    assert not steady_depth_rule(True, "multiview", 6) and not steady_depth_rule(False, "video", 40)


def test_steady_depth_term_and_its_anchor(head):
    """Zero when every timestep is at one depth; robust (quadratic, then linear) in the log-depth
    deviation from the timesteps' mean, or from a chunk's anchor."""
    fm, emb, problem, _ = _turning_sequence(head, 4)
    cfg = resolve_track_config("tiny", None, {"steady_depth_scale": 0.01})
    fit = Fitter(fm, emb, problem, cfg)
    with torch.no_grad():
        fit.params["translation"][:, 2] = 0.3
        assert float(fit.steady_depth()) == pytest.approx(0.0, abs=1e-9)
        fit.params["translation"][:, 2] = torch.tensor([0.0, 0.0, 0.02, -0.02], dtype=fit.dtype)
        expected = 2 * (np.sqrt(1 + 2.0 ** 2) - 1) / 4
        assert float(fit.steady_depth()) == pytest.approx(expected, rel=1e-6)
        fit.depth_anchor = torch.tensor(0.02, dtype=fit.dtype)
        expected = (2 * (np.sqrt(1 + 4.0) - 1) + 0 + (np.sqrt(1 + 16.0) - 1)) / 4
        assert float(fit.steady_depth()) == pytest.approx(expected, rel=1e-6)
        fit.params["translation"][:, 2] = torch.tensor([0.0, 0.0, 0.5, 0.0], dtype=fit.dtype)
        fit.depth_anchor = None
        big = float(fit.steady_depth())
        assert big < 0.5 / 0.01  # linear, not quadratic, far from the common depth


def test_steady_position_term_and_its_anchor(head):
    """Zero when the pivot keeps one position across the image; robust in its deviation from the
    timesteps' mean (or a chunk's anchor) measured as a share of the distance (pixels / focal length)."""
    from sage_core.track.fitting import PIXEL_UNIT

    fm, emb, problem, _ = _turning_sequence(head, 4)
    cfg = resolve_track_config("tiny", None, {"steady_depth_scale": 0.01})
    fit = Fitter(fm, emb, problem, cfg)
    K, _ = fit.cameras()
    fx, fy = float(K[0, 0, 0].detach()), float(K[0, 1, 1].detach())
    with torch.no_grad():
        fit.params["translation"][:, :2] = torch.tensor([0.4, -0.2], dtype=fit.dtype)
        assert float(fit.steady_position()) == pytest.approx(0.0, abs=1e-9)
        dx = 0.01 * fx / PIXEL_UNIT  # 1 % of the distance sideways, in the parameter's units
        fit.params["translation"][:, 0] = 0.4 + torch.tensor([dx, -dx, dx, -dx], dtype=fit.dtype)
        assert float(fit.steady_position()) == pytest.approx(np.sqrt(2.0) - 1, rel=1e-6)
        fit.xy_anchor = torch.tensor([0.4 + dx, -0.2 + 0.02 * fy / PIXEL_UNIT], dtype=fit.dtype)
        expected = (2 * (np.sqrt(1 + 4.0) - 1) + 4 * (np.sqrt(1 + 4.0) - 1)) / 4
        assert float(fit.steady_position()) == pytest.approx(expected, rel=1e-6)
        fit.params["translation"][:, 2] = torch.tensor([0.0, 0.0, 0.02, -0.02], dtype=fit.dtype)
        before = float(fit.steady_position())
        fit.params["translation"][:, 2] = 0.0
        assert float(fit.steady_position()) == pytest.approx(before)  # the depth is steady_depth's

    # in the priors: the depth option adds its term; the pivot alone adds both (its depth is held too)
    from dataclasses import replace

    def priors(depth: bool, pivot: bool) -> float:
        f = Fitter(fm, emb, replace(problem, steady_depth=depth, steady_pivot=pivot), cfg)
        with torch.no_grad():
            f.params["translation"].copy_(fit.params["translation"])
            return float(f.priors())

    fit.xy_anchor = None
    with torch.no_grad():
        fit.params["translation"][:, 2] = torch.tensor([0.0, 0.0, 0.02, -0.02], dtype=fit.dtype)
        depth_term, position_term = float(fit.steady_depth()), float(fit.steady_position())
    assert depth_term > 0 and position_term > 0
    plain = priors(False, False)
    assert priors(True, False) - plain == pytest.approx(depth_term, rel=1e-5)
    assert priors(False, True) - plain == pytest.approx(depth_term + position_term, rel=1e-5)


def test_steady_pivot_holds_the_pivot_and_the_pitch(head, one_thread):
    """Noisy landmarks on a head turning and nodding about a pivot that stays put: holding the pivot
    keeps its fitted position across the image far steadier than the depth prior alone and brings the
    meshes closer to the truth."""
    from dataclasses import replace

    from sage_core.track.truth import similarity_fit

    n = 6
    fm, emb, problem, verts = _turning_sequence(head, n)
    rng = np.random.default_rng(5)
    images = [replace(im, landmarks=im.landmarks + np.where(np.arange(468)[:, None] < 160, rng.normal(0, 0.8, (468, 2)), 0.0))
              for im in problem.images]
    problem = replace(problem, images=images, smooth=False, steady_depth=True)
    spread, error = {}, {}
    for pivot in (False, True):
        cfg = resolve_track_config("tiny", None, {"rigid_steps": 60, "steps": 120, "refine_steps": 0, "w_shape": 1e-4,
                                                  "w_expr": 1e-4, "w_pose": 1e-3})
        fit = Fitter(fm, emb, replace(problem, steady_pivot=pivot), cfg)
        fit.run()
        with torch.no_grad():
            spread[pivot] = float(fit.params["translation"][:, :2].std(0).sum())
            got = fit.full_vertices().double().numpy()
        true = verts.double().numpy()
        R, t, s = similarity_fit(got.reshape(-1, 3), true.reshape(-1, 3))
        error[pivot] = float(np.linalg.norm(s * got @ R.T + t - true, axis=-1).mean() * 1000)
    assert spread[True] < 0.3 * spread[False], spread
    assert error[True] < error[False], error


@pytest.mark.parametrize("keyframed", [False, True])
def test_steady_pivot_auto_holds_a_still_pivot_and_leaves_a_moving_one(head, one_thread, keyframed):
    """``steady_pivot=auto``: the frames (a long sequence's keyframes) fitted without the prior first. A
    head turning about a pivot that stays put keeps it within the prior's scale: the pivot is held and
    the fit is the one with the pivot on; a head that also moves 6 cm sideways and 8 cm in depth
    spreads it far beyond: the fit is the one without (the first fit reused, not repeated)."""
    from dataclasses import replace

    n = 8
    fm, emb, still, _ = _turning_sequence(head, n)
    _, _, moving, _ = _turning_sequence(head, n, drift=(0.06, 0.0, 0.08))
    overrides = {"rigid_steps": 60, "steps": 80, "refine_steps": 0, "w_shape": 1e-4, "w_expr": 1e-4, "w_pose": 1e-3,
                 "keyframes": 5 if keyframed else 0, "track_chunk": 4, "track_steps": 10}
    cfg = resolve_track_config("tiny", None, overrides)

    # the embedding of a held pivot: the same landmarks with a pose table (offsets 0: the same fit)
    wide = replace(emb, pose=PoseTable(np.array([-60.0, 0.0, 60.0]), np.array([0.0]), np.zeros((1, 3, len(emb), 2))))
    used = {}

    def fit(problem, **kw):
        f = Fitter(fm, emb, replace(problem, smooth=keyframed, **kw), cfg, pivot_embedding=wide)
        out = f.run()
        used[kw.get("steady_pivot_auto", False)] = f.emb
        return out

    spread = {}
    for problem, held in ((still, True), (moving, False)):
        auto = fit(problem, steady_pivot_auto=True)
        assert used[True] is (wide if held else emb)
        spread[held] = auto.pivot_check["spread"]
        assert auto.pivot_check["held"] is held
        assert (auto.pivot_check["spread"] <= 0.01) is held, auto.pivot_check
        assert auto.keyframes == ([0, 2, 4, 5, 7] if keyframed else list(range(n)))
        same = fit(problem, steady_pivot=held)
        assert same.pivot_check == {}
        for k in ("translation", "rotation", "expr", "shape"):
            np.testing.assert_allclose(getattr(auto.params, k), getattr(same.params, k), atol=1e-6, err_msg=k)
    # the moving head's spread is its motion (a standard deviation of 2 cm sideways at 0.7 m): over
    # twice the scale; the still head's what the fit leaves, clearly under it
    assert spread[True] < 0.8 * 0.01 and spread[False] > 2 * 0.01, spread
    other = replace(emb, bary=np.roll(emb.bary, 1, axis=1))
    with pytest.raises(ValueError, match="same landmarks"):
        Fitter(fm, emb, still, cfg, pivot_embedding=other)


def test_steady_depth_holds_a_noisy_sequence_together(head, one_thread):
    """Landmarks with noise on a turning head at one distance: with the prior the fitted depths agree
    far better than without it, and the meshes are no further from the truth."""
    from dataclasses import replace

    from sage_core.track.truth import similarity_fit

    n = 6
    fm, emb, problem, verts = _turning_sequence(head, n)
    rng = np.random.default_rng(3)
    images = [replace(im, landmarks=im.landmarks + np.where(np.arange(468)[:, None] < 160, rng.normal(0, 0.8, (468, 2)), 0.0))
              for im in problem.images]
    problem = replace(problem, images=images, smooth=False)
    spread, error = {}, {}
    for steady in (False, True):
        cfg = resolve_track_config("tiny", None, {"rigid_steps": 60, "steps": 120, "refine_steps": 0, "w_shape": 1e-4,
                                                  "w_expr": 1e-4, "w_pose": 1e-3, "w_steady_depth": 1.0})
        fit = Fitter(fm, emb, replace(problem, steady_depth=steady), cfg)
        fit.run()
        with torch.no_grad():
            spread[steady] = float(fit.params["translation"][:, 2].std())
            got = fit.full_vertices().double().numpy()
        true = verts.double().numpy()
        R, t, s = similarity_fit(got.reshape(-1, 3), true.reshape(-1, 3))
        error[steady] = float(np.linalg.norm(s * got @ R.T + t - true, axis=-1).mean() * 1000)
    assert spread[True] < 0.3 * spread[False], spread
    assert error[True] <= error[False] * 1.05, error


def test_triangle_plane_frame_is_the_landmark_offset_frame():
    """e1 along the first edge, e2 in the plane and perpendicular, both unit: the frame the calibration's
    pose table and the fitter's offsets share."""
    g = torch.Generator().manual_seed(3)
    tri = torch.randn(5, 3, 3, generator=g, dtype=torch.float64)
    e1, e2 = triangle_plane_frame(tri)
    edge = tri[:, 1] - tri[:, 0]
    n = torch.cross(edge, tri[:, 2] - tri[:, 0], dim=-1)
    assert torch.allclose(e1, edge / edge.norm(dim=-1, keepdim=True))
    assert torch.allclose(e2.norm(dim=-1), torch.ones(5, dtype=torch.float64))
    assert torch.allclose((e1 * e2).sum(-1), torch.zeros(5, dtype=torch.float64), atol=1e-12)
    assert torch.allclose((e2 * n).sum(-1), torch.zeros(5, dtype=torch.float64), atol=1e-10)
    # right-handed with the normal: e1 × e2 points along n
    assert bool(((torch.cross(e1, e2, dim=-1) * n).sum(-1) > 0).all())
