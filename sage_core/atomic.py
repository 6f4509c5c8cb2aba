"""Atomic file writes: a temp file beside the target, flushed and fsynced, then ``os.replace``.

The one implementation every module uses (the workspace, captures, FLAME files, images, bundles).
A reader never sees a half-written file, a failed write leaves the previous file and no temp file,
and the new file gets the usual permissions (the process umask), not a temp file's 0600.
Only the standard library is imported.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO


def temp_path(path: Path) -> Path:
    """A hidden temp name in ``path``'s folder, unique per process and call (keeps the suffix, so
    writers that pick a format by extension still work)."""
    return path.with_name(f".{path.stem}.{os.getpid()}.{time.monotonic_ns()}.tmp{path.suffix}")


def named(e: OSError, target: Path, tmp: Path) -> OSError:
    """``e`` naming ``target`` (not the temp file, and not nothing, as a failed write or fsync on a
    full disk reports it)."""
    if e.filename is None or str(e.filename) == str(tmp):
        return type(e)(e.errno, e.strerror or str(e), str(target))
    return e


@contextmanager
def atomic_writer(path: str | Path) -> Iterator[IO[bytes]]:
    """``with atomic_writer(p) as fh: ...`` writes a binary stream that appears at ``p`` only when
    the block finishes without an exception."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(target)
    try:
        with open(tmp, "xb") as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except OSError as e:
        raise named(e, target, tmp) from None
    finally:
        if tmp.exists():
            tmp.unlink()


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """``with atomic_path(p) as tmp: writer(tmp)`` for writers that want a file name: whatever is
    written to ``tmp`` replaces ``p`` when the block finishes without an exception."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(target)
    try:
        yield tmp
        os.replace(tmp, target)
    except OSError as e:
        raise named(e, target, tmp) from None
    finally:
        if tmp.exists():
            tmp.unlink()


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_writer(path) as fh:
        fh.write(data)
    return Path(path)


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write UTF-8 text atomically; returns the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def replace_dir(tmp: str | Path, out: str | Path, tag: str) -> None:
    """Put the finished folder ``tmp`` in place of ``out`` (which may not exist): the old folder is moved
    aside under a hidden name with ``tag``, the new one renamed in, then the old one deleted, so ``out``
    is at every moment either the old folder or the new one, never a mix."""
    import shutil

    tmp, out = Path(tmp), Path(out)
    if not out.exists():
        tmp.rename(out)
        return
    old = out.with_name(f".{out.name}.{tag}-old")
    if old.exists():
        shutil.rmtree(old)
    out.rename(old)
    tmp.rename(out)
    shutil.rmtree(old)
