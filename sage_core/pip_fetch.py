"""Fetching one wheel with ``pip download``: how ``sage track-models`` and ``sage lpips-weights`` get the
published files they take weights out of (on request only; nothing else in sage downloads)."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from .errors import InputError


def download_wheel(requirement: str, folder: str | Path, pattern: str, options: Sequence[str] = (),
                   pip: list[str] | None = None, hint: str = "") -> Path:
    """``pip download requirement --no-deps [options]`` into ``folder``; returns the wheel's path.

    pattern: the wheel's file name as a glob (``lpips-*.whl``); options: more pip arguments (platform
    tags, ``--only-binary``); pip: the command that runs pip (default: this interpreter's ``-m pip``);
    hint: appended to the error. Raises InputError naming ``folder`` with pip's last lines when the
    download fails (no network, no index) or leaves no wheel.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cmd = [*(pip or [sys.executable, "-m", "pip"]), "download", requirement, "--no-deps", *options,
           "--dest", str(folder), "--quiet"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wheels = sorted(folder.glob(pattern))
    if proc.returncode != 0 or not wheels:
        tail = " | ".join((proc.stderr or proc.stdout or "").strip().splitlines()[-3:])
        raise InputError(folder, f"`pip download {requirement}` failed (exit {proc.returncode}): {tail or 'no wheel'}"
                                 + (f"; {hint}" if hint else ""))
    return wheels[-1]
