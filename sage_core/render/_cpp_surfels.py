"""Native CPU compositing (C++/OpenMP): the ``backend="cpp"`` path of ``rasterize_surfels``.

The projection (splat matrix, low-pass centre, culling, candidate boxes) stays in torch and is shared
with the packed backend; this module replaces the compositing of one camera with the extension in
``csrc/surfels_cpu.cpp`` (16×16 tile binning, a forward per tile and an exact backward that walks
each pixel's contributors back to front). The rules are the packed backend's; see that file's header.

The extension is compiled by ``torch.utils.cpp_extension.load`` on first use, never at import, into
``$SAGE_CACHE_DIR`` or ``~/.cache/sage/torch_extensions/<torch version>/``. Its name carries a hash
of the source, the build flags and the torch version, so different versions never share a build
folder, and an ``fcntl`` lock (released by the OS if its holder dies) serializes concurrent builds.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import threading
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch

from ._packed import PackedImages

_SOURCE = Path(__file__).parent / "csrc" / "surfels_cpu.cpp"
_CFLAGS = ["-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math"]
_LDFLAGS = ["-fopenmp"]
_NAMESPACE = "sage_surfels_cpu"

_lock = threading.Lock()
_state: dict[str, object] = {}  # "ok": bool, "reason": str once a load was attempted
_warned = False


def _build_key() -> str:
    h = hashlib.sha256()
    h.update(_SOURCE.read_bytes())
    h.update(" ".join(_CFLAGS + _LDFLAGS).encode())
    h.update(torch.__version__.encode())
    return h.hexdigest()[:16]


def cache_dir() -> Path:
    """Folder holding the compiled extension (one sub-folder per source/flags/torch hash)."""
    root = os.environ.get("SAGE_CACHE_DIR")
    base = Path(root) if root else Path.home() / ".cache" / "sage"
    return base / "torch_extensions" / f"torch{torch.__version__.replace('+', '_')}"


@contextmanager
def _file_lock(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


def _ninja_on_path() -> str | None:
    """Make sure a ``ninja`` executable is on PATH (the PyPI package's when the system has none)."""
    if shutil.which("ninja"):
        return None
    try:
        import ninja  # type: ignore[import-not-found]
    except ImportError:
        return "no 'ninja' executable on PATH and the 'ninja' Python package is not installed"
    os.environ["PATH"] = ninja.BIN_DIR + os.pathsep + os.environ.get("PATH", "")
    return None if shutil.which("ninja") else f"'ninja' not found (looked on PATH and in {ninja.BIN_DIR})"


def _load() -> tuple[bool, str]:
    if hasattr(torch.ops, _NAMESPACE) and hasattr(getattr(torch.ops, _NAMESPACE), "forward"):
        return True, "loaded"
    if not _SOURCE.is_file():
        return False, f"the extension source {_SOURCE} is missing from the installed package"
    name = f"sage_surfels_cpu_{_build_key()}"
    build = cache_dir() / name
    lib = build / f"{name}.so"
    try:
        with _file_lock(cache_dir() / f"{name}.lock"):
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
                why = _ninja_on_path()
                if why:
                    return False, why
                from torch.utils.cpp_extension import load

                build.mkdir(parents=True, exist_ok=True)
                stale = build / "lock"  # torch's own build baton; a crashed build may have left it
                if stale.exists():
                    stale.unlink()
                load(
                    name=name,
                    sources=[str(_SOURCE)],
                    extra_cflags=_CFLAGS,
                    extra_ldflags=_LDFLAGS,
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


def available() -> tuple[bool, str]:
    """(True, where it was loaded from) once the extension is built and loaded, else (False, reason).

    The first call compiles the extension (10–40 s on 2 cores) unless a cached build exists; the
    result is remembered for the process.
    """
    with _lock:
        if "ok" not in _state:
            ok, reason = _load()
            _state["ok"], _state["reason"] = ok, reason
        return bool(_state["ok"]), str(_state["reason"])


def warn_unavailable_once(reason: str) -> None:
    """One ``warnings.warn`` per process that the torch backend is used because the extension is not."""
    global _warned
    if not _warned:
        _warned = True
        warnings.warn(
            f"sage: the native CPU rasterizer is unavailable ({reason}); rendering with the slower pure-torch "
            "backend. Install a C++ compiler (g++) and ninja to enable it.",
            RuntimeWarning,
            stacklevel=3,
        )


def _ops():  # noqa: ANN202 - a torch.ops namespace
    ok, reason = available()
    if not ok:
        raise RuntimeError(f"rasterize_surfels(backend='cpp'): {reason}")
    return getattr(torch.ops, _NAMESPACE)


def bin_tiles(boxes: torch.Tensor, width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-tile surfel lists: offsets (num_tiles + 1,) int64 and list (L,) int32, ascending in each tile.

    boxes: (Nv, 4) int64 pixel boxes (x0, y0, x1, y1), max exclusive; empty boxes are skipped.
    """
    offsets, lst = _ops().bin_tiles(boxes.contiguous(), int(width), int(height))
    return offsets, lst


class _CppComposite(torch.autograd.Function):
    """Forward/backward of the extension as one autograd node.

    table: (12, Nv), payload: (P, Nv), boxes: (Nv, 4). Returns pay_img (HW, P) Σ w·payload,
    stats (HW, 4) = (A, Σw·z, median, distortion) and count (HW,) int32 contributors per pixel.
    """

    @staticmethod
    def forward(ctx, table, payload, boxes, width, height, near, far):  # type: ignore[override]
        ops = _ops()
        tab = table.detach().T.contiguous()
        pay = payload.detach().T.contiguous()
        bx = boxes.contiguous()
        pay_img, stats, aux, auxi, offsets, lst = ops.forward(tab, pay, bx, width, height, near, far)
        ctx.save_for_backward(tab, pay, bx, offsets, lst, aux, auxi)
        ctx.dims = (width, height, near, far)
        count = auxi[:, 2].clone()
        ctx.mark_non_differentiable(count)
        return pay_img, stats, count

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_pay, g_s, _g_count):  # type: ignore[override]
        tab, pay, bx, offsets, lst, aux, auxi = ctx.saved_tensors
        width, height, near, far = ctx.dims
        HW, P = width * height, pay.shape[1]
        g_pay = torch.zeros(HW, P, dtype=tab.dtype) if g_pay is None else g_pay.to(tab.dtype).contiguous()
        g_s = torch.zeros(HW, 4, dtype=tab.dtype) if g_s is None else g_s.to(tab.dtype).contiguous()
        gtab, gpay = _ops().backward(tab, pay, bx, offsets, lst, aux, auxi, g_pay, g_s, width, height, near, far)
        return gtab.T, gpay.T, None, None, None, None, None


class _DepthNormal(torch.autograd.Function):
    """Normals from depth in the extension; depth: (H, W), kinv: (3, 3) float64 (not differentiated)."""

    @staticmethod
    def forward(ctx, depth, kinv):  # type: ignore[override]
        ctx.save_for_backward(depth.detach(), kinv)
        return _ops().depth_normal_forward(depth.detach().contiguous(), kinv)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        depth, kinv = ctx.saved_tensors
        return _ops().depth_normal_backward(depth, kinv, grad.contiguous()), None


def depth_to_normal_cpp(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Same as ``surfels.depth_to_normal`` (depth: (H, W), K: (3, 3) -> (H, W, 3)), computed in the
    extension in float64; differentiable w.r.t. depth only (K is treated as a constant)."""
    kinv = torch.linalg.inv(K.detach().double()).contiguous()
    return _DepthNormal.apply(depth, kinv)


def composite_cpp(
    table: torch.Tensor,
    payload: torch.Tensor,
    boxes: torch.Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    progress: Callable[[int, int], None] | None = None,
) -> PackedImages:
    """Render one camera from surfels sorted by centre depth (same inputs as ``composite_packed``).

    table: (12, Nv) rows Tu − c_x·Tw, Tv − c_y·Tw, Tw, low-pass centre c (2), opacity; differentiable.
    payload: (D + 3, Nv) features then camera-frame normals; differentiable.
    boxes: (Nv, 4) int64 candidate pixel boxes (``candidate_pixel_boxes``). CPU tensors, float32 or
    float64. ``num_pairs`` counts the composited pairs (as the triton backend). progress(1, 1) is
    called once the forward has run. Raises RuntimeError when the extension is unavailable.
    """
    if table.device.type != "cpu":
        raise ValueError(f"rasterize_surfels(backend='cpp'): needs CPU tensors, got {table.device}")
    if table.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"rasterize_surfels(backend='cpp'): unsupported dtype {table.dtype}")
    pay_img, stats, count = _CppComposite.apply(
        table, payload, boxes, int(width), int(height), float(near), float(far)
    )
    if progress is not None:
        progress(1, 1)
    D = payload.shape[0] - 3
    return PackedImages(
        features=pay_img[:, :D].T,
        alpha=stats[:, 0],
        depth_sum=stats[:, 1],
        normal=pay_img[:, D:].T,
        median=stats[:, 2],
        distortion=stats[:, 3],
        num_pairs=int(count.sum()),
    )
