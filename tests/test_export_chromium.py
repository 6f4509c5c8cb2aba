"""Headless Chromium checks of the viewer exports: splat-transform's HTML viewer shows the viewer-
orientation PLY upright and facing its default camera.

Chromium and splat-transform come from tests/chromium.py, so a test can wait in real time until
WebGL has drawn. Skips where Chromium, node or the ``@playcanvas/splat-transform`` package
(``tests/js``, installed by ``.ci/run``) are absent.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from chromium import Chromium, require_chromium, require_splat_transform, splat_transform, wait_for_drawing
from helpers import invoke


def _viewer_settings(html_template: Path, target: np.ndarray, distance: float, fov: float) -> dict[str, Any]:
    """The HTML viewer's own default settings with its camera moved along the default direction
    ((2, 2, −2) → origin) to ``distance`` from ``target`` (displayed world)."""
    text = html_template.read_text()
    tag = '<script type="application/json" id="sse-bootstrap">'
    start = text.index(tag) + len(tag)
    settings = json.loads(text[start : text.index("</script>", start)])["settings"]
    (default,) = settings["cameras"]
    direction = np.asarray(default["initial"]["position"], float) - np.asarray(default["initial"]["target"], float)
    direction /= np.linalg.norm(direction)
    settings["cameras"] = [{"initial": {"position": (target + distance * direction).tolist(), "target": target.tolist(), "fov": fov}}]
    return settings


def _screen_layout(img: np.ndarray) -> tuple[float, float, float]:
    """(mean row of 'top' pixels − mean row of 'bottom' pixels, fraction of 'front' pixels, head
    pixels fraction) of a screenshot of the region-coloured head (R: top, B: bottom, G: front)."""
    head = img.max(-1) > 0.3
    top = head & (img[..., 0] > 0.5)
    bottom = head & (img[..., 2] > 0.5)
    rows = np.arange(img.shape[0])[:, None] * np.ones((1, img.shape[1]))
    return float(rows[top].mean() - rows[bottom].mean()), float((img[..., 1] > 0.5)[head].mean()), float(head.mean())


def test_splat_transform_viewer_shows_the_exported_head_upright(cmd_avatar_ws, tmp_path):
    """The default (viewer-orientation) PLY, coloured by region of the head in FLAME's world (red:
    above the head centre, blue: below, green: the face side), converted by splat-transform to its
    HTML viewer and seen from the viewer's default camera direction: red above blue, and the face
    side. The same file in FLAME's orientation shows upside down and from behind."""
    require_chromium()
    require_splat_transform()
    from sage_core.export.orientation import orient
    from sage_core.export.ply import SH_C0, encode_ply, read_ply

    ws = tmp_path / "ws"
    shutil.copytree(cmd_avatar_ws, ws)
    res = invoke(["export", ws, "--ply", "--device", "cpu", "--quiet"])
    assert res.exit_code == 0, res.output
    ply = read_ply(ws / "export" / "ply" / "canonical.ply")
    flame_means = ply["means"].astype(np.float64) * np.array([1.0, -1.0, -1.0])  # back to FLAME's y-up world
    flame_quats = ply["quats"].astype(np.float64) * 1.0
    centre = np.median(flame_means, axis=0)
    top = flame_means[:, 1] > centre[1]
    front = flame_means[:, 2] > centre[2]
    rgb = np.stack([top, front, ~top], 1).astype(np.float64)
    extent = float(np.ptp(flame_means, axis=0).max())
    layouts = {}
    with Chromium(480, 480) as browser:
        for name, file_world in (("viewer", ply["means"].astype(np.float64)), ("flame", flame_means)):
            if name == "flame":
                means, quats = flame_means, flame_quats
            else:
                means, quats, _ = orient(flame_means, flame_quats, None, "viewer")
                assert np.allclose(means, file_world, atol=1e-6)
            data, _ = encode_ply(means, quats, ply["scales"], ply["opacities"], (rgb - 0.5) / SH_C0, up_axis=None)
            src = tmp_path / f"{name}.ply"
            src.write_bytes(data)
            first = tmp_path / f"{name}_default.html"
            splat_transform(src, first)
            displayed = np.median(means, axis=0) * np.array([-1.0, -1.0, 1.0])  # the viewer turns the data 180° about z
            settings = tmp_path / f"{name}_settings.json"
            settings.write_text(json.dumps(_viewer_settings(first, displayed, 2.5 * extent, 40.0)))
            html = tmp_path / f"{name}.html"
            splat_transform(src, "--viewer-settings", settings, html)
            browser.open(html.as_uri() + "?noanim")
            img = wait_for_drawing(browser, np.zeros(3), timeout=60, settle=1.5, hide=".sse-ui")
            layouts[name] = _screen_layout(img)
    up, face, cover = layouts["viewer"]
    up_f, face_f, _ = layouts["flame"]
    assert cover > 0.02, layouts  # the head fills part of the picture
    assert up < -5 and up_f > 5, layouts  # upright; FLAME's y-up world shows upside down
    # the default camera looks down on the head from 35° above, so the crown takes a good part of
    # the picture; the face side still shows much more than from behind
    assert face > 0.3 and face > face_f + 0.1, layouts
