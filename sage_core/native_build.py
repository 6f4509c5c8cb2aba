"""Compile-on-first-use loading of the package's C++/OpenMP extensions (one implementation for all).

Each extension is one ``.cpp`` file registering its operators with ``TORCH_LIBRARY(namespace, m)``.
``NativeExtension.available()`` builds it with ``torch.utils.cpp_extension.load`` the first time it is
called (never at import) into ``$SAGE_CACHE_DIR`` or ``~/.cache/sage``, under
``torch_extensions/torch<version>/<name>_<hash>/``. The hash covers the source, the build flags and
the torch version, so different versions never share a build folder; an ``fcntl`` lock (released by
the OS if its holder dies) serializes concurrent builds of the same extension. When no compiler or
``ninja`` is found, or the build fails, ``available()`` returns ``(False, reason)`` and the caller
falls back to its pure-torch path (warning once, see ``warn_unavailable``).
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import threading
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import torch

CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math")
LDFLAGS = ("-fopenmp",)


def cache_dir() -> Path:
    """Folder holding the compiled extensions (one sub-folder per name/source/flags/torch hash)."""
    root = os.environ.get("SAGE_CACHE_DIR")
    base = Path(root) if root else Path.home() / ".cache" / "sage"
    return base / "torch_extensions" / f"torch{torch.__version__.replace('+', '_')}"


@contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """Exclusive ``fcntl`` lock on ``path`` (created with its parents if missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def ninja_on_path() -> str | None:
    """Make sure a ``ninja`` executable is on PATH (the PyPI package's when the system has none).

    Returns None when one is found, else the reason it is missing.
    """
    if shutil.which("ninja"):
        return None
    try:
        import ninja  # type: ignore[import-not-found]
    except ImportError:
        return "no 'ninja' executable on PATH and the 'ninja' Python package is not installed"
    os.environ["PATH"] = ninja.BIN_DIR + os.pathsep + os.environ.get("PATH", "")
    return None if shutil.which("ninja") else f"'ninja' not found (looked on PATH and in {ninja.BIN_DIR})"


@dataclass
class NativeExtension:
    """One C++ source file built into a shared library of ``torch.ops.<namespace>`` operators.

    Args:
        name: library name prefix (the build hash is appended).
        source: path of the ``.cpp`` file.
        namespace: its ``TORCH_LIBRARY`` namespace.
        probe_op: an operator of that namespace whose presence means the library is loaded.
        what, fallback: what the extension provides and what replaces it without a build (for the
            one warning, e.g. "rasterizer" and "pure-torch backend for rendering").
        cflags, ldflags: compiler and linker flags (part of the build hash).

    ``state`` remembers the load result for the process ({"ok": bool, "reason": str} once a load was
    attempted) and ``warned`` whether the fallback warning was given; tests may replace both.
    """

    name: str
    source: Path
    namespace: str
    probe_op: str
    what: str = "extension"
    fallback: str = "pure-torch code"
    cflags: tuple[str, ...] = CFLAGS
    ldflags: tuple[str, ...] = LDFLAGS
    state: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)
    warned: bool = field(default=False, init=False, repr=False, compare=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)

    def build_key(self) -> str:
        """16 hex digits of sha256(source, flags, torch version)."""
        h = hashlib.sha256()
        h.update(self.source.read_bytes())
        h.update(" ".join(self.cflags + self.ldflags).encode())
        h.update(torch.__version__.encode())
        return h.hexdigest()[:16]

    def loaded(self) -> bool:
        """True when the operators are registered in this process."""
        return hasattr(torch.ops, self.namespace) and hasattr(getattr(torch.ops, self.namespace), self.probe_op)

    def load(self) -> tuple[bool, str]:
        """Load the cached build or compile it now: (True, library path) or (False, reason)."""
        if self.loaded():
            return True, "loaded"
        if not self.source.is_file():
            return False, f"the extension source {self.source} is missing from the installed package"
        name = f"{self.name}_{self.build_key()}"
        build = cache_dir() / name
        lib = build / f"{name}.so"
        try:
            with file_lock(cache_dir() / f"{name}.lock"):
                if lib.is_file():
                    try:
                        torch.ops.load_library(str(lib))
                        return True, f"loaded {lib}"
                    except OSError:  # a damaged cached library (e.g. an interrupted link): build it again
                        lib.unlink()
                if not lib.is_file():
                    cxx = os.environ.get("CXX", "c++")
                    if shutil.which(cxx) is None:
                        return False, f"no C++ compiler ('{cxx}') on PATH"
                    why = ninja_on_path()
                    if why:
                        return False, why
                    from torch.utils.cpp_extension import load

                    build.mkdir(parents=True, exist_ok=True)
                    stale = build / "lock"  # torch's own build baton; a crashed build may have left it
                    if stale.exists():
                        stale.unlink()
                    load(
                        name=name,
                        sources=[str(self.source)],
                        extra_cflags=list(self.cflags),
                        extra_ldflags=list(self.ldflags),
                        build_directory=str(build),
                        is_python_module=False,
                        verbose=False,
                    )
        except Exception as exc:  # compiler errors, missing headers, unwritable cache: report, fall back
            lines = str(exc).strip().splitlines()
            errors = [ln.strip() for ln in lines if "error" in ln.lower()]
            detail = errors[0] if errors else (lines[-1] if lines else type(exc).__name__)
            return False, f"building the C++ extension in {build} failed: {detail}"
        return True, f"loaded {lib}"

    def available(self) -> tuple[bool, str]:
        """``load()`` once per process, remembered in ``state``: (True, where from) or (False, reason)."""
        with self._lock:
            if "ok" not in self.state:
                ok, reason = self.load()
                self.state["ok"], self.state["reason"] = ok, reason
            return bool(self.state["ok"]), str(self.state["reason"])

    def ops(self, caller: str) -> Any:
        """The ``torch.ops`` namespace; raises RuntimeError naming ``caller`` when it is unavailable."""
        ok, reason = self.available()
        if not ok:
            raise RuntimeError(f"{caller}: {reason}")
        return getattr(torch.ops, self.namespace)

    def warn_unavailable_once(self, reason: str) -> None:
        """One ``warnings.warn`` per process that ``fallback`` runs because the extension does not."""
        if not self.warned:
            self.warned = True
            warn_unavailable(self.what, self.fallback, reason, stacklevel=4)

    def choose(self, requested: str, caller: str) -> str:
        """``cpp`` or ``auto`` on CPU tensors -> the backend that runs.

        ``auto`` gives ``cpp`` when the extension loads, else warns once and gives ``torch``; an
        explicit ``cpp`` that cannot load raises ValueError naming ``caller`` and the reason.
        """
        ok, reason = self.available()
        if ok:
            return "cpp"
        if requested == "cpp":
            raise ValueError(f"{caller}: backend='cpp' is unavailable: {reason}")
        self.warn_unavailable_once(reason)
        return "torch"


def native_extension(module_file: str | Path, stem: str, *, probe_op: str, what: str, fallback: str) -> NativeExtension:
    """The extension of ``csrc/<stem>.cpp`` beside the module ``module_file`` (its ``__file__``), named
    and registered as ``torch.ops.sage_<stem>``: the layout every extension of the package follows.
    probe_op, what, fallback: see :class:`NativeExtension`. A loader module then reads

    ``EXT = native_extension(__file__, "blur_cpu", probe_op=..., what=..., fallback=...)`` and uses
    ``EXT.available()``, ``EXT.ops(caller)`` and ``EXT.warn_unavailable_once(reason)``."""
    name = f"sage_{stem}"
    return NativeExtension(name=name, source=Path(module_file).parent / "csrc" / f"{stem}.cpp", namespace=name, probe_op=probe_op,
                           what=what, fallback=fallback)  # fmt: skip


def warn_unavailable(what: str, fallback: str, reason: str, stacklevel: int = 3) -> None:
    """The warning a caller gives (once) when it falls back from a native ``what`` to ``fallback``."""
    warnings.warn(
        f"sage: the native CPU {what} is unavailable ({reason}); using the slower {fallback}. "
        "Install a C++ compiler (g++) and ninja to enable it.",
        RuntimeWarning,
        stacklevel=stacklevel + 1,
    )
