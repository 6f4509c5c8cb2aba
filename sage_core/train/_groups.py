"""Optimizer parameter groups shared by the training phases."""

from __future__ import annotations

from typing import Any

import torch

from ..avatar.model import Avatar


def surfel_param_groups(
    avatar: Avatar,
    *,
    lr_position: float,
    lr_networks: float,
    lr_rotation: float,
    lr_scale: float,
    lr_color: float,
    lr_opacity: float,
    lr_shape: float | None = None,
    lr_app_grid: float | None = None,
    lr_opacity_offset: float = 0.0,
) -> list[dict[str, Any]]:
    """Named Adam groups of the surfels and their attribute heads.

    Always: the local offsets ``mu_loc`` and the appearance network. With attribute networks
    (``mlp``) the shape network; with free attributes the per-surfel rotation, scale, SH colour
    (the higher bands at 1/20 of the DC rate) and opacity. ``lr_shape`` (default ``lr_networks``)
    is the shape network's rate; ``lr_app_grid`` (default ``lr_networks``) the rate of the appearance
    network's own hash table when it has one; ``lr_opacity_offset`` the rate of the per-surfel opacity
    offset of attribute-network surfels that have one (:meth:`SurfelSet.enable_opacity_offset`).
    Groups whose rate is 0 are left out (those parameters stay fixed).
    """
    groups: list[dict[str, Any]] = [
        {"name": "mu_loc", "params": [avatar.surfels.mu_loc], "lr": lr_position},
        {"name": "appearance", "params": avatar.appearance.mlp_parameters(), "lr": lr_networks},
    ]
    if avatar.appearance.grid is not None:
        groups.append({"name": "appearance_grid", "params": avatar.appearance.grid_parameters(),
                       "lr": lr_networks if lr_app_grid is None else lr_app_grid})
    if avatar.shape is not None:
        groups.append({"name": "shape", "params": list(avatar.shape.parameters()), "lr": lr_networks if lr_shape is None else lr_shape})
        if avatar.surfels.opacity_offset is not None:
            groups.append({"name": "opacity_offset", "params": [avatar.surfels.opacity_offset], "lr": lr_opacity_offset})
        return [g for g in groups if g["lr"] > 0]
    s = avatar.surfels
    groups += [
        {"name": "q_loc", "params": [s.q_loc], "lr": lr_rotation},
        {"name": "s_loc", "params": [s.s_loc], "lr": lr_scale},
        {"name": "sh_dc", "params": [s.sh_dc], "lr": lr_color},
        {"name": "opacity", "params": [s.opacity], "lr": lr_opacity},
    ]
    if hasattr(s, "sh_rest"):
        groups.append({"name": "sh_rest", "params": [s.sh_rest], "lr": lr_color / 20.0})
    return [g for g in groups if g["lr"] > 0]


def adam(groups: list[dict[str, Any]]) -> torch.optim.Adam:
    """Adam over ``groups`` as one fused kernel per parameter where this torch has one for the
    parameters' device (the same update, to rounding), else the default implementation. A resumed
    optimizer takes the setting of its checkpoint."""
    try:  # on copies: a refused attempt has already written its defaults into the groups
        return torch.optim.Adam([dict(g) for g in groups], eps=1e-15, fused=True)
    except (RuntimeError, ValueError):  # no fused kernel for this device in this torch
        return torch.optim.Adam([dict(g) for g in groups], eps=1e-15)
