"""The SUBJECTS list of ``sage batch``: a CSV file, a YAML file, or a folder of capture folders.

CSV: a header row, then one subject per row; lines starting with ``#`` are comments. YAML: a list
of mappings, or a mapping ``{subjects: [...], defaults: {...}}`` whose ``defaults`` apply to every
entry. Folder: every subfolder holding a ``transforms*.json`` is a capture, its name the id.

Fields (CSV columns / YAML keys): ``id`` and ``capture`` (required), ``regime``, ``timestep``,
``camera``, ``flame_model``, ``flame_masks`` and ``set`` (extra ``stage.key=value`` overrides for
this subject; ``;``-separated in CSV, a list or a ``;``-separated string in YAML). Relative paths
are relative to the SUBJECTS file's folder. Every problem raises ``InputError`` naming the file
and the row.
"""

from __future__ import annotations

import csv
import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..config import REGIMES, canonical_regime
from ..errors import InputError

FIELDS: tuple[str, ...] = ("id", "capture", "regime", "timestep", "camera", "flame_model", "flame_masks", "set")
_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass(frozen=True)
class Subject:
    """One subject of a batch: its capture and per-subject overrides (None = the batch default)."""

    id: str
    capture: Path
    regime: str | None = None
    timestep: int | None = None
    camera: int | None = None
    flame_model: Path | None = None
    flame_masks: Path | None = None
    sets: tuple[str, ...] = field(default_factory=tuple)


def load_subjects(path: str | Path) -> list[Subject]:
    """Read and validate a SUBJECTS CSV / YAML file or capture folder (InputError on any problem)."""
    p = Path(path)
    if p.is_dir():
        return _from_folder(p)
    if not p.is_file():
        raise InputError(p, "SUBJECTS file or folder not found")
    suffix = p.suffix.lower()
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(p, f"cannot read: {e}") from None
    if suffix == ".csv":
        rows = _csv_rows(p, text)
    elif suffix in (".yaml", ".yml"):
        rows = _yaml_rows(p, text)
    else:
        raise InputError(p, "SUBJECTS must be a .csv, .yaml / .yml file or a folder of captures")
    subjects = [_subject(p, where, row) for where, row in rows]
    if not subjects:
        raise InputError(p, "lists no subjects")
    _check_unique(p, [(where, s) for (where, _), s in zip(rows, subjects)])
    return subjects


def _from_folder(folder: Path) -> list[Subject]:
    subs = sorted(d for d in folder.iterdir() if d.is_dir() and not d.name.startswith(".") and any(d.glob("transforms*.json")))
    if not subs:
        raise InputError(folder, "no capture subfolders (folders holding transforms*.json)")
    out = []
    for d in subs:
        if not _ID_RE.match(d.name):
            raise InputError(d, "folder name is not usable as a subject id (letters, digits, '.', '_', '-')")
        out.append(Subject(id=d.name, capture=d.resolve()))
    return out


def _csv_rows(path: Path, text: str) -> list[tuple[str, dict[str, Any]]]:
    lines = [(i + 1, ln) for i, ln in enumerate(text.splitlines()) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(path, "empty CSV (expected a header row: id,capture,...)")
    reader = csv.reader(io.StringIO("\n".join(ln for _, ln in lines)))
    table = list(reader)
    header = [h.strip().lower() for h in table[0]]
    _check_keys(path, f"header (line {lines[0][0]})", header)
    if len(set(header)) != len(header):
        raise InputError(path, f"header (line {lines[0][0]}): repeated column")
    rows = []
    for (lineno, _), cells in zip(lines[1:], table[1:]):
        where = f"row at line {lineno}"
        if len(cells) != len(header):
            raise InputError(path, f"{where}: {len(cells)} cells, the header has {len(header)}")
        rows.append((where, {k: c.strip() for k, c in zip(header, cells) if c.strip() != ""}))
    return rows


def _no_alias_loader() -> type:
    """A YAML SafeLoader that refuses aliases (``*name``): a few lines of them can stand for
    billions of items (each alias repeating an anchored list of aliases), and a SUBJECTS list has
    no use for them."""
    import yaml

    class NoAliasLoader(yaml.SafeLoader):
        def compose_node(self, parent: Any, index: Any) -> Any:
            if self.check_event(yaml.events.AliasEvent):
                raise yaml.composer.ComposerError(None, None, "aliases (*name) are not accepted in a SUBJECTS file",
                                                  self.peek_event().start_mark)
            return super().compose_node(parent, index)

    return NoAliasLoader


def _yaml_rows(path: Path, text: str) -> list[tuple[str, dict[str, Any]]]:
    import yaml

    try:
        doc = yaml.load(text, Loader=_no_alias_loader())  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        raise InputError(path, f"invalid YAML: {e}") from None
    except RecursionError:
        raise InputError(path, "invalid YAML: nested too deeply") from None
    defaults: dict[str, Any] = {}
    if isinstance(doc, dict):
        extra = sorted(set(doc) - {"subjects", "defaults"})
        if extra or "subjects" not in doc:
            raise InputError(path, "expected a list of subjects or a mapping with 'subjects' (and optional 'defaults')")
        defaults = doc.get("defaults") or {}
        if not isinstance(defaults, dict):
            raise InputError(path, "'defaults' must be a mapping")
        _check_keys(path, "defaults", list(defaults))
        if {"id", "capture"} & set(defaults):
            raise InputError(path, "'defaults' cannot give 'id' or 'capture'")
        doc = doc["subjects"]
    if not isinstance(doc, list):
        raise InputError(path, "expected a list of subjects")
    rows = []
    for i, entry in enumerate(doc, start=1):
        where = f"entry {i}"
        if not isinstance(entry, dict):
            raise InputError(path, f"{where}: expected a mapping with id and capture")
        _check_keys(path, where, [str(k) for k in entry])
        rows.append((where, {**defaults, **{str(k): v for k, v in entry.items() if v is not None}}))
    return rows


def _check_keys(path: Path, where: str, keys: list[str]) -> None:
    unknown = [k for k in keys if k not in FIELDS]
    if unknown:
        raise InputError(path, f"{where}: unknown field(s) {', '.join(unknown)} (known: {', '.join(FIELDS)})")


def _subject(path: Path, where: str, row: dict[str, Any]) -> Subject:
    base = path.parent

    def fail(problem: str) -> InputError:
        return InputError(path, f"{where}: {problem}")

    for key, value in row.items():
        if key != "set" and isinstance(value, (list, tuple, dict, set)):
            raise fail(f"'{key}' must be a single value, not a {'mapping' if isinstance(value, dict) else 'list'}")
    for key in ("id", "capture"):
        if key not in row or str(row[key]).strip() == "":
            raise fail(f"'{key}' is missing")
    sid = str(row["id"]).strip()
    if not _ID_RE.match(sid):
        raise fail(f"id {sid!r} must start with a letter or digit and hold only letters, digits, '.', '_', '-'")

    def folder_or_file(key: str, want_dir: bool) -> Path | None:
        if key not in row:
            return None
        p = Path(str(row[key])).expanduser()
        p = (p if p.is_absolute() else base / p).resolve()
        ok = p.is_dir() if want_dir else p.is_file()
        if not ok:
            raise fail(f"{key} {p} {'is not a folder' if want_dir else 'is not a file'}")
        return p

    def integer(key: str) -> int | None:
        if key not in row:
            return None
        v = row[key]
        if isinstance(v, bool):
            raise fail(f"{key} must be an integer, got {v!r}")
        try:
            iv = int(str(v).strip())
        except ValueError:
            raise fail(f"{key} must be an integer, got {v!r}") from None
        if iv < 0:
            raise fail(f"{key} must be non-negative, got {iv}")
        return iv

    regime = row.get("regime")
    if regime is not None:
        regime = canonical_regime(str(regime))
        if regime not in REGIMES:
            raise fail(f"unknown regime {regime!r} (choose {', '.join(REGIMES)})")
    sets_raw = row.get("set", ())
    if isinstance(sets_raw, str):
        sets = tuple(s.strip() for s in sets_raw.split(";") if s.strip())
    elif isinstance(sets_raw, (list, tuple)):
        if not all(isinstance(s, str) for s in sets_raw):
            raise fail("'set' items must be strings stage.key=value (one per item, not nested lists or mappings)")
        sets = tuple(s.strip() for s in sets_raw if s.strip())
    else:
        raise fail("'set' must be a list or a ';'-separated string of stage.key=value")
    for s in sets:
        if "=" not in s or "." not in s.split("=", 1)[0]:
            raise fail(f"set {s!r}: expected stage.key=value")
    return Subject(
        id=sid,
        capture=folder_or_file("capture", True),  # type: ignore[arg-type]
        regime=regime,
        timestep=integer("timestep"),
        camera=integer("camera"),
        flame_model=folder_or_file("flame_model", False),
        flame_masks=folder_or_file("flame_masks", False),
        sets=sets,
    )


def _check_unique(path: Path, items: list[tuple[str, Subject]]) -> None:
    seen: dict[str, str] = {}
    for where, s in items:
        key = s.id.lower()
        if key in seen:
            raise InputError(path, f"{where}: id {s.id!r} repeats {seen[key]}")
        seen[key] = where
