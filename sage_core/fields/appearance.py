"""Appearance network f_app(x, v, n, z) -> (colour, opacity), conditioned on the SDF."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ..geometry.sh import sh_basis
from .hashgrid import HashGrid


class AppearanceNetwork(nn.Module):
    """Colour and opacity of a surface point: ``c, alpha = f_app(x, v, n, z)`` (paper eq. for c-hat, alpha-hat).

    Inputs of ``forward``:
        x: (N, 3) canonical world points (normalized with the box given here to [-1, 1]).
        view_dir: (N, 3) unit viewing directions (camera -> point); ignored when ``view_dependent`` is False
            (monocular / one-shot regimes) and may then be None.
        normal: (N, 3) unit SDF normals n = grad f / |grad f|.
        feature: (N, feature_dim) geometry feature z from the SDF network.
    Output: rgb (N, 3) in (0, 1) (sigmoid) and opacity (N,) in (0, 1) (sigmoid).

    Args:
        feature_dim: F_z of the SDF network.
        bbox_min, bbox_max: (3,) box used to normalize x (the SDF box).
        hidden: MLP width; n_layers: hidden layers (ReLU).
        sh_degree: degree (0..3) of the spherical-harmonics view encoding.
        view_dependent: use the view direction.
        opacity_bias: initial bias of the opacity logit (0: surfels start at opacity 0.5; phase 1
            passes logit(app_init_opacity)).
        grid: optional :class:`HashGrid` kwargs (n_levels, n_features, log2_table, base_res, max_res) of
            an appearance-only hash grid over the same box; its features at x join the MLP input.
            The SDF feature z carries colour only through the SDF network, whose hash grid and MLP are
            shaped by the geometry losses; an own grid gives colour detail (iris, lips) its own
            capacity without moving the geometry.

    Presets: ``tiny`` hidden 32, 2 layers, sh_degree 2; ``default`` hidden 64, 2 layers, sh_degree 3.
    """

    def __init__(
        self,
        feature_dim: int,
        bbox_min: Sequence[float] | torch.Tensor,
        bbox_max: Sequence[float] | torch.Tensor,
        hidden: int = 64,
        n_layers: int = 2,
        sh_degree: int = 3,
        view_dependent: bool = True,
        opacity_bias: float = 0.0,
        grid: dict[str, int] | None = None,
    ) -> None:
        super().__init__()
        lo = torch.as_tensor(bbox_min, dtype=torch.float32).reshape(3)
        hi = torch.as_tensor(bbox_max, dtype=torch.float32).reshape(3)
        self.register_buffer("center", 0.5 * (lo + hi))
        self.half_extent = float(0.5 * (hi - lo).max().item())
        self.feature_dim = int(feature_dim)
        self.sh_degree = int(sh_degree)
        self.view_dependent = bool(view_dependent)
        n_view = (self.sh_degree + 1) ** 2 if self.view_dependent else 0
        self.grid: HashGrid | None = HashGrid(lo, hi, **grid) if grid else None
        n_grid = self.grid.output_dim if self.grid is not None else 0
        dims = [3 + n_view + 3 + self.feature_dim + n_grid] + [hidden] * n_layers + [4]
        layers: list[nn.Module] = []
        for i in range(len(dims) - 1):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            if i < len(dims) - 2:
                layers.append(nn.ReLU())
        self.mlp = nn.Sequential(*layers)
        with torch.no_grad():
            last = self.mlp[-1]
            assert isinstance(last, nn.Linear)
            last.bias.zero_()
            last.bias[3] = opacity_bias

    def grid_parameters(self) -> list[nn.Parameter]:
        """The appearance hash table (empty without a grid)."""
        return [self.grid.table] if self.grid is not None else []

    def mlp_parameters(self) -> list[nn.Parameter]:
        """Every parameter but the hash table."""
        return list(self.mlp.parameters())

    def forward(
        self,
        x: torch.Tensor,
        view_dir: torch.Tensor | None,
        normal: torch.Tensor,
        feature: torch.Tensor,
        grid_features: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """See the class docstring: -> rgb (N, 3), opacity (N,). grid_features: (N, L·F) the grid's
        features at x when already computed (the same values as ``self.grid(x)``)."""
        xn = (x - self.center.to(x.dtype)) / self.half_extent
        parts = [xn]
        if self.view_dependent:
            if view_dir is None:
                raise ValueError("view_dir is required when view_dependent is True")
            d = view_dir / view_dir.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            parts.append(sh_basis(d, self.sh_degree))
        parts += [normal, feature]
        if self.grid is not None:
            parts.append(self.grid(x) if grid_features is None else grid_features)
        out = self.mlp(torch.cat(parts, -1))
        return torch.sigmoid(out[:, :3]), torch.sigmoid(out[:, 3])
