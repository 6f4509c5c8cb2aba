"""`sage export --web`: the page's own WebGL2 renderer, in headless Chromium, against `sage reenact`.

A screenshot of a given frame from the reference camera is compared with `sage reenact`'s render of
the same frame and camera (PSNR), and two frames whose expressions differ give different pictures
where the reference renders differ. Skips where Chromium is absent.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from chromium import Chromium, require_chromium
from helpers import invoke

# Measured on the tiny test avatar (128x186, camera 8, headless Chromium with SwiftShader): 50.30 dB
# at frame 0 and 53.23 dB at frame 4 (38.65 and 38.91 dB with colours baked once and ±3σ quads; 42.09
# dB with each frame's colours). The page evaluates the rasterizer's per-pixel ray-surfel
# intersection and low-pass bound over the same tile pixels; what remains is the 8-bit colours and
# opacities, the rasterizer's early termination and float32 on the GPU.
MIN_PSNR = 45.0


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


@pytest.fixture(scope="module")
def web_ws(cmd_avatar_ws, tiny_capture, tmp_path_factory):
    ws = tmp_path_factory.mktemp("web") / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    res = invoke(["export", ws, "--web", "--flame-seq", tiny_capture, "--color-camera", "8", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    return ws


def test_web_folder_is_self_contained(web_ws):
    out = web_ws / "export" / "web"
    assert sorted(p.name for p in out.iterdir()) == ["avatar.js", "index.html", "player.js"]
    html = (out / "index.html").read_text()
    for name in ("index.html", "player.js"):
        text = (out / name).read_text()
        assert "http://" not in text and "https://" not in text and "//cdn" not in text  # nothing from the network
    assert '<script src="avatar.js">' in html and '<script src="player.js">' in html
    text = (out / "avatar.js").read_text()
    doc = json.loads(text[text.index("{") : text.rindex("}") + 1])
    assert doc["n_frames"] >= 3 and doc["n_surfels"] > 100 and doc["camera"]["width"] > 0
    # per frame only the mesh: the data grows by 6 bytes per vertex and frame
    import base64

    blob = base64.b64decode(doc["data"])
    N, V, T = doc["n_surfels"], doc["n_vertices"], doc["n_frames"]
    assert doc["frame_colors"] and not doc["frame_correction"]  # colours baked for camera 8 change with the pose
    assert len(blob) == 52 * N + 6 * V * T + 3 * N * T
    entry = json.loads((web_ws / "export" / "results.json").read_text())["web"]
    assert entry["frames"] == doc["n_frames"] and entry["files"] == ["web/index.html", "web/player.js", "web/avatar.js"]
    for control in ('id="speed"', 'id="reset"', 'id="fps"'):
        assert control in html


def test_web_data_carries_each_frames_colours_and_surfel_correction(cmd_avatar_ws, tiny_capture):
    """With phase 2's surfel correction, the page's posing (re-implemented here from the blob) gives
    sage's corrected surfels, and its colours are sage's for each frame."""
    import base64

    import torch

    from helpers import load_phase1_renderer
    from sage_core.export.bundle import RenderSettings
    from sage_core.export.web import web_player_data
    from sage_core.flame.frames import triangle_frames
    from sage_core.geometry.rotations import quat_to_matrix
    from sage_core.stages.avatars import AvatarRenderer

    data, loaded, _ = load_phase1_renderer(cmd_avatar_ws)
    av = loaded.avatar
    renderer = AvatarRenderer(av, RenderSettings(correction={}))
    params = av.params.select([0, av.params.n_timesteps - 1])
    doc = web_player_data(av, params, data.cameras[8], renderer=renderer)
    assert doc["frame_correction"]
    N, V, T = doc["n_surfels"], doc["n_vertices"], doc["n_frames"]
    blob = base64.b64decode(doc["data"])
    tri = np.frombuffer(blob, "<u4", N * 3, 0).reshape(N, 3).astype(np.int64)
    mu = np.frombuffer(blob, "<f4", N * 3, 12 * N).reshape(N, 3)
    rot = np.frombuffer(blob, "<f4", N * 4, 24 * N).reshape(N, 4)
    scl = np.frombuffer(blob, "<f4", N * 2, 40 * N).reshape(N, 2)
    off = 52 * N + 6 * V * T
    cols = None
    if doc["frame_colors"]:
        cols = np.frombuffer(blob, np.uint8, T * N * 3, off).reshape(T, N, 3)
        off += T * N * 3
    dq = np.frombuffer(blob, np.int8, T * N * 4, off).reshape(T, N, 4) / 127.0
    lf = np.frombuffer(blob, np.int8, T * N * 2, off + T * N * 4).reshape(T, N, 2) / doc["log_factor_scale"]
    assert len(blob) == off + 6 * T * N
    keep = None
    moved = 0.0
    for r in range(T):
        with torch.no_grad():
            inputs = av.params_inputs(params, r)
            ref = renderer.posed(inputs, None)
            plain = av.posed(inputs, None)
        if keep is None:  # the page's surfels are those above the opacity floor, in order
            from sage_core.export.ply import MIN_OPACITY

            keep = (ref.opacities >= MIN_OPACITY).numpy()
            assert keep.sum() == N
        v = torch.as_tensor(ref.vertices.numpy(), dtype=torch.float64)
        R, Tc, k = (a.numpy() for a in triangle_frames(v, torch.as_tensor(tri)))  # the N bound triangles' frames
        rs = R @ quat_to_matrix(torch.tensor(rot, dtype=torch.float64)).numpy() @ quat_to_matrix(torch.tensor(dq[r])).numpy()
        means = k[:, None] * np.einsum("nij,nj->ni", R, mu) + Tc
        scales = k[:, None] * scl * np.exp(lf[r])
        assert np.abs(means - ref.means.numpy()[keep]).max() < 1e-5
        assert np.abs(rs - quat_to_matrix(ref.quats.double()).numpy()[keep]).max() < 0.03  # int8 quaternions
        assert np.abs(np.log(scales / ref.scales.numpy()[keep])).max() < 0.02  # log factors in steps of 1/64
        moved = max(moved, float(np.abs(np.log(ref.scales.numpy() / plain.scales.numpy())).max()))
        if cols is not None:
            assert np.abs(cols[r] / 255.0 - ref.colors.clamp(0, 1).numpy()[keep]).max() <= 0.5 / 255 + 1e-6
    assert moved > 0.01  # the correction really changed the surfels


def test_web_page_matches_sage_reenact(web_ws, tiny_capture, tmp_path):
    require_chromium()
    from sage_core.data.imageio import read_image

    out = web_ws / "export" / "web"
    text = (out / "avatar.js").read_text()
    doc = json.loads(text[text.index("{") : text.rindex("}") + 1])
    T = doc["n_frames"]
    ref_dir = tmp_path / "reenact"
    res = invoke(["reenact", web_ws, "--flame-seq", tiny_capture, "--camera", "8", "--no-video", "--out", ref_dir,
                  "--device", "cpu", "--quiet"])  # fmt: skip
    assert res.exit_code == 0, res.output
    refs = [read_image(ref_dir / "frames" / f"{i:05d}.png")[..., :3] for i in range(T)]
    # the frame whose render differs most from frame 0 (an expression change)
    a = 0
    b = int(np.argmax([np.abs(r - refs[0]).mean() for r in refs]))
    assert b != a
    W, H = doc["camera"]["width"], doc["camera"]["height"]
    shots = {}
    with Chromium(max(W, 200), max(H, 200)) as browser:
        for f in (a, b):
            browser.open((out / "index.html").as_uri() + f"?frame={f}&camera=ref&ui=0")
            browser.wait_until("window.sageReady === true || !!window.sageError", timeout=60)
            assert browser.evaluate("window.sageError || ''") == ""
            assert browser.evaluate("window.sageFrame") == f
            shots[f] = browser.screenshot()[:H, :W]
    for f in (a, b):
        psnr = _psnr(shots[f], refs[f])
        print(f"frame {f}: PSNR {psnr:.2f} dB against sage reenact")
        assert psnr > MIN_PSNR, (f, psnr)
    # the two frames differ, and where the reference renders differ
    d_web = np.abs(shots[a] - shots[b]).max(-1)
    d_ref = np.abs(refs[a] - refs[b]).max(-1)
    changed = d_ref > 0.1
    assert changed.mean() > 0.002
    assert d_web[changed].mean() > 4 * d_web[~changed].mean()
    assert d_web.max() > 0.2


def test_web_page_orbits_and_plays(web_ws):
    """Dragging turns the orbit camera; space starts playback."""
    require_chromium()
    import time

    out = web_ws / "export" / "web"
    with Chromium(320, 320) as browser:
        browser.open((out / "index.html").as_uri() + "?frame=1&ui=0")
        browser.wait_until("window.sageReady === true || !!window.sageError", timeout=60)
        assert browser.evaluate("window.sageError || ''") == ""
        before = browser.screenshot()
        assert float((np.abs(before - before[0, 0]).max(-1) > 0.1).mean()) > 0.02  # the head is drawn
        for kind, x in (("mousePressed", 160), ("mouseMoved", 200), ("mouseMoved", 240), ("mouseReleased", 240)):
            browser.call("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": 160, "button": "left", "buttons": 1, "clickCount": 1}, session=True)
        time.sleep(0.5)
        after = browser.screenshot()
        assert np.abs(after - before).max() > 0.3  # the camera turned
        assert browser.evaluate("window.sageFrame") == 1
        for kind in ("keyDown", "keyUp"):
            browser.call("Input.dispatchKeyEvent", {"type": kind, "code": "Space", "key": " ", "windowsVirtualKeyCode": 32}, session=True)
        browser.wait_until("window.sageFrame !== 1", timeout=10)  # playing
        browser.wait_until("window.sageFps > 0", timeout=10)  # the readout measures the drawing rate
        assert browser.evaluate("document.getElementById('fps').textContent").endswith("fps")
        # the view reset (key R) brings back the first picture of frame 1
        for kind in ("keyDown", "keyUp"):
            browser.call("Input.dispatchKeyEvent", {"type": kind, "code": "Space", "key": " ", "windowsVirtualKeyCode": 32}, session=True)
        browser.evaluate("(() => { const s = document.getElementById('slider'); s.value = '1'; s.oninput(); })()")
        for kind in ("keyDown", "keyUp"):
            browser.call("Input.dispatchKeyEvent", {"type": kind, "code": "KeyR", "key": "r", "windowsVirtualKeyCode": 82}, session=True)
        browser.wait_until("window.sageFrame === 1", timeout=10)
        time.sleep(0.5)
        diff = np.abs(browser.screenshot() - before).max(-1)
        moved = np.abs(after - before).max(-1)
        # measured: 0.09 % of the pixels differ, along one surfel edge (software WebGL), against the turned view's
        assert (diff > 0.02).mean() < 0.005 and (moved > 0.02).mean() > 20 * (diff > 0.02).mean()


def test_web_page_playback_speed(web_ws):
    """?speed=0.25 plays four times slower than 2x: frames advanced in the same wall time."""
    require_chromium()
    out = web_ws / "export" / "web"
    with Chromium(200, 200) as browser:
        browser.open((out / "index.html").as_uri() + "?ui=0&speed=0.25")
        browser.wait_until("window.sageReady === true || !!window.sageError", timeout=60)
        assert browser.evaluate("window.sageSpeed()") == 0.25
        browser.evaluate("(() => { const s = document.getElementById('speed'); s.value = '2'; s.onchange(); })()")
        assert browser.evaluate("window.sageSpeed()") == 2
