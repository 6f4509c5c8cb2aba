"""Imports in ``sage_core`` run down the layers of the design (DEVELOPERS.md, "Layers"): the CLI over
the stages over train / export / evaluate over the avatar over render, fields and flame over
geometry, with a few small foundation modules (errors, atomic writes, image metrics, …) at the
bottom. A package imports only from a lower layer or from itself: never from a higher layer, and
never sideways from another package of its own layer. The check reads every module's imports with
``ast`` (including the ones inside functions and under ``TYPE_CHECKING``); the engine never imports
the CLI."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "sage_core"

LAYERS: list[tuple[str, ...]] = [
    # foundation: no sage_core imports besides each other's lower rows
    ("errors", "atomic", "_version"),
    ("config", "native_build", "npz", "serialization", "pip_fetch"),
    ("image_metrics",),  # its SSIM blur is a native extension
    ("workspace",),
    ("geometry",),
    ("flame",),
    ("data",),
    ("render", "fields"),
    ("avatar", "runtime"),
    ("train", "export", "evaluate", "track"),
    ("stages",),
    ("batch", "api"),
    ("__init__",),  # the flat API names of ``import sage_core as sage``
]
"""Units of sage_core (subpackages and top-level modules), lowest layer first."""

ALLOWED: dict[tuple[str, str], str] = {}
"""(importing module, imported module) pairs that cross the layers, each with its reason (none today)."""


def _level(unit: str) -> int:
    for i, row in enumerate(LAYERS):
        if unit in row:
            return i
    raise AssertionError(f"sage_core.{unit} is in no layer of tests/test_layers.py: add it to LAYERS")


def _unit(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _module_name(path: Path, package: Path = PACKAGE) -> tuple[str, str]:
    """(dotted module name, dotted package that relative imports resolve against)."""
    rel = path.relative_to(package.parent).with_suffix("")
    name = ".".join(rel.parts)
    if name.endswith(".__init__"):
        name = name[: -len(".__init__")]
        return name, name
    return name, name.rsplit(".", 1)[0]


def _is_type_checking(node: ast.AST) -> bool:
    """Whether ``node`` is an ``if TYPE_CHECKING:`` block (imports for annotations only)."""
    if not isinstance(node, ast.If):
        return False
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _nodes(tree: ast.AST, runtime_only: bool) -> list[ast.AST]:
    """Every node of ``tree``; with ``runtime_only`` not those inside ``if TYPE_CHECKING:``."""
    out: list[ast.AST] = []
    todo = [tree]
    while todo:
        node = todo.pop()
        out.append(node)
        if runtime_only and _is_type_checking(node):
            todo.extend(node.orelse)  # type: ignore[attr-defined]
            continue
        todo.extend(ast.iter_child_nodes(node))
    return out


def _imports(path: Path, root: Path = PACKAGE, runtime_only: bool = False) -> list[tuple[str, int]]:
    """(imported sage_core / sage_cli module or name, line) of every import statement in ``path``
    (``runtime_only``: leaving out the imports under ``if TYPE_CHECKING:``)."""
    _, package = _module_name(path, root)
    out: list[tuple[str, int]] = []
    for node in _nodes(ast.parse(path.read_text(encoding="utf-8"), str(path)), runtime_only):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            if node.module is None:  # from . import x: x is a submodule or a name of the package
                out += [(f"{module}.{a.name}", node.lineno) for a in node.names]
            else:
                out.append((module, node.lineno))
    return sorted(((m, line) for m, line in out if m.split(".")[0] in ("sage_core", "sage_cli")), key=lambda ml: ml[1])


def _violations(root: Path = PACKAGE) -> list[str]:
    """One line per import of a module under ``root`` (a ``sage_core`` folder) against the layers."""
    bad: list[str] = []
    for path in sorted(root.rglob("*.py")):
        name, _ = _module_name(path, root)
        unit = _unit(name)
        for target, line in _imports(path, root):
            where = f"{path.relative_to(root.parent)}:{line}: {name} imports {target}"
            if target.startswith("sage_cli"):
                bad.append(f"{where} (the engine never imports the CLI)")
                continue
            other = _unit(target)
            if other == unit or (name, target) in ALLOWED:
                continue
            lo, hi = _level(other), _level(unit)
            if lo > hi:
                bad.append(f"{where} (a higher layer)")
            elif lo == hi:
                bad.append(f"{where} (sideways, within layer {LAYERS[hi]})")
    return bad


def test_sage_core_imports_only_go_down_the_layers() -> None:
    bad = _violations()
    assert not bad, "imports against the layers of DEVELOPERS.md:\n" + "\n".join(bad)


def _import_circles(root: Path = PACKAGE) -> list[list[str]]:
    """Circles of runtime imports between the modules under ``root`` (also imports made inside
    functions; not those under ``TYPE_CHECKING``, nor the allow-list)."""
    mods = {_module_name(p, root)[0]: p for p in root.rglob("*.py")}
    graph: dict[str, set[str]] = {name: set() for name in mods}
    for name, path in mods.items():
        for target, _ in _imports(path, root, runtime_only=True):
            if not target.startswith("sage_core") or (name, target) in ALLOWED:
                continue
            while target not in mods and "." in target:  # a name imported from a module
                target = target.rsplit(".", 1)[0]
            if target != name:
                graph[name].add(target)
    # Tarjan's strongly connected components, iteratively
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    circles.append(sorted(comp))
    return circles


def test_no_import_circle() -> None:
    circles = _import_circles()
    assert not circles, f"modules that import each other (move the shared piece down): {circles}"


def test_allowed_crossings_still_exist() -> None:
    """Every allow-list entry names an import that is really there (a stale entry is removed)."""
    found = {(_module_name(p)[0], t) for p in PACKAGE.rglob("*.py") for t, _ in _imports(p)}
    stale = sorted(set(ALLOWED) - found)
    assert not stale, f"allow-list entries without such an import: {stale}"


def test_checker_reports_backward_sideways_and_cli_imports(tmp_path: Path) -> None:
    """On a small package of the same shape, each kind of bad import is reported and good ones are not."""
    root = tmp_path / "sage_core"
    (root / "train").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / "train" / "__init__.py").write_text("from .losses import x\n")
    (root / "train" / "losses.py").write_text(
        "from ..image_metrics import ssim\n"
        "from ..geometry import rigid\n"
        "def f():\n"
        "    from ..stages.avatars import load_stage_avatar\n"
        "    from ..evaluate import metrics\n"
        "    import sage_cli.app\n"
    )
    (root / "geometry").mkdir()
    (root / "geometry" / "rigid.py").write_text("from .. import avatar\n")
    bad = _violations(root)
    assert len(bad) == 4, bad
    text = "\n".join(bad)
    assert "losses.py:4: sage_core.train.losses imports sage_core.stages.avatars (a higher layer)" in text
    assert "losses.py:5: sage_core.train.losses imports sage_core.evaluate (sideways" in text
    assert "losses.py:6: sage_core.train.losses imports sage_cli.app (the engine never imports the CLI)" in text
    assert "rigid.py:1: sage_core.geometry.rigid imports sage_core.avatar (a higher layer)" in text
    assert _import_circles(root) == []
    (root / "train" / "helpers.py").write_text("from .losses import f\n")
    (root / "train" / "losses.py").write_text((root / "train" / "losses.py").read_text() + "    from .helpers import g\n")
    assert _import_circles(root) == [["sage_core.train.helpers", "sage_core.train.losses"]]


def test_the_version_has_one_source_below_every_module() -> None:
    """``sage_core._version`` holds the version that ``pyproject.toml`` declares; the package root
    only re-exports it, so reading the version imports nothing of the flat API."""
    import re
    import subprocess
    import sys

    from sage_core import __version__
    from sage_core._version import __version__ as version

    declared = re.search(r'^version = "([^"]+)"', (PACKAGE.parent / "pyproject.toml").read_text(encoding="utf-8"), re.M)
    assert declared and version == declared.group(1) == __version__
    code = "import sys, sage_core.workspace; print(sorted(m for m in sys.modules if m.startswith('sage_core.') and m.count('.') == 1))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=PACKAGE.parent).stdout
    assert "sage_core.api" not in out and "sage_core.stages" not in out, out


def test_every_native_extension_follows_the_loader_layout() -> None:
    """Each native extension is built from ``csrc/<stem>.cpp`` beside its loader and registers
    ``torch.ops.sage_<stem>`` (:func:`sage_core.native_build.native_extension`), and every C++ source
    has a loader."""
    import importlib

    from sage_core.native_build import NativeExtension

    loaders = {"sage_core.image_metrics": "BLUR_EXT", "sage_core.fields._cpp_eigh": "EXT", "sage_core.fields._cpp_hashgrid": "EXT",
               "sage_core.fields._cpp_sdf": "EXT", "sage_core.render._cpp_surfels": "EXT"}  # fmt: skip
    sources = set()
    for module, attr in loaders.items():
        ext = getattr(importlib.import_module(module), attr)
        assert isinstance(ext, NativeExtension) and ext.source.is_file(), module
        assert ext.name == ext.namespace == f"sage_{ext.source.stem}" and ext.source.parent.name == "csrc", module
        sources.add(ext.source.resolve())
    assert sources == {p.resolve() for p in PACKAGE.rglob("csrc/*.cpp")}
