"""Differentiable 2D Gaussian surfel rasterizer (2DGS / hbb1 maths, packed pure-torch backend).

Conventions: OpenCV cameras, pixel centres at +0.5, images channels-last ``(H, W, ch)`` (a leading
C for a batch of cameras). Rendering rules follow docs/rendering.md §1–2: α = min(0.99, o·e^(−ρ/2)) with
the low-pass ρ = min(ρ3d, 2‖c − x‖²); pairs with h_z = 0, depth < near or α < 1/255 are skipped;
compositing stops before the first surfel with T·(1 − α) < 1e-4; each pixel composites its surfels
in order of their centre view depth. On the low-pass (2D) branch the depth of a pair is the surfel's
centre depth, on the 3D branch the ray–surfel intersection depth.

Surfels with a zero scale give h_z = 0 at every pixel and therefore contribute nothing (the
low-pass filter does not revive them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType

import torch
import torch.nn.functional as F

from ._camera import RenderCamera
from ._packed import composite_packed
from ._project import candidate_pixel_boxes, project_surfels
from ..geometry.sh import eval_sh_colors

BACKENDS = ("torch", "cpp", "triton", "auto")


@dataclass
class SurfelRender:
    """Rendered images and per-surfel statistics; a batch of C cameras adds a leading C everywhere.

    Attributes:
        color: (H, W, D) Σ w·c + (1 − A)·background.
        alpha: (H, W) A = Σ w.
        depth: (H, W) expected intersection depth D/A, 0 where A = 0.
        depth_sum: (H, W) D = Σ w·z.
        median_depth: (H, W) depth of the last contributor whose T before it is > 0.5, else 0.
        normal_cam, normal_world: (H, W, 3) Σ w·n, unnormalized, n flipped to face the camera.
        surf_normal_cam, surf_normal_world: (H, W, 3) normals from finite differences of the
            back-projected expected depth, 1-px border 0, multiplied by A.detach().
        distortion: (H, W) Σ_i w_i Σ_{j<i} w_j (m_i − m_j)², m(z) = f/(f−n)·(1 − n/z).
        visible: (N,) bool, surfel kept by culling and touching at least one tile.
        radii: (N,) int32 hbb1 screen radius in px (0 where not visible).
        means2d: (N, 2) projected surfel centres in px. Its gradient is z_c·∂L/∂(Tu[2], Tv[2]),
            hbb1's densification proxy in pixel units; multiply by (W/2, H/2) for hbb1's NDC units
            (the 2e-4 threshold). Call ``.retain_grad()`` before backward.
        num_pairs: (C,) or scalar number of composited (surfel, pixel) pairs kept per camera.
    """

    color: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    depth_sum: torch.Tensor
    median_depth: torch.Tensor
    normal_cam: torch.Tensor
    normal_world: torch.Tensor
    surf_normal_cam: torch.Tensor
    surf_normal_world: torch.Tensor
    distortion: torch.Tensor
    visible: torch.Tensor | None
    radii: torch.Tensor | None
    means2d: torch.Tensor | None
    num_pairs: torch.Tensor


def depth_to_points(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Back-project z-depth: P(x, y) = z·K⁻¹(x + 0.5, y + 0.5, 1)ᵀ. depth: (H, W), K: (3, 3) -> (H, W, 3)."""
    H, W = depth.shape
    xs = torch.arange(W, dtype=depth.dtype, device=depth.device) + 0.5
    ys = torch.arange(H, dtype=depth.dtype, device=depth.device) + 0.5
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    pix = torch.stack([gx, gy, torch.ones_like(gx)], -1)
    rays = pix @ torch.linalg.inv(K.to(depth.dtype)).T
    return depth.unsqueeze(-1) * rays


def depth_to_normal(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Camera-frame normals from depth by central differences (docs/rendering.md §2.2).

    N = normalize((P(y+1,x) − P(y−1,x)) × (P(y,x+1) − P(y,x−1))), zero on the 1-px border.
    depth: (H, W), K: (3, 3) -> (H, W, 3). A fronto-parallel plane gives (0, 0, −1).
    """
    P = depth_to_points(depth, K)
    if depth.shape[0] < 3 or depth.shape[1] < 3:
        return torch.zeros_like(P)
    dV = P[2:, 1:-1] - P[:-2, 1:-1]
    dH = P[1:-1, 2:] - P[1:-1, :-2]
    n = F.normalize(torch.linalg.cross(dV, dH, dim=-1), dim=-1)
    return F.pad(n, (0, 0, 1, 1, 1, 1))


def _check_finite(name: str, t: torch.Tensor) -> None:
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"rasterize_surfels: '{name}' contains NaN or Inf values")


def _validate(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: RenderCamera,
    near: float,
    far: float,
) -> None:
    N = means.shape[0] if means.dim() == 2 else -1
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"rasterize_surfels: 'means' must be (N, 3), got {tuple(means.shape)}")
    for name, t, shape in (("quats", quats, (N, 4)), ("scales", scales, (N, 2)), ("opacities", opacities, (N,))):
        if tuple(t.shape) != shape:
            raise ValueError(f"rasterize_surfels: '{name}' must be {shape}, got {tuple(t.shape)}")
    if colors.dim() not in (2, 3) or colors.shape[0] != N or (colors.dim() == 3 and colors.shape[2] != 3):
        raise ValueError(f"rasterize_surfels: 'colors' must be (N, D) or (N, K, 3), got {tuple(colors.shape)}")
    for name, t in (("means", means), ("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors)):
        _check_finite(name, t)
    _check_finite("camera.K", camera.K)
    _check_finite("camera.w2c", camera.w2c)
    if N > 0:
        if bool((scales < 0).any()):
            raise ValueError("rasterize_surfels: 'scales' must be non-negative")
        if bool(((opacities < 0) | (opacities > 1)).any()):
            raise ValueError("rasterize_surfels: 'opacities' must lie in [0, 1]")
    if not (0 < near < far):
        raise ValueError(f"rasterize_surfels: need 0 < near < far, got near={near}, far={far}")


def _triton_module(backend: str, device: torch.device) -> ModuleType | None:
    """The Triton backend module when ``backend`` selects it for ``device``, else None.

    "triton" raises ValueError when triton is missing or cannot run on ``device``; "auto" picks
    triton only for CUDA tensors with compiled (not interpreted) kernels.
    """
    if backend not in ("triton", "auto") or (backend == "auto" and device.type != "cuda"):
        return None
    try:
        from . import _triton_surfels
    except ImportError as exc:
        if backend == "auto":
            return None
        raise ValueError(f"rasterize_surfels: backend='triton' needs the 'triton' package ({exc})") from exc
    if backend == "auto":
        return None if _triton_surfels.INTERPRETED else _triton_surfels
    if not _triton_surfels.device_supported(device):
        raise ValueError(
            f"rasterize_surfels: backend='triton' runs on CUDA tensors (got {device}); on CPU only under "
            "Triton's interpreter (TRITON_INTERPRET=1 set before the first triton render)"
        )
    return _triton_surfels


def resolve_backend(name: str, device: torch.device | str) -> str:
    """The backend that ``rasterize_surfels(..., backend=name)`` runs for tensors on ``device``.

    Returns "torch", "cpp" or "triton". "auto" is triton on CUDA (compiled kernels), the native CPU
    backend on CPU when its extension builds (the first call may compile it; if it cannot, one
    warning is issued and "torch" is returned), else torch. An explicit "cpp" or "triton" that
    cannot run on ``device`` raises ValueError with the reason.
    """
    if name not in BACKENDS:
        raise ValueError(f"rasterize_surfels: unknown backend {name!r}; available: {', '.join(BACKENDS)}")
    dev = torch.device(device)
    if name == "torch":
        return "torch"
    if name == "triton" or (name == "auto" and dev.type == "cuda"):
        return "triton" if _triton_module(name, dev) is not None else "torch"
    if dev.type != "cpu":
        if name == "cpp":
            raise ValueError(f"rasterize_surfels: backend='cpp' runs on CPU tensors (got {dev})")
        return "torch"
    from . import _cpp_surfels

    return _cpp_surfels.EXT.choose(name, "rasterize_surfels")


def _camera_features(colors: torch.Tensor, means: torch.Tensor, w2c: torch.Tensor, sh_degree: int) -> torch.Tensor:
    """Per-surfel features seen by one camera: colors (N, D) as given, or SH coefficients (N, K, D)
    evaluated along the view directions from the camera centre of w2c (4, 4). Returns (N, D)."""
    if colors.dim() != 3:
        return colors
    centre = -(w2c[:3, :3].T @ w2c[:3, 3])
    return eval_sh_colors(colors, F.normalize(means - centre, dim=-1), sh_degree)


def rasterize_surfels(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: RenderCamera,
    background: torch.Tensor | float = 0.0,
    near: float = 0.2,
    far: float = 100.0,
    sh_degree: int | None = None,
    backend: str = "torch",
    chunk_pairs: int = 1 << 20,
    return_statistics: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> SurfelRender:
    """Render 2D Gaussian surfels into one camera or a batch of C cameras.

    means: (N, 3) world centres; quats: (N, 4) wxyz (normalized here); scales: (N, 2) ≥ 0;
    opacities: (N,) in [0, 1]; colors: (N, D) features passed through unchanged, or (N, K, 3) SH
    coefficients (3DGS order) evaluated with world view directions (camera centre → mean) as
    max(SH + 0.5, 0); ``sh_degree`` defaults to √K − 1. background: scalar or (D,).
    near: cull plane for surfel centres and per-pixel skip depth; near and far also define the
    distortion's normalized depth. chunk_pairs bounds the candidate pairs evaluated at once in the
    no-grad stage (peak memory). progress(i, n) is called after each candidate chunk.
    backend: "torch" (packed pure torch), "cpp" (native C++/OpenMP tile backend of ``_cpp_surfels``;
    CPU tensors, float32/float64, compiled on first use), "triton" (tile kernels of
    ``_triton_surfels``; CUDA tensors, or CPU under Triton's interpreter) or "auto" (see
    :func:`resolve_backend`: triton on CUDA, cpp on CPU when it builds, else torch).
    All outputs have the dtype and device of ``means``. Raises ValueError on bad shapes or NaN/Inf,
    or when an explicitly requested backend cannot run here.
    """
    if backend not in BACKENDS:
        raise ValueError(f"rasterize_surfels: unknown backend {backend!r}; available: {', '.join(BACKENDS)}")
    _validate(means, quats, scales, opacities, colors, camera, near, far)
    dtype, device = means.dtype, means.device
    chosen = resolve_backend(backend, device)
    if chosen == "cpp" and dtype not in (torch.float32, torch.float64):
        if backend == "cpp":
            raise ValueError(f"rasterize_surfels: backend='cpp' supports float32 and float64, got {dtype}")
        chosen = "torch"
    tri = _triton_module(backend, device) if chosen == "triton" else None
    cpp = None
    if chosen == "cpp":
        from . import _cpp_surfels as cpp
    cam = camera.to(device=device, dtype=dtype)
    Ks = cam.K if cam.batched else cam.K[None]
    w2cs = cam.w2c if cam.batched else cam.w2c[None]
    C, W, H = Ks.shape[0], cam.width, cam.height

    if colors.dim() == 3:
        if sh_degree is None:
            deg = round(colors.shape[1] ** 0.5) - 1
            if (deg + 1) ** 2 != colors.shape[1]:
                raise ValueError(f"rasterize_surfels: cannot infer sh_degree from {colors.shape[1]} coefficients")
            sh_degree = deg
        Dch = 3
    else:
        if sh_degree is not None:
            raise ValueError("rasterize_surfels: sh_degree needs colors of shape (N, K, 3)")
        Dch = colors.shape[1]
    bg = torch.as_tensor(background, dtype=dtype, device=device)
    _check_finite("background", bg)
    if bg.dim() == 0:
        bg = bg.expand(Dch)
    if tuple(bg.shape) != (Dch,):
        raise ValueError(f"rasterize_surfels: 'background' must be a scalar or ({Dch},), got {tuple(bg.shape)}")

    if cpp is not None and not (Ks.requires_grad or w2cs.requires_grad):
        # the whole render in the extension (a differentiated camera keeps the torch projection below)
        feats_per_cam = [_camera_features(colors, means, w2cs[c], sh_degree) for c in range(C)]
        res = cpp.render_cpp(
            means, quats, scales, opacities, feats_per_cam, Ks, w2cs, bg, W, H, near, far, cam.batched, progress
        )
        return SurfelRender(
            **res.images,
            visible=res.visible if return_statistics else None,
            radii=res.radii if return_statistics else None,
            means2d=res.means2d if return_statistics else None,
            num_pairs=res.num_pairs,
        )

    proj = project_surfels(means, quats, scales, Ks, w2cs, W, H, near, squeeze=not cam.batched)

    outs: dict[str, list[torch.Tensor]] = {}
    num_pairs = []
    for c in range(C):
        Rcw = w2cs[c, :3, :3]
        feats = _camera_features(colors, means, w2cs[c], sh_degree)
        vid = torch.nonzero(proj.valid[c], as_tuple=False).squeeze(1)
        vid = vid[torch.argsort(proj.depth[c, vid].detach(), stable=True)]
        M = proj.M[c].index_select(0, vid)
        centre2d = proj.center[c].index_select(0, vid)
        op = opacities.index_select(0, vid)
        rows = torch.cat([M[:, :2] - centre2d.unsqueeze(-1) * M[:, 2:], M[:, 2:]], 1)  # shifted Tu, Tv; Tw
        table = torch.cat([rows.reshape(-1, 9), centre2d, op[:, None]], 1).T
        payload = torch.cat([feats.index_select(0, vid), proj.normal[c].index_select(0, vid)], 1).T
        boxes = candidate_pixel_boxes(M, centre2d, op, proj.rect[c].index_select(0, vid), W, H)
        if tri is not None:
            img = tri.composite_triton(table, payload, boxes, W, H, near, far, progress)
        elif cpp is not None:
            img = cpp.composite_cpp(table, payload, boxes, W, H, near, far, progress)
        else:
            img = composite_packed(table, payload, boxes, W, H, near, far, chunk_pairs, progress)
        num_pairs.append(img.num_pairs)

        alpha = img.alpha.reshape(H, W)
        dsum = img.depth_sum.reshape(H, W)
        depth = torch.where(alpha > 0, dsum / torch.where(alpha > 0, alpha, torch.ones_like(alpha)), torch.zeros_like(alpha))
        color = img.features.T.reshape(H, W, Dch) + (1.0 - alpha).unsqueeze(-1) * bg
        ncam = img.normal.T.reshape(H, W, 3)
        if cpp is not None and not Ks.requires_grad:
            sn_cam = cpp.depth_to_normal_cpp(depth, Ks[c]) * alpha.detach().unsqueeze(-1)
        else:
            sn_cam = depth_to_normal(depth, Ks[c]) * alpha.detach().unsqueeze(-1)
        for k, v in (
            ("color", color),
            ("alpha", alpha),
            ("depth", depth),
            ("depth_sum", dsum),
            ("median_depth", img.median.reshape(H, W)),
            ("normal_cam", ncam),
            ("normal_world", ncam @ Rcw),
            ("surf_normal_cam", sn_cam),
            ("surf_normal_world", sn_cam @ Rcw),
            ("distortion", img.distortion.reshape(H, W)),
        ):
            outs.setdefault(k, []).append(v)

    def pick(vs: list[torch.Tensor]) -> torch.Tensor:
        return torch.stack(vs) if cam.batched else vs[0]

    images = {k: pick(v) for k, v in outs.items()}
    pairs = torch.tensor(num_pairs, dtype=torch.long)
    if return_statistics:
        visible = proj.valid if cam.batched else proj.valid[0]
        radii = (proj.radius if cam.batched else proj.radius[0]).to(torch.int32)
        means2d = proj.means2d
    else:
        visible = radii = means2d = None
    return SurfelRender(
        **images,
        visible=visible,
        radii=radii,
        means2d=means2d,
        num_pairs=pairs if cam.batched else pairs[0],
    )
