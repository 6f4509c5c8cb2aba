"""The shared image reader: headers (size, EXIF orientation and focal length), upright reading,
16-bit and alpha channels kept, and errors that name the file."""

from __future__ import annotations

import numpy as np
import pytest

from sage_core.data.imageio import ImageHeader, apply_orientation, image_size, read_header, read_image, write_image
from sage_core.errors import InputError


def _upright_by_definition(a: np.ndarray, orientation: int) -> np.ndarray:
    """The upright image of pixels ``a`` (H, W, C) stored with an EXIF orientation, pixel by pixel from
    the EXIF definitions (2 mirror, 3 rotate 180°, 4 flip, 5 transpose, 6 rotate 90° clockwise,
    7 transverse, 8 rotate 90° anticlockwise)."""
    H, W = a.shape[:2]
    swap = orientation in (5, 6, 7, 8)
    out = np.zeros((W, H, a.shape[2]) if swap else a.shape, a.dtype)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            src = {1: (i, j), 2: (i, W - 1 - j), 3: (H - 1 - i, W - 1 - j), 4: (H - 1 - i, j),
                   5: (j, i), 6: (H - 1 - j, i), 7: (H - 1 - j, W - 1 - i), 8: (j, W - 1 - i)}[orientation]
            out[i, j] = a[src]
    return out


@pytest.mark.parametrize("orientation", range(1, 9))
def test_every_exif_orientation_turns_the_image_upright(orientation):
    a = np.arange(2 * 3 * 2, dtype=np.float32).reshape(2, 3, 2)
    got = apply_orientation(a, orientation)
    assert np.array_equal(got, _upright_by_definition(a, orientation)) and got.flags.c_contiguous
    assert apply_orientation(a[:, :, 0], orientation).shape == got.shape[:2]  # (H, W) images too
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(oiio.ImageSpec(3, 2, 2, oiio.FLOAT))  # OpenImageIO's own reorientation agrees
    buf.set_pixels(oiio.ROI(), a)
    buf.specmod().attribute("Orientation", orientation)
    np.testing.assert_array_equal(oiio.ImageBufAlgo.reorient(buf).get_pixels(oiio.FLOAT), got)


def _write_tiff(path, pixels: np.ndarray, orientation: int, focal_35mm: int | None = None):
    import OpenImageIO as oiio

    h, w, c = pixels.shape
    spec = oiio.ImageSpec(w, h, c, oiio.UINT16)
    spec.attribute("Orientation", orientation)
    if focal_35mm is not None:
        spec.attribute("Exif:FocalLengthIn35mmFilm", focal_35mm)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.round(pixels * 65535).astype(np.uint16))
    out.close()
    return path


def test_header_and_upright_reading_of_a_rotated_16_bit_photo(tmp_path):
    rng = np.random.default_rng(0)
    stored = (rng.integers(0, 65536, (5, 7, 3)) / 65535.0).astype(np.float32)
    path = _write_tiff(tmp_path / "photo.tif", stored, 6, 26)
    head = read_header(path)
    assert head == ImageHeader(7, 5, 3, 6, pytest.approx(26.0))
    assert head.upright_size == (5, 7) and head.focal_px == pytest.approx(26 / 36 * 7)
    assert image_size(path) == (7, 5, 3)  # as stored
    np.testing.assert_array_equal(read_image(path), stored)  # 16-bit values exactly, as stored
    up = read_image(path, upright=True)
    assert up.shape == (7, 5, 3) and up.dtype == np.float32
    np.testing.assert_array_equal(up, _upright_by_definition(stored, 6))
    write_image(tmp_path / "plain.png", stored)
    plain = read_header(tmp_path / "plain.png")
    assert plain.orientation == 1 and plain.focal_35mm is None and plain.focal_px is None and plain.upright_size == (7, 5)


def test_grey_and_alpha_channels_are_kept(tmp_path):
    import cv2

    bgra = np.zeros((3, 4, 4), np.uint16)
    bgra[..., 0], bgra[..., 1], bgra[..., 2] = 1000, 30000, 60000
    bgra[..., 3] = np.array([0, 65535, 32768, 16384])[None]  # PNG stores colours unassociated with alpha
    assert cv2.imwrite(str(tmp_path / "rgba.png"), bgra)
    got = read_image(tmp_path / "rgba.png")
    alpha = bgra[..., 3:] / 65535.0
    assert got.shape == (3, 4, 4) and got.dtype == np.float32
    np.testing.assert_allclose(got[..., 3:], alpha, atol=1e-6)
    np.testing.assert_allclose(got[..., :3], bgra[..., 2::-1] / 65535.0 * alpha, atol=1e-4)  # colours come premultiplied
    grey = (np.arange(12).reshape(3, 4) * 5000).astype(np.uint16)
    assert cv2.imwrite(str(tmp_path / "grey16.png"), grey)
    got = read_image(tmp_path / "grey16.png")
    assert got.shape == (3, 4, 1)
    np.testing.assert_array_equal(got[..., 0], (grey / 65535.0).astype(np.float32))  # 16-bit exactly


def test_unreadable_images_are_named(tmp_path):
    good = tmp_path / "good.png"
    write_image(good, np.random.default_rng(0).random((64, 64, 3)).astype(np.float32))  # the cut lands in the pixels
    (tmp_path / "garbage.png").write_bytes(b"\x00not an image" * 10)
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    (tmp_path / "folder.png").mkdir()
    jpg = tmp_path / "good.jpg"
    write_image(jpg, np.random.default_rng(1).random((64, 80, 3)).astype(np.float32))
    (tmp_path / "cut.jpg").write_bytes(jpg.read_bytes()[: len(jpg.read_bytes()) // 2])  # libjpeg would fill it with grey
    assert read_image(jpg).shape == (64, 80, 3)
    cases = {"missing.png": "image file not found", "folder.png": "is a folder", "garbage.png": "cannot open the image",
             "cut.png": "cannot decode the image (truncated or corrupt file)",
             "cut.jpg": "cannot decode the image (truncated file: the data ends early)"}
    for name, text in cases.items():
        with pytest.raises(InputError, match=text.replace("(", r"\(").replace(")", r"\)")) as e:
            read_image(tmp_path / name, upright=True)
        assert e.value.path == tmp_path / name
    for name in ("missing.png", "garbage.png"):
        with pytest.raises(InputError) as e:
            read_header(tmp_path / name)
        assert e.value.path == tmp_path / name


def test_half_transparent_pixels_on_white_take_their_alpha_once(tmp_path):
    """A PNG pixel of colour c (stored unassociated) at alpha a shows c·a + (1 - a) on white, in the
    shared helper, in sage track's reader and in the reader sage ingest uses."""
    import cv2

    from sage_core.data.imageio import over_white
    from sage_core.data.imageio import read_on_white
    from sage_core.track.inputs import read_rgb

    bgra = np.zeros((2, 3, 4), np.uint8)
    bgra[..., :3] = 200
    bgra[..., 3] = np.array([255, 128, 0], np.uint8)[None]
    assert cv2.imwrite(str(tmp_path / "edge.png"), bgra)
    a = np.array([255, 128, 0]) / 255.0
    want = 200 / 255.0 * a + (1 - a)  # 0.784, 0.894, 1.0
    for got in (over_white(read_image(tmp_path / "edge.png")), read_rgb(tmp_path / "edge.png"), read_on_white(tmp_path / "edge.png")):
        assert got.shape == (2, 3, 3)
        np.testing.assert_allclose(got[0, :, 0], want, atol=2e-3)
    grey = over_white(np.full((1, 2, 2), 0.25, np.float32))  # grey 0.25 premultiplied at alpha 0.25
    np.testing.assert_allclose(grey, 1.0)
    with pytest.raises(ValueError):
        over_white(np.zeros((1, 1, 5), np.float32))
    five = tmp_path / "five.exr"
    write_image(five, np.zeros((2, 2, 5), np.float32))
    with pytest.raises(InputError, match="5 channels") as e:
        read_on_white(five)
    assert e.value.path == five
