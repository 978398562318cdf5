"""The measured PSF of a sensor (``SensorConfig.psf_model = "image"``): its file read, checked and normalised
(:func:`load_psf_image`, cached per process) and its content hash (:func:`psf_image_sha256`, stored in the spec).

The file is an odd-sized (<= :data:`PSF_IMAGE_MAX_PX` px per side) 2-D array of non-negative numbers sampled on
the sensor's own pixel grid: a ``.npy`` array (no pickles) or an image (PNG, TIFF, FITS, read by
:func:`dualsight.kernels.imageio.read_image`; colour converted to grey).  The renderer resamples it per star
(:mod:`dualsight.kernels.psf_models`); :func:`dualsight.kernels.sensor_config.with_psf_digest` is the one
step that reads it when a spec is built.
"""

import hashlib
import io
import os
import threading
from pathlib import Path

import numpy as np

from dualsight.errors import InputError, read_user_file
from dualsight.kernels.imageio import read_image

__all__ = ["PSF_IMAGE_MAX_PX", "psf_image_sha256", "load_psf_image"]

PSF_IMAGE_MAX_PX = 64
"""Largest side (px) of a measured PSF image."""
_PSF_IMAGE_MAX_BYTES = 1 << 20

_psf_cache: dict = {}
_psf_lock = threading.Lock()


def psf_image_sha256(a: np.ndarray) -> str:
    """SHA-256 (hex) of a loaded PSF (:func:`load_psf_image`: unit-sum float64): its shape and little-endian values.
    Stored in the sensor spec, so a run's identity covers the PSF's content, not only its file name."""
    h = hashlib.sha256(f"{a.shape[0]}x{a.shape[1]}:".encode())
    h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


def load_psf_image(path: str, key: str = "SensorConfig.psf_image") -> np.ndarray:
    """The measured PSF of ``path`` as a read-only (ny, nx) float64 array of unit sum (cached per process).

    ``.npy`` (numpy, no pickles) or an image (PNG, TIFF, FITS; colour is converted to grey).  Checked:
    2-D, both sides odd and <= :data:`PSF_IMAGE_MAX_PX`, every value finite and >= 0, positive sum.
    Relative paths are relative to the working directory.  Every failure is one-line ValueError naming
    ``key`` and the file.  The cache key is (absolute path, size, modification time), so the file is read
    once per process (a job's worker) unless it changes.
    """
    p = Path(os.path.abspath(os.fspath(path)))

    def fail(msg):
        return ValueError(f"{key}: {str(path)!r}: {msg}")

    try:
        st = p.stat()
    except OSError as e:
        raise fail(f"cannot read the file ({e.strerror or e})") from None
    ck = (str(p), st.st_size, st.st_mtime_ns)
    with _psf_lock:
        got = _psf_cache.get(ck)
    if got is not None:
        return got
    try:
        if p.suffix.lower() == ".npy":
            data = read_user_file(p, what="PSF file", max_bytes=_PSF_IMAGE_MAX_BYTES)
            a = np.load(io.BytesIO(data), allow_pickle=False)
        else:
            a = read_image(p, as_gray=True).pixels
    except InputError as e:
        raise fail(str(getattr(e, "detail", e)).replace("\n", " ")) from None
    except (ValueError, OSError, EOFError) as e:
        raise fail(f"not a readable .npy/PNG/TIFF/FITS array ({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None
    a = np.asarray(a)
    if a.ndim != 2:
        raise fail(f"must be a 2-D array, got shape {a.shape}")
    if a.dtype.kind not in "uif":
        raise fail(f"must hold numbers, got dtype {a.dtype}")
    ny, nx = a.shape
    if ny % 2 == 0 or nx % 2 == 0 or ny > PSF_IMAGE_MAX_PX or nx > PSF_IMAGE_MAX_PX:
        raise fail(f"must have odd sides <= {PSF_IMAGE_MAX_PX} px (centred on its middle pixel), got {ny} x {nx}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise fail("holds non-finite values")
    if a.min() < 0:
        raise fail(f"holds negative values (min {a.min():g})")
    total = float(a.sum())
    if not total > 0:
        raise fail("sums to zero")
    a = np.ascontiguousarray(a / total)
    a.setflags(write=False)
    with _psf_lock:
        _psf_cache.clear()  # one PSF per job: keep only the latest
        _psf_cache[ck] = a
    return a
