"""Workspace layout, manifests, atomic writes, checkpoints and the per-workspace lock.

A workspace ``WS`` holds one folder per stage (docs/method.md §1): ``WS/data`` (ingest),
``WS/init`` (init-mesh), ``WS/phase1``, ``WS/phase2``, ``WS/eval``, ``WS/export``. A stage runs in
``WS/.work/<stage>/`` (which also keeps its checkpoints between interrupted runs) and, on
success, its outputs are promoted to ``WS/<stage folder>/`` by a directory rename; the stage's
``manifest.json`` is written last and atomically. A failed or interrupted stage therefore leaves
the previous good output untouched.

Freshness: every manifest records its stage's config hash and the fingerprints of the inputs it
read (upstream manifests' fingerprints and external files, by content). A stage's own fingerprint
is the hash of both. Re-running with the same config and inputs skips; an upstream stage that was
re-run with different inputs changes its fingerprint, which makes every stage that read the old
one stale, and later stages refuse to run on it. The manifest also lists every file of the stage
folder (with its size when written); a stage whose listed files are gone is "incomplete".

Promotion cannot lose a finished run: the manifest is written into the work folder first, the
work folder is renamed into place, and only then are its checkpoints removed. A promotion that was
cut short is completed by the next run (:meth:`Workspace.recover`).

Checkpoints, like every binary file sage reads, are safetensors files (:mod:`sage_core.serialization`)
that cannot run code when loaded; a damaged newest checkpoint falls back to the one before it.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import shutil
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from ._version import __version__
from .atomic import atomic_write_bytes, atomic_write_text
from .errors import InputError, StageError, UnsafeFileError, WorkspaceError
from .serialization import CHECKPOINT_FORMAT, CHECKPOINT_KIND

# stage name -> folder name, in pipeline order
STAGE_FOLDERS: dict[str, str] = {
    "ingest": "data",
    "init-mesh": "init",
    "phase1": "phase1",
    "phase2": "phase2",
    "eval": "eval",
    "export": "export",
}

HASH_CACHE = ".cache/content-hashes.json"
"""Per-workspace cache of file content hashes keyed by path, size and mtime (see :func:`content_hashes`)."""
# files of a work folder that are not outputs of the stage
_RUN_FILES = ("RUN", "FAILED", "RUNNING", "manifest.json")
_MARKERS = ("RUN", "FAILED", "RUNNING")
"""Run markers: ``RUN`` (the run's identity, for resuming), ``FAILED`` (why it failed) and
``RUNNING`` (pid, host and start time of the live process)."""

log = logging.getLogger("sage")


# --------------------------------------------------------------------------------------------
# Atomic file helpers
# --------------------------------------------------------------------------------------------


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


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def content_hashes(paths: list[Path], cache_file: str | Path | None = None) -> dict[str, str]:
    """sha256 of each file's content, {str(resolved path): hex}; a missing file hashes to "<missing>".

    cache_file: a JSON cache {path: [size, mtime_ns, sha256]} (e.g. ``WS/.cache/content-hashes.json``)
    so that files whose size and mtime did not change are not read again; it is updated atomically
    (best effort: a cache that cannot be written is simply not kept).
    """
    cache: dict[str, Any] = {}
    cpath = Path(cache_file) if cache_file is not None else None
    if cpath is not None and cpath.is_file():
        try:
            loaded = read_json(cpath)
            cache = loaded if isinstance(loaded, dict) else {}
        except (OSError, ValueError):
            cache = {}
    out: dict[str, str] = {}
    changed = False
    for p in paths:
        key = str(Path(p).resolve())
        try:
            st = os.stat(key)
        except OSError:
            out[key] = "<missing>"
            continue
        hit = cache.get(key)
        if isinstance(hit, list) and len(hit) == 3 and hit[0] == st.st_size and hit[1] == st.st_mtime_ns:
            out[key] = str(hit[2])
            continue
        digest = file_sha256(Path(key))
        out[key] = digest
        cache[key] = [st.st_size, st.st_mtime_ns, digest]
        changed = True
    if cpath is not None and changed:
        try:
            atomic_write_json(cpath, cache)
        except OSError:
            pass
    return out


def combined_hash(hashes: dict[str, str]) -> str:
    """One 16-hex fingerprint of a {name: hash} map (order-independent)."""
    return hashlib.sha256(json.dumps(hashes, sort_keys=True).encode()).hexdigest()[:16]


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
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fh = open(self.path, "a+")
        except OSError as e:
            raise WorkspaceError(self.path.parent, f"cannot write to the workspace ({e.strerror or e}); check its permissions "
                                                   "or choose another folder") from None
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
    status: str  # "missing" | "complete" | "stale" | "incomplete" | "corrupt" | "interrupted" | "failed" | "running"
    manifest: dict[str, Any] | None
    reason: str = ""
    rerun: str | None = None
    """The stage to re-run to mend a stale stage: the furthest upstream one that is incomplete,
    corrupt or was re-run (None when the stage itself is the one)."""


class Workspace:
    """Paths and manifests of one workspace folder."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root).resolve()
        check_workspace_path(self.root)
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
        """The stage's manifest, or None when it has never completed or is unreadable
        (:meth:`manifest_problem` says why)."""
        p = self.manifest_path(stage)
        if not p.is_file():
            return None
        try:
            m = read_json(p)
        except (OSError, ValueError):
            return None
        return m if isinstance(m, dict) else None

    def manifest_problem(self, stage: str) -> str | None:
        """Why an existing ``manifest.json`` cannot be used ("is not a JSON object", ...: the
        problem, without the path), or None when it is absent or fine."""
        p = self.manifest_path(stage)
        if not p.is_file():
            return None
        try:
            m = read_json(p)
        except OSError as e:
            return f"cannot be read ({e.strerror or e})"
        except ValueError as e:
            return f"is not valid JSON ({e})"
        if not isinstance(m, dict):
            return f"is not a JSON object but a {type(m).__name__}"
        if not isinstance(m.get("status"), str):
            return "has no status"
        return None

    def missing_outputs(self, stage: str, m: dict[str, Any]) -> list[str]:
        """Files the manifest lists (``files``: relative path -> size when written) that are gone."""
        folder = self.stage_dir(stage)
        files = m.get("files")
        if not isinstance(files, dict):
            return []
        return [f"{rel} is missing" for rel in files if not (folder / rel).is_file()]

    # freshness ---------------------------------------------------------------------------
    def status(self, stage: str) -> StageStatus:
        """Complete / stale / incomplete / corrupt / missing / interrupted / failed state of a stage."""
        m = self.manifest(stage)
        folder = self.stage_dir(stage)
        problem = self.manifest_problem(stage)
        if problem is not None:
            return StageStatus(stage, folder, "corrupt", None, f"{self.manifest_path(stage)} {problem}")
        if (self.work_dir(stage) / "manifest.json").is_file():
            return StageStatus(stage, folder, "interrupted", m, "a finished run was not moved into place; the next run of "
                                                                "this stage completes the move")
        if m is None or m.get("status") != "complete":
            if self.work_dir(stage).exists():
                live = running_process(self.work_dir(stage))
                if live is not None:
                    return StageStatus(stage, folder, "running", m, live)
                st = "failed" if (self.work_dir(stage) / "FAILED").exists() else "interrupted"
                return StageStatus(stage, folder, st, m, "an earlier run did not finish")
            return StageStatus(stage, folder, "missing", m)
        gone = self.missing_outputs(stage, m)
        if gone:
            more = f" (and {len(gone) - 1} more)" if len(gone) > 1 else ""
            return StageStatus(stage, folder, "incomplete", m, f"output {gone[0]}{more}")
        for up, fp in (m.get("inputs", {}).get("stages") or {}).items():
            um = self.manifest(up)
            if um is None or um.get("status") != "complete":
                return StageStatus(stage, folder, "stale", m, f"its input stage '{up}' is missing", rerun=up)
            if um.get("fingerprint") != fp:
                return StageStatus(stage, folder, "stale", m, f"'{up}' was re-run since", rerun=stage)
            ust = self.status(up)
            if ust.status in ("stale", "incomplete", "corrupt"):
                return StageStatus(stage, folder, "stale", m, f"'{up}' is {ust.status} ({ust.reason})", rerun=ust.rerun or up)
        return StageStatus(stage, folder, "complete", m)

    def require(self, stage: str, by: str) -> dict[str, Any]:
        """Manifest of an upstream stage that ``by`` needs; StageError naming the stage to re-run if
        it (or a stage it depends on) is missing, stale, incomplete or corrupt."""
        st = self.status(stage)
        if st.status == "complete":
            assert st.manifest is not None
            return st.manifest
        if st.status == "stale":
            fix = st.rerun or stage
            raise StageError(f"'{by}' needs stage '{stage}', which is stale ({st.reason}): re-run `sage {fix} {self.root}`"
                             + (" and the stages after it" if fix != stage else ""))
        if st.status in ("incomplete", "corrupt"):
            raise StageError(f"'{by}' needs stage '{stage}', which is {st.status} ({st.reason}): re-run `sage {stage} {self.root}`")
        if st.status == "running":
            raise StageError(f"'{by}' needs stage '{stage}', which is still running ({st.reason}); wait for it to finish")
        raise StageError(f"'{by}' needs stage '{stage}', which has not completed: run `sage {stage} {self.root}` first")

    def verify(self, stage: str) -> list[str]:
        """Outputs of a complete stage whose bytes differ from the SHA-256 its manifest recorded
        (``hashes``), or are gone: one line each (empty when all match or nothing was recorded)."""
        m = self.manifest(stage) or {}
        hashes = m.get("hashes")
        if not isinstance(hashes, dict):
            return []
        folder = self.stage_dir(stage)
        problems = []
        for rel, digest in sorted(hashes.items()):
            p = folder / rel
            if not p.is_file():
                problems.append(f"{rel} is missing")
            elif file_sha256(p) != digest:
                problems.append(f"{rel} changed since the stage finished (its SHA-256 differs from the manifest's)")
        return problems

    def stages(self) -> Iterator[StageStatus]:
        for s in STAGE_FOLDERS:
            yield self.status(s)

    # writing -----------------------------------------------------------------------------
    def check_writable(self) -> None:
        """WorkspaceError unless a file can be created in ``WS/.work`` (checked before a stage
        starts, so that a long run cannot end in an unwritable folder)."""
        check_workspace_path(self.root)
        try:
            _probe_write(self.root / ".work")
        except OSError as e:
            raise WorkspaceError(self.root, f"the workspace is not writable ({e.strerror or e}); check its permissions "
                                            "or choose another folder") from None

    def needs_recovery(self, stage: str) -> bool:
        """Whether :meth:`recover` has something to do for ``stage`` (read-only, no lock needed)."""
        final = self.stage_dir(stage)
        if (final / "RUN").is_file() or (self.work_dir(stage) / "manifest.json").is_file():
            return True
        return any((self.root / ".work").glob(f".old-{final.name}-*"))

    def recover(self, stage: str) -> bool:
        """Complete a promotion that was cut short: the work folder holds a finished run with its
        manifest (promote it), the promoted folder still holds the run's checkpoints and marker
        (remove them), or a previous output moved aside was left behind (put it back when the stage
        folder is missing, else remove it). Returns True when it promoted. The caller holds the lock."""
        work = self.work_dir(stage)
        final = self.stage_dir(stage)
        if (final / "RUN").is_file() and self.manifest(stage) is not None:
            # promoted, but the clean-up after it was cut short
            shutil.rmtree(final / "checkpoints", ignore_errors=True)
            for marker in _MARKERS:
                (final / marker).unlink(missing_ok=True)
        m_path = work / "manifest.json"
        m = None
        if m_path.is_file():
            try:
                m = read_json(m_path)
            except (OSError, ValueError):
                m = None
            if not isinstance(m, dict) or m.get("status") != "complete":
                m_path.unlink(missing_ok=True)
                m = None
        promoted = False
        if m is not None:
            _promote(self, stage, work, keep_checkpoints=False)
            promoted = True
        # previous outputs moved aside by a promotion that was cut short
        trash = sorted((self.root / ".work").glob(f".old-{final.name}-*"), key=lambda p: p.stat().st_mtime)
        if trash and not final.exists():
            os.replace(trash.pop(), final)
        for t in trash:
            shutil.rmtree(t, ignore_errors=True)
        return promoted


def running_process(work_dir: Path) -> str | None:
    """``pid N on HOST since T`` when the ``RUNNING`` marker of a work folder names a live process
    of this host (or another host, which cannot be checked from here), else None."""
    p = work_dir / "RUNNING"
    try:
        info = read_json(p)
        pid, host, since = int(info["pid"]), str(info["host"]), str(info["since"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if host == socket.gethostname():
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
    return f"pid {pid} on {host} since {since}"


def check_workspace_path(root: Path) -> None:
    """WorkspaceError when ``root`` exists and is not a folder, or lies under a file."""
    if root.exists() and not root.is_dir():
        raise WorkspaceError(root, "is a file, not a workspace folder; choose a folder path")
    for anc in root.parents:
        if anc.exists():
            if not anc.is_dir():
                raise WorkspaceError(root, f"cannot be created: {anc} is a file, not a folder")
            break


def _probe_write(folder: Path) -> None:
    """Create ``folder`` and a file in it, then remove the file (OSError when not writable)."""
    folder.mkdir(parents=True, exist_ok=True)
    probe = folder / f".write-probe-{os.getpid()}"
    with open(probe, "wb") as fh:
        fh.write(b"ok")
    probe.unlink()


def _inventory(folder: Path) -> dict[str, int]:
    """{relative path: size} of every output file of a finished work folder (checkpoints and run
    markers excluded)."""
    out: dict[str, int] = {}
    for f in sorted(folder.rglob("*")):
        rel = f.relative_to(folder)
        if not f.is_file() or rel.parts[0] == "checkpoints" or str(rel) in _RUN_FILES:
            continue
        out[rel.as_posix()] = f.stat().st_size
    return out


def _promote(ws: Workspace, stage: str, work: Path, keep_checkpoints: bool) -> None:
    """Rename ``work`` (which already holds its manifest) into the stage folder, then clean up.

    The previous output is moved aside first and put back if the rename fails; checkpoints and run
    markers are removed only once the new output is in place.
    """
    final = ws.stage_dir(stage)
    trash = ws.root / ".work" / f".old-{final.name}-{os.getpid()}"
    if trash.exists():
        shutil.rmtree(trash)
    moved = False
    try:
        if final.exists():
            os.replace(final, trash)
            moved = True
        os.replace(work, final)
    except OSError as e:
        if moved and not final.exists():
            os.replace(trash, final)
        raise WorkspaceError(final, f"cannot move the finished run into place ({e.strerror or e}); it is kept in "
                                    f"{work} and the next run of this stage completes the move") from None
    if not keep_checkpoints:
        shutil.rmtree(final / "checkpoints", ignore_errors=True)
    for marker in _MARKERS:
        (final / marker).unlink(missing_ok=True)
    if trash.exists():
        shutil.rmtree(trash, ignore_errors=True)


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
        """Write the manifest into ``work_dir``, promote it to the stage folder, then remove the
        checkpoints and run markers. Returns the manifest.

        An interruption at any point leaves either the finished run in the work folder (the next
        run promotes it, :meth:`Workspace.recover`) or the promoted folder with its manifest."""
        (self.work_dir / "RUNNING").unlink(missing_ok=True)
        files = _inventory(self.work_dir)
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
            "outputs": {k: self._relative(v) for k, v in self.outputs.items()},
            "files": files,
            "hashes": {rel: file_sha256(self.work_dir / rel) for rel in files},
        }
        atomic_write_json(self.work_dir / "manifest.json", manifest)
        _promote(self.ws, self.stage, self.work_dir, keep_checkpoints)
        return manifest

    def _relative(self, path: str) -> str:
        """An output path as written into the manifest: relative to the workspace root (POSIX) when
        it lies in the workspace or the run's work folder, so that a copied or moved workspace
        still finds it; other paths (and empty ones) as given."""
        if not path:
            return path
        p = Path(path)
        for base, to in ((self.work_dir, self.ws.stage_dir(self.stage)), (self.ws.root, self.ws.root)):
            try:
                return (to / p.relative_to(base)).relative_to(self.ws.root).as_posix()
            except ValueError:
                continue
        return path

    def fail(self, message: str) -> None:
        """Mark the work folder as failed (its checkpoints stay for a resume)."""
        if self.work_dir.exists():
            atomic_write_text(self.work_dir / "FAILED", message + "\n")
            (self.work_dir / "RUNNING").unlink(missing_ok=True)

    def interrupted(self) -> None:
        """The run was stopped (Ctrl-C, SIGTERM): the work folder stays, marked neither running
        nor failed, so the stage reads as interrupted and resumes from its newest checkpoint."""
        (self.work_dir / "RUNNING").unlink(missing_ok=True)


def _stage_fingerprint(
    ws: Workspace, stage: str, config_hash: str, requires: list[str], external_inputs: dict[str, str] | None
) -> tuple[dict[str, Any], str]:
    """The run's inputs (upstream fingerprints, external files) and its fingerprint; StageError when
    an upstream stage is not complete and fresh."""
    inputs: dict[str, Any] = {"stages": {}, "files": dict(external_inputs or {})}
    for up in requires:
        inputs["stages"][up] = ws.require(up, stage)["fingerprint"]
    fp = hashlib.sha256(json.dumps({"config": config_hash, "inputs": inputs}, sort_keys=True).encode()).hexdigest()[:16]
    return inputs, fp


def _complete_as(ws: Workspace, stage: str, fingerprint: str, seed: int) -> bool:
    m = ws.manifest(stage)
    return (m is not None and m.get("status") == "complete" and m.get("fingerprint") == fingerprint and m.get("seed") == seed
            and not ws.missing_outputs(stage, m))


def stage_up_to_date(
    ws: Workspace,
    stage: str,
    config_hash: str,
    *,
    requires: list[str] = (),  # type: ignore[assignment]
    external_inputs: dict[str, str] | None = None,
    seed: int = 0,
) -> bool:
    """Whether ``stage`` already completed with this config, these inputs and this seed, read without
    the workspace lock: manifests and stage folders are only ever replaced whole (atomic renames),
    so a reader sees the old or the new state of a stage, never a mix. A stage that is up to date
    can be reported as skipped while another process holds the lock to run a different stage
    (e.g. phase 1 training while a second process asks for ingest). False when anything is
    missing, stale or unreadable, or when an interrupted promotion is left to recover;
    :func:`begin_stage` under the lock then decides."""
    if not ws.root.is_dir() or ws.needs_recovery(stage):
        return False
    try:
        _, fp = _stage_fingerprint(ws, stage, config_hash, requires, external_inputs)
        return _complete_as(ws, stage, fp, seed)
    except (StageError, OSError, ValueError):
        return False


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
    ws.recover(stage)
    inputs, fp = _stage_fingerprint(ws, stage, config_hash, requires, external_inputs)
    run_id = {"config_hash": config_hash, "inputs": inputs, "seed": seed}
    if not force and _complete_as(ws, stage, fp, seed):
        return None
    ws.check_writable()
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
    atomic_write_json(work / "RUNNING", {"pid": os.getpid(), "host": socket.gethostname(), "since": now_iso()})
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
    """Save a versioned checkpoint atomically as ``ckpt_{step:08d}.pt``; keep the newest ``keep``.

    ``state`` maps names to state dicts / tensors / plain data (parameters, optimizers,
    schedulers, RNG states, …): anything :func:`sage_core.serialization.encode` takes. The file is a
    safetensors file (despite its historical ``.pt`` name) holding ``{"format": CHECKPOINT_FORMAT,
    "version", "step", "state"}``; loading it cannot run code.
    """
    from .serialization import save_file

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    path = d / f"ckpt_{int(step):08d}.pt"
    blob = {"format": CHECKPOINT_FORMAT, "version": __version__, "step": int(step), "state": state}
    save_file(path, blob, CHECKPOINT_KIND, CHECKPOINT_FORMAT)
    ckpts = sorted(d.glob("ckpt_*.pt"))
    for old in ckpts[:-keep] if keep > 0 else []:
        old.unlink(missing_ok=True)
    return path


def latest_checkpoint(directory: str | Path) -> Path | None:
    """Newest usable ``ckpt_*.pt`` in a folder, or None.

    A damaged or truncated newest checkpoint (bad header, wrong size, checksum mismatch) is skipped
    for the one before it, with a warning on the ``sage`` logger. An old pickle checkpoint is
    returned as it is, so that :func:`load_checkpoint` refuses it with a clear message.
    """
    from .serialization import inspect_file, verify_file

    d = Path(directory)
    if not d.is_dir():
        return None
    ckpts = sorted(d.glob("ckpt_*.pt"), reverse=True)
    for i, ck in enumerate(ckpts):
        chk = inspect_file(ck)
        if chk.status == "pickle":
            return ck
        problem = chk.reason if chk.status != "ok" else (None if chk.kind == CHECKPOINT_KIND else f"not a checkpoint ({chk.kind!r})")
        if problem is None:
            problem = verify_file(ck)
        if problem is None:
            return ck
        nxt = ckpts[i + 1].name if i + 1 < len(ckpts) else None
        log.warning("checkpoint %s is damaged (%s); %s", ck, problem,
                    f"resuming from {nxt} instead" if nxt else "no earlier checkpoint: starting from the beginning")
    return None


def load_checkpoint(path: str | Path, map_location: Any = "cpu") -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint`; StageError on a damaged, foreign,
    newer or old pickle file (the latter is not loaded: nothing in it runs)."""
    from .serialization import load_file

    p = Path(path)
    try:
        data, _ = load_file(p, CHECKPOINT_KIND, CHECKPOINT_FORMAT, "checkpoint", map_location=map_location)
    except UnsafeFileError as e:
        raise StageError(f"{p}: {e.problem} (or start the stage over with --force)") from None
    except InputError as e:
        raise StageError(f"{p}: {e.problem}") from None
    if not isinstance(data, dict) or "format" not in data or "state" not in data:
        raise StageError(f"{p}: not a sage checkpoint")
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
