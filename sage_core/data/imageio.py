"""Image reading and writing through OpenImageIO (PNG 8/16-bit, JPEG, TIFF, EXR float, ...).

Images are float32 arrays in [0, 1], shape (H, W, C), linear as stored. Headers (size, EXIF
orientation and focal length) can be read without decoding the pixels (:func:`read_header`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_path
from ..errors import InputError, require_file


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header says, before any pixel is decoded.

    Attributes:
        width, height, channels: as stored in the file.
        orientation: EXIF orientation 1..8 (1: upright as stored; 5..8 swap width and height).
        focal_35mm: EXIF ``FocalLengthIn35mmFilm`` in millimetres, or None when absent.
    """

    width: int
    height: int
    channels: int
    orientation: int = 1
    focal_35mm: float | None = None

    @property
    def upright_size(self) -> tuple[int, int]:
        """(width, height) of the image once its EXIF orientation is applied."""
        return (self.height, self.width) if self.orientation in (5, 6, 7, 8) else (self.width, self.height)

    @property
    def focal_px(self) -> float | None:
        """The 35 mm equivalent focal length in pixels (36 mm across the longer side), or None."""
        if self.focal_35mm is None:
            return None
        return self.focal_35mm / 36.0 * max(self.width, self.height)


def apply_orientation(image: np.ndarray, orientation: int) -> np.ndarray:
    """Turn/mirror an image (H, W, ...) stored with EXIF orientation 1..8 so it shows upright.

    Returns a contiguous array, (W, H, ...) for orientations 5..8; other values return ``image``.
    """
    ops = {2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
           5: lambda a: np.swapaxes(a, 0, 1), 6: lambda a: np.rot90(a, -1),
           7: lambda a: np.swapaxes(a[::-1, ::-1], 0, 1), 8: lambda a: np.rot90(a, 1)}
    return np.ascontiguousarray(ops[orientation](image)) if orientation in ops else image


TRUNCATED = "Premature end of JPEG file"
"""libjpeg's message for a file whose data stops before the image ends (other libjpeg warnings, such as
extraneous bytes, also come with readable files and are not errors)."""


def _open(path: Path) -> Any:
    """An open OpenImageIO input of ``path``; InputError naming the file when it is missing or unreadable."""
    import OpenImageIO as oiio

    require_file(path, "image file")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(path, f"cannot open the image ({oiio.geterror().strip() or 'unknown format'})")
    return inp


def _header_of(spec: Any) -> ImageHeader:
    f35 = float(spec.get_float_attribute("Exif:FocalLengthIn35mmFilm", 0.0))
    return ImageHeader(int(spec.width), int(spec.height), int(spec.nchannels),
                       int(spec.get_int_attribute("Orientation", 1)), f35 if f35 > 0 else None)


def read_header(path: str | Path) -> ImageHeader:
    """The header of an image file (size, channels, EXIF orientation and focal length), no pixels.

    Raises InputError naming the file when it is missing or unreadable.
    """
    path = Path(path)
    inp = _open(path)
    try:
        return _header_of(inp.spec())
    finally:
        inp.close()


def read_image(path: str | Path, upright: bool = False) -> np.ndarray:
    """Read an image as float32 (H, W, C) in [0, 1] (EXR values are returned unscaled).

    8- and 16-bit files are scaled to [0, 1]; every channel is kept (grey (H, W, 1), alpha last, the
    colours then premultiplied by it as OpenImageIO associates alpha on reading).
    upright: apply the file's EXIF orientation (photos from phones and cameras), so (H, W) are the
    upright size (:attr:`ImageHeader.upright_size`); False returns the pixels as stored.
    Raises InputError naming the file when it is missing, unreadable, truncated or corrupt.
    """
    path = Path(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        orientation = _header_of(spec).orientation
        data = inp.read_image(0, 0, 0, spec.nchannels, "float")
        error = inp.geterror()
    finally:
        inp.close()
    if TRUNCATED in error:  # libjpeg fills the missing rows with grey and only warns
        raise InputError(path, "cannot decode the image (truncated file: the data ends early)")
    if data is None or not isinstance(data, np.ndarray) or data.size == 0:
        raise InputError(path, "cannot decode the image (truncated or corrupt file)")
    data = np.asarray(data, dtype=np.float32)
    if data.ndim == 2:
        data = data[:, :, None]
    return apply_orientation(data, orientation) if upright else data


def over_white(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) colours of an image read by :func:`read_image` on a white background.

    image: (H, W, C) with C = 1 (grey), 2 (grey, alpha), 3 (RGB) or 4 (RGBA). The colours of an image
    with alpha are premultiplied (as read), so white is added where the alpha is below one:
    ``rgb + (1 - alpha)``; grey is repeated to three channels. Raises ValueError for other C.
    """
    c = image.shape[2]
    if c not in (1, 2, 3, 4):
        raise ValueError(f"image has {c} channels, expected 1 to 4")
    rgb = image[:, :, : 3 if c >= 3 else 1]
    if c in (2, 4):
        rgb = rgb + (1.0 - image[:, :, -1:])
    if rgb.shape[2] == 1:
        rgb = np.repeat(rgb, 3, axis=2)
    return rgb


def read_on_white(path: str | Path, upright: bool = False) -> np.ndarray:
    """An image file as (H, W, 3) float32 on white: :func:`read_image` then :func:`over_white`.

    Raises InputError naming the file as :func:`read_image` does, and for a channel count other than 1 to 4.
    """
    try:
        return np.ascontiguousarray(over_white(read_image(path, upright=upright)), dtype=np.float32)
    except ValueError as exc:
        raise InputError(Path(path), str(exc)) from None


def image_size(path: str | Path) -> tuple[int, int, int]:
    """(width, height, channels) read from the header only, as stored (no EXIF orientation)."""
    h = read_header(path)
    return h.width, h.height, h.channels


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
