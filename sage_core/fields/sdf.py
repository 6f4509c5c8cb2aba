"""Canonical SDF network (hash grid + Softplus MLP), its derivatives and principal curvatures.

The SDF is returned in world units (metres): the MLP works on normalized coordinates
``x_n = (x - centre) / half_extent`` (``half_extent`` = half the largest side of the box) and its raw output
is multiplied by ``half_extent``, so ``|grad f| = 1`` means the same in both spaces and a sphere init of
normalized radius ``r`` is a world sphere of radius ``r * half_extent`` around the box centre.

Backends (``SDFNetwork.backend``): ``torch`` is the autograd reference (the encoding then runs its own
``HashGrid.backend``); ``cpp`` is the fused native kernel of ``_cpp_sdf`` for one hidden layer on CPU
(encoding, MLP, the analytic gradient and the exact backward of all three in one autograd node);
``auto`` (the default) uses ``cpp`` when the network and the tensors allow it and the extension builds,
and ``torch`` otherwise (a missing build warns once).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import torch
from torch import nn

from .hashgrid import BACKENDS, HashGrid

if TYPE_CHECKING:
    from . import _cpp_sdf

GradientFn = Callable[[torch.Tensor], torch.Tensor]


def resolve_fused_backend(backend: str, device: torch.device | str) -> str:
    """``auto|torch|cpp`` for a one-hidden-layer :class:`SDFNetwork` on ``device`` -> the path that runs:
    ``cpp`` (the fused native kernel) or ``torch``. Like :func:`sage_core.fields.hashgrid.resolve_backend`:
    CUDA always gives ``torch``; ``auto`` on CPU gives ``cpp`` when the extension is available (building it
    on first use) and otherwise warns once; an explicit ``cpp`` that cannot be built raises ValueError."""
    if backend not in BACKENDS:
        raise ValueError(f"SDFNetwork: unknown backend {backend!r} (choose from {', '.join(BACKENDS)})")
    if backend == "torch" or torch.device(device).type != "cpu":
        return "torch"
    from . import _cpp_sdf

    return _cpp_sdf.EXT.choose(backend, "SDFNetwork")


def hessian_fd(grad_fn: GradientFn, x: torch.Tensor, eps: float) -> torch.Tensor:
    """Symmetrized Hessian by central differences of an analytic gradient.

    ``H[:, :, j] = (g(x + eps e_j) - g(x - eps e_j)) / (2 eps)``, then ``H <- (H + H^T) / 2``.

    grad_fn: (M, 3) -> (M, 3) gradient of the field; x: (N, 3); eps: step in world units -> (N, 3, 3).
    """
    n = x.shape[0]
    eye = torch.eye(3, dtype=x.dtype, device=x.device) * eps
    offsets = torch.cat([eye, -eye], 0)  # (6, 3)
    pts = (x[:, None, :] + offsets[None]).reshape(-1, 3)
    g = grad_fn(pts).reshape(n, 6, 3)
    cols = (g[:, :3, :] - g[:, 3:, :]) / (2.0 * eps)  # (N, j, i) = dg_i/dx_j
    h = cols.transpose(1, 2)
    return 0.5 * (h + h.transpose(1, 2))


def tangent_basis(normal: torch.Tensor) -> torch.Tensor:
    """Orthonormal tangent vectors for unit normals.

    normal: (N, 3) -> (N, 2, 3) rows e1, e2 with e1 x e2 = normal.
    """
    ex = torch.zeros_like(normal)
    ex[:, 0] = 1.0
    ey = torch.zeros_like(normal)
    ey[:, 1] = 1.0
    helper = torch.where((normal[:, :1].abs() > 0.9), ey, ex)
    e1 = helper - (helper * normal).sum(-1, keepdim=True) * normal
    e1 = e1 / e1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    e2 = torch.cross(normal, e1, dim=-1)
    return torch.stack([e1, e2], 1)


def principal_curvatures(
    grad_fn: GradientFn, x: torch.Tensor, eps: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Principal curvatures of the level set through each point, for any field with a gradient function.

    Builds the finite-difference Hessian H (``hessian_fd``), a tangent basis E of the normal
    ``n = g/|g|`` and solves the 2x2 eigenproblem of ``E^T H E / |g|`` (the shape operator ``P H P / |g|``
    restricted to the tangent plane). Sign: positive on convex parts of an SDF that is negative inside
    (``f = |x| - r`` gives ``k1 = k2 = 1/r``).

    grad_fn: (M, 3) -> (M, 3); x: (N, 3); eps: finite-difference step (world units).
    Returns kappa (N, 2) with k1 >= k2, directions (N, 2, 3) unit tangents (rows), normal (N, 3).
    """
    g = grad_fn(x)
    gnorm = g.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    normal = g / gnorm
    h = hessian_fd(grad_fn, x, eps)
    basis = tangent_basis(normal)  # (N, 2, 3)
    m = basis @ h @ basis.transpose(1, 2) / gnorm[..., None]  # (N, 2, 2)
    m = 0.5 * (m + m.transpose(1, 2))
    evals, evecs = torch.linalg.eigh(m)  # ascending
    kappa = evals.flip(-1)
    vecs = evecs.flip(-1)  # columns: k1, k2
    directions = vecs.transpose(1, 2) @ basis  # (N, 2, 3)
    return kappa, directions, normal


class SDFNetwork(nn.Module):
    """Signed distance field ``f(x)`` plus a geometry feature ``z(x)`` on a hash grid.

    Input ``[x_n, enc(x)]`` (x_n in [-1, 1] on the longest box axis, enc the hash grid over the box)
    -> Linear -> Softplus(beta) -> (n_hidden_layers - 1) x [Linear -> Softplus] -> Linear -> (sdf, feature).

    Geometric init (instant-nsr-pl / Neuralangelo): first layer xyz weights and hidden weights
    N(0, sqrt(2)/sqrt(n_out)), encoding weights 0, biases 0; the SDF row of the last layer
    N(sqrt(pi)/sqrt(n_in), 1e-4) with bias -sphere_radius. The zero level set then starts as a sphere of
    world radius ``sphere_radius * half_extent`` around the box centre: choose the box so that this encloses
    the head (e.g. a cube of half extent 1.5x the head's half size with sphere_radius 0.8).

    Args:
        bbox_min, bbox_max: (3,) world box of the field (hash grid domain).
        n_levels, n_features, log2_table, base_res, max_res: hash grid (see ``HashGrid``).
        hidden: MLP width.
        n_hidden_layers: hidden layers (1 or 2 in the presets).
        feature_dim: F_z, size of the geometry feature passed to the attribute networks.
        sphere_radius: init sphere radius relative to the half extent of the box.
        softplus_beta: Softplus sharpness (100 keeps analytic second derivatives meaningful).
        backend: ``auto`` | ``torch`` | ``cpp`` (see the module docstring and ``fused_reason``); an attribute
            that may be changed later, not part of the state dict.

    The fused ``cpp`` path serves ``gradient`` and ``gradient_with_encoding`` (all of their outputs are
    differentiable once; a loss on a gradient of their gradients raises) and ``forward``/``sdf`` unless x
    requires a gradient in grad mode (then the torch path runs, so that ``autograd.grad(sdf, x,
    create_graph=True)`` stays available to the caller).

    Presets: ``tiny`` L=8..12, F=2, log2 T=14..16, N_min=16, N_max=256, hidden 32..64, 1 hidden layer,
    feature_dim 13; ``default`` L=16, F=2, log2 T=19, N_min=16, N_max=2048, hidden 64, 1-2 hidden layers,
    feature_dim 13.
    """

    def __init__(
        self,
        bbox_min: Sequence[float] | torch.Tensor,
        bbox_max: Sequence[float] | torch.Tensor,
        n_levels: int = 16,
        n_features: int = 2,
        log2_table: int = 19,
        base_res: int = 16,
        max_res: int = 2048,
        hidden: int = 64,
        n_hidden_layers: int = 1,
        feature_dim: int = 13,
        sphere_radius: float = 0.5,
        softplus_beta: float = 100.0,
        backend: str = "auto",
    ) -> None:
        super().__init__()
        if n_hidden_layers < 1:
            raise ValueError("n_hidden_layers must be >= 1")
        if backend not in BACKENDS:
            raise ValueError(f"SDFNetwork: unknown backend {backend!r} (choose from {', '.join(BACKENDS)})")
        self.backend = backend
        self.encoding = HashGrid(bbox_min, bbox_max, n_levels, n_features, log2_table, base_res, max_res)
        lo, hi = self.encoding.bbox_min, self.encoding.bbox_max
        self.register_buffer("center", 0.5 * (lo + hi))
        self.half_extent = float(0.5 * (hi - lo).max().item())
        self.feature_dim = int(feature_dim)
        self.sphere_radius = float(sphere_radius)
        n_in = 3 + self.encoding.output_dim
        dims = [n_in] + [hidden] * n_hidden_layers + [1 + self.feature_dim]
        self.layers = nn.ModuleList(nn.Linear(dims[i], dims[i + 1]) for i in range(len(dims) - 1))
        self.activation = nn.Softplus(beta=softplus_beta)
        self._geometric_init()

    @property
    def bbox_min(self) -> torch.Tensor:
        """(3,) world box lower corner."""
        return self.encoding.bbox_min

    @property
    def bbox_max(self) -> torch.Tensor:
        """(3,) world box upper corner."""
        return self.encoding.bbox_max

    def _geometric_init(self) -> None:
        with torch.no_grad():
            for i, layer in enumerate(self.layers):
                n_in, n_out = layer.in_features, layer.out_features
                if i == len(self.layers) - 1:
                    nn.init.normal_(layer.weight, 0.0, 1e-4)
                    nn.init.normal_(layer.weight[:1], math.sqrt(math.pi) / math.sqrt(n_in), 1e-4)
                    layer.bias.zero_()
                    layer.bias[0] = -self.sphere_radius
                else:
                    nn.init.normal_(layer.weight, 0.0, math.sqrt(2.0) / math.sqrt(n_out))
                    layer.bias.zero_()
                    if i == 0:
                        layer.weight[:, 3:] = 0.0

    def mlp_parameters(self) -> list[nn.Parameter]:
        """Parameters of the MLP (for a separate learning rate from the grid table)."""
        return list(self.layers.parameters())

    def grid_parameters(self) -> list[nn.Parameter]:
        """The hash table parameter."""
        return [self.encoding.table]

    # ------------------------------------------------------------------ backend choice
    def fused_reason(self, x: torch.Tensor) -> str | None:
        """Why the fused kernel cannot evaluate this network at x (N, 3), or None when it can.

        The kernel needs CPU float32/float64 tensors of one dtype, one hidden layer and a Softplus.
        """
        if x.device.type != "cpu":
            return f"x is on {x.device}"
        if x.dtype not in (torch.float32, torch.float64):
            return f"dtype {x.dtype}"
        if len(self.layers) != 2:
            return f"{len(self.layers) - 1} hidden layers (the fused kernel has one)"
        if not isinstance(self.activation, nn.Softplus):
            return f"activation {type(self.activation).__name__}"
        for t in (self.encoding.table, *self.layers.parameters()):
            if t.device.type != "cpu" or t.dtype != x.dtype:
                return f"a parameter is {t.dtype} on {t.device}, x is {x.dtype}"
        return None

    def resolve_backend(self, x: torch.Tensor) -> str:
        """The backend that evaluates the network at x (N, 3): ``cpp`` or ``torch``.

        ``auto`` gives ``cpp`` when ``fused_reason(x)`` is None and the extension is available (building it
        on first use; a failed build warns once), ``torch`` otherwise. An explicit ``cpp`` raises
        ValueError when the network has more than one hidden layer or the extension cannot be built, and
        falls back to ``torch`` for other tensors (CUDA, float16, mixed dtypes) as ``HashGrid`` does.
        """
        if self.backend not in BACKENDS:
            raise ValueError(f"SDFNetwork: unknown backend {self.backend!r} (choose from {', '.join(BACKENDS)})")
        if self.backend == "torch":
            return "torch"
        why = self.fused_reason(x)
        if why is not None:
            if self.backend == "cpp" and len(self.layers) != 2:
                raise ValueError(f"SDFNetwork: backend='cpp' is unavailable: {why}")
            return "torch"
        from . import _cpp_sdf

        return _cpp_sdf.EXT.choose(self.backend, "SDFNetwork")

    def fused_layout(self, dtype: torch.dtype) -> _cpp_sdf.Layout:
        """The non-trainable part of the network for the fused kernel, for points of ``dtype``."""
        from . import _cpp_sdf

        enc, act = self.encoding, self.activation
        assert isinstance(act, nn.Softplus)
        lo, hi = enc.bbox_min.to(dtype), enc.bbox_max.to(dtype)
        return _cpp_sdf.Layout(
            levels=enc._layout,
            scales=enc._scales.to(torch.float64),
            mask=enc.level_mask.to(torch.float64),
            box=torch.stack([lo, hi - lo, self.center.to(dtype)]),
            half_extent=self.half_extent,
            beta=float(act.beta),
            threshold=float(act.threshold),
        )

    def _fused(
        self, x: torch.Tensor, with_grad: bool, with_encoding: bool = False, keep: bool = True, with_feature: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The native kernel (``_cpp_sdf.evaluate``): x (N, 3) -> sdf (N,), grad (N, 3) (empty unless
        ``with_grad``), feature (N, F_z) (empty unless ``with_feature``), encoding (N, L*F) (empty unless
        ``with_encoding``)."""
        from . import _cpp_sdf

        first, last = self.layers[0], self.layers[1]
        return _cpp_sdf.evaluate(
            x, self.encoding.table, first.weight, first.bias, last.weight, last.bias, self.fused_layout(x.dtype),
            with_grad, with_encoding, keep, with_feature,
        )  # fmt: skip

    # ------------------------------------------------------------------ evaluation
    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (N, 3) world -> sdf (N,) world units, feature (N, feature_dim).

        Fused unless x requires a gradient in grad mode (see the class docstring).
        """
        if self._fused_forward(x):
            sdf, _, feature, _ = self._fused(x, with_grad=False)
            return sdf, feature
        return self._forward_torch(x)

    def _fused_forward(self, x: torch.Tensor) -> bool:
        """Whether ``forward`` at x (N, 3) runs the fused kernel (see the class docstring)."""
        return not (x.requires_grad and torch.is_grad_enabled()) and self.resolve_backend(x) == "cpp"

    def _forward_torch(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The autograd reference of ``forward``."""
        sdf, feature, _ = self._forward_torch_with_encoding(x)
        return sdf, feature

    def _forward_torch_with_encoding(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x (N, 3) -> sdf (N,), feature (N, F_z), encoding (N, L*F), in autograd."""
        xn = (x - self.center.to(x.dtype)) / self.half_extent
        enc = self.encoding(x)
        h = torch.cat([xn, enc], -1)
        for layer in self.layers[:-1]:
            h = self.activation(layer(h))
        out = self.layers[-1](h)
        return out[:, 0] * self.half_extent, out[:, 1:], enc

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, 3) -> sdf (N,), ``forward(x)[0]`` (the fused kernel then leaves the feature out)."""
        if self._fused_forward(x):
            return self._fused(x, with_grad=False, with_feature=False)[0]
        return self._forward_torch(x)[0]

    def gradient(
        self, x: torch.Tensor, create_graph: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Analytic gradient by autograd (``torch``) or by the fused kernel (``cpp``).

        x: (N, 3) -> sdf (N,), grad (N, 3), feature (N, F_z). With ``create_graph`` the gradient is
        differentiable (eikonal loss); otherwise it is detached from the parameters' graph, while
        ``sdf`` and ``feature`` keep theirs (the graph is retained so they can still be
        back-propagated). The graph is built even under ``no_grad``, as by ``autograd.grad``.
        """
        if self.resolve_backend(x) == "cpp":
            with torch.enable_grad():
                sdf, grad, feature, _ = self._fused(x if create_graph else x.detach(), with_grad=True)
            return sdf, (grad if create_graph else grad.detach()), feature
        with torch.enable_grad():
            xg = x if (x.requires_grad and create_graph) else x.detach().requires_grad_(True)
            sdf, feature = self._forward_torch(xg)
            (grad,) = torch.autograd.grad(sdf.sum(), xg, create_graph=create_graph, retain_graph=True)
        return sdf, grad, feature

    def gradient_with_encoding(
        self, x: torch.Tensor, create_graph: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``gradient`` that also returns the hash encoding of x, for networks that share it.

        x: (N, 3) -> sdf (N,), grad (N, 3), feature (N, F_z), encoding (N, L*F). With ``create_graph``
        all four are differentiable (in x and the parameters; the gradient as in ``gradient``). Without
        it sdf, grad and feature are detached, and the encoding keeps its graph to x and the table when
        grad mode is on (and is detached otherwise).
        """
        if self.resolve_backend(x) == "cpp":
            if create_graph:
                with torch.enable_grad():
                    return self._fused(x, with_grad=True, with_encoding=True)
            # only the encoding keeps a graph: its backward recomputes the hash features it needs
            sdf, grad, feature, enc = self._fused(x, with_grad=True, with_encoding=True, keep=False)
            return sdf.detach(), grad.detach(), feature.detach(), enc
        with torch.enable_grad():
            xg = x if (x.requires_grad and create_graph) else x.detach().requires_grad_(True)
            sdf, feature, enc = self._forward_torch_with_encoding(xg)
            (grad,) = torch.autograd.grad(sdf.sum(), xg, create_graph=create_graph)
        if not create_graph:
            sdf, feature = sdf.detach(), feature.detach()
            enc = self.encoding(x) if torch.is_grad_enabled() else enc.detach()
        return sdf, grad, feature, enc

    def sdf_and_normal(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: (N, 3) -> sdf (N,), unit normal (N, 3) (detached gradient direction)."""
        sdf, grad, _ = self.gradient(x)
        return sdf, grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def default_fd_step(self) -> float:
        """Finite-difference step: the finest active cell size in world units."""
        return self.encoding.finest_cell_size()

    def hessian(self, x: torch.Tensor, eps: float | None = None) -> torch.Tensor:
        """x: (N, 3) -> (N, 3, 3) symmetrized central-difference Hessian of the analytic gradient."""
        step = self.default_fd_step() if eps is None else float(eps)
        return hessian_fd(lambda p: self.gradient(p)[1], x, step)

    def curvature(
        self, x: torch.Tensor, eps: float | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """x: (N, 3) -> kappa (N, 2) k1 >= k2, directions (N, 2, 3), normal (N, 3); see principal_curvatures."""
        step = self.default_fd_step() if eps is None else float(eps)
        return principal_curvatures(lambda p: self.gradient(p)[1], x, step)
