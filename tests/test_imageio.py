"""Image reading, bit-depth detection, dark/flat correction and error reporting (scene/imageio.py).

Real frames are read from ../shared/data/real (or $DUALSIGHT_SHARED/data/real); tests that need them skip
with a reason when absent.  The other truths are synthetic arrays written by OpenCV / astropy themselves.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dualsight.errors import ImageError, InputError
from dualsight.scene.imageio import (Image, calibrate_frame, effective_bit_depth, list_images, read_image,
                                     read_images)
from helpers import shared_real

ESA = shared_real() / "esa_tetra3"
CHESS = shared_real() / "opencv_chessboard"
ESA_FRAME = ESA / "2019-07-29T204726_Alt40_Azi-135_Try1.tiff"
ESA_SATURATED = ESA / "2019-07-29T204726_Alt40_Azi135_Try1.tiff"  # has 65535 (saturated) pixels
CHESS_JPG = CHESS / "left01.jpg"

needs_esa = pytest.mark.skipif(not ESA_FRAME.exists(), reason=f"real ESA tetra3 frames not found at {ESA}")
needs_chess = pytest.mark.skipif(not CHESS_JPG.exists(), reason=f"real OpenCV chessboard photos not found at {CHESS}")


# ---------------------------------------------------------------------------------------------- real frames
@needs_esa
@pytest.mark.parametrize("frame", [ESA_FRAME, ESA_SATURATED], ids=["plain", "saturated"])
def test_esa_tiff_is_12_bit_shifted_by_4(frame):
    img = read_image(frame)
    assert img.pixels.dtype == np.uint16 and img.pixels.shape == (768, 1024)
    assert (img.bit_depth, img.shift, img.channels) == (12, 4, 1)
    assert img.full_scale == 0xFFF0
    counts = img.adc_counts()
    assert counts.max() <= 4095
    # values below saturation really are multiples of 16 (README: 12-bit values shifted left by 4)
    unsat = img.pixels[img.pixels < 65535]
    assert np.all(unsat % 16 == 0)
    assert np.array_equal(counts[img.pixels < 65535] * 16, unsat)


@needs_chess
def test_chessboard_jpeg_is_8_bit_gray():
    img = read_image(CHESS_JPG)
    assert img.pixels.dtype == np.uint8 and img.pixels.shape == (480, 640)
    assert (img.bit_depth, img.shift, img.channels, img.width, img.height) == (8, 0, 1, 640, 480)
    ref = cv2.imread(str(CHESS_JPG), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(img.pixels, ref)


# ---------------------------------------------------------------------------------------------- formats
def _rgb(h=12, w=17, dtype=np.uint8, seed=0):
    rng = np.random.default_rng(seed)
    hi = np.iinfo(dtype).max
    return rng.integers(0, hi, size=(h, w, 3), endpoint=True).astype(dtype)


@pytest.mark.parametrize("ext", [".png", ".tif", ".tiff"])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_lossless_colour_roundtrip_in_rgb_order(tmp_path, ext, dtype):
    rgb = _rgb(dtype=dtype)
    p = tmp_path / f"c{ext}"
    assert cv2.imwrite(str(p), rgb[..., ::-1])  # OpenCV writes BGR
    img = read_image(p)
    assert img.channels == 3 and img.pixels.dtype == dtype
    assert np.array_equal(img.pixels, rgb), "channel 0 must be red"
    gray = read_image(p, as_gray=True)
    assert gray.channels == 1 and gray.pixels.shape == rgb.shape[:2] and gray.pixels.dtype == dtype
    luma = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]  # ITU-R BT.601
    # OpenCV uses fixed-point weights: allow one count plus a few parts in 1e5 of the value
    assert np.all(np.abs(gray.pixels.astype(float) - luma) <= 1.0 + 4e-5 * luma)


def test_pure_red_pixel_is_red(tmp_path):
    bgr = np.zeros((4, 5, 3), np.uint8)
    bgr[..., 2] = 255  # red in OpenCV's BGR
    p = tmp_path / "red.png"
    cv2.imwrite(str(p), bgr)
    px = read_image(p).pixels
    assert px[0, 0].tolist() == [255, 0, 0]


def test_rgba_png(tmp_path):
    bgra = np.dstack([_rgb()[..., ::-1], np.full((12, 17), 77, np.uint8)])
    p = tmp_path / "a.png"
    cv2.imwrite(str(p), bgra)
    img = read_image(p)
    assert img.channels == 4 and np.array_equal(img.pixels[..., :3], bgra[..., 2::-1])
    assert np.all(img.pixels[..., 3] == 77)
    assert read_image(p, as_gray=True).channels == 1


def test_jpeg_colour_and_mono(tmp_path):
    rgb = np.zeros((32, 32, 3), np.uint8)
    rgb[..., 0] = 200  # flat red: JPEG keeps flat colours almost exactly
    cv2.imwrite(str(tmp_path / "c.jpg"), rgb[..., ::-1])
    (tmp_path / "C.JPEG").write_bytes((tmp_path / "c.jpg").read_bytes())  # extension in any case
    img = read_image(tmp_path / "C.JPEG")
    assert img.channels == 3 and abs(int(img.pixels[16, 16, 0]) - 200) <= 3 and img.pixels[16, 16, 2] <= 3
    cv2.imwrite(str(tmp_path / "m.jpeg"), np.full((8, 8), 99, np.uint8))
    m = read_image(tmp_path / "m.jpeg")
    assert m.channels == 1 and m.pixels.ndim == 2 and abs(int(m.pixels.mean()) - 99) <= 1


@pytest.mark.parametrize("shift", [0, 2, 4, 6])
def test_bit_depth_of_left_shifted_16_bit(tmp_path, shift):
    rng = np.random.default_rng(shift)
    adc_bits = 16 - shift
    counts = rng.integers(1, 2 ** adc_bits, size=(40, 50)).astype(np.uint16)
    counts[0, 0] = 1  # make sure an odd count exists, so the shift is exactly `shift`
    p = tmp_path / "s.tif"
    cv2.imwrite(str(p), (counts << shift).astype(np.uint16))
    img = read_image(p)
    assert (img.bit_depth, img.shift) == (adc_bits, shift)
    assert np.array_equal(img.adc_counts(), counts)


def test_effective_bit_depth_edge_cases():
    assert effective_bit_depth(np.zeros((3, 3), np.uint16)) == (16, 0)
    assert effective_bit_depth(np.full((3, 3), 65535, np.uint16)) == (16, 0)  # all saturated
    assert effective_bit_depth(np.array([[16, 65535]], np.uint16)) == (12, 4)  # saturation ignored
    assert effective_bit_depth(np.ones((2, 2), np.float32)) == (None, 0)
    assert effective_bit_depth(np.ones((2, 2), np.uint8)) == (8, 0)


def test_fits_mono_uint16_float_and_colour_cube(tmp_path):
    from astropy.io import fits

    u16 = (np.arange(30 * 20, dtype=np.uint16).reshape(30, 20) * 16)
    fits.PrimaryHDU(u16).writeto(tmp_path / "u16.fits")  # stored as int16 + BZERO 32768
    img = read_image(tmp_path / "u16.fits")
    assert img.pixels.dtype == np.uint16 and np.array_equal(img.pixels, u16)
    assert (img.bit_depth, img.shift, img.channels) == (12, 4, 1)

    f32 = np.linspace(0, 1, 600, dtype=np.float32).reshape(20, 30)
    fits.PrimaryHDU(f32).writeto(tmp_path / "f.fit")
    img = read_image(tmp_path / "f.fit")
    assert img.pixels.dtype == np.float32 and np.array_equal(img.pixels, f32) and img.bit_depth is None

    cube = np.stack([np.full((6, 7), v, np.uint8) for v in (10, 20, 30)])  # FITS colour: (C, H, W)
    fits.PrimaryHDU(cube).writeto(tmp_path / "c.fts")
    img = read_image(tmp_path / "c.fts")
    assert img.pixels.shape == (6, 7, 3) and img.pixels[0, 0].tolist() == [10, 20, 30] and img.channels == 3


def test_list_images_natural_order(tmp_path):
    for n in ("img10.png", "img2.png", "img1.PNG", "notes.txt"):
        (tmp_path / n).write_bytes(b"x")
    assert [p.name for p in list_images(tmp_path)] == ["img1.PNG", "img2.png", "img10.png"]
    with pytest.raises(ImageError, match="folder not found"):
        list_images(tmp_path / "nope")


# ---------------------------------------------------------------------------------------------- errors
def _expect_error(path, *fragments):
    with pytest.raises(ImageError) as ei:
        read_image(path)
    msg = str(ei.value)
    assert str(path) in msg, msg
    for f in fragments:
        assert f in msg, msg
    assert isinstance(ei.value, InputError) and isinstance(ei.value, ValueError)
    return msg


@needs_chess
@pytest.mark.parametrize("fraction", [0.5, 0.99])
def test_truncated_real_jpeg(tmp_path, fraction):
    data = CHESS_JPG.read_bytes()
    p = tmp_path / "cut.jpg"
    p.write_bytes(data[: int(len(data) * fraction)])
    _expect_error(p, "truncated JPEG")


@needs_esa
def test_truncated_real_tiff(tmp_path):
    data = ESA_FRAME.read_bytes()
    p = tmp_path / "cut.tiff"
    p.write_bytes(data[: len(data) // 2])
    _expect_error(p, "TIFF", "truncated or corrupt")


def test_truncated_png(tmp_path):
    ok, buf = cv2.imencode(".png", _rgb(64, 64))
    p = tmp_path / "cut.png"
    p.write_bytes(buf.tobytes()[: len(buf) // 2])
    _expect_error(p, "truncated PNG")


def test_zero_byte_file(tmp_path):
    p = tmp_path / "empty.png"
    p.write_bytes(b"")
    _expect_error(p, "empty")


def test_text_file_named_png(tmp_path):
    p = tmp_path / "notes.png"
    p.write_text("this is not an image\n")
    _expect_error(p, "not a PNG file", "text")


def test_jpeg_named_png(tmp_path):
    p = tmp_path / "wrong.png"
    cv2.imwrite(str(tmp_path / "x.jpg"), np.zeros((8, 8), np.uint8))
    p.write_bytes((tmp_path / "x.jpg").read_bytes())
    _expect_error(p, "not a PNG file", "JPEG")


def test_missing_file(tmp_path):
    _expect_error(tmp_path / "nope.tiff", "not found")


def test_folder_instead_of_file(tmp_path):
    d = tmp_path / "dir.png"
    d.mkdir()
    _expect_error(d, "folder")


@pytest.mark.parametrize("name", ["frame.bmp", "frame.gif", "frame"])
def test_unsupported_extension(tmp_path, name):
    p = tmp_path / name
    p.write_bytes(b"BM" + bytes(100))
    msg = _expect_error(p, "unsupported image type")
    assert ".png" in msg and ".fits" in msg  # names what is allowed


def test_corrupt_fits(tmp_path):
    p = tmp_path / "bad.fits"
    p.write_bytes(b"SIMPLE  =                    T" + b"garbage" * 10)
    _expect_error(p, "FITS")


def test_truncated_fits(tmp_path):
    from astropy.io import fits

    fits.PrimaryHDU(np.arange(100 * 100, dtype=np.uint16).reshape(100, 100)).writeto(tmp_path / "whole.fits")
    data = (tmp_path / "whole.fits").read_bytes()
    p = tmp_path / "cut.fits"
    p.write_bytes(data[: len(data) - 3000])
    _expect_error(p, "truncated FITS")


def test_read_images_reports_bad_and_keeps_good(tmp_path):
    good1, good2 = tmp_path / "a.png", tmp_path / "c.tif"
    cv2.imwrite(str(good1), np.full((5, 6), 1, np.uint8))
    cv2.imwrite(str(good2), np.full((5, 6), 2, np.uint16))
    empty = tmp_path / "b.png"
    empty.write_bytes(b"")
    missing = tmp_path / "gone.jpg"
    images, errors = read_images([good1, empty, missing, good2])
    assert [im.path for im in images] == [good1, good2]
    assert [p for p, _ in errors] == [empty, missing]
    assert all(isinstance(e, ImageError) for _, e in errors)
    assert "empty" in str(errors[0][1]) and "not found" in str(errors[1][1])


# ---------------------------------------------------------------------------------------------- dark / flat
def test_calibrate_frame_recovers_signal():
    rng = np.random.default_rng(3)
    signal = rng.uniform(100, 1000, size=(20, 30))
    flat = rng.uniform(0.8, 1.2, size=(20, 30))
    flat /= flat.mean()
    dark = rng.uniform(50, 60, size=(20, 30))
    raw = signal * flat + dark
    out = calibrate_frame(raw, dark=dark, flat=flat * 7.0)  # flat at any scale
    assert out.dtype == np.float32 and out.shape == raw.shape
    np.testing.assert_allclose(out, signal, rtol=1e-5)
    np.testing.assert_allclose(calibrate_frame(raw, dark=dark), signal * flat, rtol=1e-5)
    np.testing.assert_array_equal(calibrate_frame(raw.astype(np.uint16)), raw.astype(np.uint16).astype(np.float32))


def test_calibrate_frame_image_input_dead_pixels_and_colour():
    px = np.full((4, 4), 160, np.uint16)
    img = Image(pixels=px, bit_depth=12, path=Path("x.tif"), channels=1, shift=4)
    flat = np.ones((4, 4))
    flat[1, 2] = 0.0  # dead pixel
    out = calibrate_frame(img, dark=32, flat=flat)
    assert out[1, 2] == 0.0
    # mean over the 15 good pixels is 1, so the others are unchanged: 160 - 32
    assert np.all(np.delete(out.ravel(), 1 * 4 + 2) == 128)
    rgb = np.full((4, 4, 3), 100.0)
    np.testing.assert_allclose(calibrate_frame(rgb, dark=np.full((4, 4), 10.0), flat=np.full((4, 4), 2.0)), 90.0)


def test_calibrate_frame_shape_mismatch_names_shapes():
    with pytest.raises(ImageError, match=r"dark frame has shape \(3, 3\)"):
        calibrate_frame(np.zeros((4, 4)), dark=np.zeros((3, 3)))
    with pytest.raises(ImageError, match="flat field has shape"):
        calibrate_frame(np.zeros((4, 4)), flat=np.ones((4, 5)))
    with pytest.raises(ImageError, match="no finite positive"):
        calibrate_frame(np.zeros((4, 4)), flat=np.zeros((4, 4)))


def test_jpeg_with_padding_after_the_end_marker_reads_and_a_truncated_one_is_refused(tmp_path):
    """Cameras and some writers pad a JPEG with 0xFF or 0x00 after its end-of-image marker: still a whole image.
    Cut inside the compressed data, it is refused as truncated."""
    import cv2

    from dualsight.errors import ImageError
    from dualsight.scene.imageio import read_image

    rng = np.random.default_rng(3)
    img = (rng.random((48, 64)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    data = buf.tobytes()
    ref = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    for pad in (b"\xff" * 100, b"\x00" * 37, b"\xff\x00\xff"):
        p = tmp_path / "padded.jpg"
        p.write_bytes(data + pad)
        np.testing.assert_array_equal(read_image(p, as_gray=True).pixels, ref)
    p = tmp_path / "cut.jpg"
    p.write_bytes(data[: len(data) // 2] + b"\xff" * 10)
    with pytest.raises(ImageError, match="truncated"):
        read_image(p, as_gray=True)
