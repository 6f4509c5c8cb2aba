"""Per-frame exposure gain for single-camera clips (SV-HR, one-shot).

When a head turns under lighting fixed in the world, and a phone camera adapts its exposure, the
same skin changes brightness from frame to frame. A view-independent colour explains the shared
appearance; a per-frame gain g_i (scalar, or one per channel) explains the rest. It multiplies the
foreground only, so the known background stays put:

    C' = g_i·(C − (1 − α)·b) + (1 − α)·b,

with α the rendered opacity and b the background. Gains are stored as log g (initialised to 0,
g = 1) and held near 1 by the weak prior mean((log g)²).
"""

from __future__ import annotations

import torch
from torch import nn


class ExposureGain(nn.Module):
    """Per-frame log gains ``log_gain`` (n_frames, C), C = 3 per channel or 1."""

    def __init__(self, n_frames: int, per_channel: bool = False) -> None:
        super().__init__()
        if n_frames < 1:
            raise ValueError("n_frames must be at least 1")
        self.per_channel = bool(per_channel)
        self.log_gain = nn.Parameter(torch.zeros(n_frames, 3 if per_channel else 1))

    @property
    def n_frames(self) -> int:
        return int(self.log_gain.shape[0])

    def gain(self, index: int) -> torch.Tensor:
        """(C,) gain of one frame."""
        return torch.exp(self.log_gain[index])

    def gains(self) -> torch.Tensor:
        """(n_frames, C) all gains."""
        return torch.exp(self.log_gain)

    def apply(self, color: torch.Tensor, alpha: torch.Tensor, index: int, background: torch.Tensor | float) -> torch.Tensor:
        """Scale the foreground of a render.

        color: (..., 3) composited on ``background``; alpha: (...) or (..., 1) opacity; index: the
        frame -> (..., 3).
        """
        a = alpha if alpha.dim() == color.dim() else alpha[..., None]
        bg = torch.as_tensor(background, dtype=color.dtype, device=color.device)
        back = (1.0 - a) * bg
        g = self.gain(index).to(color)
        return g * (color - back) + back

    def prior(self) -> torch.Tensor:
        """Weak prior toward g = 1: mean((log g)²), 0-d."""
        return (self.log_gain**2).mean()
