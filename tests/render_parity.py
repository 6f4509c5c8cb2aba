"""Shared helpers of the rasterizer backend tests: scene tensors, a loss over every output, and the
value-and-gradient comparison of a backend against the packed torch reference."""

from __future__ import annotations

import numpy as np
import torch

from sage_core.render import RenderCamera, rasterize_surfels

OUTPUTS = (
    "color",
    "alpha",
    "depth",
    "depth_sum",
    "median_depth",
    "normal_cam",
    "normal_world",
    "surf_normal_cam",
    "surf_normal_world",
    "distortion",
)
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
