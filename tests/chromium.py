"""Headless Chromium for the viewer tests, driven over the DevTools protocol on a pipe
(``--remote-debugging-pipe``: no port, no network), and the ``@playcanvas/splat-transform`` tool
(``tests/js``, installed by ``.ci/run``): plain helpers that skip the calling test where Chromium,
node or the package are absent."""

from __future__ import annotations

import base64
import fcntl
import io
import json
import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

JS_DIR = Path(__file__).parent / "js"
SPLAT_TRANSFORM = JS_DIR / "node_modules" / ".bin" / "splat-transform"
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
    "--allow-file-access-from-files", "--hide-scrollbars", "--mute-audio",
]  # fmt: skip


def chromium_path() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def require_chromium() -> str:
    p = chromium_path()
    if p is None:
        pytest.skip("Chromium is not installed (apt-get install chromium; .ci/run installs it)")
    return p


def require_splat_transform() -> Path:
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    if not SPLAT_TRANSFORM.exists():
        pytest.skip("@playcanvas/splat-transform is not installed (npm install in tests/js; .ci/run does it)")
    return SPLAT_TRANSFORM


def splat_transform(*args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess:
    tool = require_splat_transform()
    res = subprocess.run([str(tool), "-w", *map(str, args)], capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout + res.stderr
    return res


class Chromium:
    """A headless Chromium driven over the DevTools protocol on a pipe (one page)."""

    def __init__(self, width: int, height: int) -> None:
        exe = require_chromium()
        self.profile = tempfile.mkdtemp(prefix="sage-chromium-")
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()

        def child_fds() -> None:  # the protocol pipes are fds 3 (read) and 4 (write) in Chromium
            a = fcntl.fcntl(to_chrome_r, fcntl.F_DUPFD_CLOEXEC, 10)
            b = fcntl.fcntl(from_chrome_w, fcntl.F_DUPFD_CLOEXEC, 10)
            os.dup2(a, 3)
            os.dup2(b, 4)

        args = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={self.profile}", f"--window-size={width},{height}",
                "--remote-debugging-pipe", "about:blank"]  # fmt: skip
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, preexec_fn=child_fds,
                                     close_fds=False)  # fmt: skip (os.pipe ends are close-on-exec; only 3 and 4 are inherited)
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buf = b""
        self._id = 0
        self.width, self.height = width, height
        self.session = ""
        self.call("Target.setDiscoverTargets", {"discover": False})

    def _read_message(self, deadline: float) -> dict[str, Any]:
        while b"\0" not in self._buf:
            if time.monotonic() > deadline:
                raise TimeoutError("no answer from Chromium")
            chunk = os.read(self._from_chrome, 1 << 20)
            if not chunk:
                raise RuntimeError("Chromium closed the protocol pipe")
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, params: dict[str, Any] | None = None, session: bool = False, timeout: float = 60) -> dict[str, Any]:
        self._id += 1
        msg: dict[str, Any] = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = self.session
        os.write(self._to_chrome, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            reply = self._read_message(deadline)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def open(self, url: str) -> None:
        """Open ``url`` in a new page of the window size (the page the other calls talk to)."""
        target = self.call("Target.createTarget", {"url": url})["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.call("Emulation.setDeviceMetricsOverride",
                  {"width": self.width, "height": self.height, "deviceScaleFactor": 1, "mobile": False}, session=True)  # fmt: skip
        self.call("Page.enable", session=True)

    def evaluate(self, expr: str) -> Any:
        r = self.call("Runtime.evaluate", {"expression": expr, "returnByValue": True, "awaitPromise": True}, session=True)
        return r.get("result", {}).get("value")

    def wait_until(self, expr: str, timeout: float = 60.0) -> Any:
        """Evaluate ``expr`` until it is truthy; returns its value (TimeoutError after ``timeout``)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            value = self.evaluate(expr)
            if value:
                return value
            time.sleep(0.2)
        raise TimeoutError(f"{expr} stayed false for {timeout} s")

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) float32 in [0, 1]."""
        from PIL import Image

        data = self.call("Page.captureScreenshot", {"format": "png"}, session=True)["data"]
        img = Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB")
        return np.asarray(img, dtype=np.float32) / 255.0

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=10)
        except Exception:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._to_chrome)
        os.close(self._from_chrome)
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def wait_for_drawing(browser: Chromium, background: np.ndarray, timeout: float = 60.0, settle: float = 2.0,
                     hide: str | None = None) -> np.ndarray:
    """Screenshots until more than 0.5 % of the pixels differ from ``background`` (3,) and the image
    stops changing (or ``timeout`` passes); returns the last one. ``hide``: a CSS selector of page
    elements (controls) hidden before each screenshot."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        if hide is not None:
            browser.evaluate(f"document.querySelectorAll({json.dumps(hide)}).forEach(e => e.style.display = 'none')")
        img = browser.screenshot()
        drawn = float((np.abs(img - background).max(-1) > 0.1).mean())
        if drawn > 0.005:
            if last is not None and np.abs(img - last).max() < 0.02:
                return img
            last = img
            time.sleep(settle)
        else:
            time.sleep(0.5)
    if last is None:
        raise AssertionError("nothing was drawn")
    return last
