"""`sage export --gaussian-avatars`: GA's file layout in GA's own FLAME topology (the model's rows plus
GA's 120 teeth rows, bindings inside GA's face table), and GA's posing math (docs/formats.md §6),
re-implemented here in numpy, reproducing sage's own posed surfels at several frames."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from helpers import invoke, load_phase1_renderer


@pytest.fixture(scope="module")
def ga_ws(cmd_avatar_ws, tmp_path_factory):
    ws = tmp_path_factory.mktemp("ga") / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    res = invoke(["export", ws, "--format", "gaussian-avatars", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    return ws


def _read_ply_rows(path):
    """(names, (N, P) float32 rows) of a binary little-endian all-float PLY."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    head = raw[:end].decode().splitlines()
    assert head[1] == "format binary_little_endian 1.0"
    names = [ln.split()[2] for ln in head if ln.startswith("property")]
    assert all(ln.split()[1] == "float" for ln in head if ln.startswith("property"))
    n = int(next(ln.split()[2] for ln in head if ln.startswith("element vertex")))
    return names, np.frombuffer(raw, "<f4", n * len(names), end).reshape(n, len(names)).astype(np.float64)


def _unit(x):
    return x / np.sqrt(np.maximum((x * x).sum(-1, keepdims=True), 1e-20))


def _ga_frames(v, faces):
    """GA's per-face R = [a0 | a1 | a2], T, k (docs/formats.md §6)."""
    v0, v1, v2 = (v[faces[:, i]] for i in range(3))
    a0 = _unit(v1 - v0)
    a1 = _unit(np.cross(a0, v2 - v0))
    a2 = np.cross(a0, a1)
    R = np.stack([a0, a1, a2], -1)
    k = 0.5 * (np.linalg.norm(v1 - v0, axis=-1) + np.abs((a2 * (v2 - v0)).sum(-1)))
    return R, (v0 + v1 + v2) / 3.0, k


def _quat_matrix(q):
    w, x, y, z = _unit(q).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)  # fmt: skip


def _ga_topology_numbers(av):
    md = av.model_data
    n = int(md.n_base_vertices)
    n_faces = int((av.faces.numpy() < n).all(1).sum())
    return n, n_faces


def test_point_cloud_and_flame_param_layout(ga_ws):
    out = ga_ws / "export" / "gaussian_avatars"
    names, rows = _read_ply_rows(out / "point_cloud.ply")
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "binding_0"])  # fmt: skip
    assert names == expected
    _, loaded, _ = load_phase1_renderer(ga_ws)
    av = loaded.avatar
    n_model, f_model = _ga_topology_numbers(av)
    assert av.model_data.v_template.shape[0] > n_model + 120  # sage's model carries more than GA's rows
    assert rows.shape[0] == av.surfels.n
    binding = rows[:, -1]
    assert np.array_equal(binding, np.round(binding))
    sage_b = av.surfels.binding.numpy()
    on_model = sage_b < f_model
    assert 0 < (~on_model).sum() < on_model.sum()  # some surfels sit on sage's mouth interior
    # surfels on the model's own faces keep them; the others are rebound inside the model's faces
    assert np.array_equal(binding[on_model].astype(np.int64), sage_b[on_model])
    assert binding.min() >= 0 and binding.max() < f_model + 168
    record = json.loads((out / "sage_export.json").read_text())
    assert record["n_vertices"] == n_model + 120 and record["n_faces"] == f_model + 168
    assert record["rebound"] == int((~on_model).sum()) and "zeros" in record["teeth_rows"]
    entry = json.loads((ga_ws / "export" / "results.json").read_text())["gaussian-avatars"]
    assert sorted(entry["files"]) == ["gaussian_avatars/flame_param.npz", "gaussian_avatars/point_cloud.ply",
                                      "gaussian_avatars/sage_export.json"]  # fmt: skip
    assert not rows[:, 9:54].any()  # f_rest zero (view-independent colours)
    with np.load(out / "flame_param.npz") as z:
        arrays = {k: z[k] for k in z.files}
    V = n_model + 120
    T = av.params.n_timesteps
    want = {"shape": (300,), "expr": (T, 100), "rotation": (T, 3), "neck_pose": (T, 3), "jaw_pose": (T, 3),
            "eyes_pose": (T, 6), "translation": (T, 3), "static_offset": (1, V, 3), "dynamic_offset": (T, V, 3)}  # fmt: skip
    assert {k: v.shape for k, v in arrays.items()} == want
    assert all(v.dtype == np.float32 for v in arrays.values())
    assert not arrays["static_offset"][:, n_model:].any()  # this model's teeth are not GA's: zero rows
    if av.params.static_offset is not None:
        so = np.asarray(av.params.static_offset).reshape(-1, 3)
        assert np.allclose(arrays["static_offset"][0, :n_model], so[:n_model], atol=1e-7)
    assert not arrays["shape"][av.params.n_shape :].any() and not arrays["expr"][:, av.params.n_expr :].any()
    assert np.allclose(arrays["expr"][:, : av.params.n_expr], av.params.expr, atol=1e-7)
    assert (out / "flame_param.npz").stat().st_mode & 0o044 == 0o044  # readable by others, like every export
    # colours and opacities are the avatar's at the canonical pose
    from sage_core.flame.canonical import canonical_inputs

    with torch.no_grad():
        posed = av.posed(canonical_inputs(av.params, av.canonical_timestep), None)
    rgb = 0.5 + 0.28209479177387814 * rows[:, 6:9]
    assert np.allclose(rgb, posed.colors.clamp(0, 1).numpy(), atol=1e-5)
    assert np.allclose(1 / (1 + np.exp(-rows[:, 54])), posed.opacities.numpy(), atol=1e-5)


def test_ga_posing_math_reproduces_sage_posed_surfels(ga_ws):
    out = ga_ws / "export" / "gaussian_avatars"
    names, rows = _read_ply_rows(out / "point_cloud.ply")
    col = {n: i for i, n in enumerate(names)}
    mu_loc = rows[:, [col["x"], col["y"], col["z"]]]
    log_s = rows[:, [col["scale_0"], col["scale_1"], col["scale_2"]]]
    q_loc = rows[:, [col["rot_0"], col["rot_1"], col["rot_2"], col["rot_3"]]]
    b = rows[:, col["binding_0"]].astype(np.int64)
    _, loaded, _ = load_phase1_renderer(ga_ws)
    av = loaded.avatar
    n_model, f_model = _ga_topology_numbers(av)
    on_model = av.surfels.binding.numpy() < f_model
    assert (b < f_model).all()  # every face used exists in sage's mesh too (GA's teeth are not used here)
    faces = av.faces.numpy()[:f_model]
    with np.load(out / "flame_param.npz") as z:
        fp = {k: z[k] for k in z.files}
    params = av.params
    # rest (canonical timestep) and the two rows whose expressions differ most from it
    rest = params.row_of(av.canonical_timestep)
    dist = np.abs(params.expr - params.expr[rest]).sum(1)
    rows_checked = [rest, *np.argsort(-dist)[:2].tolist()]
    assert dist[rows_checked[1]] > 0  # a non-rest expression is among them
    for r in rows_checked:
        # GA's rows of the model drive sage's mesh (sage's appended parts get no offset from GA's file)
        inputs = {
            "shape": torch.as_tensor(fp["shape"][None, : params.n_shape]),
            "expr": torch.as_tensor(fp["expr"][r : r + 1, : params.n_expr]),
            **{k: torch.as_tensor(fp[k][r : r + 1]) for k in ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")},
            "static_offset": torch.as_tensor(fp["static_offset"][:, :n_model]),
            "dynamic_offset": torch.as_tensor(fp["dynamic_offset"][r : r + 1, :n_model]),
        }
        with torch.no_grad():
            verts = av.pose_mesh(inputs).double().numpy()
            ref = av.posed(av.params_inputs(params, r), None)
        assert np.allclose(verts[:n_model], ref.vertices.numpy()[:n_model], atol=1e-5)  # the npz drives the same mesh
        R, T, k = _ga_frames(verts, faces)
        Rb, Tb, kb = R[b], T[b], k[b]
        means = kb[:, None] * np.einsum("nij,nj->ni", Rb, mu_loc) + Tb
        scales = kb[:, None] * np.exp(log_s)
        rot = Rb @ _quat_matrix(q_loc)
        # at rest (a rigid move of the canonical pose) every surfel matches, the rebound ones too;
        # elsewhere the surfels on the model's own faces do
        sel = np.ones_like(on_model) if r == rest else on_model
        assert np.abs(means - ref.means.numpy())[sel].max() < 1e-5, r
        assert np.allclose(scales[sel, :2], ref.scales.numpy()[sel], rtol=1e-4), r
        assert np.allclose(scales[sel, 2], 1e-3 * ref.scales.numpy()[sel].min(1), rtol=1e-4), r
        assert np.abs(rot - _quat_matrix(ref.quats.double().numpy()))[sel].max() < 1e-4, r


def _flame_sized_model():
    """The synthetic head padded to FLAME's 5023 vertices (isolated extra vertices), with sage's teeth
    appended in GaussianAvatars' order and sage's mouth cavity after them: the topology sage builds
    from a real FLAME file."""
    from sage_core.data.synthetic.head import build_head
    from sage_core.data.synthetic.model_files import flame_model_data
    from sage_core.flame import add_mouth_interior, add_teeth
    from sage_core.flame.regions import Regions

    head = build_head(head_rows=48, head_cols=64)
    md = flame_model_data(head)
    extra = 5023 - md.n_vertices
    assert extra > 0

    def pad(a, axis=0):
        reps = np.repeat(np.take(a, [0], axis=axis), extra, axis=axis)
        return np.concatenate([a, reps], axis=axis)

    md.v_template = pad(md.v_template)
    md.shapedirs, md.exprdirs, md.posedirs = pad(md.shapedirs), pad(md.exprdirs), pad(md.posedirs)
    md.lbs_weights = pad(md.lbs_weights)
    md.j_regressor = np.concatenate([md.j_regressor, np.zeros((md.j_regressor.shape[0], extra))], 1)
    md.n_base_vertices = 5023
    md.face_table = "flame"
    md = add_teeth(md)
    masks = {k: np.asarray(v) for k, v in head.masks.items()}
    md = add_mouth_interior(md, Regions(masks, md.faces, md.n_vertices, md.vertex_groups), cavity=True)
    return md


def test_flame_topology_keeps_the_teeth_rows_and_binds_the_mouth_to_gas_teeth():
    """On a model with FLAME's vertex count and GA-ordered teeth, the teeth rows are sage's own and the
    surfels of sage's teeth and cavity are rebound to GA's first upper / lower teeth triangle; since both
    move rigidly with the neck or jaw, GA's posing through that triangle reproduces the posing through
    sage's own face under any expression, jaw and neck pose."""
    from sage_core.export.gaussian_avatars import ga_binding, ga_offset_rows, ga_topology
    from sage_core.flame import FlameModel
    from sage_core.flame.frames import triangle_frames

    md = _flame_sized_model()
    topo = ga_topology(md)
    assert topo.sage_teeth_are_ga and topo.n_model_vertices == 5023 and topo.n_vertices == 5143
    assert topo.n_model_faces == int((md.faces < 5023).all(1).sum()) and topo.n_faces == topo.n_model_faces + 168
    # offsets: the model's rows and sage's teeth rows, never the cavity's
    so = np.random.default_rng(0).normal(size=(md.n_vertices, 3))
    ga = ga_offset_rows(so, 5023, True)
    assert ga.shape == (5143, 3) and np.array_equal(ga, so[:5143])
    assert not ga_offset_rows(so, 5023, False)[5023:].any()
    # one point per face of sage's teeth and cavity, slightly off its face
    model = FlameModel(md).double()
    rng = np.random.default_rng(1)
    ext = np.flatnonzero(~(md.faces < 5023).all(1))
    assert len(ext) > 168  # teeth and cavity faces
    z = lambda n: torch.zeros(1, n, dtype=torch.float64)  # noqa: E731
    shape = torch.as_tensor(rng.normal(size=(1, 20)) * 0.5)
    rest = model(shape=shape, expr=z(10), rotation=z(3), neck_pose=z(3), jaw_pose=z(3), eyes_pose=z(6), translation=z(3))
    v0 = rest.vertices[0]
    R, T, k = triangle_frames(v0, torch.as_tensor(md.faces))
    loc = torch.as_tensor(rng.normal(size=(len(ext), 3)) * 0.3)
    pts = k[ext, None] * (R[ext] @ loc[..., None])[..., 0] + T[ext]
    rows, n_moved = ga_binding(md, topo, ext, v0.numpy(), pts.numpy())
    assert n_moved == len(ext) and set(np.unique(rows)) <= {topo.n_model_faces, topo.n_model_faces + 1}
    assert set(topo.ga_face_ids[rows]) == {topo.n_model_faces, topo.n_model_faces + 84}
    Ra, Ta, ka = triangle_frames(v0, torch.as_tensor(topo.faces))
    b = torch.as_tensor(rows)
    loc_ga = (Ra[b].transpose(-1, -2) @ (pts - Ta[b])[..., None])[..., 0] / ka[b, None]
    pose = dict(shape=shape, expr=torch.as_tensor(rng.normal(size=(1, 10))), rotation=torch.tensor([[0.1, -0.2, 0.05]], dtype=torch.float64),
                neck_pose=torch.tensor([[0.2, 0.3, -0.1]], dtype=torch.float64), jaw_pose=torch.tensor([[0.35, 0.0, 0.02]], dtype=torch.float64),
                eyes_pose=z(6), translation=torch.tensor([[0.01, 0.02, -0.03]], dtype=torch.float64))  # fmt: skip
    v1 = model(**pose).vertices[0]
    R1, T1, k1 = triangle_frames(v1, torch.as_tensor(md.faces))
    want = k1[ext, None] * (R1[ext] @ loc[..., None])[..., 0] + T1[ext]
    Ra1, Ta1, ka1 = triangle_frames(v1, torch.as_tensor(topo.faces))
    got = ka1[b, None] * (Ra1[b] @ loc_ga[..., None])[..., 0] + Ta1[b]
    assert (want - pts).norm(dim=1).max() > 1e-3  # the pose really moved them
    assert (got - want).norm(dim=1).max() < 1e-9
