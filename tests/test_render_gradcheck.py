"""torch.autograd.gradcheck of the packed surfel rasterizer on tiny float64 scenes.

Scenes are drawn until every (surfel, pixel) pair sits away from the discrete switches (the 1/255
cut, the 0.99 clamp, the ρ3d = ρ2d branch, tile rectangles and radii) and the median surfel is
stable, so finite differences see a smooth function.
"""

from __future__ import annotations

import functools
import math

import torch

from sage_core.render import RenderCamera, depth_to_normal, rasterize_surfels
from sage_core.render._packed import eval_pairs
from sage_core.render._project import project_surfels

W, H = 20, 18
NEAR, FAR = 0.2, 6.0


def _camera() -> RenderCamera:
    f = 22.0
    K = torch.tensor([[f, 0.0, W / 2 + 0.2], [0.0, f, H / 2 - 0.1], [0.0, 0.0, 1.0]], dtype=torch.float64)
    a = 0.1
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = torch.tensor(
        [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]], dtype=torch.float64
    )
    w2c[:3, 3] = torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64)
    return RenderCamera(K, w2c, W, H)


def _scene(seed: int, sh: bool) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    n = 4
    z = 2.0 + 0.6 * torch.rand(n, generator=g, dtype=torch.float64)
    xy = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 0.3
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64) + 0.5 * torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = 0.1 + 0.1 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    scales[0] = torch.tensor([0.012, 0.03], dtype=torch.float64)  # about half a pixel: the low-pass branch
    opac = 0.3 + 0.4 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 4, 3, generator=g, dtype=torch.float64) - 0.3 if sh else torch.rand(n, 3, generator=g, dtype=torch.float64)
    return [means, quats, scales, opac, colors]


def _signature(params: list[torch.Tensor], cam: RenderCamera) -> tuple[torch.Tensor, ...]:
    means, quats, scales, opac = params[:4]
    proj = project_surfels(means, quats, scales, cam.K[None], cam.w2c[None], W, H, NEAR)
    M, c = proj.M[0], proj.center[0]
    rows = torch.cat([M[:, :2] - c.unsqueeze(-1) * M[:, 2:], M[:, 2:]], 1)
    n = means.shape[0]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    xf = xs.flatten().repeat(n) + 0.5
    yf = ys.flatten().repeat(n) + 0.5
    sid = torch.arange(n).repeat_interleave(H * W)
    g = torch.cat([rows.reshape(-1, 9), c, 1e-3 * opac[:, None]], 1).T[:, sid]
    a_small, z, hz, use3d = eval_pairs(g, xf, yf)
    raw = a_small * 1e3  # o·exp(−ρ/2) without the clamp
    return (
        proj.valid,
        proj.rect,
        proj.radius,
        use3d,
        raw >= 1.0 / 255.0,
        raw >= 0.99,
        z >= NEAR,
        hz != 0,
    )


def _stable(params: list[torch.Tensor], cam: RenderCamera, sh: bool) -> bool:
    base = _signature(params, cam)
    med0 = rasterize_surfels(*params, cam, far=FAR).median_depth
    g = torch.Generator().manual_seed(123)
    for _ in range(6):
        pert = [p + 2e-5 * torch.randn(p.shape, generator=g, dtype=p.dtype) for p in params]
        pert[3] = pert[3].clamp(0, 1)
        sig = _signature(pert, cam)
        if any(not torch.equal(a, b) for a, b in zip(base, sig)):
            return False
        if (rasterize_surfels(*pert, cam, far=FAR).median_depth - med0).abs().max() > 1e-3:
            return False
    return True


@functools.lru_cache(maxsize=2)
def _pick_scene(sh: bool) -> list[torch.Tensor]:
    cam = _camera()
    for seed in range(30):
        params = _scene(seed, sh)
        if _stable(params, cam, sh):
            return [p.detach() for p in params]
    raise AssertionError("no scene away from the rasterizer's switches in 30 seeds")


def _outputs(cam: RenderCamera, weights: dict[str, torch.Tensor]):
    def f(*params: torch.Tensor) -> torch.Tensor:
        out = rasterize_surfels(*params, cam, background=torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64), far=FAR)
        vals = []
        for k, w in weights.items():
            if k == "depth_normal":  # surf_normal_cam without the detached alpha factor
                vals.append((depth_to_normal(out.depth, cam.K) * w).sum())
            else:
                vals.append((getattr(out, k) * w).sum())
        return torch.stack(vals)

    return f


def _weights() -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(7)
    shapes = {
        "color": (H, W, 3),
        "alpha": (H, W),
        "depth": (H, W),
        "median_depth": (H, W),
        "normal_cam": (H, W, 3),
        "normal_world": (H, W, 3),
        "depth_normal": (H, W, 3),
        "distortion": (H, W),
    }
    return {k: torch.rand(s, generator=g, dtype=torch.float64) for k, s in shapes.items()}


def test_gradcheck_features() -> None:
    cam = _camera()
    params = _pick_scene(sh=False)
    out = rasterize_surfels(*params, cam, far=FAR)
    assert out.distortion.max() > 1e-6 and out.median_depth.max() > 0 and int(out.visible.sum()) == 4
    inputs = [p.clone().requires_grad_(True) for p in params]
    assert torch.autograd.gradcheck(_outputs(cam, _weights()), inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_gradcheck_spherical_harmonics() -> None:
    cam = _camera()
    params = _pick_scene(sh=True)
    inputs = [p.clone().requires_grad_(True) for p in params]
    weights = {k: v for k, v in _weights().items() if k in ("color", "depth", "distortion")}
    assert torch.autograd.gradcheck(_outputs(cam, weights), inputs, eps=1e-6, atol=1e-5, rtol=1e-3)


def test_lowpass_branch_is_exercised() -> None:
    cam = _camera()
    params = _pick_scene(sh=False)
    sig = _signature(params, cam)
    use3d, significant = sig[3], sig[4] & sig[6] & sig[7]
    n2d = int((~use3d & significant).sum())
    n3d = int((use3d & significant).sum())
    assert n2d > 5 and n3d > 50


def test_pair_eval_backward_matches_autograd() -> None:
    from sage_core.render._packed import _PairEval

    cam = _camera()
    params = [p.clone() for p in _pick_scene(sh=False)]
    params[3] = torch.tensor([0.3, 1.0, 0.5, 0.6], dtype=torch.float64)  # one surfel hits the 0.99 clamp
    proj = project_surfels(params[0], params[1], params[2], cam.K[None], cam.w2c[None], W, H, NEAR)
    M, c = proj.M[0].detach(), proj.center[0].detach()
    rows = torch.cat([M[:, :2] - c.unsqueeze(-1) * M[:, 2:], M[:, 2:]], 1)
    table = torch.cat([rows.reshape(-1, 9), c, params[3][:, None]], 1).T.contiguous()
    n = table.shape[1]
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rank = torch.arange(n).repeat_interleave(H * W)
    xf, yf = xs.flatten().repeat(n) + 0.5, ys.flatten().repeat(n) + 0.5
    # plus samples at the low-pass centres, where ρ = 0 and an opaque surfel hits the clamp
    rank = torch.cat([rank, torch.arange(n)])
    xf, yf = torch.cat([xf, c[:, 0]]), torch.cat([yf, c[:, 1]])
    with torch.no_grad():
        a0, _, hz0, use3d = eval_pairs(table[:, rank], xf, yf)
    keep = (hz0 != 0) & (a0 >= 1 / 255)
    rank, xf, yf, use3d = rank[keep], xf[keep], yf[keep], use3d[keep]
    assert int((~use3d).sum()) > 5 and int((a0[keep] == 0.99).sum()) > 0
    ga = torch.randn(rank.shape[0], dtype=torch.float64)
    gz = torch.randn(rank.shape[0], dtype=torch.float64)
    t1 = table.clone().requires_grad_(True)
    a1, z1, _ = _PairEval.apply(t1, rank, xf, yf, use3d)
    (a1 * ga + z1 * gz).sum().backward()
    t2 = table.clone().requires_grad_(True)
    a2, z2, _, _ = eval_pairs(t2.index_select(1, rank), xf, yf, use3d)
    (a2 * ga + z2 * gz).sum().backward()
    assert torch.equal(a1, a2) and torch.equal(z1, z2)
    assert torch.allclose(t1.grad, t2.grad, rtol=1e-10, atol=1e-10)
