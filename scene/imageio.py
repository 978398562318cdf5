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
import math
import os
import re
import struct
import sys
import tempfile
import threading
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from dualsight.errors import ImageError, check_regular, open_user_file

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

#: most pixels (width x height) an image may declare: 2**27 = 134 Mpx (e.g. 16384 x 8192).  Checked on the file's
#: header (PNG IHDR, TIFF first IFD, JPEG SOF, FITS NAXISn) before anything is decoded.
MAX_IMAGE_PIXELS = 1 << 27
#: most bytes an image's decoded samples may take (width x height x channels x bytes per sample): 256 MiB, e.g.
#: 134 Mpx of 16-bit mono; checked with :data:`MAX_IMAGE_PIXELS`.
MAX_IMAGE_BYTES = 1 << 28
#: largest image file read at all (an uncompressed image at :data:`MAX_IMAGE_BYTES` plus its metadata)
MAX_FILE_BYTES = 2 * MAX_IMAGE_BYTES


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
    ImageError naming the file: missing, a folder, pipe, socket or device (checked before opening), unreadable,
    empty, larger than :data:`MAX_FILE_BYTES`, unsupported extension, content not of the claimed format, a header
    declaring more than :data:`MAX_IMAGE_PIXELS` or :data:`MAX_IMAGE_BYTES` (refused before decoding), truncated
    (JPEG without end-of-image marker, PNG without IEND chunk), or not decodable (with the decoding library's
    own reason; its messages never reach the terminal).
    """
    path = Path(path)
    fmt = _format_of(path)
    data = _read_checked(path, fmt)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)     # numpy's, around decoding: never before our line
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


def check_image_file(path: str | Path):
    """Refuse, without decoding, an image no run should start on: a named pipe, socket, device or folder (checked
    with ``os.stat`` before opening), a file larger than :data:`MAX_FILE_BYTES`, or one whose header declares
    more than :data:`MAX_IMAGE_PIXELS` / :data:`MAX_IMAGE_BYTES`.  Raises ImageError naming the file and the
    limit.  A missing or unreadable file, an unknown extension or a header this module cannot parse pass:
    :func:`read_image` reports those per image."""
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError:
        return
    check_regular(path, ImageError, what="image file", st=st)
    _check_file_size(path, st.st_size)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None or not os.access(path, os.R_OK):
        return
    with open_user_file(path, ImageError, what="image file") as fh:
        try:
            header = image_header(fh, fmt)
        except OSError:
            return
    _check_header(path, header)


@dataclass(frozen=True)
class ImageHeader:
    """What an image file's header declares (nothing decoded): size, samples per pixel and bits per sample
    (``bits`` < 0: IEEE floating point, as FITS's BITPIX)."""

    width: int
    height: int
    channels: int
    bits: int

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def nbytes(self) -> int:
        """Bytes of the decoded samples (a sample of up to 8 bits takes one byte, of 9-16 bits two, ...)."""
        per = max(1, (abs(self.bits) + 7) // 8)
        return self.pixels * max(1, self.channels) * (1 << (per - 1).bit_length())


def image_header(fh, fmt: str) -> ImageHeader | None:
    """The :class:`ImageHeader` of an open binary image file (PNG IHDR, TIFF first IFD: classic and BigTIFF, both
    byte orders, JPEG SOF marker, FITS NAXISn/BITPIX of the first image HDU), read with a few small seeks and
    reads; None when the header is not one of those or cannot be parsed (the decoder's own checks apply)."""
    parse = {"PNG": _png_header, "TIFF": _tiff_header, "JPEG": _jpeg_header, "FITS": _fits_header}.get(fmt)
    if parse is None:
        return None
    try:
        fh.seek(0)
        return parse(fh)
    except (struct.error, ValueError, OverflowError):
        return None


def _read_at(fh, offset: int, n: int) -> bytes:
    fh.seek(offset)
    b = fh.read(n)
    if len(b) != n:
        raise ValueError("short read")
    return b


#: PNG colour type -> channels OpenCV decodes it to (palette -> BGR, grey + alpha -> BGRA)
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 4, 6: 4}


def _png_header(fh) -> ImageHeader | None:
    b = _read_at(fh, 0, 29)
    if b[12:16] != b"IHDR":
        return None
    w, h, depth, colour = struct.unpack(">IIBB", b[16:26])
    return ImageHeader(w, h, _PNG_CHANNELS.get(colour, 4), 16 if depth > 8 else 8)


_TIFF_TYPES = {1: ("B", 1), 3: ("H", 2), 4: ("I", 4), 16: ("Q", 8)}     # BYTE, SHORT, LONG, LONG8
_TIFF_MAX_ENTRIES = 4096


def _tiff_header(fh) -> ImageHeader | None:
    b = _read_at(fh, 0, 16)
    e = {b"II": "<", b"MM": ">"}.get(b[:2])
    if e is None:
        return None
    magic = struct.unpack(e + "H", b[2:4])[0]
    if magic == 42:
        ifd, cnt_fmt, entry, val_size = struct.unpack(e + "I", b[4:8])[0], "H", 12, 4
        head_fmt = e + "HHI"
    elif magic == 43:
        ifd, cnt_fmt, entry, val_size = struct.unpack(e + "Q", b[8:16])[0], "Q", 20, 8
        head_fmt = e + "HHQ"
    else:
        return None
    cnt_size = struct.calcsize(cnt_fmt)
    n = struct.unpack(e + cnt_fmt, _read_at(fh, ifd, cnt_size))[0]
    raw = _read_at(fh, ifd + cnt_size, min(n, _TIFF_MAX_ENTRIES) * entry)
    tags = {}
    for k in range(min(n, _TIFF_MAX_ENTRIES)):
        rec = raw[k * entry:(k + 1) * entry]
        tag, typ, count = struct.unpack(head_fmt, rec[:entry - val_size])
        if tag not in (256, 257, 258, 277) or typ not in _TIFF_TYPES or count < 1:
            continue
        code, size = _TIFF_TYPES[typ]
        value = rec[entry - val_size:]
        if count * size > val_size:           # stored elsewhere: the first value is enough
            off = struct.unpack(e + ("I" if val_size == 4 else "Q"), value)[0]
            value = _read_at(fh, off, size)
        tags[tag] = struct.unpack(e + code, value[:size])[0]
    if 256 not in tags or 257 not in tags:
        return None
    return ImageHeader(tags[256], tags[257], tags.get(277, 1), tags.get(258, 1))


#: JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic, hierarchical); not DHT/JPG/DAC
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_MAX_SEGMENTS = 1024


def _jpeg_header(fh) -> ImageHeader | None:
    pos = 2                                   # after SOI
    for _ in range(_JPEG_MAX_SEGMENTS):
        b = _read_at(fh, pos, 2)
        if b[0] != 0xFF:
            return None
        if b[1] == 0xFF:                      # fill byte before a marker
            pos += 1
            continue
        marker = b[1]
        if marker == 0x01 or 0xD0 <= marker <= 0xD7:   # stand-alone markers
            pos += 2
            continue
        if marker in (0xD9, 0xDA):            # end of image, start of scan: no frame header before it
            return None
        length = struct.unpack(">H", _read_at(fh, pos + 2, 2))[0]
        if marker in _SOF:
            precision, h, w, comps = struct.unpack(">BHHB", _read_at(fh, pos + 4, 6))
            return ImageHeader(w, h, comps, precision)
        if length < 2:
            return None
        pos += 2 + length
    return None


_FITS_BLOCK = 2880
_FITS_MAX_BLOCKS = 4096                       # header blocks read in all (11.8 MB): more is not an image header
_FITS_MAX_HDUS = 64


def _fits_cards(fh, pos: int, budget: list) -> tuple[dict, int] | None:
    """The cards (keyword -> value text) of the header at ``pos`` and the offset after it (None: no END card
    within the file or the budget of header blocks)."""
    cards = {}
    while budget[0] > 0:
        budget[0] -= 1
        fh.seek(pos)
        block = fh.read(_FITS_BLOCK)
        pos += _FITS_BLOCK
        for i in range(0, len(block), 80):
            card = block[i:i + 80].decode("ascii", "replace")
            key = card[:8].strip()
            if key == "END":
                return cards, pos
            if card[8:10] == "= " and key not in cards:
                cards[key] = card[10:].split("/", 1)[0].strip().strip("'").strip()
        if len(block) < _FITS_BLOCK:
            return None
    return None


def _fits_header(fh) -> ImageHeader | None:
    pos, budget = 0, [_FITS_MAX_BLOCKS]
    for _ in range(_FITS_MAX_HDUS):
        got = _fits_cards(fh, pos, budget)
        if got is None:
            return None
        cards, pos = got
        z = "Z" if cards.get("ZIMAGE") == "T" else ""         # tile-compressed image in a binary table
        naxis = int(cards.get(z + "NAXIS", 0))
        if (z or cards.get("XTENSION") in (None, "IMAGE")) and naxis >= 2:
            dims = [int(cards.get(f"{z}NAXIS{i}", 0)) for i in range(1, naxis + 1)]
            return ImageHeader(dims[0], dims[1], math.prod(dims[2:]), int(cards.get(z + "BITPIX", 8)))
        axes = math.prod(int(cards.get(f"NAXIS{i}", 0)) for i in range(1, int(cards.get("NAXIS", 0)) + 1))
        if int(cards.get("NAXIS", 0)) == 0:
            axes = 0
        data = abs(int(cards.get("BITPIX", 8))) // 8 * int(cards.get("GCOUNT", 1)) * (int(cards.get("PCOUNT", 0))
                                                                                     + axes)
        pos += -(-data // _FITS_BLOCK) * _FITS_BLOCK
    return None


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
    if a.max() < top:          # no saturated sample (the usual frame): OR every sample, without a filtered copy
        flat = flat.view(np.dtype(f"u{a.dtype.itemsize}"))
    else:
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


def _read_checked(path: Path, fmt: str) -> bytes:
    """The file's bytes, after the checks that need no decoding: a regular file (stat before opening), not
    empty, at most :data:`MAX_FILE_BYTES`, the format's signature, and the header's size within the limits."""
    with open_user_file(path, ImageError, what="image file") as fh:
        size = _check_file_size(path, os.fstat(fh.fileno()).st_size)
        try:
            head = fh.read(512)
            _check_signature(path, fmt, head, size)
            _check_header(path, image_header(fh, fmt))
            fh.seek(0)
            data = fh.read(size)
        except OSError as e:
            raise ImageError(f"cannot be read ({e.strerror or e})", source=str(path)) from None
    if not data:
        raise ImageError("file is empty (0 bytes)", source=str(path))
    return data


def _check_file_size(path: Path, size: int) -> int:
    if size == 0:
        raise ImageError("file is empty (0 bytes)", source=str(path))
    if size > MAX_FILE_BYTES:
        raise ImageError(f"is {size / 2**20:.0f} MiB; image files of at most {MAX_FILE_BYTES // 2**20} MiB are read",
                         source=str(path))
    return size


def _check_header(path: Path, header: ImageHeader | None):
    if header is None:          # a header this parser does not know: the decoder's own checks apply
        return
    if header.pixels > MAX_IMAGE_PIXELS or header.nbytes > MAX_IMAGE_BYTES:
        raise ImageError(f"declares {header.width} x {header.height} px of {header.channels} x "
                         f"{header.bits}-bit samples ({header.pixels / 1e6:.0f} Mpx, {header.nbytes / 2**20:.0f} MiB "
                         f"decoded); images of at most {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx ({MAX_IMAGE_PIXELS} px) "
                         f"and {MAX_IMAGE_BYTES // 2**20} MiB are read", source=str(path))


def _check_signature(path: Path, fmt: str, data: bytes, size: int):
    if not any(data.startswith(m) for m in _MAGIC[fmt]):
        found = _sniff(data)
        what = f"looks like {found}" if found else f"starts with {data[:8]!r}"
        raise ImageError(f"is not a {fmt} file: its content {what} ({size} bytes)", source=str(path))


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

    said = []
    try:
        with _library_stderr(said, cv2):
            arr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:  # pragma: no cover - OpenCV usually returns None instead
        raise ImageError(f"cannot decode {fmt} data ({str(e).strip().splitlines()[-1]})", source=str(path)) from None
    if arr is None or arr.size == 0:
        why = _library_reason("".join(said))
        raise ImageError(f"cannot decode {fmt} data: truncated or corrupt ({len(data)} bytes"
                         + (f"; {why})" if why else ")"), source=str(path))
    if arr.ndim == 3:
        c = arr.shape[2]
        if c == 1:
            arr = arr[..., 0]
        elif c == 3:
            arr = cv2.cvtColor(arr, cv2.COLOR_BGR2RGB)
        elif c == 4:
            arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2RGBA)
    return arr


_STDERR_LOCK = threading.Lock()
_OPENCV_PREFIX = re.compile(r"^\[\s*[A-Z]+:[^\]]*\]\s+(global\s+)?\S+:\d+\s+")


@contextmanager
def _library_stderr(said: list, cv2):
    """Hold what C libraries print (libpng, libjpeg, libtiff through OpenCV's log, lowered to errors) to the
    process's stderr while decoding: file descriptor 2 goes to a temporary file, whose text is appended to
    ``said``.  One decode at a time per process holds it (the descriptor is process-wide)."""
    log = cv2.utils.logging
    with _STDERR_LOCK:
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (OSError, ValueError, AttributeError):      # no stderr to hold: decode as is
            saved = None
        level = log.getLogLevel()
        log.setLogLevel(min(level, log.LOG_LEVEL_ERROR))
        try:
            if saved is None:
                yield
                return
            with tempfile.TemporaryFile() as tmp:
                os.dup2(tmp.fileno(), 2)
                try:
                    yield
                finally:
                    os.dup2(saved, 2)
                    tmp.seek(0)
                    said.append(tmp.read(1 << 16).decode("utf-8", "replace"))
        finally:
            log.setLogLevel(level)
            if saved is not None:
                os.close(saved)


def _library_reason(text: str) -> str:
    """The last line a decoding library printed, without OpenCV's log prefix (``[ERROR:0@0.03] global
    grfmt_tiff.cpp:117``), at most 200 characters; "" when it printed nothing."""
    lines = [_OPENCV_PREFIX.sub("", ln).strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    return lines[-1][:200] if lines else ""


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
