"""Reading real camera frames (PNG, JPEG, TIFF, FITS) for the hardware-in-the-loop path and calibration (and the
measured PSF images of :mod:`dualsight.scene.psf_file`).  numpy, OpenCV and, for FITS, astropy (both imported on
first use); no project import but :mod:`dualsight.errors`.

Every failure is an :class:`dualsight.errors.ImageError` that names the file and what is wrong
(missing, empty, truncated, not the format its name claims, unsupported extension), so that a
batch can report one bad frame and go on with the others (:func:`read_images`).

Pixel layout
    ``Image.pixels`` is ``(H, W)`` for mono and ``(H, W, C)`` for colour, in the file's native dtype
    (uint8, uint16, float32, ...). Colour is returned in **RGB(A)** order (OpenCV decodes BGR; we
    convert), so channel 0 is red whatever the file format.  Row 0 is the top of the image (FITS
    files, whose first row is the bottom by convention, are read as stored: row 0 = first row in the
    file; flip them yourself if your FITS writer followed the bottom-up convention).

Effective bit depth
    Many machine-vision cameras deliver 10/12/14-bit ADC values left-aligned in 16-bit words: the
    ESA tetra3 frames are 12-bit values shifted left by 4, so every pixel's low 4 bits are zero and the
    largest value is 0xFFF0 = 65520.  :func:`read_image` detects such a shift as the number of trailing
    zero bits common to all pixels **that are not saturated** (saturated pixels are written as the
    dtype's maximum, 65535 = 0xFFFF, in the ESA frames, which would otherwise hide the shift) and
    reports ``bit_depth = container bits - shift`` and ``shift``.  ``Image.adc_counts()`` gives the
    values shifted back.  A 12-bit image stored right-aligned (values < 4096 in uint16) cannot be told
    from a dark 16-bit image and is reported as 16 bit.  Floating-point images have ``bit_depth = None``.
"""

from __future__ import annotations

import io
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from dualsight.errors import ImageError, read_user_file

#: extension (lower case) -> format name
FORMATS = {
    ".png": "PNG",
    ".jpg": "JPEG",
    ".jpeg": "JPEG",
    ".tif": "TIFF",
    ".tiff": "TIFF",
    ".fits": "FITS",
    ".fit": "FITS",
    ".fts": "FITS",
}

_MAGIC = {
    "PNG": (b"\x89PNG\r\n\x1a\n",),
    "JPEG": (b"\xff\xd8\xff",),
    "TIFF": (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"),  # classic and BigTIFF, both byte orders
    "FITS": (b"SIMPLE  =",),
}


@dataclass(frozen=True, eq=False)
class Image:
    """One decoded frame.

    Attributes
    ----------
    pixels : (H, W) or (H, W, C) ndarray in the file's native dtype; colour channels in RGB(A) order.
    bit_depth : effective bits per sample (e.g. 12 for 12-bit data left-shifted into uint16;
        8 for uint8), or None for floating-point data.
    path : the file it came from.
    channels : 1 for mono, 3 (RGB) or 4 (RGBA) for colour.
    shift : number of low bits that are always zero (the left shift of the ADC values), 0 if none.
    """

    pixels: np.ndarray
    bit_depth: int | None
    path: Path
    channels: int
    shift: int = 0

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    @property
    def full_scale(self) -> float:
        """Largest value a non-saturated sample can take in ``pixels`` units
        (``(2**bit_depth - 1) << shift``; 1.0 for floating-point data)."""
        if self.bit_depth is None:
            return 1.0
        return float(((1 << self.bit_depth) - 1) << self.shift)

    def adc_counts(self) -> np.ndarray:
        """Pixel values shifted right by ``shift`` (the ADC's own counts, same dtype); saturated
        samples (dtype maximum) map to the ADC maximum."""
        if self.shift == 0 or self.bit_depth is None:
            return self.pixels
        return self.pixels >> self.shift


# ---------------------------------------------------------------------------------------------- reading
def read_image(path: str | Path, *, as_gray: bool = False) -> Image:
    """Read a PNG, JPEG, TIFF (8/16-bit, mono or colour) or FITS image.

    Parameters
    ----------
    path : the image file; the format is taken from the extension (see ``FORMATS``) and checked
        against the file's signature bytes.
    as_gray : convert colour to one channel (OpenCV's ITU-R BT.601 luma, 0.299 R + 0.587 G + 0.114 B,
        same dtype); an alpha channel is dropped.

    Returns
    -------
    :class:`Image`.

    Raises
    ------
    ImageError naming the file: missing, a folder, unreadable, empty, unsupported extension,
    content not of the claimed format, truncated (JPEG without end-of-image marker, PNG without
    IEND chunk), or not decodable.
    """
    path = Path(path)
    fmt = _format_of(path)
    data = _read_bytes(path)
    _check_signature(path, fmt, data)
    if fmt == "FITS":
        pixels = _decode_fits(path, data)
    else:
        _check_complete(path, fmt, data)
        pixels = _decode_opencv(path, fmt, data)
    bit_depth, shift = effective_bit_depth(pixels)
    if pixels.ndim == 3 and as_gray:
        pixels = to_gray(pixels)
    channels = 1 if pixels.ndim == 2 else int(pixels.shape[2])
    return Image(pixels=pixels, bit_depth=bit_depth, path=path, channels=channels, shift=shift)


def read_images(paths: Iterable[str | Path], *, as_gray: bool = False
                ) -> tuple[list[Image], list[tuple[Path, ImageError]]]:
    """Read many images; a bad one is reported, the rest are still read.

    Returns
    -------
    images : the frames that could be read, in input order.
    errors : (path, ImageError) for each frame that could not.
    """
    images, errors = [], []
    for p in paths:
        try:
            images.append(read_image(p, as_gray=as_gray))
        except ImageError as e:
            errors.append((Path(p), e))
    return images, errors


def list_images(folder: str | Path) -> list[Path]:
    """Image files (supported extensions, any case) directly inside ``folder``, in natural order
    (``img2`` before ``img10``). Raises ImageError if the folder does not exist."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ImageError("folder not found" if not folder.exists() else "is not a folder", source=str(folder))
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FORMATS]
    return sorted(files, key=_natural_key)


def effective_bit_depth(pixels: np.ndarray) -> tuple[int | None, int]:
    """(bit_depth, shift) of integer pixel data; (None, 0) for floating point.

    ``shift`` is the number of trailing zero bits common to every sample below the dtype's maximum
    (saturated samples are ignored, see module docstring), capped so that at least 1 bit remains;
    an image whose samples are all 0 or saturated has shift 0.
    """
    a = np.asarray(pixels)
    if not np.issubdtype(a.dtype, np.integer):
        return None, 0
    bits = a.dtype.itemsize * 8
    if a.dtype == np.uint8 or a.size == 0:
        return bits, 0
    top = np.iinfo(a.dtype).max
    flat = a.ravel()
    flat = flat[flat != top].view(np.dtype(f"u{a.dtype.itemsize}"))
    ored = int(np.bitwise_or.reduce(flat)) if flat.size else 0
    if ored == 0:
        return bits, 0
    shift = min((ored & -ored).bit_length() - 1, bits - 1)
    return bits - shift, shift


def to_gray(pixels: np.ndarray) -> np.ndarray:
    """(H, W, 3 or 4) RGB(A) -> (H, W) luma in the same dtype (OpenCV's RGB2GRAY weights)."""
    import cv2

    if pixels.ndim == 2:
        return pixels
    c = pixels.shape[2]
    if c == 1:
        return pixels[..., 0]
    code = {3: cv2.COLOR_RGB2GRAY, 4: cv2.COLOR_RGBA2GRAY}.get(c)
    if code is None:
        raise ImageError(f"cannot convert {c} channels to gray (expected 1, 3 or 4)")
    return cv2.cvtColor(np.ascontiguousarray(pixels), code)


# ---------------------------------------------------------------------------------------------- dark/flat
def calibrate_frame(img, dark=None, flat=None) -> np.ndarray:
    """Dark-frame and flat-field correction: ``(img - dark) / (flat / mean(flat))`` as float32.

    Parameters
    ----------
    img : :class:`Image` or ndarray (H, W) or (H, W, C), the light frame.
    dark : same shape (or broadcastable, e.g. a scalar bias), same exposure and temperature as
        ``img``, in the same units (e.g. both left-shifted); optional.
    flat : flat-field response, same shape, dark/bias already removed, any scale: it is divided by
        its mean over finite positive pixels (per channel for colour), so a flat normalised to 1
        leaves the level of ``img`` unchanged.  Pixels where the flat is <= 0 or not finite (dead
        pixels) are set to 0 in the output.  Optional.

    Returns
    -------
    float32 array of the shape of ``img``, in ``img``'s units.  With neither dark nor flat this is
    just ``img`` as float32.

    Raises
    ------
    ImageError if the shapes do not match or the flat has no usable pixel.
    """
    a = _as_array(img)
    out = a.astype(np.float32, copy=True)
    src = str(img.path) if isinstance(img, Image) else None
    if dark is not None:
        d = _as_array(dark).astype(np.float32, copy=False)
        if d.ndim == 2 and out.ndim == 3:
            d = d[..., None]  # one dark for all channels
        _check_broadcast(out, d, "dark frame", src)
        out -= d
    if flat is not None:
        f = _as_array(flat).astype(np.float64, copy=False)
        if f.shape != out.shape and not (f.ndim == 2 and out.ndim == 3 and f.shape == out.shape[:2]):
            raise ImageError(f"flat field has shape {f.shape}, the frame {out.shape}", source=src)
        good = np.isfinite(f) & (f > 0)
        if not good.any():
            raise ImageError("flat field has no finite positive pixel", source=src)
        axes = (0, 1)
        fg = np.where(good, f, 0.0)
        mean = fg.sum(axis=axes) / np.maximum(good.sum(axis=axes), 1)
        norm = np.where(good, f / mean, 1.0)
        if norm.ndim == 2 and out.ndim == 3:
            norm, good = norm[..., None], good[..., None]
        out = np.where(good, out / norm, 0.0).astype(np.float32)
    return out


# ---------------------------------------------------------------------------------------------- helpers
def _natural_key(p: Path):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", p.name)]


def _format_of(path: Path) -> str:
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        allowed = ", ".join(sorted(FORMATS))
        raise ImageError(f"unsupported image type '{path.suffix or '(no extension)'}'; supported: {allowed}",
                         source=str(path))
    return fmt


def _read_bytes(path: Path) -> bytes:
    return read_user_file(path, ImageError, what="image file")


def _check_signature(path: Path, fmt: str, data: bytes):
    if not any(data.startswith(m) for m in _MAGIC[fmt]):
        found = _sniff(data)
        what = f"looks like {found}" if found else f"starts with {data[:8]!r}"
        raise ImageError(f"is not a {fmt} file: its content {what} ({len(data)} bytes)", source=str(path))


def _sniff(data: bytes) -> str | None:
    for fmt, magics in _MAGIC.items():
        if any(data.startswith(m) for m in magics):
            return f"a {fmt} file"
    head = data[:512]
    try:
        head.decode("utf-8")
        return "text"
    except UnicodeDecodeError:
        return None


def _check_complete(path: Path, fmt: str, data: bytes):
    """Cheap structural checks that catch truncated files before decoding."""
    if fmt == "JPEG":
        # the last end-of-image marker, followed by nothing but padding (some writers and cameras append 0x00
        # or 0xFF fill after it); inside the entropy-coded data 0xFF is always stuffed, so FFD9 is a marker
        eoi = data.rfind(b"\xff\xd9")
        if eoi < 0 or data[eoi + 2:].strip(b"\x00\xff\r\n "):
            raise ImageError(f"truncated JPEG: no end-of-image marker (FFD9) at the end of its {len(data)} bytes",
                             source=str(path))
    elif fmt == "PNG":
        if b"IEND" not in data[-64:]:
            raise ImageError(f"truncated PNG: no IEND chunk at the end of its {len(data)} bytes", source=str(path))


def _decode_opencv(path: Path, fmt: str, data: bytes) -> np.ndarray:
    import cv2

    try:
        arr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:  # pragma: no cover - OpenCV usually returns None instead
        raise ImageError(f"cannot decode {fmt} data ({str(e).strip().splitlines()[-1]})", source=str(path)) from None
    if arr is None or arr.size == 0:
        raise ImageError(f"cannot decode {fmt} data: truncated or corrupt ({len(data)} bytes)", source=str(path))
    if arr.ndim == 3:
        c = arr.shape[2]
        if c == 1:
            arr = arr[..., 0]
        elif c == 3:
            arr = cv2.cvtColor(arr, cv2.COLOR_BGR2RGB)
        elif c == 4:
            arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2RGBA)
    return arr


def _decode_fits(path: Path, data: bytes) -> np.ndarray:
    from astropy.io import fits

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # truncation is checked below, header quibbles do not matter
            with fits.open(io.BytesIO(data), memmap=False) as hdul:
                index = next((i for i, h in enumerate(hdul) if h.is_image and h.header.get("NAXIS", 0) >= 2), None)
                if index is None:
                    raise ImageError("FITS file has no image HDU with 2-D data", source=str(path))
                hdu = hdul[index]
                need = abs(int(hdu.header["BITPIX"])) // 8 * int(np.prod(hdu.shape))
                start = hdul.fileinfo(index)["datLoc"]
                if start + need > len(data):
                    raise ImageError(f"truncated FITS: data of shape {hdu.shape} needs {start + need} bytes, "
                                     f"the file has {len(data)}", source=str(path))
                arr = np.array(hdu.data)  # applies BSCALE/BZERO (e.g. int16 + 32768 -> uint16)
    except ImageError:
        raise
    except Exception as e:  # astropy raises OSError/ValueError/TypeError/VerifyError for bad files
        raise ImageError(f"cannot read FITS data: {type(e).__name__}: {e}", source=str(path)) from None
    if arr.ndim == 3:
        if arr.shape[0] in (3, 4):  # FITS colour cubes are (C, H, W)
            arr = np.moveaxis(arr, 0, -1)
        elif arr.shape[0] == 1:
            arr = arr[0]
        else:
            raise ImageError(f"FITS cube of shape {arr.shape}: expected (H, W) or (3|4, H, W)", source=str(path))
    elif arr.ndim > 3:
        raise ImageError(f"FITS data of shape {arr.shape}: expected (H, W) or (3|4, H, W)", source=str(path))
    arr = np.ascontiguousarray(arr)
    if arr.dtype.byteorder not in ("=", "|"):
        arr = arr.astype(arr.dtype.newbyteorder("="))
    return arr


def _as_array(x) -> np.ndarray:
    return x.pixels if isinstance(x, Image) else np.asarray(x)


def _check_broadcast(out: np.ndarray, d: np.ndarray, what: str, src):
    try:
        shape = np.broadcast_shapes(out.shape, d.shape)
    except ValueError:
        shape = None
    if shape != out.shape:
        raise ImageError(f"{what} has shape {d.shape}, the frame {out.shape}", source=src)
