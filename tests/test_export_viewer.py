"""Viewer exports: orientation, SH padding, ``.splat`` and PlayCanvas' compressed PLY, each read back
by an independent decoder (and by @playcanvas/splat-transform where node and the package exist)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sage_core.export.compressed_ply import decode_compressed_ply, encode_compressed_ply, is_compressed_ply
from sage_core.export.orientation import orient, orientation_matrix, oriented_up_axis
from sage_core.export.ply import SH_C0, decode_ply, encode_ply, encode_splat, pad_sh_rest
from sage_core.geometry import quat_to_matrix
from sage_core.geometry.sh import eval_sh_colors


def _gaussians(n: int = 700, k: int = 15, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "means": rng.normal(size=(n, 3)) * 0.1,
        "quats": rng.normal(size=(n, 4)),
        "scales": rng.uniform(0.001, 0.02, (n, 3)),
        "opacities": rng.uniform(0.05, 0.99, n),
        "sh_dc": rng.normal(size=(n, 3)),
        "sh_rest": rng.normal(size=(n, k, 3)) * 0.3 if k else None,
    }


def _unit(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _rot_err(a: np.ndarray, b: np.ndarray) -> float:
    """Largest 1 − |⟨a, b⟩| over rows of unit-normalised quaternions (q and −q are one rotation)."""
    return float((1.0 - np.abs((_unit(a) * _unit(b)).sum(1))).max())


def _match_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Index i of b's rows for every row of a (nearest position); both (N, 3)."""
    d = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return d.argmin(1)


# -------------------------------------------------------------------------------- orientation


def test_viewer_orientation_is_a_rotation_applied_to_positions_rotations_and_sh():
    g = _gaussians(n=40, k=15)
    m, q, rest = orient(g["means"], g["quats"], g["sh_rest"], "viewer")
    S = orientation_matrix("viewer")
    assert np.allclose(S, np.diag([1.0, -1.0, -1.0])) and np.isclose(np.linalg.det(S), 1.0)
    assert np.allclose(m, g["means"] @ S.T)
    R0 = quat_to_matrix(torch.as_tensor(g["quats"])).numpy()
    R1 = quat_to_matrix(torch.as_tensor(q)).numpy()
    assert np.allclose(R1, S[None] @ R0, atol=1e-12)
    # the colour seen along a world direction d before equals the colour along S·d after
    rng = np.random.default_rng(1)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    dc = torch.as_tensor(g["sh_dc"])[:, None]
    before = eval_sh_colors(torch.cat([dc, torch.as_tensor(g["sh_rest"])], 1), torch.as_tensor(d), 3)
    after = eval_sh_colors(torch.cat([dc, torch.as_tensor(rest)], 1), torch.as_tensor(d @ S.T), 3)
    assert torch.allclose(before, after, atol=1e-10)
    assert not np.allclose(rest, g["sh_rest"])  # some coefficients did change sign
    # the FLAME orientation is the identity
    m2, q2, r2 = orient(g["means"], g["quats"], g["sh_rest"], "flame")
    assert np.array_equal(m2, g["means"]) and np.array_equal(q2, g["quats"]) and np.array_equal(r2, g["sh_rest"])
    assert oriented_up_axis("y", "viewer") == "-y" and oriented_up_axis("y", "flame") == "y"
    assert oriented_up_axis("-z", "viewer") == "z" and oriented_up_axis("x", "viewer") == "x"
    with pytest.raises(ValueError, match="orientation"):
        orient(g["means"], g["quats"], None, "sideways")


def test_sh_padding_to_degree_three_keeps_colours():
    g = _gaussians(n=30, k=0)
    rest = pad_sh_rest(None, 30, 3)
    assert rest.shape == (30, 15, 3) and not rest.any()
    data, _ = encode_ply(g["means"], g["quats"], g["scales"], g["opacities"], g["sh_dc"], rest)
    head = data[: data.index(b"end_header")].decode()
    assert head.count("property float f_rest_") == 45
    back = decode_ply(data)
    assert back["sh_rest"].shape == (30, 15, 3) and not back["sh_rest"].any()
    with pytest.raises(ValueError, match="down to degree"):
        pad_sh_rest(np.zeros((3, 15, 3)), 3, 1)


# -------------------------------------------------------------------------------- .splat


def test_splat_read_back_by_an_independent_reader():
    g = _gaussians(n=300, k=0)
    data, dropped = encode_splat(g["means"], g["quats"], g["scales"], g["opacities"], g["sh_dc"])
    assert dropped == 0 and len(data) == 32 * 300
    raw = np.frombuffer(data, dtype=np.uint8).reshape(300, 32)
    pos = raw[:, :12].copy().view("<f4").astype(np.float64)
    scl = raw[:, 12:24].copy().view("<f4").astype(np.float64)
    rgba = raw[:, 24:28].astype(np.float64) / 255.0
    rot = (raw[:, 28:32].astype(np.float64) - 128.0) / 128.0
    i = _match_rows(pos, g["means"])
    assert np.allclose(pos, g["means"][i], atol=1e-6) and len(set(i.tolist())) == 300
    assert np.allclose(scl, g["scales"][i], rtol=1e-6)
    assert np.allclose(rgba[:, :3], np.clip(0.5 + SH_C0 * g["sh_dc"][i], 0, 1), atol=0.5 / 255 + 1e-9)
    assert np.allclose(rgba[:, 3], g["opacities"][i], atol=0.5 / 255 + 1e-9)
    assert _rot_err(rot, g["quats"][i]) < 5e-4


# -------------------------------------------------------------------------------- compressed PLY


def _decode_compressed_independently(data: bytes) -> dict[str, np.ndarray]:
    """A second reader written from the layout description alone (bit by bit per row)."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode().splitlines()
    counts = {ln.split()[1]: int(ln.split()[2]) for ln in head if ln.startswith("element")}
    n_chunk, n = counts["chunk"], counts["vertex"]
    chunks = np.frombuffer(data, "<f4", n_chunk * 18, end).reshape(n_chunk, 18).astype(np.float64)
    words = np.frombuffer(data, "<u4", n * 4, end + n_chunk * 72).reshape(n, 4)
    out = {k: [] for k in ("means", "quats", "log_scales", "rgb", "alpha")}
    for r in range(n):
        c = chunks[r // 256]
        pos_w, rot_w, scl_w, col_w = (int(w) for w in words[r])

        def three(word: int, lo: np.ndarray, hi: np.ndarray) -> list[float]:
            parts = [(word >> 21) & 2047, (word >> 11) & 1023, word & 2047]
            return [lo[j] + (hi[j] - lo[j]) * parts[j] / (2047.0, 1023.0, 2047.0)[j] for j in range(3)]

        out["means"].append(three(pos_w, c[0:3], c[3:6]))
        out["log_scales"].append(three(scl_w, c[6:9], c[9:12]))
        small = [((rot_w >> s) & 1023) / 1023.0 * 2 * np.sqrt(0.5) - np.sqrt(0.5) for s in (20, 10, 0)]
        big = np.sqrt(max(0.0, 1.0 - sum(v * v for v in small)))
        q = small[:]
        q.insert(rot_w >> 30, big)
        out["quats"].append(q)
        out["rgb"].append([c[12 + j] + (c[15 + j] - c[12 + j]) * ((col_w >> (24 - 8 * j)) & 255) / 255.0 for j in range(3)])
        out["alpha"].append((col_w & 255) / 255.0)
    res = {k: np.asarray(v) for k, v in out.items()}
    if "sh" in counts:
        k3 = sum(1 for ln in head if ln.startswith("property uchar f_rest_"))
        b = np.frombuffer(data, np.uint8, n * k3, end + n_chunk * 72 + n * 16).reshape(n, k3).astype(np.float64)
        res["sh_rest"] = ((b + 0.5) / 256.0 - 0.5) * 8.0
    return res


def _check_compressed_against(dec: dict[str, np.ndarray], g: dict, order: np.ndarray, span_pos: float, k: int) -> None:
    assert np.allclose(dec["means"], g["means"][order], atol=span_pos / 1023 * 0.51 + 1e-6)
    assert _rot_err(dec["quats"], g["quats"][order]) < 1e-5
    ls = np.log(g["scales"][order])
    assert np.allclose(np.log(dec["scales"]) if "scales" in dec else dec["log_scales"], ls, atol=(ls.max() - ls.min()) / 1023 * 0.51 + 1e-5)
    if k:
        rest = g["sh_rest"][order].transpose(0, 2, 1).reshape(len(order), -1) if "sh_rest" in dec and dec["sh_rest"].ndim == 2 else g["sh_rest"][order]
        assert np.allclose(dec["sh_rest"], np.clip(rest, -4, 4), atol=8 / 256 + 1e-6)


def test_compressed_ply_layout_and_read_back():
    g = _gaussians(n=700, k=15)
    data, dropped = encode_compressed_ply(**g, comments=["test"])
    assert dropped == 0 and is_compressed_ply(data)
    head = data[: data.index(b"end_header")].decode()
    assert "element chunk 3" in head and "element vertex 700" in head and "element sh 700" in head
    assert "property uint packed_position" in head and "property uchar f_rest_44" in head
    assert len(data) - (data.index(b"end_header\n") + 11) == 3 * 72 + 700 * 16 + 700 * 45
    ind = _decode_compressed_independently(data)
    order = _match_rows(ind["means"], g["means"])
    assert len(set(order.tolist())) == 700  # every splat once
    span = float((g["means"].max(0) - g["means"].min(0)).max())
    _check_compressed_against(ind, g, order, span, 15)
    assert np.allclose(ind["rgb"], 0.5 + SH_C0 * g["sh_dc"][order], atol=(np.abs(g["sh_dc"]).max() * 2 * SH_C0) / 255 * 0.51 + 1e-6)
    assert np.allclose(ind["alpha"], g["opacities"][order], atol=0.51 / 255)
    # the module's own decoder agrees with the independent one
    dec = decode_compressed_ply(data)
    assert np.allclose(dec["means"], ind["means"], atol=1e-5) and np.allclose(dec["opacities"], ind["alpha"], atol=1e-6)
    assert np.allclose(dec["sh_dc"], (ind["rgb"] - 0.5) / SH_C0, atol=1e-4)
    assert np.allclose(dec["sh_rest"].transpose(0, 2, 1).reshape(700, 45), ind["sh_rest"], atol=1e-5)
    # degree 0: no sh element; a low-opacity row is dropped
    g0 = _gaussians(n=10, k=0)
    g0["opacities"][3] = 1e-4
    d0, dropped0 = encode_compressed_ply(**g0)
    assert dropped0 == 1 and b"element sh" not in d0 and decode_compressed_ply(d0)["means"].shape == (9, 3)


def test_splat_transform_reads_the_compressed_ply_and_splat(tmp_path):
    from chromium import splat_transform

    g = _gaussians(n=600, k=15)
    data, _ = encode_compressed_ply(**g)
    src = tmp_path / "a.compressed.ply"
    src.write_bytes(data)
    splat_transform(src, tmp_path / "a.ply")
    back = decode_ply((tmp_path / "a.ply").read_bytes())
    ours = decode_compressed_ply(data)
    assert back["means"].shape == (600, 3)
    order = _match_rows(back["means"], ours["means"])
    assert np.allclose(back["means"], ours["means"][order], atol=1e-5)
    assert _rot_err(back["quats"], ours["quats"][order]) < 1e-6
    assert np.allclose(back["scales"], ours["scales"][order], rtol=1e-4)
    assert np.allclose(back["opacities"], ours["opacities"][order], atol=1e-4)
    assert np.allclose(back["sh_dc"], ours["sh_dc"][order], atol=1e-3)
    assert np.allclose(back["sh_rest"], ours["sh_rest"][order], atol=1e-4)
    # .splat
    s, _ = encode_splat(g["means"], g["quats"], g["scales"], g["opacities"], g["sh_dc"])
    (tmp_path / "b.splat").write_bytes(s)
    splat_transform(tmp_path / "b.splat", tmp_path / "b.ply")
    back = decode_ply((tmp_path / "b.ply").read_bytes())
    order = _match_rows(back["means"], g["means"])
    assert np.allclose(back["means"], g["means"][order], atol=1e-6)
    assert np.allclose(back["scales"], g["scales"][order], rtol=1e-5)
    assert np.allclose(back["opacities"], g["opacities"][order], atol=1 / 255)


# -------------------------------------------------------------------------------- sage export


@pytest.fixture(scope="module")
def viewer_ws(cmd_avatar_ws, tmp_path_factory):
    import shutil

    ws = tmp_path_factory.mktemp("viewer") / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    return ws


def test_export_viewer_files_default_to_the_viewer_orientation(viewer_ws):
    from helpers import invoke, load_phase1_renderer
    from sage_core.export.ply import MIN_OPACITY, read_ply
    from sage_core.flame.canonical import canonical_inputs

    res = invoke(["export", viewer_ws, "--ply", "--splat", "--compressed-ply", "--sh-degree", "3", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    out = viewer_ws / "export" / "ply"
    raw = (out / "canonical.ply").read_bytes()
    head = raw[: raw.index(b"end_header")].decode()
    assert "Vertical Axis: -y" in head and head.count("property float f_rest_") == 45 and "binding" not in head
    _, loaded, renderer = load_phase1_renderer(viewer_ws)
    av = loaded.avatar
    posed = renderer.posed(canonical_inputs(av.params, av.canonical_timestep), None)
    keep = (posed.opacities >= MIN_OPACITY).numpy()
    ply = read_ply(out / "canonical.ply")
    flip = np.array([1.0, -1.0, -1.0])
    assert np.allclose(ply["means"], posed.means.numpy()[keep] * flip, atol=1e-6)
    R = quat_to_matrix(torch.as_tensor(ply["quats"])).numpy()
    R_ref = quat_to_matrix(posed.quats[torch.as_tensor(keep)]).numpy()
    assert np.abs(R - np.diag(flip)[None] @ R_ref).max() < 1e-5
    assert not ply["sh_rest"].any()
    # .splat and compressed PLY hold the same Gaussians
    splat = np.frombuffer((out / "canonical.splat").read_bytes(), np.uint8).reshape(-1, 32)
    pos = splat[:, :12].copy().view("<f4")
    assert pos.shape[0] == ply["means"].shape[0]
    i = _match_rows(pos.astype(np.float64), ply["means"].astype(np.float64))
    assert np.allclose(pos, ply["means"][i], atol=1e-6)
    comp = decode_compressed_ply((out / "canonical.compressed.ply").read_bytes())
    span = float((ply["means"].max(0) - ply["means"].min(0)).max())
    j = _match_rows(comp["means"], ply["means"])
    assert np.abs(comp["means"] - ply["means"][j]).max() < span / 1023
    assert comp["sh_rest"].shape[1] == 0  # zero padding is left out of the compressed file (bytes cannot hold 0)
    # the FLAME orientation keeps sage's world; a wrong --up is refused
    res = invoke(["export", viewer_ws, "--ply", "--up", "y", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert np.allclose(read_ply(out / "canonical-flame.ply")["means"], posed.means.numpy()[keep], atol=1e-6)
    assert np.allclose(read_ply(out / "canonical.ply")["means"], posed.means.numpy()[keep] * flip, atol=1e-6)  # kept beside it
    res = invoke(["export", viewer_ws, "--ply", "--up", "z", "--quiet"])
    assert res.exit_code != 0 and "--up" in res.output
