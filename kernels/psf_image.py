"""The measured PSF of a sensor (``SensorConfig.psf_model = "image"``) as an array: its checks and
normalisation (:func:`unit_sum_psf`), the renderer's check of what it is handed (:func:`check_psf`) and its
content hash (:func:`psf_image_sha256`, stored in the spec).  Arrays in, arrays out: the file is read in the
scene layer (:func:`dualsight.scene.psf_file.load_psf_image`), which hands the renderer
(:mod:`dualsight.kernels.psf_models`) the array this module checks.

A PSF is an odd-sized (<= :data:`PSF_IMAGE_MAX_PX` px per side) 2-D array of non-negative numbers sampled on
the sensor's own pixel grid, centred on its middle pixel; the renderer takes it as (ny, nx) float64 of unit sum
(the fraction of a star's electrons per pixel).
"""

import hashlib

import numpy as np

__all__ = ["PSF_IMAGE_MAX_PX", "psf_image_sha256", "unit_sum_psf", "check_psf"]

PSF_IMAGE_MAX_PX = 64
"""Largest side (px) of a measured PSF image."""
PSF_SUM_TOLERANCE = 1e-9
"""Largest |sum - 1| of a PSF handed to the renderer (:func:`check_psf`); :func:`unit_sum_psf` gives ~1e-16."""


def psf_image_sha256(a: np.ndarray) -> str:
    """SHA-256 (hex) of a loaded PSF (:func:`unit_sum_psf`: unit-sum float64): its shape and little-endian values.
    Stored in the sensor spec, so a run's identity covers the PSF's content, not only its file name."""
    h = hashlib.sha256(f"{a.shape[0]}x{a.shape[1]}:".encode())
    h.update(np.ascontiguousarray(a, dtype="<f8").tobytes())
    return h.hexdigest()


def unit_sum_psf(a) -> np.ndarray:
    """``a`` (the numbers of a PSF file) checked and divided by its sum: a read-only C-contiguous (ny, nx)
    float64 array of unit sum.

    Checked: 2-D, numbers (unsigned, signed or float dtype), both sides odd and <= :data:`PSF_IMAGE_MAX_PX`,
    every value finite and >= 0, positive sum.  A failure is a one-line ValueError saying what is wrong (the
    caller prefixes the file's name).
    """
    a = np.asarray(a)
    if a.ndim != 2:
        raise ValueError(f"must be a 2-D array, got shape {a.shape}")
    if a.dtype.kind not in "uif":
        raise ValueError(f"must hold numbers, got dtype {a.dtype}")
    ny, nx = a.shape
    if ny % 2 == 0 or nx % 2 == 0 or ny > PSF_IMAGE_MAX_PX or nx > PSF_IMAGE_MAX_PX:
        raise ValueError(f"must have odd sides <= {PSF_IMAGE_MAX_PX} px (centred on its middle pixel), got {ny} x {nx}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError("holds non-finite values")
    if a.min() < 0:
        raise ValueError(f"holds negative values (min {a.min():g})")
    total = float(a.sum())
    if not total > 0:
        raise ValueError("sums to zero")
    a = np.ascontiguousarray(a / total)
    a.setflags(write=False)
    return a


def check_psf(psf, psf_model: str) -> np.ndarray:
    """The PSF array a renderer is handed for a sensor of ``psf_model``, checked: with ``psf_model = "image"``
    a (ny, nx) float64 array (odd sides <= :data:`PSF_IMAGE_MAX_PX`, finite, >= 0, sum within
    :data:`PSF_SUM_TOLERANCE` of 1: :func:`unit_sum_psf`'s output), returned C-contiguous with its values
    untouched; for every other model ``psf`` is ignored and a (1, 1) zero array is returned (the kernels'
    placeholder).  One-line ValueError otherwise."""
    if psf_model != "image":
        return np.zeros((1, 1))
    if psf is None:
        raise ValueError("SensorConfig.psf_model = \"image\" needs the measured PSF as an array (psf=: "
                         "dualsight.scene.psf_file.sensor_psf(cfg), a (ny, nx) float64 array of unit sum)")
    a = np.asarray(psf)
    if a.ndim != 2 or a.dtype != np.float64:
        raise ValueError(f"psf must be a 2-D float64 array, got {a.dtype} of shape {a.shape}")
    ny, nx = a.shape
    if ny % 2 == 0 or nx % 2 == 0 or ny > PSF_IMAGE_MAX_PX or nx > PSF_IMAGE_MAX_PX:
        raise ValueError(f"psf must have odd sides <= {PSF_IMAGE_MAX_PX} px, got {ny} x {nx}")
    if not np.all(np.isfinite(a)) or a.min() < 0 or not abs(float(a.sum()) - 1.0) <= PSF_SUM_TOLERANCE:
        raise ValueError("psf must hold finite values >= 0 of unit sum (dualsight.kernels.psf_image.unit_sum_psf)")
    return np.ascontiguousarray(a)
