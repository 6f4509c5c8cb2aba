"""Brute-force float64 reference of the surfel rasterizer, for tests of faster backends.

Every pixel is tested against every surfel in numpy float64, independently of the packed code:
the ray–surfel intersection is solved in world space (ray from the camera centre, plane of the
surfel), the screen box is rebuilt from the dual conic, and each pixel is composited by an explicit
loop that applies hbb1's skip and termination rules literally. Only tiny scenes are practical
(N ≲ 200, ≤ 32×32 px).
"""

from __future__ import annotations

import math

import numpy as np

_TILE = 16
_CUT = 3.0
_FILTER = math.sqrt(2.0) / 2.0


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def reference_screen_boxes(
    means: np.ndarray, quats: np.ndarray, scales: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int, near: float
) -> dict[str, np.ndarray]:
    """hbb1 preprocessing in float64: low-pass centre (N, 2), radius (N,), tile rect (N, 4), valid (N,),
    centre depth (N,), camera-frame normal facing the camera (N, 3)."""
    R = _quat_to_matrix(quats)
    Rcw, t = w2c[:3, :3], w2c[:3, 3]
    a = (R[:, :, 0] * scales[:, :1]) @ Rcw.T
    b = (R[:, :, 1] * scales[:, 1:]) @ Rcw.T
    pc = means @ Rcw.T + t
    M = np.einsum("ij,njk->nik", K, np.stack([a, b, pc], -1))
    Tu, Tv, Tw = M[:, 0], M[:, 1], M[:, 2]
    tvec = np.array([_CUT**2, _CUT**2, -1.0])
    d = (tvec * Tw * Tw).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = tvec / d[:, None]
        cx = (f * Tu * Tw).sum(-1)
        cy = (f * Tv * Tw).sum(-1)
        hx = np.sqrt(np.maximum(1e-4, cx * cx - (f * Tu * Tu).sum(-1)))
        hy = np.sqrt(np.maximum(1e-4, cy * cy - (f * Tv * Tv).sum(-1)))
    n = R[:, :, 2] @ Rcw.T
    cos = -(pc * n).sum(-1)
    n = n * np.where(cos > 0, 1.0, -1.0)[:, None]
    ok = (pc[:, 2] > near) & (d < 0) & (cos != 0)
    r = np.where(ok, np.ceil(np.maximum(np.maximum(hx, hy), _CUT * _FILTER)), 0.0)
    gx, gy = -(-width // _TILE), -(-height // _TILE)
    px, py = np.where(ok, cx - 0.5, 0.0), np.where(ok, cy - 0.5, 0.0)
    rect = np.stack(
        [
            np.clip(np.floor((px - r) / _TILE), 0, gx),
            np.clip(np.floor((py - r) / _TILE), 0, gy),
            np.clip(np.floor((px + r + _TILE - 1) / _TILE), 0, gx),
            np.clip(np.floor((py + r + _TILE - 1) / _TILE), 0, gy),
        ],
        -1,
    ).astype(np.int64)
    valid = ok & ((rect[:, 2] - rect[:, 0]) * (rect[:, 3] - rect[:, 1]) > 0)
    rect[~valid] = 0
    return {
        "center": np.stack([cx, cy], -1),
        "radius": np.where(valid, r, 0).astype(np.int64),
        "rect": rect,
        "valid": valid,
        "depth": pc[:, 2],
        "normal": n,
    }


def reference_depth_to_normal(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Central-difference normals of back-projected depth (pixel centres +0.5), 1-px border 0. (H, W, 3)."""
    H, W = depth.shape
    Kinv = np.linalg.inv(K)
    out = np.zeros((H, W, 3))
    for y in range(1, H - 1):
        for x in range(1, W - 1):

            def P(yy: int, xx: int) -> np.ndarray:
                return depth[yy, xx] * (Kinv @ np.array([xx + 0.5, yy + 0.5, 1.0]))

            n = np.cross(P(y + 1, x) - P(y - 1, x), P(y, x + 1) - P(y, x - 1))
            out[y, x] = n / max(np.linalg.norm(n), 1e-12)
    return out


def render_dense_reference(
    means: np.ndarray,
    quats: np.ndarray,
    scales: np.ndarray,
    opacities: np.ndarray,
    features: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    background: np.ndarray | float = 0.0,
    near: float = 0.2,
    far: float = 100.0,
) -> dict[str, np.ndarray]:
    """Reference images for one camera, float64.

    means (N, 3), quats (N, 4) wxyz, scales (N, 2), opacities (N,), features (N, D), K (3, 3),
    w2c (4, 4). Returns color (H, W, D), alpha, depth, depth_sum, median_depth, distortion (H, W),
    normal_cam, normal_world, surf_normal_cam, surf_normal_world (H, W, 3), and ``counts``, a dict
    of how often each rule fired (terminated pixels, low-pass contributions, pairs skipped by the
    near plane, contributions), so tests can check that a scene exercises them.
    """
    means, quats, scales = (np.asarray(v, np.float64) for v in (means, quats, scales))
    opacities, features = np.asarray(opacities, np.float64), np.asarray(features, np.float64)
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    N, D = features.shape
    H, W = height, width
    bg = np.broadcast_to(np.asarray(background, np.float64), (D,))
    pre = reference_screen_boxes(means, quats, scales, K, w2c, width, height, near)
    R = _quat_to_matrix(quats)
    Rcw = w2c[:3, :3]
    cam_c = -Rcw.T @ w2c[:3, 3]
    Kinv = np.linalg.inv(K)
    order = np.argsort(pre["depth"], kind="stable")

    ys, xs = np.meshgrid(np.arange(H) + 0.5, np.arange(W) + 0.5, indexing="ij")
    d_cam = np.stack([xs, ys, np.ones_like(xs)], -1) @ Kinv.T  # (H, W, 3), z component 1
    d_w = d_cam @ Rcw  # world directions (rows): Rcwᵀ d
    tw = R[:, :, 2]
    denom = np.einsum("hwk,nk->nhw", d_w, tw)
    num = ((means - cam_c) * tw).sum(-1)[:, None, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = num / denom  # (N, H, W): camera-frame z of the hit point
        hit = cam_c + lam[..., None] * d_w[None]
        rel = hit - means[:, None, None, :]
        u = np.einsum("nhwk,nk->nhw", rel, R[:, :, 0]) / scales[:, 0, None, None]
        v = np.einsum("nhwk,nk->nhw", rel, R[:, :, 1]) / scales[:, 1, None, None]
    parallel = (denom == 0) | (scales[:, 0] * scales[:, 1] == 0)[:, None, None]
    rho3d = u * u + v * v
    c = pre["center"]
    rho2d = 2.0 * ((c[:, 0, None, None] - xs) ** 2 + (c[:, 1, None, None] - ys) ** 2)
    use3d = rho3d <= rho2d
    rho = np.where(use3d, rho3d, rho2d)
    z = np.where(use3d, lam, pre["depth"][:, None, None])
    alpha = np.minimum(0.99, opacities[:, None, None] * np.exp(-0.5 * rho))

    out = {k: np.zeros((H, W)) for k in ("alpha", "depth_sum", "median_depth", "distortion")}
    counts = {"terminated": 0, "lowpass": 0, "near_skipped": 0, "contributions": 0}
    color = np.zeros((H, W, D))
    normal = np.zeros((H, W, 3))
    rect = pre["rect"]
    for y in range(H):
        for x in range(W):
            tx, ty = x // _TILE, y // _TILE
            T = 1.0
            ws: list[float] = []
            ms: list[float] = []
            for i in order:
                if not pre["valid"][i] or not (rect[i, 0] <= tx < rect[i, 2] and rect[i, 1] <= ty < rect[i, 3]):
                    continue
                if parallel[i, y, x]:
                    continue
                zi = z[i, y, x]
                a = alpha[i, y, x]
                if zi < near:
                    counts["near_skipped"] += int(a >= 1.0 / 255.0)
                    continue
                if a < 1.0 / 255.0:
                    continue
                test_T = T * (1.0 - a)
                if test_T < 1e-4:
                    counts["terminated"] += 1
                    break
                counts["contributions"] += 1
                counts["lowpass"] += int(not use3d[i, y, x])
                w = a * T
                if T > 0.5:
                    out["median_depth"][y, x] = zi
                color[y, x] += w * features[i]
                normal[y, x] += w * pre["normal"][i]
                out["alpha"][y, x] += w
                out["depth_sum"][y, x] += w * zi
                ws.append(w)
                ms.append(far / (far - near) * (1.0 - near / zi))
                T = test_T
            dist = 0.0
            for i in range(len(ws)):
                for j in range(i):
                    dist += ws[i] * ws[j] * (ms[i] - ms[j]) ** 2
            out["distortion"][y, x] = dist
            color[y, x] += T * bg
    A = out["alpha"]
    out["depth"] = np.where(A > 0, out["depth_sum"] / np.where(A > 0, A, 1.0), 0.0)
    out["color"] = color
    out["normal_cam"] = normal
    out["normal_world"] = normal @ Rcw
    sn = reference_depth_to_normal(out["depth"], K) * A[..., None]
    out["surf_normal_cam"] = sn
    out["surf_normal_world"] = sn @ Rcw
    out["counts"] = counts
    return out


def distortion_grad_closed_form(w: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact gradients of L = Σ_i w_i Σ_{j<i} w_j (m_i − m_j)² for one pixel's contributors (docs/rendering.md §2.3).

    w, m: (K,) -> (∂L/∂w (K,), ∂L/∂m (K,)) with ∂L/∂w_k = m_k²A − 2m_kM1 + M2 and
    ∂L/∂m_k = 2w_k(m_kA − M1), where A = Σw, M1 = Σwm, M2 = Σwm² over all contributors.
    """
    A, M1, M2 = w.sum(), (w * m).sum(), (w * m * m).sum()
    return m * m * A - 2.0 * m * M1 + M2, 2.0 * w * (m * A - M1)


def random_test_scene(
    seed: int, num: int = 50, width: int = 32, height: int = 32, num_features: int = 4
) -> dict[str, np.ndarray | int]:
    """A small random float64 scene that exercises the rasterizer's rules.

    Random surfels in front of a slightly rotated camera (sizes from sub-pixel, which hits the
    low-pass branch, to a few pixels), plus a stack of opaque fronto-parallel surfels in the middle
    so that compositing terminates there. Returns means, quats, scales, opacities, features, K,
    w2c, width, height.
    """
    rng = np.random.default_rng(seed)
    f = 1.2 * width
    z = 2.0 + 2.0 * rng.random(num)
    xy = (rng.random((num, 2)) - 0.5) * 2.2 * (width / 2) / f * z[:, None]
    means = np.concatenate([xy, z[:, None]], 1)
    quats = rng.normal(size=(num, 4))
    scales = np.exp(rng.normal(size=(num, 2)) * 0.7 - 2.4)
    opac = rng.random(num)
    opac[: num // 5] = 1.0
    stack = 4
    means[:stack] = np.array([[0.05, -0.03, 2.5 + 0.2 * k] for k in range(stack)])
    quats[:stack] = np.array([1.0, 0.0, 0.0, 0.0]) + 0.05 * rng.normal(size=(stack, 4))
    scales[:stack] = 0.25 + 0.05 * rng.random((stack, 2))
    # below 1 so that two clamped layers (T = 0.01² = 1e-4) do not tie with the termination threshold
    opac[:stack] = 0.97
    K = np.array([[f, 0.0, width / 2 + 0.3], [0.0, f * 1.05, height / 2 - 0.2], [0.0, 0.0, 1.0]])
    ang = 0.05
    Rz = np.array([[math.cos(ang), -math.sin(ang), 0.0], [math.sin(ang), math.cos(ang), 0.0], [0.0, 0.0, 1.0]])
    w2c = np.eye(4)
    w2c[:3, :3] = Rz
    w2c[:3, 3] = [0.02, -0.01, 0.1]
    return {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opac,
        "features": rng.random((num, num_features)),
        "K": K,
        "w2c": w2c,
        "width": width,
        "height": height,
    }
