"""Image reading and writing through OpenImageIO (PNG 8/16-bit, EXR float).

Images are float32 arrays in [0, 1], shape (H, W, C), linear as stored.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError, require_file


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as float32 (H, W, C) in [0, 1] (EXR values are returned unscaled).

    Raises InputError naming the file when it is missing or unreadable.
    """
    import OpenImageIO as oiio

    path = Path(path)
    require_file(path, "image file")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(path, f"cannot open image: {oiio.geterror()}")
    try:
        spec = inp.spec()
        data = inp.read_image(0, 0, 0, spec.nchannels, "float")
    finally:
        inp.close()
    if data is None or not isinstance(data, np.ndarray):
        raise InputError(path, "cannot decode image")
    data = np.asarray(data, dtype=np.float32)
    if data.ndim == 2:
        data = data[:, :, None]
    return data


def image_size(path: str | Path) -> tuple[int, int, int]:
    """(width, height, channels) read from the header only."""
    import OpenImageIO as oiio

    path = Path(path)
    require_file(path, "image file")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(path, f"cannot open image: {oiio.geterror()}")
    try:
        spec = inp.spec()
        return int(spec.width), int(spec.height), int(spec.nchannels)
    finally:
        inp.close()


def write_image(path: str | Path, image: np.ndarray, bits: int = 8) -> None:
    """Write an image atomically (temp file + rename).

    image: (H, W) or (H, W, C) float in [0, 1] (clamped for integer formats). The format follows
    the suffix: ``.png`` (``bits`` 8 or 16), ``.exr`` (half float), ``.jpg``.
    """
    import OpenImageIO as oiio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[:, :, None]
    h, w, c = img.shape
    suffix = path.suffix.lower()
    if suffix == ".exr":
        fmt = oiio.HALF
        data = img
    else:
        data = np.clip(img, 0.0, 1.0)
        if bits == 16:
            fmt = oiio.UINT16
            data = np.round(data * 65535.0).astype(np.uint16)
        else:
            fmt = oiio.UINT8
            data = np.round(data * 255.0).astype(np.uint8)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OSError(f"{path}: no image writer for this format: {oiio.geterror()}")
        spec = oiio.ImageSpec(w, h, c, fmt)
        if suffix == ".exr":
            spec.attribute("compression", "zip")
        if not out.open(str(tmp), spec):
            raise OSError(f"{path}: cannot write: {out.geterror()}")
        ok = out.write_image(np.ascontiguousarray(data))
        out.close()
        if not ok:
            raise OSError(f"{path}: write failed")
