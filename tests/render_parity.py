"""Shared helpers of the rasterizer backend tests: scene tensors, a loss over every output, and the
value-and-gradient comparison of a backend against the packed torch reference."""

from __future__ import annotations

import numpy as np
import torch

from sage_core.render import RenderCamera, rasterize_surfels
from sage_core.render._packed import IMAGE_OUTPUTS

OUTPUTS = IMAGE_OUTPUTS
"""Every image output of :func:`rasterize_surfels`."""
PARAMS = ("means", "quats", "scales", "opacities", "features")
"""Scene keys of the surfel parameters, in ``rasterize_surfels`` order."""


def scene_tensors(scene: dict, dtype: torch.dtype, device: str = "cpu") -> tuple[list[torch.Tensor], RenderCamera]:
    """A ``random_test_scene`` dict -> (surfel parameter tensors, camera)."""
    t = {k: torch.as_tensor(v, dtype=dtype, device=device) for k, v in scene.items() if isinstance(v, np.ndarray)}
    return [t[k] for k in PARAMS], RenderCamera(t["K"], t["w2c"], scene["width"], scene["height"])


def render_with_grads(params: list[torch.Tensor], cam: RenderCamera, backend: str, **kw):
    """Render, back-propagate a fixed random weighting of every output; return the render and the
    gradients of the parameters and of ``means2d``."""
    ps = [p.detach().clone().requires_grad_(True) for p in params]
    out = rasterize_surfels(*ps, cam, backend=backend, **kw)
    out.means2d.retain_grad()
    g = torch.Generator().manual_seed(3)
    loss = torch.zeros((), dtype=ps[0].dtype, device=ps[0].device)
    for name in OUTPUTS:
        v = getattr(out, name)
        loss = loss + (v * torch.rand(v.shape, generator=g, dtype=v.dtype).to(v.device)).sum()
    loss.backward()
    return out, [p.grad for p in ps] + [out.means2d.grad]


def compare_backends(params, cam, backend: str, atol: float, grad_rtol: float, **kw) -> tuple:
    """Assert ``backend`` matches the torch backend: every output within ``atol``, every gradient
    within ``grad_rtol`` of that input's largest gradient, the same visibility and radii."""
    a, ga = render_with_grads(params, cam, "torch", **kw)
    b, gb = render_with_grads(params, cam, backend, **kw)
    for name in OUTPUTS:
        x, y = getattr(a, name).detach(), getattr(b, name).detach()
        assert x.shape == y.shape and x.dtype == y.dtype, name
        assert float((x - y).abs().max()) <= atol, (name, float((x - y).abs().max()))
    for name, x, y in zip(PARAMS + ("means2d",), ga, gb):
        scale = float(x.abs().max())
        assert scale > 0, name
        assert float((x - y).abs().max()) <= grad_rtol * scale, (name, float((x - y).abs().max()), scale)
    assert torch.equal(a.visible, b.visible) and torch.equal(a.radii, b.radii)
    return a, b


def check_tile_binning(bin_tiles) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Assert that ``bin_tiles(boxes, W, H) -> (offsets, list)`` lists every surfel, in order, in each
    16×16 tile its (half-open) pixel box touches, and no other, on 40 random boxes over a 70×37 image
    (some empty, none reaching the last tile column). Returns (boxes, offsets, list)."""
    g = torch.Generator().manual_seed(0)
    W, H, n = 70, 37, 40
    x0 = torch.randint(-5, 40, (n,), generator=g)  # nothing reaches the last tile column (x ≥ 64)
    y0 = torch.randint(-5, H, (n,), generator=g)
    x1 = x0 + torch.randint(0, 20, (n,), generator=g)
    boxes = torch.stack([x0, y0, x1, y0 + torch.randint(0, 30, (n,), generator=g)], 1)
    boxes[:, 0::2] = boxes[:, 0::2].clamp(0, W)
    boxes[:, 1::2] = boxes[:, 1::2].clamp(0, H)
    offsets, lst = bin_tiles(boxes, W, H)
    gx, gy = (W + 15) // 16, (H + 15) // 16
    assert offsets.shape == (gx * gy + 1,) and int(offsets[-1]) == lst.shape[0]
    for tile in range(gx * gy):
        tx, ty = tile % gx, tile // gx
        expect = [
            i
            for i, (a0, b0, a1, b1) in enumerate(boxes.tolist())
            if a1 > a0 and b1 > b0 and a0 < 16 * (tx + 1) and a1 > 16 * tx and b0 < 16 * (ty + 1) and b1 > 16 * ty
        ]
        assert lst[int(offsets[tile]) : int(offsets[tile + 1])].tolist() == expect, tile
    assert int(((boxes[:, 2] <= boxes[:, 0]) | (boxes[:, 3] <= boxes[:, 1])).sum()) > 0  # empty boxes occur
    return boxes, offsets, lst
