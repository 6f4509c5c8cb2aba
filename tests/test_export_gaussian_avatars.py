"""`sage export --gaussian-avatars`: GA's file layout, and GA's posing math (docs/formats.md §6),
re-implemented here in numpy, reproduces sage's own posed surfels at several frames."""

from __future__ import annotations

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


def test_point_cloud_and_flame_param_layout(ga_ws):
    out = ga_ws / "export" / "gaussian_avatars"
    names, rows = _read_ply_rows(out / "point_cloud.ply")
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "binding_0"])  # fmt: skip
    assert names == expected
    _, loaded, _ = load_phase1_renderer(ga_ws)
    av = loaded.avatar
    assert rows.shape[0] == av.surfels.n
    binding = rows[:, -1]
    assert np.array_equal(binding, np.round(binding)) and np.array_equal(binding.astype(np.int64), av.surfels.binding.numpy())
    assert not rows[:, 9:54].any()  # f_rest zero (view-independent colours)
    with np.load(out / "flame_param.npz") as z:
        arrays = {k: z[k] for k in z.files}
    V = av.model_data.v_template.shape[0]
    T = av.params.n_timesteps
    want = {"shape": (300,), "expr": (T, 100), "rotation": (T, 3), "neck_pose": (T, 3), "jaw_pose": (T, 3),
            "eyes_pose": (T, 6), "translation": (T, 3), "static_offset": (1, V, 3), "dynamic_offset": (T, V, 3)}  # fmt: skip
    assert {k: v.shape for k, v in arrays.items()} == want
    assert all(v.dtype == np.float32 for v in arrays.values())
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
    faces = av.faces.numpy()
    with np.load(out / "flame_param.npz") as z:
        fp = {k: z[k] for k in z.files}
    params = av.params
    # rest (canonical timestep) and the two rows whose expressions differ most from it
    rest = params.row_of(av.canonical_timestep)
    dist = np.abs(params.expr - params.expr[rest]).sum(1)
    rows_checked = [rest, *np.argsort(-dist)[:2].tolist()]
    assert dist[rows_checked[1]] > 0  # a non-rest expression is among them
    for r in rows_checked:
        inputs = {
            "shape": torch.as_tensor(fp["shape"][None, : params.n_shape]),
            "expr": torch.as_tensor(fp["expr"][r : r + 1, : params.n_expr]),
            **{k: torch.as_tensor(fp[k][r : r + 1]) for k in ("rotation", "neck_pose", "jaw_pose", "eyes_pose", "translation")},
            "static_offset": torch.as_tensor(fp["static_offset"]),
            "dynamic_offset": torch.as_tensor(fp["dynamic_offset"][r : r + 1]),
        }
        with torch.no_grad():
            verts = av.pose_mesh(inputs).double().numpy()
            ref = av.posed(av.params_inputs(params, r), None)
        assert np.allclose(verts, ref.vertices.numpy(), atol=1e-5)  # the npz drives the same mesh
        R, T, k = _ga_frames(verts, faces)
        Rb, Tb, kb = R[b], T[b], k[b]
        means = kb[:, None] * np.einsum("nij,nj->ni", Rb, mu_loc) + Tb
        scales = kb[:, None] * np.exp(log_s)
        rot = Rb @ _quat_matrix(q_loc)
        assert np.abs(means - ref.means.numpy()).max() < 1e-5, r
        assert np.allclose(scales[:, :2], ref.scales.numpy(), rtol=1e-4), r
        assert np.allclose(scales[:, 2], 1e-3 * ref.scales.numpy().min(1), rtol=1e-4), r
        assert np.abs(rot - _quat_matrix(ref.quats.double().numpy())).max() < 1e-4, r
