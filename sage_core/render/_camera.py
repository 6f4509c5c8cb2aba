"""Camera tensors consumed by the surfel rasterizer."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

if TYPE_CHECKING:  # the rasterizer reads any object with K, w2c, width and height
    from ..data.cameras import Camera


@dataclass
class RenderCamera:
    """One camera or a batch of C cameras sharing an image size, as torch tensors.

    OpenCV axes (x right, y down, z forward), pixel centres at +0.5 (pixel column j spans
    [j, j+1] and is sampled at x = j + 0.5).

    Attributes:
        K: (3, 3) or (C, 3, 3) intrinsics in pixels.
        w2c: (4, 4) or (C, 4, 4) world-to-camera.
        width, height: image size in pixels.
    """

    K: torch.Tensor
    w2c: torch.Tensor
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.K.shape[-2:] != (3, 3) or self.K.dim() not in (2, 3):
            raise ValueError(f"RenderCamera.K must be (3,3) or (C,3,3), got {tuple(self.K.shape)}")
        if self.w2c.shape[-2:] != (4, 4) or self.w2c.dim() != self.K.dim():
            raise ValueError(f"RenderCamera.w2c must be (4,4) or (C,4,4) like K, got {tuple(self.w2c.shape)}")
        if self.K.dim() == 3 and self.K.shape[0] != self.w2c.shape[0]:
            raise ValueError("RenderCamera.K and w2c disagree on the number of cameras")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"RenderCamera size must be positive, got {self.width}x{self.height}")
        self.width = int(self.width)
        self.height = int(self.height)

    @property
    def batched(self) -> bool:
        """True when the tensors carry a leading camera dimension."""
        return self.K.dim() == 3

    @property
    def num_cameras(self) -> int:
        """C for a batch, 1 for a single camera."""
        return int(self.K.shape[0]) if self.batched else 1

    def select(self, i: int) -> "RenderCamera":
        """Camera i of a batch as a single (unbatched) camera."""
        if not self.batched:
            if i != 0:
                raise IndexError(i)
            return self
        return RenderCamera(self.K[i], self.w2c[i], self.width, self.height)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "RenderCamera":
        """The same camera(s) on another device / dtype."""
        return RenderCamera(self.K.to(device=device, dtype=dtype), self.w2c.to(device=device, dtype=dtype), self.width, self.height)

    @staticmethod
    def from_camera(cam: Camera, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> "RenderCamera":
        """Single camera from a :class:`sage_core.data.cameras.Camera`."""
        K = torch.as_tensor(np.asarray(cam.K, dtype=np.float64), dtype=dtype, device=device)
        w2c = torch.as_tensor(np.asarray(cam.w2c, dtype=np.float64), dtype=dtype, device=device)
        return RenderCamera(K, w2c, int(cam.width), int(cam.height))

    @staticmethod
    def from_cameras(
        cams: Sequence[Camera], device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
    ) -> "RenderCamera":
        """Batch of C cameras; all must share one image size."""
        if len(cams) == 0:
            raise ValueError("from_cameras needs at least one camera")
        sizes = {(int(c.width), int(c.height)) for c in cams}
        if len(sizes) != 1:
            raise ValueError(f"cameras in a batch must share one image size, got {sorted(sizes)}")
        K = torch.as_tensor(np.stack([np.asarray(c.K, np.float64) for c in cams]), dtype=dtype, device=device)
        w2c = torch.as_tensor(np.stack([np.asarray(c.w2c, np.float64) for c in cams]), dtype=dtype, device=device)
        return RenderCamera(K, w2c, int(cams[0].width), int(cams[0].height))

    @staticmethod
    def stack(cams: Sequence["RenderCamera"]) -> "RenderCamera":
        """Batch from single RenderCameras of one image size."""
        if len(cams) == 0:
            raise ValueError("stack needs at least one camera")
        if len({(c.width, c.height) for c in cams}) != 1 or any(c.batched for c in cams):
            raise ValueError("stack needs unbatched cameras of one image size")
        return RenderCamera(torch.stack([c.K for c in cams]), torch.stack([c.w2c for c in cams]), cams[0].width, cams[0].height)
