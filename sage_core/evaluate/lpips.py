"""LPIPS v0.1 (Zhang et al. 2018) with an AlexNet backbone, loaded from a local state dict.

The network is built here from plain torch layers laid out like torchvision's
``alexnet().features`` (so the state-dict keys ``features.{0,3,6,8,10}.*`` match), plus the five
1×1 linear heads ``lin.{0..4}.weight``. Weights are never downloaded: the file is found by
:func:`find_lpips_weights` (explicit path, then ``$SAGE_LPIPS_WEIGHTS``, then
``~/.cache/sage/lpips_alex_v0.1.pth``). When no file is found, LPIPS is unavailable and callers
report ``None`` (:func:`load_lpips_or_none`, :func:`lpips_or_none`), never a number.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from pathlib import Path

import torch
import torch.nn as nn

from ..errors import InputError, require_file
from ..workspace import file_sha256

ENV_VAR = "SAGE_LPIPS_WEIGHTS"
DEFAULT_CACHE_PATH = Path("~/.cache/sage/lpips_alex_v0.1.pth")
LPIPS_ALEX_SHA256 = "a27c00d6924e2f5624ef7ebbd35e58220712595fd71f4a2f309742e8d8c4308f"

# scaling layer of LPIPS, applied to inputs in [-1, 1]
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
_TAP_CHANNELS = (64, 192, 384, 256, 256)
_EPS = 1e-10

EXPECTED_SHAPES: dict[str, tuple[int, ...]] = {
    "features.0.weight": (64, 3, 11, 11),
    "features.0.bias": (64,),
    "features.3.weight": (192, 64, 5, 5),
    "features.3.bias": (192,),
    "features.6.weight": (384, 192, 3, 3),
    "features.6.bias": (384,),
    "features.8.weight": (256, 384, 3, 3),
    "features.8.bias": (256,),
    "features.10.weight": (256, 256, 3, 3),
    "features.10.bias": (256,),
    **{f"lin.{i}.weight": (1, c, 1, 1) for i, c in enumerate(_TAP_CHANNELS)},
}


def default_weights_path() -> Path:
    """The default cache location, ``~/.cache/sage/lpips_alex_v0.1.pth`` (user-expanded)."""
    return DEFAULT_CACHE_PATH.expanduser()


def find_lpips_weights(explicit: str | Path | None = None) -> Path | None:
    """Locate the LPIPS AlexNet weights file.

    Order: ``explicit`` (``--lpips-weights``), then ``$SAGE_LPIPS_WEIGHTS``, then the default cache
    path. A path the user named (argument or environment variable) that is not a file raises
    :class:`InputError`; only an absent default file returns None (LPIPS unavailable).
    """
    if explicit is not None and str(explicit) != "":
        p = Path(explicit).expanduser()
        require_file(p, "LPIPS weights file (--lpips-weights)")
        return p
    env = os.environ.get(ENV_VAR, "")
    if env:
        p = Path(env).expanduser()
        require_file(p, f"LPIPS weights file (${ENV_VAR})")
        return p
    p = default_weights_path()
    return p if p.is_file() else None


def load_lpips_state_dict(path: str | Path, check_sha256: bool = False) -> dict[str, torch.Tensor]:
    """Load and validate the LPIPS AlexNet state dict (docs/formats.md §8.1: 15 float tensors).

    Raises :class:`InputError` naming the file when it cannot be read, is not a state dict, lacks
    or adds keys, or has a wrong shape; with ``check_sha256`` also when its hash differs from
    :data:`LPIPS_ALEX_SHA256`.
    """
    path = Path(path)
    require_file(path, "LPIPS weights file")
    if check_sha256:
        digest = file_sha256(path)
        if digest != LPIPS_ALEX_SHA256:
            raise InputError(path, f"sha256 {digest} does not match the expected LPIPS weights")
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, OSError, EOFError, ValueError, pickle.UnpicklingError,
            zipfile.BadZipFile) as e:
        raise InputError(path, f"cannot be read as a PyTorch state dict ({e})") from e
    if not isinstance(sd, dict):
        raise InputError(path, f"expected a state dict, found {type(sd).__name__}")
    missing = sorted(set(EXPECTED_SHAPES) - set(sd))
    extra = sorted(set(sd) - set(EXPECTED_SHAPES))
    if missing or extra:
        raise InputError(
            path,
            "not an LPIPS AlexNet v0.1 state dict"
            + (f"; missing keys {missing}" if missing else "")
            + (f"; unexpected keys {extra}" if extra else ""),
        )
    for k, shape in EXPECTED_SHAPES.items():
        v = sd[k]
        if not isinstance(v, torch.Tensor) or not v.is_floating_point():
            raise InputError(path, f"entry {k!r} is not a floating-point tensor")
        if tuple(v.shape) != shape:
            raise InputError(path, f"entry {k!r} has shape {tuple(v.shape)}, expected {shape}")
    return {k: sd[k].float() for k in EXPECTED_SHAPES}


def _alexnet_features() -> nn.Sequential:
    """AlexNet convolutional trunk with torchvision's ``features`` indices (0..11 used)."""
    return nn.Sequential(
        nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),  # 0
        nn.ReLU(inplace=False),  # 1  tap 1
        nn.MaxPool2d(kernel_size=3, stride=2),  # 2
        nn.Conv2d(64, 192, kernel_size=5, padding=2),  # 3
        nn.ReLU(inplace=False),  # 4  tap 2
        nn.MaxPool2d(kernel_size=3, stride=2),  # 5
        nn.Conv2d(192, 384, kernel_size=3, padding=1),  # 6
        nn.ReLU(inplace=False),  # 7  tap 3
        nn.Conv2d(384, 256, kernel_size=3, padding=1),  # 8
        nn.ReLU(inplace=False),  # 9  tap 4
        nn.Conv2d(256, 256, kernel_size=3, padding=1),  # 10
        nn.ReLU(inplace=False),  # 11 tap 5
    )


_TAP_INDICES = (1, 4, 7, 9, 11)


class LPIPS(nn.Module):
    """LPIPS v0.1, AlexNet. Parameters are frozen; gradients flow to the inputs.

    rescale_inputs: True (default) maps inputs in [0, 1] to [-1, 1] with ``2x − 1`` as the LPIPS
    recipe requires; False feeds [0, 1] images directly, reproducing the GaussianAvatars
    evaluation quirk (its values are not comparable with the standard ones).
    """

    def __init__(self, rescale_inputs: bool = True) -> None:
        super().__init__()
        self.rescale_inputs = rescale_inputs
        self.features = _alexnet_features()
        self.lin = nn.ModuleList(nn.Conv2d(c, 1, kernel_size=1, bias=False) for c in _TAP_CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1), persistent=False)
        self.requires_grad_(False)
        self.eval()

    @classmethod
    def from_path(
        cls,
        path: str | Path,
        device: torch.device | str = "cpu",
        rescale_inputs: bool = True,
        check_sha256: bool = False,
    ) -> "LPIPS":
        """Build the network from a weights file (see :func:`load_lpips_state_dict`)."""
        model = cls(rescale_inputs=rescale_inputs)
        model.load_state_dict(load_lpips_state_dict(path, check_sha256=check_sha256), strict=True)
        return model.to(device)

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out: list[torch.Tensor] = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAP_INDICES:
                out.append(x)
        return out

    def forward(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """LPIPS distance per image.

        pred, gt: (B, 3, H, W) or (3, H, W), values in [0, 1] -> (B,) or 0-d.
        Inputs are not clamped (the evaluation protocol clamps before calling).
        """
        if pred.shape != gt.shape:
            raise ValueError(f"image shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
        single = pred.dim() == 3
        if single:
            pred, gt = pred.unsqueeze(0), gt.unsqueeze(0)
        if pred.dim() != 4 or pred.shape[1] != 3:
            raise ValueError(f"expected (B, 3, H, W) or (3, H, W), got {tuple(pred.shape)}")
        dtype = self.shift.dtype
        b = pred.shape[0]
        x = torch.cat([pred, gt], 0).to(dtype)
        if self.rescale_inputs:
            x = 2.0 * x - 1.0
        x = (x - self.shift) / self.scale
        total = x.new_zeros(b)
        for lin, f in zip(self.lin, self._taps(x)):
            n = f / (f.square().sum(1, keepdim=True).sqrt() + _EPS)
            d = (n[:b] - n[b:]).square()
            total = total + lin(d).mean((1, 2, 3))
        return total[0] if single else total


def load_lpips_or_none(
    explicit: str | Path | None = None,
    device: torch.device | str = "cpu",
    rescale_inputs: bool = True,
) -> LPIPS | None:
    """Find and load LPIPS, or return None when no weights file is configured or cached.

    A file the user named but that is missing or malformed raises :class:`InputError`.
    """
    path = find_lpips_weights(explicit)
    if path is None:
        return None
    return LPIPS.from_path(path, device=device, rescale_inputs=rescale_inputs)


@torch.no_grad()
def lpips_or_none(
    model: LPIPS | None, pred: torch.Tensor, gt: torch.Tensor
) -> torch.Tensor | None:
    """LPIPS per image for evaluation, or None when the model is unavailable.

    pred, gt: (B, 3, H, W) or (3, H, W) in [0, 1] -> (B,) / 0-d, or None. No gradients.
    """
    if model is None:
        return None
    return model(pred, gt)
