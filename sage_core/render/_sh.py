"""Spherical harmonics for the rasterizer (defined in :mod:`sage_core.geometry.sh`)."""

from ..geometry.sh import eval_sh_colors, num_sh_coeffs, sh_basis

__all__ = ["eval_sh_colors", "num_sh_coeffs", "sh_basis"]
