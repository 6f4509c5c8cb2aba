"""Workspace layout, manifests, atomic writes, checkpoints and the per-workspace lock.

A workspace ``WS`` holds one folder per stage (design.md "Data flow"): ``WS/data`` (ingest),
``WS/init`` (init-mesh), ``WS/phase1``, ``WS/phase2``, ``WS/eval``, ``WS/export``. A stage runs in
``WS/.work/<stage>/`` (which also keeps its checkpoints between interrupted runs) and, on
success, its outputs are promoted to ``WS/<stage folder>/`` by a directory rename; the stage's
``manifest.json`` is written last and atomically. A failed or interrupted stage therefore leaves
the previous good output untouched.

Freshness: every manifest records its stage's config hash and the fingerprints of the inputs it
read (upstream manifests' fingerprints and external files). A stage's own fingerprint is the hash
of both. Re-running with the same config and inputs skips; an upstream stage that was re-run
with different inputs changes its fingerprint, which makes every stage that read the old one
stale, and later stages refuse to run on it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import shutil
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from . import __version__
from .errors import StageError

# stage name -> folder name, in pipeline order
STAGE_FOLDERS: dict[str, str] = {
    "ingest": "data",
    "init-mesh": "init",
    "phase1": "phase1",
    "phase2": "phase2",
    "eval": "eval",
    "export": "export",
}

CHECKPOINT_FORMAT = 1


# --------------------------------------------------------------------------------------------
# Atomic file helpers
# --------------------------------------------------------------------------------------------


def _tmp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.{time.monotonic_ns()}.tmp")


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write bytes to ``path`` through a temp file and ``os.replace``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_path(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write text (UTF-8) atomically."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, data: Any) -> None:
    """Write JSON (indented, sorted keys) atomically."""
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=True, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_json(path: str | Path) -> Any:
    """Read a JSON file."""
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def file_fingerprint(path: str | Path, content: bool = True) -> str:
    """Fingerprint of a file or folder.

    Files: sha256 of the content (``content=True``) or of (size, mtime). Folders: a hash over the
    sorted relative paths with each file's (size, mtime_ns) — cheap for image folders.
    """
    p = Path(path)
    h = hashlib.sha256()
    if p.is_dir():
        for f in sorted(p.rglob("*")):
            if f.is_file():
                st = f.stat()
                h.update(f"{f.relative_to(p)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    elif p.is_file():
        if content:
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
        else:
            st = p.stat()
            h.update(f"{st.st_size}\0{st.st_mtime_ns}".encode())
    else:
        h.update(b"<missing>")
    return h.hexdigest()[:16]


def now_iso() -> str:
    """UTC timestamp, ISO 8601, seconds."""
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


# --------------------------------------------------------------------------------------------
# Lock
# --------------------------------------------------------------------------------------------


class WorkspaceLock:
    """An exclusive advisory lock on ``WS/.lock`` (fcntl), so two processes cannot run stages on
    one workspace at once. Re-entrant within a process."""

    def __init__(self, root: Path) -> None:
        self.path = root / ".lock"
        self._fh: Any = None
        self._depth = 0

    def acquire(self) -> None:
        import fcntl

        if self._depth:
            self._depth += 1
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fh = open(self.path, "a+")
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            fh.close()
            raise StageError(f"{self.path.parent}: workspace is in use by {holder}; wait for it to finish") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}")
        fh.flush()
        self._fh = fh
        self._depth = 1

    def release(self) -> None:
        import fcntl

        if not self._depth:
            return
        self._depth -= 1
        if self._depth == 0 and self._fh is not None:
            self._fh.seek(0)
            self._fh.truncate()
            fcntl.flock(self._fh.fileno(), fcntl.LOCK_UN)
            self._fh.close()
            self._fh = None

    def __enter__(self) -> "WorkspaceLock":
        self.acquire()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.release()


# --------------------------------------------------------------------------------------------
# Workspace
# --------------------------------------------------------------------------------------------


@dataclass
class StageStatus:
    """What ``sage info`` shows for one stage."""

    stage: str
    folder: Path
    status: str  # "missing" | "complete" | "stale" | "interrupted" | "failed"
    manifest: dict[str, Any] | None
    reason: str = ""


class Workspace:
    """Paths and manifests of one workspace folder."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()
        self.lock = WorkspaceLock(self.root)

    # paths -------------------------------------------------------------------------------
    def stage_dir(self, stage: str) -> Path:
        """Final output folder of a stage."""
        if stage not in STAGE_FOLDERS:
            raise StageError(f"unknown stage '{stage}'")
        return self.root / STAGE_FOLDERS[stage]

    def work_dir(self, stage: str) -> Path:
        """Scratch folder where a running stage writes; it keeps checkpoints across interruptions."""
        return self.root / ".work" / STAGE_FOLDERS[stage]

    @property
    def logs_dir(self) -> Path:
        return self.root / "logs"

    def manifest_path(self, stage: str) -> Path:
        return self.stage_dir(stage) / "manifest.json"

    def manifest(self, stage: str) -> dict[str, Any] | None:
        """The stage's manifest, or None when it has never completed."""
        p = self.manifest_path(stage)
        if not p.is_file():
            return None
        try:
            return read_json(p)
        except (OSError, json.JSONDecodeError):
            return None

    # freshness ---------------------------------------------------------------------------
    def status(self, stage: str) -> StageStatus:
        """Complete / stale / missing / interrupted state of a stage."""
        m = self.manifest(stage)
        folder = self.stage_dir(stage)
        if m is None or m.get("status") != "complete":
            if self.work_dir(stage).exists():
                st = "failed" if (self.work_dir(stage) / "FAILED").exists() else "interrupted"
                return StageStatus(stage, folder, st, m, "an earlier run did not finish")
            return StageStatus(stage, folder, "missing", m)
        for up, fp in (m.get("inputs", {}).get("stages") or {}).items():
            um = self.manifest(up)
            if um is None or um.get("status") != "complete":
                return StageStatus(stage, folder, "stale", m, f"its input stage '{up}' is missing")
            if um.get("fingerprint") != fp:
                return StageStatus(stage, folder, "stale", m, f"'{up}' was re-run since")
            ust = self.status(up)
            if ust.status == "stale":
                return StageStatus(stage, folder, "stale", m, f"'{up}' is stale ({ust.reason})")
        return StageStatus(stage, folder, "complete", m)

    def require(self, stage: str, by: str) -> dict[str, Any]:
        """Manifest of an upstream stage that ``by`` needs; StageError if missing or stale."""
        st = self.status(stage)
        if st.status == "complete":
            assert st.manifest is not None
            return st.manifest
        if st.status == "stale":
            raise StageError(f"'{by}' needs stage '{stage}', which is stale ({st.reason}): re-run `sage {stage} {self.root}`")
        raise StageError(f"'{by}' needs stage '{stage}', which has not completed: run `sage {stage} {self.root}` first")

    def stages(self) -> Iterator[StageStatus]:
        for s in STAGE_FOLDERS:
            yield self.status(s)


# --------------------------------------------------------------------------------------------
# Stage run
# --------------------------------------------------------------------------------------------


@dataclass
class StageRun:
    """One execution of a stage (see :meth:`begin_stage`).

    Write outputs into ``work_dir``; checkpoints go to ``checkpoint_dir`` (kept across interrupted
    runs with the same config and inputs, removed on success unless ``keep_checkpoints``). Call
    :meth:`finish` to promote the outputs and write the manifest.
    """

    ws: Workspace
    stage: str
    config: dict[str, Any]
    config_hash: str
    inputs: dict[str, Any]
    seed: int
    device: str
    work_dir: Path
    started_at: str
    resumed: bool
    metrics: dict[str, Any] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    _t0: float = field(default_factory=time.time)

    @property
    def checkpoint_dir(self) -> Path:
        return self.work_dir / "checkpoints"

    @property
    def fingerprint(self) -> str:
        blob = json.dumps({"config": self.config_hash, "inputs": self.inputs}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def finish(self, keep_checkpoints: bool = False) -> dict[str, Any]:
        """Promote ``work_dir`` to the stage folder and write the manifest last. Returns it."""
        if not keep_checkpoints and self.checkpoint_dir.exists():
            shutil.rmtree(self.checkpoint_dir)
        for marker in ("RUN", "FAILED"):
            (self.work_dir / marker).unlink(missing_ok=True)
        final = self.ws.stage_dir(self.stage)
        trash = self.ws.root / ".work" / f".old-{final.name}-{os.getpid()}"
        if final.exists():
            if trash.exists():
                shutil.rmtree(trash)
            os.replace(final, trash)
        os.replace(self.work_dir, final)
        manifest = {
            "stage": self.stage,
            "status": "complete",
            "fingerprint": self.fingerprint,
            "config_hash": self.config_hash,
            "inputs": self.inputs,
            "version": __version__,
            "seed": self.seed,
            "device": self.device,
            "started_at": self.started_at,
            "finished_at": now_iso(),
            "wall_time_s": round(time.time() - self._t0, 3),
            "resumed": self.resumed,
            "metrics": self.metrics,
            "outputs": self.outputs,
        }
        atomic_write_json(final / "manifest.json", manifest)
        if trash.exists():
            shutil.rmtree(trash, ignore_errors=True)
        return manifest

    def fail(self, message: str) -> None:
        """Mark the work folder as failed (its checkpoints stay for a resume)."""
        if self.work_dir.exists():
            atomic_write_text(self.work_dir / "FAILED", message + "\n")


def begin_stage(
    ws: Workspace,
    stage: str,
    config: dict[str, Any],
    config_hash: str,
    *,
    requires: list[str] = (),  # type: ignore[assignment]
    external_inputs: dict[str, str] | None = None,
    seed: int = 0,
    device: str = "cpu",
    force: bool = False,
) -> StageRun | None:
    """Decide whether a stage runs, and prepare its work folder.

    Checks that every required upstream stage is complete and fresh (StageError otherwise), then
    returns None when the stage already completed with the same config and inputs (and not
    ``force``): the caller reports the skip. Otherwise returns a :class:`StageRun` whose
    ``work_dir`` is fresh, or kept from an interrupted run with the same config and inputs
    (``resumed=True``), so the caller can resume from its newest checkpoint. The caller must hold
    ``ws.lock``.
    """
    inputs: dict[str, Any] = {"stages": {}, "files": dict(external_inputs or {})}
    for up in requires:
        inputs["stages"][up] = ws.require(up, stage)["fingerprint"]
    run_id = {"config_hash": config_hash, "inputs": inputs, "seed": seed}
    fp = hashlib.sha256(json.dumps({"config": config_hash, "inputs": inputs}, sort_keys=True).encode()).hexdigest()[:16]
    m = ws.manifest(stage)
    if not force and m is not None and m.get("status") == "complete" and m.get("fingerprint") == fp and m.get("seed") == seed:
        return None
    work = ws.work_dir(stage)
    state_file = work / "RUN"
    resumed = False
    if work.exists():
        prev = None
        if state_file.is_file():
            try:
                prev = read_json(state_file)
            except (OSError, json.JSONDecodeError):
                prev = None
        if prev == run_id and not force:
            resumed = True
        else:
            shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    (work / "FAILED").unlink(missing_ok=True)
    atomic_write_json(state_file, run_id)
    atomic_write_json(work / "config.json", config)
    return StageRun(
        ws=ws,
        stage=stage,
        config=config,
        config_hash=config_hash,
        inputs=inputs,
        seed=seed,
        device=device,
        work_dir=work,
        started_at=now_iso(),
        resumed=resumed,
    )


# --------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------


def save_checkpoint(directory: str | Path, step: int, state: dict[str, Any], keep: int = 2) -> Path:
    """Save a versioned checkpoint dict atomically as ``ckpt_{step:08d}.pt``; keep the newest ``keep``.

    ``state`` maps names to state dicts / tensors / plain data (parameters, optimizers,
    schedulers, RNG states, …). The file holds ``{"format": CHECKPOINT_FORMAT, "version",
    "step", "state"}``.
    """
    import io

    import torch

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save({"format": CHECKPOINT_FORMAT, "version": __version__, "step": int(step), "state": state}, buf)
    path = d / f"ckpt_{int(step):08d}.pt"
    atomic_write_bytes(path, buf.getvalue())
    ckpts = sorted(d.glob("ckpt_*.pt"))
    for old in ckpts[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
    return path


def latest_checkpoint(directory: str | Path) -> Path | None:
    """Newest ``ckpt_*.pt`` in a folder, or None."""
    d = Path(directory)
    if not d.is_dir():
        return None
    ckpts = sorted(d.glob("ckpt_*.pt"))
    return ckpts[-1] if ckpts else None


def load_checkpoint(path: str | Path, map_location: Any = "cpu") -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint`; StageError on a foreign or newer format."""
    import torch

    p = Path(path)
    try:
        data = torch.load(p, map_location=map_location, weights_only=False)
    except Exception as e:  # noqa: BLE001
        raise StageError(f"{p}: cannot read checkpoint: {e}") from None
    if not isinstance(data, dict) or "format" not in data or "state" not in data:
        raise StageError(f"{p}: not a sage checkpoint")
    if int(data["format"]) > CHECKPOINT_FORMAT:
        raise StageError(f"{p}: checkpoint format {data['format']} is newer than this sage supports ({CHECKPOINT_FORMAT})")
    return data


def rng_state() -> dict[str, Any]:
    """Capture the torch (CPU and CUDA), numpy and python RNG states."""
    import random

    import numpy as np
    import torch

    st: dict[str, Any] = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        st["cuda"] = torch.cuda.get_rng_state_all()
    return st


def set_rng_state(st: dict[str, Any]) -> None:
    """Restore states captured by :func:`rng_state`."""
    import random

    import numpy as np
    import torch

    torch.set_rng_state(st["torch"])
    np.random.set_state(st["numpy"])
    random.setstate(st["python"])
    if "cuda" in st and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(st["cuda"])


def seed_everything(seed: int) -> None:
    """Seed python, numpy and torch (all devices)."""
    import random

    import numpy as np
    import torch

    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def resolve_device(name: str) -> str:
    """``auto`` -> ``cuda`` when available else ``cpu``; validates ``cuda[:N]``."""
    import torch

    from .errors import ConfigError

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cpu":
        return "cpu"
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError(f"--device {name}: CUDA is not available on this machine (use --device cpu or auto)")
        if ":" in name:
            idx = name.split(":", 1)[1]
            if not idx.isdigit() or int(idx) >= torch.cuda.device_count():
                raise ConfigError(f"--device {name}: no such CUDA device ({torch.cuda.device_count()} visible)")
        return name
    raise ConfigError(f"--device {name}: expected auto, cpu or cuda[:N]")
