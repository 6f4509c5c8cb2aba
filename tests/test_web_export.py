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

# Measured on the tiny test avatar (128x186, camera 8, headless Chromium with SwiftShader): 38.65 dB
# (frame 0) and 38.91 dB (frame 4). The page draws quads over ±3σ with a perspective-correct
# Gaussian, blends back to front by centre depth and bakes colours once; the reference rasterizer
# sorts per tile and evaluates view-dependent colours per frame.
MIN_PSNR = 34.0


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
    assert len(blob) == 52 * doc["n_surfels"] + 6 * doc["n_vertices"] * doc["n_frames"]
    entry = json.loads((web_ws / "export" / "results.json").read_text())["web"]
    assert entry["frames"] == doc["n_frames"] and entry["files"] == ["web/index.html"]


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
