"""The measured PSF file of a sensor (``SensorConfig.psf_model = "image"``, ``psf_image = "file"``): read, checked
and normalised (:func:`load_psf_image`, cached per process), its content hash put into the sensor's spec
(:func:`with_psf_digest`) and the array handed to the renderer (:func:`sensor_psf`).

The file is an odd-sized (<= :data:`dualsight.kernels.psf_image.PSF_IMAGE_MAX_PX` px per side) 2-D array of
non-negative numbers sampled on the sensor's own pixel grid: a ``.npy`` array (no pickles) or an image (PNG,
TIFF, FITS, read by :func:`dualsight.scene.imageio.read_image`; colour converted to grey).  The checks and the
normalisation are the array kernel :func:`dualsight.kernels.psf_image.unit_sum_psf`; the renderer
(:mod:`dualsight.kernels.psf_models`) takes the resulting array as an argument and reads no file.
"""

import io
import os
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np

from dualsight.errors import InputError, read_user_file
from dualsight.kernels.psf_image import psf_image_sha256, unit_sum_psf
from dualsight.kernels.sensor_config import SensorConfig
from dualsight.scene.imageio import read_image

__all__ = ["load_psf_image", "with_psf_digest", "sensor_psf"]

_PSF_IMAGE_MAX_BYTES = 1 << 20

_psf_cache: dict = {}
_psf_lock = threading.Lock()


def load_psf_image(path: str, key: str = "SensorConfig.psf_image") -> np.ndarray:
    """The measured PSF of ``path`` as a read-only (ny, nx) float64 array of unit sum (cached per process).

    ``.npy`` (numpy, no pickles) or an image (PNG, TIFF, FITS; colour is converted to grey).  Checked
    (:func:`dualsight.kernels.psf_image.unit_sum_psf`): 2-D, both sides odd and <= ``PSF_IMAGE_MAX_PX``, every
    value finite and >= 0, positive sum.  Relative paths are relative to the working directory.  Every failure
    is one-line ValueError naming ``key`` and the file.  The cache key is (absolute path, size, modification
    time), so the file is read once per process (a job's worker) unless it changes.
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
    try:
        a = unit_sum_psf(a)
    except ValueError as e:
        raise fail(str(e)) from None
    with _psf_lock:
        _psf_cache.clear()  # one PSF per job: keep only the latest
        _psf_cache[ck] = a
    return a


def with_psf_digest(cfg: SensorConfig, error=ValueError) -> SensorConfig:
    """``cfg`` with the content hash of its measured PSF in ``psf_image_sha256``: the step that reads the
    ``psf_image`` file a spec names (the job layer calls it where it builds the spec, so the stored spec and the
    run's hash cover the PSF's content, not only its path).

    Without ``psf_image``: ``cfg`` itself, no I/O.  Otherwise the file is read and checked
    (:func:`load_psf_image`, cached per process) and hashed
    (:func:`dualsight.kernels.psf_image.psf_image_sha256`); a ``cfg`` that already states the hash (a stored
    spec being resumed or replayed) must state the file's.  ``error`` builds the exception raised, from its
    one-line message, for a bad or missing file or a changed content (default ValueError; the job layer's names
    the spec's source).
    """
    if cfg.psf_image is None:
        return cfg
    try:
        got = psf_image_sha256(load_psf_image(cfg.psf_image))
    except ValueError as e:
        raise error(str(e)) from None
    if cfg.psf_image_sha256 is None:
        return replace(cfg, psf_image_sha256=got)
    if cfg.psf_image_sha256 != got:
        raise error(f"SensorConfig.psf_image_sha256: the PSF file {cfg.psf_image!r} is not the one this spec was "
                    f"made with (content sha256 {got[:12]}..., the spec says {cfg.psf_image_sha256[:12]}...); "
                    "restore the file or start a new run")
    return cfg


def sensor_psf(cfg: SensorConfig, error=ValueError) -> np.ndarray | None:
    """The measured PSF the renderer takes for ``cfg`` (the ``psf`` argument of
    :func:`dualsight.kernels.starfield.render_star_fields` and :meth:`SensorConfig.psf_reach_px`): None unless
    ``cfg.psf_image`` is set; else the read-only (ny, nx) float64 unit-sum array of :func:`load_psf_image`
    (cached per process), checked against ``cfg.psf_image_sha256`` when ``cfg`` states it (as
    :func:`with_psf_digest`; ``error`` as there)."""
    if cfg.psf_image is None:
        return None
    with_psf_digest(cfg, error=error)
    return load_psf_image(cfg.psf_image)
