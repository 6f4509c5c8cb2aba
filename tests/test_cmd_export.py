"""`sage export`: viewer PLY (round trip, header order, render equivalence), meshes, bundle."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
import trimesh

from helpers import invoke, load_phase1_renderer

# A PLY stores float32 positions, log scales, logit opacities, normalised quaternions and SH DC;
# decoding them and rasterizing again reproduces the avatar's own render up to float32 rounding
# of those conversions and the rows dropped for opacity < 1/255.
RENDER_TOL = 1e-4


@pytest.fixture(scope="module")
def base_ws(cmd_avatar_ws):
    return cmd_avatar_ws


@pytest.fixture
def ws(base_ws, tmp_path):
    dst = tmp_path / "ws"
    shutil.copytree(base_ws, dst)
    return dst


def _header(path):
    raw = path.read_bytes()
    head = raw[: raw.index(b"end_header")].decode("ascii").splitlines()
    return [ln.split()[-1] for ln in head if ln.startswith("property")], [ln for ln in head if ln.startswith("comment")]


def test_canonical_ply_round_trip_and_header(ws):
    from sage_core.export.avatar_ply import sh_dc_to_rgb
    from sage_core.export.ply import MIN_OPACITY, property_names, read_ply
    from sage_core.flame.canonical import canonical_inputs

    res = invoke(["export", ws, "--ply", "--orientation", "flame", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    path = ws / "export" / "ply" / "canonical-flame.ply"  # the orientation is in the name
    props, comments = _header(path)
    assert props == property_names(0)  # INRIA order, SH degree 0, no binding_0
    assert any("Vertical Axis: y" in c for c in comments)
    assert "rows dropped" in res.output
    data, loaded, renderer = load_phase1_renderer(ws)
    av = loaded.avatar
    posed = renderer.posed(canonical_inputs(av.params, av.canonical_timestep), None)
    keep = (posed.opacities >= MIN_OPACITY).numpy()
    ply = read_ply(path)
    n = int(keep.sum())
    assert ply["means"].shape == (n, 3)
    entry = json.loads((ws / "export" / "results.json").read_text())["ply:canonical-flame"]
    assert entry["orientation"] == "flame" and entry["avatar_stage"] == "phase1" and entry["files"] == ["ply/canonical-flame.ply"]
    assert entry["rows"] == n and entry["rows_dropped"] == len(keep) - n
    assert np.allclose(ply["means"], posed.means.numpy()[keep], atol=1e-6)
    q_ref = posed.quats.numpy()[keep]
    q_ref = q_ref / np.linalg.norm(q_ref, axis=1, keepdims=True)
    assert np.allclose(ply["quats"], q_ref, atol=1e-5)
    assert np.allclose(ply["scales"][:, :2], posed.scales.numpy()[keep], rtol=1e-5)
    assert np.allclose(ply["scales"][:, 2], 1e-3 * posed.scales.numpy()[keep].min(1), rtol=1e-4)
    assert np.allclose(ply["opacities"], posed.opacities.numpy()[keep], atol=1e-5)
    rgb = sh_dc_to_rgb(torch.as_tensor(ply["sh_dc"])).numpy()
    assert np.allclose(rgb, posed.colors.clamp(0, 1).numpy()[keep], atol=1e-5)
    # canonical pose: zero global rotation and translation -> the canonical surfel centres
    with torch.no_grad():
        canon = av.canonical_state(with_sdf=False)
    assert np.allclose(posed.means.numpy(), canon.means.numpy(), atol=1e-5)


def test_ply_rendered_back_matches_the_avatar_render(ws):
    from sage_core.export.avatar_ply import ply_render_inputs
    from sage_core.export.ply import read_ply
    from sage_core.render import RenderCamera, rasterize_surfels

    data, loaded, renderer = load_phase1_renderer(ws)
    fr = data.val[0]
    res = invoke(["export", ws, "--ply", "--frame", fr.timestep, "--color-camera", fr.camera_index, "--up", "y", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    ply = read_ply(ws / "export" / "ply" / f"frame_{fr.timestep:05d}-flame.ply")
    cam = RenderCamera.from_camera(fr.camera)
    s = loaded.render
    with torch.no_grad():
        img = rasterize_surfels(*ply_render_inputs(ply), cam, s.background, near=s.near, far=s.far, return_statistics=False).color
        ref, _ = loaded.avatar.render(cam, loaded.avatar.frame_inputs(fr.timestep), s.background, near=s.near, far=s.far,
                                      return_statistics=False)  # fmt: skip
    err = (img - ref.color).abs().max().item()
    assert err < RENDER_TOL, err
    assert float((ref.color < 0.99).float().mean()) > 0.02  # not an empty image
    # another pose gives another image (the PLY really is posed at that timestep)
    other = data.test[0].timestep
    with torch.no_grad():
        ref2, _ = loaded.avatar.render(cam, loaded.avatar.frame_inputs(other), s.background, near=s.near, far=s.far, return_statistics=False)
    assert (img - ref2.color).abs().max().item() > 10 * RENDER_TOL


def test_export_meshes(ws):
    from sage_core.flame.canonical import canonical_inputs

    res = invoke(["export", ws, "--mesh", "--mc-resolution", "32", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    out = ws / "export" / "mesh"
    data, loaded, _ = load_phase1_renderer(ws)
    av = loaded.avatar
    with torch.no_grad():
        verts = av.pose_mesh(canonical_inputs(av.params, av.canonical_timestep)).numpy()
    for ext in ("ply", "obj"):
        m = trimesh.load(out / f"flame_canonical.{ext}", process=False)
        assert np.array_equal(np.asarray(m.faces), av.faces.numpy())
        assert np.allclose(np.asarray(m.vertices), verts, atol=1e-5)
        sdf_m = trimesh.load(out / f"sdf_mesh.{ext}", process=False)
        assert len(sdf_m.faces) > 100
    sdf_m = trimesh.load(out / "sdf_mesh.ply", process=False)
    v = torch.as_tensor(np.asarray(sdf_m.vertices), dtype=torch.float32)
    with torch.no_grad():
        d = av.sdf.sdf(v).abs()
    cell = float((av.sdf.bbox_max - av.sdf.bbox_min).max()) / 31
    assert float(d.mean()) < 0.5 * cell  # the vertices lie on the zero level set
    # the PLY of an earlier export is kept beside the meshes
    res = invoke(["export", ws, "--ply", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert (out / "sdf_mesh.obj").is_file() and (ws / "export" / "ply" / "canonical.ply").is_file()
    res = invoke(["export", ws, "--ply", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0 and "skipping" in res.output


def test_bundle_loads_without_the_workspace_and_renders_the_same(ws, tmp_path, tiny_capture):
    from sage_core.errors import InputError
    from sage_core.export.bundle import FRAME_CONVENTION, load_bundle
    from sage_core.stages.avatars import AvatarRenderer
    from sage_core.workspace import file_sha256

    res = invoke(["export", ws, "--bundle", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert "--flame-model" in res.output  # the panel says what loading it needs
    data, loaded, renderer = load_phase1_renderer(ws)
    fr = data.val[0]
    inputs = loaded.avatar.frame_inputs(fr.timestep)
    ref = renderer.render(fr.camera, inputs)
    moved = tmp_path / "elsewhere" / "bundle"
    shutil.copytree(ws / "export" / "bundle", moved)
    res = invoke(["export", ws, "--bundle", "--include-flame-model", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    with_model = tmp_path / "elsewhere" / "with_model"
    shutil.copytree(ws / "export" / "bundle", with_model)
    shutil.rmtree(ws)  # nothing of the workspace is left
    meta = json.loads((moved / "bundle.json").read_text())
    assert meta["format"] == 3 and meta["source"]["workspace"] == "../.."  # no absolute path of this machine
    assert meta["surfels"]["frame_convention"] == FRAME_CONVENTION == "surfel-flat [a0,-a2,a1]"
    assert meta["surfels"]["dimensions"] == 2 and meta["up_axis"] == "y"
    assert meta["flame"]["n_vertices"] == loaded.avatar.model_data.v_template.shape[0]
    assert meta["flame"]["n_faces"] == loaded.avatar.faces.shape[0]
    # the model is referenced by its file name and SHA-256, not carried
    model = meta["flame"]["model"]
    assert model["included"] is False and model["file"] == tiny_capture.model_path.name
    assert model["file_sha256"] == file_sha256(tiny_capture.model_path) and model["mouth_interior"]["cavity"] is True
    arrays = meta["arrays"]["avatar.safetensors"]
    assert not any(k.startswith("flame/") for k in arrays) and "state/canonical_vertices" in arrays
    assert any(k.startswith("flame/") for k in json.loads((with_model / "bundle.json").read_text())["arrays"]["avatar.safetensors"])
    size = sum(f.stat().st_size for f in moved.iterdir())
    assert size < 0.8 * sum(f.stat().st_size for f in with_model.iterdir())
    assert [e["timestep"] for e in meta["timestep_map"]] == [int(t) for t in loaded.avatar.params.timesteps]
    with np.load(moved / "flame_param.npz") as z:
        assert z["shape"].ndim == 1 and z["expr"].shape[0] == len(meta["timestep_map"])
    with pytest.raises(InputError, match="--flame-model"):
        load_bundle(moved)
    other = tmp_path / "other.npz"
    other.write_bytes(tiny_capture.model_path.read_bytes() + b"\0")
    with pytest.raises(InputError, match="SHA-256"):  # refused by its hash, before it is read
        load_bundle(moved, flame_model=other)
    for folder, model_file in ((moved, tiny_capture.model_path), (with_model, None)):
        b = load_bundle(folder, flame_model=model_file)
        assert b.reference_camera is not None and b.reference_camera.index == fr.camera_index
        img = AvatarRenderer(b.avatar, b.render).render(b.reference_camera, b.avatar.frame_inputs(fr.timestep))
        assert torch.equal(img, ref)
    # a format-2 bundle (the model inside, no model section) still loads
    meta2 = json.loads((with_model / "bundle.json").read_text())
    meta2["format"] = 2
    del meta2["flame"]["model"]
    (with_model / "bundle.json").write_text(json.dumps(meta2))
    assert load_bundle(with_model).avatar.surfels.n == loaded.avatar.surfels.n
    # a tampered face table is refused
    meta["flame"]["faces_sha256"] = "0" * 64
    (moved / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="faces_sha256"):
        load_bundle(moved, flame_model=tiny_capture.model_path)


def test_bundle_drives_an_orbit_without_the_workspace(ws, tmp_path, tiny_capture):
    res = invoke(["export", ws, "--bundle", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    moved = tmp_path / "b"
    shutil.copytree(ws / "export" / "bundle", moved)
    shutil.rmtree(ws)
    out = tmp_path / "orbit"
    res = invoke(["reenact", "--bundle", moved, "--flame-seq", tiny_capture, "--orbit", "--max-frames", "3",
                  "--out", out, "--device", "cpu", "--quiet"])  # fmt: skip
    assert res.exit_code == 2 and "--flame-model" in res.output  # the bundle names the model it needs
    res = invoke(["reenact", "--bundle", moved, "--flame-model", tiny_capture.model_path, "--flame-seq", tiny_capture,
                  "--orbit", "--max-frames", "3", "--out", out, "--device", "cpu", "--quiet"])  # fmt: skip
    assert res.exit_code == 0, res.output
    frames = sorted((out / "frames").glob("*.png"))
    assert len(frames) == 3 and (out / "video.mp4").stat().st_size > 0
    from sage_core.data.imageio import read_image

    a, b = read_image(frames[0]), read_image(frames[1])
    assert np.abs(a - b).max() > 0.1  # the camera moved
    rec = json.loads((out / "reenact.json").read_text())
    assert rec["report"]["n_frames"] == 3 and "orbit" in rec["cameras"]
    # its reference camera is the bundle's, not a camera of "this capture"
    res = invoke(["reenact", "--bundle", moved, "--flame-model", tiny_capture.model_path, "--flame-seq", tiny_capture,
                  "--max-frames", "1", "--no-video", "--out", tmp_path / "ref", "--device", "cpu", "--quiet"])  # fmt: skip
    assert res.exit_code == 0, res.output
    cams = json.loads((tmp_path / "ref" / "reenact.json").read_text())["cameras"]
    assert cams.startswith("the bundle's reference camera") and "this capture" not in res.output


def test_export_sequence_writes_one_ply_per_frame(ws, tiny_capture):
    from sage_core.export.ply import read_ply

    res = invoke(["export", ws, "--ply", "--flame-seq", tiny_capture, "--max-frames", "3", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    folder = ws / "export" / "ply" / f"seq_{tiny_capture.name}"
    files = sorted(folder.glob("*.ply"))
    assert [f.name for f in files] == ["00000.ply", "00001.ply", "00002.ply"]
    a, b = read_ply(files[0]), read_ply(files[2])
    assert a["means"].shape[1] == 3 and not np.allclose(a["means"][:10], b["means"][:10])
    entry = json.loads((ws / "export" / "results.json").read_text())[f"ply:seq_{tiny_capture.name}"]
    assert entry["frames"] == 3 and entry["orientation"] == "viewer" and entry["avatar_stage"] == "phase1"
    # a .splat of the same motion joins the folder; a shorter cut of it replaces every format there
    res = invoke(["export", ws, "--splat", "--flame-seq", tiny_capture, "--max-frames", "3", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert len(list(folder.glob("*.splat"))) == 3 and len(list(folder.glob("*.ply"))) == 3
    res = invoke(["export", ws, "--ply", "--flame-seq", tiny_capture, "--max-frames", "2", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    assert sorted(f.name for f in folder.iterdir()) == ["00000.ply", "00001.ply"]  # no stale .splat of the 3-frame cut
    doc = json.loads((ws / "export" / "results.json").read_text())
    assert f"splat:seq_{tiny_capture.name}" not in doc and doc[f"ply:seq_{tiny_capture.name}"]["frames"] == 2
    res = invoke(["export", ws, "--frame", 999, "--quiet"])
    assert res.exit_code == 2 and "999" in res.output


def test_a_later_export_keeps_every_file_of_the_web_player(ws):
    """--web then --mesh: the web player's three files survive, the record lists them, and a file
    deleted afterwards makes the stage incomplete and the web player redone."""
    from sage_core.workspace import Workspace

    res = invoke(["export", ws, "--web", "--max-frames", "2", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    res = invoke(["export", ws, "--mesh", "--mc-resolution", "16", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    web = ws / "export" / "web"
    assert sorted(p.name for p in web.iterdir()) == ["avatar.js", "index.html", "player.js"]
    doc = json.loads((ws / "export" / "results.json").read_text())
    assert doc["web"]["files"] == ["web/index.html", "web/player.js", "web/avatar.js"]
    m = json.loads((ws / "export" / "manifest.json").read_text())
    assert {"web/avatar.js", "web/player.js", "mesh/sdf_mesh.ply"} <= set(m["files"])
    assert all(not str(v).startswith("/") for v in m["outputs"].values())  # outputs are workspace-relative
    (web / "avatar.js").unlink()
    st = Workspace(ws).status("export")
    assert st.status == "incomplete" and "avatar.js" in st.reason
    res = invoke(["export", ws, "--web", "--max-frames", "2", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0 and "skipping" not in res.output, res.output
    assert (web / "avatar.js").is_file() and (ws / "export" / "mesh" / "sdf_mesh.obj").is_file()
    assert Workspace(ws).status("export").status == "complete"


@pytest.mark.parametrize("args, needle", [
    (["--web", "--frame", "0", "--max-frames", "2"], "--max-frames"),
    (["--ply", "--max-frames", "2"], "--max-frames"),
    (["--bundle", "--frame", "0"], "--frame"),
    (["--mesh", "--flame-seq", "."], "--flame-seq"),
])  # fmt: skip
def test_options_that_would_be_ignored_are_refused(ws, args, needle):
    res = invoke(["export", ws, *args, "--device", "cpu", "--quiet"])
    assert res.exit_code == 3 and needle in res.output, res.output
    assert not (ws / "export").exists()


def test_web_at_a_frame_plays_that_timestep_and_the_preset_is_the_workspaces(ws):
    from sage_core.stages.export import workspace_preset

    assert workspace_preset(ws) == "tiny"  # the avatar workspace was built with the tiny preset
    res = invoke(["export", ws, "--web", "--mesh", "--frame", "0", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    doc = json.loads((ws / "export" / "results.json").read_text())
    assert doc["web"]["frames"] == 1 and doc["web"]["sequence"] == "timestep 0"
    assert doc["mesh:sdf"]["mc_resolution"] == 128  # the tiny preset's, not the default 256
    js = (ws / "export" / "web" / "avatar.js").read_text()
    assert '"timesteps":[0]' in js
