"""Results without the paths of the machine that produced them.

The suite records where it wrote things (logs, workspaces, metrics files), the commands it ran and
the errors it met, all with absolute paths of its ``--out`` folder and of the LPIPS weights. The
documents in ``docs/`` must read the same on any machine, so before they are written:

* a path field (:data:`PATH_KEYS`) under ``--out`` becomes relative to it (``logs/sage__phase1.log``);
* in every other string (commands, errors) the ``--out`` folder is written ``OUT``
  (``sage eval OUT/ws/sage ...``), a named file (the LPIPS weights) by its file name, and any
  other absolute path by its last component.

The functions are pure; :func:`portable_doc` returns a new document.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Iterable

OUT = "OUT"
"""What commands and errors call the suite's ``--out`` folder."""

PATH_KEYS: frozenset[str] = frozenset({"log", "metrics", "workspace", "motion", "out"})
"""Keys whose string values are paths (written relative to ``--out``)."""

_ABS = re.compile(r"(?<![\w.~/-])/(?!/)[^\s'\"=:;,()\[\]{}|]+")
"""An absolute path inside a string: from a ``/`` not preceded by a name character or a slash (nor
followed by one: ``https://``), up to a space, a quote or a separator that cannot be part of a path
on the command lines the suite writes."""


def _under(path: str, root: str) -> str | None:
    """``path`` relative to ``root`` ('' for the root itself), or None when it is not under it."""
    root = root.rstrip("/")
    if path == root:
        return ""
    if path.startswith(root + "/"):
        return path[len(root) + 1 :]
    return None


def portable_text(text: str, outs: Iterable[str | Path] = (), named: Iterable[str | Path] = ()) -> str:
    """``text`` with its absolute paths made portable: under one of ``outs`` -> ``OUT/<relative>``,
    one of ``named`` (or under it) -> its file name, any other -> its last component."""
    roots = sorted((str(o).rstrip("/") for o in outs), key=len, reverse=True)
    names = {str(n).rstrip("/"): Path(n).name for n in named}

    def one(m: re.Match[str]) -> str:
        p = m.group(0)
        trail = "/" if p.endswith("/") and len(p) > 1 else ""
        core = p.rstrip("/") or "/"
        for n, name in names.items():
            rel = _under(core, n)
            if rel is not None:
                return (name + ("/" + rel if rel else "")) + trail
        for r in roots:
            rel = _under(core, r)
            if rel is not None:
                return (OUT + ("/" + rel if rel else "")) + trail
        return Path(core).name + trail

    return _ABS.sub(one, text)


def portable_path(path: str | Path, out: str | Path, named: Iterable[str | Path] = ()) -> str:
    """A path field: relative to ``out`` when under it (``.`` for ``out`` itself), else as
    :func:`portable_text` writes it."""
    p = str(path)
    rel = _under(p.rstrip("/"), str(out))
    if rel is not None:
        return rel or "."
    return portable_text(p, (out,), named)


def portable_doc(doc: Any, outs: Iterable[str | Path], named: Iterable[str | Path] = (), primary: str | Path | None = None) -> Any:
    """A copy of a JSON document with every string portable: the values of :data:`PATH_KEYS`
    relative to ``primary`` (the run's ``--out``; the first of ``outs`` when None), the other
    strings through :func:`portable_text`. ``outs``: every ``--out`` folder the document's records
    come from."""
    outs = [str(o) for o in outs]
    named = [str(n) for n in named]
    base = str(primary) if primary is not None else (outs[0] if outs else "/")

    def path_value(v: str) -> str:
        for o in sorted(outs, key=len, reverse=True):  # relative to the out folder it lies in
            if _under(v.rstrip("/"), o) is not None:
                return portable_path(v, o, named)
        return portable_path(v, base, named)

    def walk(x: Any, key: str | None = None) -> Any:
        if isinstance(x, dict):
            return {k: walk(v, k) for k, v in x.items()}
        if isinstance(x, list):
            return [walk(v, key) for v in x]
        if isinstance(x, str):
            if key in PATH_KEYS and x.startswith("/"):
                return path_value(x)
            return portable_text(x, outs, named)
        return x

    return walk(doc)
