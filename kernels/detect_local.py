"""Star detection for real sensors: local background and noise, matched filter, hot-pixel and saturation
handling, PSF-fit centroids with their Cramér-Rao uncertainty.

:func:`detect_real` returns the same :class:`~dualsight.kernels.detect.Detections` as
:func:`dualsight.kernels.detect.detect_stars` (as :class:`LocalDetections`, a subclass that adds per-frame
counters), so identification and attitude take either.  Every frame is processed on its own (numpy and
OpenCV, no Taichi: a one-image process starts no kernels): its detections do not depend on the batch it is
in, and a star's PSF fit does not depend on the other stars (each leaves the batched fit when it converges).  Per frame:

1. **Local background and noise.**  The frame is cut into ``tile_px`` squares (mirrored at the far edges
   to whole tiles).  Each tile's pixels are sorted once; then, ``clip_iters`` times, the kept pixels are
   the contiguous run of sorted values within ``clip_sigma`` standard deviations of the centre (3-sigma
   clipping).  The first window is centred on the tile's median with sigma = 1.4826 MAD (computed
   exactly on the sorted tile); the following ones on the clipped mean with the clipped standard
   deviation corrected for the truncation (for a normal distribution clipped at +-c sigma the standard
   deviation is sigma sqrt(1 - 2 c phi(c) / (2 Phi(c) - 1)): 0.98657 sigma at c = 3).  The tile's level is
   the final clipped mean and its noise the corrected clipped standard deviation — not the median and
   the MAD themselves, which on integer ADU with sigma ~2-3 ADU move in 0.5-ADU steps: a 0.5 ADU error
   of the level is 0.65 sigma of the matched-filtered image at PSF sigma 0.9 px.  Tiles that keep less
   than half of their pixels (a bright star, a glare) are replaced by the frame's median tile; a 3 x 3
   median filter over the tile grid (``mesh_filter``, as SExtractor's BACK_FILTERSIZE) removes the
   remaining outliers.  Level and noise are interpolated bilinearly between tile centres (tile (i, j)'s
   centre is pixel coordinate ((j + 0.5) T, (i + 0.5) T); constant beyond the outer centres).
2. **Matched filter.**  The background-subtracted frame R is correlated with the pixel-integrated
   Gaussian PSF of standard deviation ``psf_sigma_px`` (separable kernel k_i = Phi((i + 1/2)/s) -
   Phi((i - 1/2)/s), |i| <= ceil(3 s), normalised; R = 0 outside the frame).  The filtered image's own
   noise is measured: the clipped standard deviation of a strided sample of the filtered image F divided
   by that of R at the same pixels (for white noise sum_i k_i^2; a correlated noise gives more) scales the
   local noise map; near the edges the kernel's missing taps are accounted for exactly.  Pixels of
   Z = F / sigma_F > ``k_sigma`` are foreground.  For a star of flux Fs with pixel fractions P_i on white
   noise sigma, Z at the star's pixel is (up to the pixel phase) the optimal, PSF-weighted integrated SNR
   Fs sqrt(sum_i P_i^2) / sigma ~= Fs / (sigma sqrt(4 pi (s^2 + 1/12))).  ``k_sigma`` is a threshold on
   this integrated SNR, not on the peak pixel's SNR: a pixel-centred 5-sigma star is found with
   probability ~0.5 (Z at each pixel is Gaussian with unit variance around its noise-free value;
   tests/test_detect_real.py checks the rate against that expectation), a 7-sigma star ~98 %.
3. **Candidates.**  Foreground components (OpenCV's connected components of Z > ``k_sigma``; the same
   components as :mod:`dualsight.kernels.labelling`, tests/test_hil_speed.py) larger than ``max_blob_pixels`` are not
   stars (a glare, the Moon): they are counted (``large_blobs``), not centroided.  In each component the
   local maxima of Z (3 x 3) are candidates; a secondary maximum is a second star only when it is at
   least ``deblend_min_sep_px`` from every brighter maximum of the component and Z dips between them
   below (1 - ``deblend_contrast``) times its own Z (else it is the same star).
4. **Hot pixels and cosmic rays.**  At the candidate's brightest pixel p of R (its 3 x 3 neighbourhood),
   t = R_p - r_max * mean(R of p's 4 neighbours), with r_max = (1 + ``sharpness_tolerance``) times the
   largest peak-to-4-neighbour-mean ratio the PSF can produce (a star centred on a pixel: a0 / a1, with
   a0 = 2 Phi(1/(2s)) - 1 and a1 = Phi(3/(2s)) - Phi(1/(2s)); 1.75 at s = 0.9 px, 4.35 at 0.5 px).  A star
   has t <= 0 up to noise (the tolerance absorbs real PSFs sharper than the fitted Gaussian); a single-pixel
   spike is rejected when t > ``hot_pixel_k`` * sigma * sqrt(1 + r_max^2 / 4) (sigma: local noise; the
   standard deviation of t), i.e. spikes above ~8 sigma at s = 0.9 px, ~17 sigma at s = 0.5 px: fainter
   spikes cannot be told from faint sharp stars by one frame.  If the
   candidate is still above ``k_sigma`` without the spike's excess it is kept (a star under a hot pixel)
   and the spike gets weight 0 in the fit; otherwise it is dropped and counted (``hot_pixels``).
5. **Centroid and uncertainty.**  A weighted least-squares fit (Gauss-Newton) of the pixel-integrated
   Gaussian PSF plus a constant, mu_i = A P_i(x, y) + b, to R on a (2h + 1)^2 stamp around p,
   h = max(2, ceil(2.5 s)).  Pixel variance: sigma^2 + max(mu_i - b, 0) / gain (``gain_e_per_adu``; None =
   background-limited, sigma^2).  The stated uncertainty is the Cramér-Rao bound at the fit: the inverse
   of the Fisher matrix I = sum_i grad(mu_i) grad(mu_i)^T / var_i over (x, y, A, b), ``sigma_px`` =
   sqrt((C_xx + C_yy) / 2) (Winick 1986, "Cramér-Rao lower bounds on the performance of charge-coupled-
   device optical position estimators", JOSA A 3, 1809).  Background-limited and well sampled it is
   sigma_px = sqrt(8 pi) s^2 sigma / Fs = sqrt(2) s / SNR; photon-limited, s / sqrt(N_photons).  The fit
   is the maximum-likelihood estimate under that model, which reaches the bound at moderate SNR
   (measured: tests/test_detect_real.py).  A fit that does not converge falls back to the 3 x 3
   intensity-weighted centroid with sigma_px = sqrt(2) s / Z.
6. **Saturation.**  Pixels at or above the saturation level (``saturation_adu``, or the caller's, e.g.
   the camera's 2^bits - 1) get weight 0: a saturated star is fitted on its unsaturated rim (stamp grown
   by the plateau's radius); with fewer than 6 rim pixels, or a rim fit that does not converge, its
   centroid is the plateau's centre (mean of the saturated pixels' centres).  Such stars are flagged
   (``Detections.saturated``).
7. **No silent caps.**  At most ``max_blobs_per_frame`` stars per frame (the highest fitted flux) are
   returned; the others are counted in ``blobs_dropped`` and a warning is logged, as for ``large_blobs``.

With ``psf_sigma_px`` None the PSF width is measured per frame: a first pass at ``psf_sigma_init_px``
fits the width of up to 25 bright (SNR > 30), unsaturated, isolated stars; their median (needs 3) is used
for the final pass, else the initial width.

Centroids use the continuous pixel convention (pixel (r, c) has its centre at (c + 0.5, r + 0.5)).
Cost (1024 x 768, one core): ~15-25 ms per frame with a given PSF width, ~+30 % when it is measured
(``benchmarks/bench_detect.py``); ~37 ms CPU on the ESA frames (~250 stars each, width measured) on a loaded
2-core machine (``benchmarks/bench_hil_speed.py frame``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from dualsight.config import check_fields
from dualsight.kernels import starfield as sf
from dualsight.kernels.detect import Detections

__all__ = ["LocalDetectConfig", "LocalDetections", "detect_real", "tile_background", "interpolate_tiles",
           "subtract_local_background", "psf_kernel_1d", "sharpness_limit", "crb_sigma_px"]

log = logging.getLogger(__name__)

_UNITS = {"k_sigma": "sigma", "psf_sigma_px": "px", "psf_sigma_init_px": "px", "tile_px": "px",
          "clip_sigma": "sigma", "hot_pixel_k": "sigma", "saturation_adu": "ADU", "gain_e_per_adu": "e-/ADU",
          "noise_floor_adu": "ADU", "max_blob_pixels": "px", "deblend_min_sep_px": "px"}


@dataclass(frozen=True)
class LocalDetectConfig:
    """Settings of :func:`detect_real` (module docstring).  Every range is part of the field's type.

    Attributes
    ----------
    k_sigma : detection threshold on the matched-filtered SNR (integrated, PSF-weighted SNR), in [1, 1000].
    psf_sigma_px : Gaussian PSF standard deviation (px) of the matched filter and the fit, in [0.2, 20];
        None = measured per frame.
    psf_sigma_init_px : first-pass width when ``psf_sigma_px`` is None, in [0.2, 20].
    tile_px : background tile side (px), an integer in [8, 4096].
    clip_sigma : sigma clipping of the tile statistics, in [1.5, 10].
    clip_iters : clipping iterations, an integer in [0, 20] (0 = median and 1.4826 MAD of the whole tile).
    mesh_filter : median filter over the tile grid, 1 (off), 3 or 5 tiles.
    hot_pixel_k : significance of the hot-pixel test (sigma), in [0, 1000]; 0 = off.
    sharpness_tolerance : allowed excess of the peak-to-neighbour ratio over the PSF's largest, in [0, 10].
    saturation_adu : pixels at or above it are saturated, None or in [0, 2^24]; None = the caller's level
        (``detect_real(..., saturation_adu=)``), else the largest value of an integer dtype, else none.
    gain_e_per_adu : conversion gain for the stars' shot noise in the fit weights and sigma_px, None or in
        [1e-3, 1e4]; None = background-limited (the frame's measured noise only).
    noise_floor_adu : smallest noise sigma used (ADU), in [0, 2^24]: noise-free frames (0.29 = 1/sqrt(12),
        the quantisation noise of an integer ADC).
    max_blob_pixels : foreground components larger than this are not stars (counted, not centroided),
        an integer in [1, 2^32].
    max_blobs_per_frame : at most this many stars per frame (the brightest), in [1, 10^6]; the rest counted.
    deblend_min_sep_px : smallest separation of two stars in one component (px), in [0, 100].
    deblend_contrast : relative dip of Z between two maxima that makes them two stars, in [0, 1].
    connectivity : 8 or 4 (foreground components).
    """

    k_sigma: Annotated[float, Field(ge=1.0, le=1000.0)] = 5.0
    psf_sigma_px: Annotated[float, Field(ge=0.2, le=20.0)] | None = None
    psf_sigma_init_px: Annotated[float, Field(ge=0.2, le=20.0)] = 1.0
    tile_px: Annotated[int, Field(ge=8, le=4096)] = 32
    clip_sigma: Annotated[float, Field(ge=1.5, le=10.0)] = 3.0
    clip_iters: Annotated[int, Field(ge=0, le=20)] = 3
    mesh_filter: Literal[1, 3, 5] = 3
    hot_pixel_k: Annotated[float, Field(ge=0.0, le=1000.0)] = 5.0
    sharpness_tolerance: Annotated[float, Field(ge=0.0, le=10.0)] = 0.5
    saturation_adu: Annotated[float, Field(ge=0, le=sf.MAX_ADU)] | None = None
    gain_e_per_adu: Annotated[float, Field(ge=1e-3, le=1e4)] | None = None
    noise_floor_adu: Annotated[float, Field(ge=0, le=sf.MAX_ADU)] = 0.29
    max_blob_pixels: Annotated[int, Field(ge=1, le=2 ** 32)] = 4096
    max_blobs_per_frame: Annotated[int, Field(ge=1, le=10 ** 6)] = 1000
    deblend_min_sep_px: Annotated[float, Field(ge=0.0, le=100.0)] = 2.0
    deblend_contrast: Annotated[float, Field(ge=0.0, le=1.0)] = 0.2
    connectivity: Literal[4, 8] = 8

    def __post_init__(self):
        check_fields(self, units=_UNITS)


@dataclass(frozen=True)
class LocalDetections(Detections):
    """:class:`~dualsight.kernels.detect.Detections` plus what :func:`detect_real` counted per frame.

    blobs_dropped : (B,) int64 stars beyond ``max_blobs_per_frame`` (the faintest), not returned.
    large_blobs : (B,) int64 foreground components over ``max_blob_pixels`` (not stars), not returned.
    hot_pixels : (B,) int64 candidates rejected as hot pixels / cosmic rays.
    n_saturated : (B,) int64 returned stars with saturated pixels.
    noise_adu : (B,) float64 median local pixel noise sigma.
    psf_sigma_px : (B,) float64 PSF sigma used (given or measured).
    """

    blobs_dropped: np.ndarray | None = None
    large_blobs: np.ndarray | None = None
    hot_pixels: np.ndarray | None = None
    n_saturated: np.ndarray | None = None
    noise_adu: np.ndarray | None = None
    psf_sigma_px: np.ndarray | None = None


# ============================================================================ normal distribution
_SQRT2 = math.sqrt(2.0)


def _erf(x):
    """erf (Abramowitz & Stegun 7.1.26, |error| <= 1.5e-7), vectorised."""
    x = np.asarray(x, np.float64)
    s = np.sign(x)
    a = np.abs(x)
    t = 1.0 / (1.0 + 0.3275911 * a)
    y = 1.0 - (((((1.061405429 * t - 1.453152027) * t) + 1.421413741) * t - 0.284496736) * t
               + 0.254829592) * t * np.exp(-a * a)
    return s * y


def _Phi(z):
    return 0.5 * (1.0 + _erf(np.asarray(z, np.float64) / _SQRT2))


def _phi(z):
    z = np.asarray(z, np.float64)
    return np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


def _clip_var_factor(c: float) -> float:
    """Variance of a standard normal truncated to [-c, c]."""
    p = math.erf(c / _SQRT2)
    return 1.0 - 2.0 * c * math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi) / p


# ============================================================================ background
def _sorted_mad(s: np.ndarray, med: np.ndarray) -> np.ndarray:
    """Exact median absolute deviation from ``med`` of each row of sorted ``s`` (T, N): the k-th smallest
    |s - med| (k = ceil(N / 2)) is min over windows [i, i + k) of max(med - s[i], s[i + k - 1] - med); the
    window's two ends move in opposite directions, so the best start is found by bisection (one gather per
    row and step)."""
    T, N = s.shape
    rows = np.arange(T)
    k = max((N + 1) // 2, 1)
    a, b = np.zeros(T, np.int64), np.full(T, N - k, np.int64)          # candidate starts [a, b]
    for _ in range(int(math.ceil(math.log2(N + 1))) + 1):
        m = (a + b) // 2
        g = (s[rows, m + k - 1] - med) - (med - s[rows, m])
        go = (g < 0) & (m < b)
        a = np.where(go, m + 1, a)
        b = np.where(go, b, m)
    ip = np.maximum(a - 1, 0)
    d1 = np.maximum(med - s[rows, a], s[rows, a + k - 1] - med)
    d0 = np.maximum(med - s[rows, ip], s[rows, ip + k - 1] - med)
    return np.minimum(d0, d1).astype(np.float64)


def _clipped_stats(s: np.ndarray, clip: float, iters: int):
    """Sigma-clipped level and noise of each row of sorted values ``s`` (T, N) (module docstring, step 1).

    The kept pixels are always a contiguous run [lo, hi) of a sorted row: its bounds are counts of values
    below the window's ends and its sums one ``add.reduceat`` over all rows, on the values relative to the
    row's median (float32 is exact enough: a window never includes the bright tail).  For 8/16-bit frames
    the counts are one ``searchsorted`` over all rows at once (row r's values offset by r x a power of two
    beyond their range: exact in float64, the same counts as the float32 comparisons), else comparisons.
    Returns (level (T,), sigma (T,), kept fraction (T,)) float64."""
    T, N = s.shape
    rows = np.arange(T, dtype=np.int64)
    med = 0.5 * (s[:, (N - 1) // 2].astype(np.float64) + s[:, N // 2])
    sig = 1.4826 * _sorted_mad(s, med)
    if iters <= 0:
        return med, sig, np.ones(T)
    d = np.zeros((T, N + 1), np.float32)            # a zero column ends every row: windows never run past it
    np.subtract(s, med.astype(np.float32)[:, None], out=d[:, :N], casting="unsafe")
    dd = d * d
    flat, flat2 = d.ravel(), dd.ravel()
    if s.dtype.kind == "u" and s.dtype.itemsize <= 2:      # s - med: half-integers, exact in float32 and float64
        span = float(max((s[:, -1] - med).max(), (med - s[:, 0]).max()))
        half = 2.0 ** math.ceil(math.log2(2.0 * span + 2.0))
        base = rows * (2.0 * half)
        keys = s.astype(np.float64)
        keys += (base - med)[:, None]
        keys = keys.ravel()
        first = rows * N

        def count(t, side):          # values of each row < t (side "left") or <= t ("right")
            return np.searchsorted(keys, base + np.clip(t, -half, half), side) - first
    else:
        def count(t, side):
            return (d[:, :N] < t[:, None]).sum(1) if side == "left" else (d[:, :N] <= t[:, None]).sum(1)
    corr = 1.0 / math.sqrt(_clip_var_factor(clip))
    centre = np.zeros(T)                             # relative to med
    lo, hi = np.zeros(T, np.int64), np.full(T, N, np.int64)
    idx = np.empty(2 * T, np.int64)
    for _ in range(iters):
        lo = count((centre - clip * sig).astype(np.float32), "left")
        hi = count((centre + clip * sig).astype(np.float32), "right")
        idx[0::2] = rows * (N + 1) + lo
        idx[1::2] = rows * (N + 1) + hi
        n = hi - lo
        good = n > 0
        m = np.maximum(n, 1)
        mean = np.add.reduceat(flat, idx)[0::2].astype(np.float64) / m
        var = np.maximum(np.add.reduceat(flat2, idx)[0::2].astype(np.float64) / m - mean * mean, 0.0)
        centre = np.where(good, mean, centre)
        sig = np.where(good & (sig > 0), np.sqrt(var) * corr, sig)
    return med + centre, sig, (hi - lo) / N


def _robust_std(v: np.ndarray, clip: float = 3.0, iters: int = 3) -> float:
    """Sigma-clipped standard deviation (truncation-corrected) of a 1-D sample: median and 1.4826 MAD for the
    first window, then the clipped mean and standard deviation (0 for an empty or constant sample)."""
    v = np.asarray(v, np.float64).ravel()
    if v.size < 8:
        return 0.0
    c = float(np.median(v))
    sd = 1.4826 * float(np.median(np.abs(v - c)))
    if sd <= 0:
        return 0.0
    corr = 1.0 / math.sqrt(_clip_var_factor(clip))
    for _ in range(iters):
        w = v[np.abs(v - c) <= clip * sd]
        if w.size < 8:
            break
        c, sd = float(w.mean()), float(w.std()) * corr
    return sd


def tile_background(img: np.ndarray, tile: int = 32, clip: float = 3.0, iters: int = 3, mesh: int = 3):
    """Level and noise sigma of every ``tile`` x ``tile`` square of one (H, W) frame (module docstring, step 1).

    Returns (level (ny, nx) float32, sigma (ny, nx) float32), ny = ceil(H / tile), nx = ceil(W / tile)."""
    import cv2

    H, W = img.shape
    ny, nx = -(-H // tile), -(-W // tile)
    a = img
    if a.dtype.kind == "u" and a.dtype.itemsize <= 2:
        kind = "stable"                     # radix sort for 8/16-bit integers: ~4x faster than quicksort
    else:
        a = a.astype(np.float32, copy=False)
        kind = "quicksort"
    if (ny * tile, nx * tile) != (H, W):
        a = np.pad(a, ((0, ny * tile - H), (0, nx * tile - W)), mode="symmetric")
    t = np.ascontiguousarray(a.reshape(ny, tile, nx, tile).transpose(0, 2, 1, 3)).reshape(ny * nx, tile * tile)
    s = np.sort(t, axis=1, kind=kind)
    level, sig, kept = _clipped_stats(s, clip, iters)
    bad = kept < 0.5
    if bad.any() and not bad.all():
        level[bad] = np.median(level[~bad])
        sig[bad] = np.median(sig[~bad])
    level = level.reshape(ny, nx).astype(np.float32)
    sig = sig.reshape(ny, nx).astype(np.float32)
    if mesh > 1 and ny * nx > 1:
        level = cv2.medianBlur(level, mesh)
        sig = cv2.medianBlur(sig, mesh)
    return level, sig


def interpolate_tiles(grid: np.ndarray, tile: int, H: int, W: int) -> np.ndarray:
    """(H, W) float32 bilinear interpolation of a tile grid between the tiles' centres (pixel (r, c) at
    grid coordinate ((r + 0.5) / tile - 0.5, (c + 0.5) / tile - 0.5); constant beyond the outer centres)."""
    import cv2

    ny, nx = grid.shape
    return cv2.resize(np.ascontiguousarray(grid, np.float32), (nx * tile, ny * tile),
                      interpolation=cv2.INTER_LINEAR)[:H, :W]


def subtract_local_background(images: np.ndarray, cfg: LocalDetectConfig = LocalDetectConfig()):
    """(residual (B, H, W) float32, median tile level (B,)) of frames minus the interpolated tile background
    that :func:`detect_real` uses (for overlays and reports)."""
    images = np.asarray(images)
    B, H, W = images.shape
    out = np.empty((B, H, W), np.float32)
    lev = np.zeros(B)
    for b in range(B):     # one frame at a time (bounded memory), as detect_real
        level, _ = tile_background(images[b], cfg.tile_px, cfg.clip_sigma, cfg.clip_iters, cfg.mesh_filter)
        np.subtract(images[b], interpolate_tiles(level, cfg.tile_px, H, W), out=out[b], casting="unsafe")
        lev[b] = float(np.median(level))
    return out, lev


# ============================================================================ PSF helpers
def psf_kernel_1d(sigma: float) -> np.ndarray:
    """Normalised 1-D pixel-integrated Gaussian, k_i = Phi((i + 1/2) / sigma) - Phi((i - 1/2) / sigma),
    |i| <= ceil(3 sigma)."""
    h = max(1, int(math.ceil(3.0 * sigma)))
    i = np.arange(-h, h + 1, dtype=np.float64)
    k = _Phi((i + 0.5) / sigma) - _Phi((i - 0.5) / sigma)
    return k / k.sum()


def sharpness_limit(sigma: float) -> float:
    """Largest ratio of a pixel-integrated Gaussian star's brightest pixel to the mean of its 4 neighbours
    (over sub-pixel positions: the star centred on a pixel), a0 / a1 (module docstring, step 4)."""
    u = np.linspace(-0.5, 0.5, 21)
    a0 = _Phi((0.5 - u) / sigma) - _Phi((-0.5 - u) / sigma)
    ap = _Phi((1.5 - u) / sigma) - _Phi((0.5 - u) / sigma)
    am = _Phi((-0.5 - u) / sigma) - _Phi((-1.5 - u) / sigma)
    # 2-D, offsets (u, v): peak a0(u) a0(v); neighbours a0(v)(ap(u) + am(u)) + a0(u)(ap(v) + am(v))
    A0 = a0[:, None] * a0[None, :]
    N4 = a0[None, :] * (ap + am)[:, None] + a0[:, None] * (ap + am)[None, :]
    return float((A0 / (N4 / 4.0)).max())


def crb_sigma_px(flux_adu, noise_adu, psf_sigma_px, gain_e_per_adu=None) -> np.ndarray:
    """Cramér-Rao bound (px, per axis) of the position of a pixel-integrated Gaussian star of total flux
    ``flux_adu`` centred on a pixel, on white noise ``noise_adu`` (+ its own shot noise with a gain), with
    flux and a constant background unknown: the same Fisher matrix as the fit's, on a 15 x 15 stamp."""
    shape = np.shape(flux_adu)
    f = np.atleast_1d(np.asarray(flux_adu, np.float64)).ravel()
    n = np.broadcast_to(np.asarray(noise_adu, np.float64), shape).ravel()
    s = float(psf_sigma_px)
    h = max(7, int(math.ceil(4 * s)))
    c = np.arange(-h, h + 1, dtype=np.float64)
    p = _Phi((c + 1 - 0.5) / s) - _Phi((c - 0.5) / s)
    dp = -(_phi((c + 1 - 0.5) / s) - _phi((c - 0.5) / s)) / s
    P = p[:, None] * p[None, :]
    Jx = p[:, None] * dp[None, :]
    Jy = dp[:, None] * p[None, :]
    out = np.empty(f.shape)
    for i in range(f.size):     # a handful of values (tests, reports): not a loop over pixels of a frame
        var = n[i] ** 2 + (np.maximum(f[i] * P, 0) / gain_e_per_adu if gain_e_per_adu else 0.0)
        J = np.stack([f[i] * Jx, f[i] * Jy, P, np.ones_like(P)], -1).reshape(-1, 4)
        I = J.T @ (J / var.reshape(-1, 1))
        out[i] = math.sqrt(np.linalg.inv(I)[0, 0])
    return out.reshape(shape)


# ============================================================================ PSF fit
def _profiles(x, c0, n, s):
    """1-D pixel fractions and their derivatives (d/dx, d/ds) of stamps starting at pixel c0: (K, n) each."""
    c = c0[:, None] + np.arange(n)[None, :]
    a = (c - x[:, None]) / s[:, None]
    b = a + 1.0 / s[:, None]
    Pa, Pb, pa, pb = _Phi(a), _Phi(b), _phi(a), _phi(b)
    return Pb - Pa, -(pb - pa) / s[:, None], -(b * pb - a * pa) / s[:, None]


def _fit(stamp, w0, r0, c0, x, y, s, noise, gain, fit_sigma=False, iters=10):
    """Weighted least-squares fit of A P(x, y; s) + b to (K, n, n) stamps whose top-left pixel is (r0, c0).

    w0 : (K, n, n) 1 = usable pixel, 0 = excluded (saturated, hot, outside the frame).  x, y, s : initial
    values (K,).  Returns x, y, A, b, s, cov (K, 4, 4) of (x, y, A, b) (Fisher inverse), ok (K,)."""
    K, n, _ = stamp.shape
    x, y, s = x.astype(np.float64).copy(), y.astype(np.float64).copy(), s.astype(np.float64).copy()
    d = stamp.astype(np.float64)
    nv = noise.astype(np.float64)[:, None, None] ** 2
    px, _, _ = _profiles(x, c0, n, s)
    py, _, _ = _profiles(y, r0, n, s)
    P = py[:, :, None] * px[:, None, :]
    A = np.maximum((w0 * d * P).sum((1, 2)) / np.maximum((w0 * P * P).sum((1, 2)), 1e-12), 1e-3)
    b = np.zeros(K)
    npar = 5 if fit_sigma else 4
    lam = np.full(K, 1e-3)

    def model(i, x, y, A, b, s):          # stars i (index array) at parameters (x, y, A, b, s) of those stars
        px, dpx, spx = _profiles(x, c0[i], n, s)
        py, dpy, spy = _profiles(y, r0[i], n, s)
        P = py[:, :, None] * px[:, None, :]
        mu = A[:, None, None] * P + b[:, None, None]
        k = len(i)
        J = np.empty((k, n, n, npar))
        Ay = A[:, None] * py
        np.multiply(Ay[:, :, None], dpx[:, None, :], out=J[..., 0])
        np.multiply((A[:, None] * dpy)[:, :, None], px[:, None, :], out=J[..., 1])
        J[..., 2] = P
        J[..., 3] = 1.0
        if fit_sigma:
            J[..., 4] = A[:, None, None] * (spy[:, :, None] * px[:, None, :] + py[:, :, None] * spx[:, None, :])
        return mu, J.reshape(k, n * n, npar)

    def weights(i, mu, b):
        var = nv[i] + (np.maximum(mu - b[:, None, None], 0.0) / gain if gain else 0.0)
        return (w0[i] / var).reshape(len(i), -1)

    everyone = np.arange(K)
    dflat = d.reshape(K, -1)
    mu, J = model(everyone, x, y, A, b, s)
    W = weights(everyone, mu, b)
    chi = (W * (dflat - mu.reshape(K, -1)) ** 2).sum(1)
    eye = np.eye(npar)[None]
    active = everyone
    for _ in range(iters):          # Levenberg-Marquardt; a star leaves the loop when it has converged
        if active.size == 0:
            break
        i = active
        Ji, Wi = J[i], W[i]
        r = dflat[i] - mu[i].reshape(len(i), -1)
        JW = Ji * Wi[:, :, None]
        H = JW.transpose(0, 2, 1) @ Ji
        g = np.einsum("kpj,kp->kj", JW, r)
        diag = np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-12)
        Hd = H + lam[i, None, None] * eye * diag[:, :, None]
        try:
            step = np.linalg.solve(Hd, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            step = np.zeros_like(g)
            for k in range(len(i)):     # singular systems only (degenerate stamps); never per pixel
                step[k] = np.linalg.lstsq(Hd[k], g[k], rcond=None)[0]
        step[:, :2] = np.clip(step[:, :2], -0.5, 0.5)
        if fit_sigma:
            step[:, 4] = np.clip(step[:, 4], -0.3 * s[i], 0.3 * s[i])
        xn, yn, An, bn = x[i] + step[:, 0], y[i] + step[:, 1], A[i] + step[:, 2], b[i] + step[:, 3]
        sn = np.clip(s[i] + step[:, 4], 0.2, 20.0) if fit_sigma else s[i]
        mun, Jn = model(i, xn, yn, An, bn, sn)
        Wn = weights(i, mun, bn)
        chin = (Wn * (dflat[i] - mun.reshape(len(i), -1)) ** 2).sum(1)
        better = np.isfinite(chin) & (chin <= chi[i])
        u = i[better]
        x[u], y[u], A[u], b[u], s[u] = xn[better], yn[better], An[better], bn[better], sn[better]
        mu[u], J[u], W[u], chi[u] = mun[better], Jn[better], Wn[better], chin[better]
        lam[i] = np.where(better, np.maximum(lam[i] / 10, 1e-6), lam[i] * 10)
        done = (better & (np.abs(step[:, :2]).max(1) < 1e-4)) | (lam[i] >= 1e4)
        active = i[~done]
    J4 = J[..., :4]
    H = (J4 * W[:, :, None]).transpose(0, 2, 1) @ J4
    ok = np.isfinite(H).all((1, 2)) & (np.abs(np.linalg.det(H)) > 0)
    cov = np.full((K, 4, 4), np.nan)
    if ok.any():
        cov[ok] = np.linalg.inv(H[ok])
    half = n / 2.0
    ok &= (A > 0) & np.isfinite(x) & np.isfinite(y) & (np.abs(x - (c0 + half)) < half - 0.5) \
        & (np.abs(y - (r0 + half)) < half - 0.5) & (np.diagonal(cov, axis1=1, axis2=2)[:, :2] > 0).all(1)
    return x, y, A, b, s, cov, ok


def _stamps(R, valid, r, c, h):
    """(K, n, n) stamps of R and of the usable pixels (inside the frame and ``valid``, None = all) centred on
    pixels (r, c), n = 2h + 1, and the stamps' first row and column."""
    H, W = R.shape
    n = 2 * h + 1
    rr = r[:, None] - h + np.arange(n)[None, :]
    cc = c[:, None] - h + np.arange(n)[None, :]
    ok = ((rr >= 0) & (rr < H))[:, :, None] & ((cc >= 0) & (cc < W))[:, None, :]
    rcl, ccl = np.clip(rr, 0, H - 1)[:, :, None], np.clip(cc, 0, W - 1)[:, None, :]
    st = R[rcl, ccl]
    if valid is not None:
        ok &= valid[rcl, ccl]
    return st, ok.astype(np.float64), rr[:, 0], cc[:, 0]


# ============================================================================ one frame
@dataclass
class _Frame:
    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    npix: np.ndarray
    sigma_px: np.ndarray
    saturated: np.ndarray
    level: float
    threshold: float
    noise: float
    psf_sigma: float
    large: int
    hot: int


def _filter(R, sig_map, s, floor, cache=None):
    """Matched-filtered SNR image Z (float32) of residual R with PSF sigma s, and the noise ratio sigma_F / sigma.

    Outside the frame R is 0 (its expectation), so near an edge F sums fewer pixels and its white-noise sigma
    is sigma sqrt(sum over the kernel's in-frame part of K^2): Z is normalised by that, exactly, per row and
    column.  ``sig_map`` is overwritten; ``cache`` (a dict) keeps R's sample noise between calls on the same R."""
    import cv2

    H, W = R.shape
    k = psf_kernel_1d(s)
    h = len(k) // 2
    F = cv2.sepFilter2D(R, cv2.CV_32F, k.astype(np.float32), k.astype(np.float32), borderType=cv2.BORDER_CONSTANT)
    inner = (slice(h, max(h + 1, H - h), 4), slice(h, max(h + 1, W - h), 4))
    sa = cache.get(h) if cache is not None else None       # R's noise at the sample: the same for both passes
    if sa is None:
        sa = _robust_std(R[inner])
        if cache is not None:
            cache[h] = sa
    sfv = _robust_std(F[inner])
    k2 = k * k
    white = float(k2.sum())
    ratio = sfv / sa if sa > 0 and sfv > 0 else white
    np.maximum(sig_map, floor, out=sig_map)
    sig_map *= np.float32(ratio)
    cum = np.concatenate([[0.0], np.cumsum(k2)])

    def edge(n):    # sqrt(in-frame sum of k_i^2 / sum k_i^2) for the first min(h, n) positions from an edge
        i = np.arange(min(h, n))
        return np.sqrt((cum[-1] - cum[np.maximum(h - i, 0)]) / cum[-1]).astype(np.float32)  # taps i - h .. h

    er, ec = edge(H), edge(W)
    sig_map[:er.size] *= er[:, None]
    sig_map[H - er.size:] *= er[::-1, None]
    sig_map[:, :ec.size] *= ec[None, :]
    sig_map[:, W - ec.size:] *= ec[None, ::-1]
    np.divide(F, sig_map, out=F)
    return F, ratio


def _candidates(Z, cfg: LocalDetectConfig):
    """Local maxima of Z above the threshold, grouped into components and deblended.

    Returns (rows, cols, npix of their component) of the kept maxima, number of large components."""
    import cv2

    H, W = Z.shape
    # foreground Z > k_sigma (float32 compare equal to the float64 one: kernels.labelling.native_threshold)
    t = np.float32(cfg.k_sigma)
    if float(t) > cfg.k_sigma:
        t = np.nextafter(t, np.float32(-np.inf))
    fg = Z > t
    n_lab, lab = cv2.connectedComponents(fg.view(np.uint8), connectivity=cfg.connectivity, ltype=cv2.CV_32S)
    if n_lab <= 1:
        e = np.zeros(0, np.int64)
        return e, e, e, 0
    f = np.flatnonzero(fg)                       # the foreground pixels (a few thousand): work on them only
    lab_f = lab.ravel()[f]
    npix_c = np.bincount(lab_f, minlength=n_lab)[1:].astype(np.int64)
    # the 3 x 3 local maxima among the foreground pixels (outside the frame ignored, as clipped indices do)
    peak = Z.ravel()[f] >= cv2.dilate(Z, np.ones((3, 3), np.uint8)).ravel()[f]
    f = f[peak]
    pr, pc = np.divmod(f.astype(np.int64), W)
    cid = lab_f[peak].astype(np.int64) - 1
    large = npix_c > cfg.max_blob_pixels
    n_large = int(large.sum())
    keep = ~large[cid]
    pr, pc, cid = pr[keep], pc[keep], cid[keep]
    z = Z[pr, pc]
    order = np.lexsort((pc, pr, -z, cid))
    pr, pc, cid, z = pr[order], pc[order], cid[order], z[order]
    first = np.ones(len(cid), bool)
    first[1:] = cid[1:] != cid[:-1]
    accept = first.copy()
    multi = np.flatnonzero(~first)
    if multi.size:
        # pairs (j, i): j a secondary maximum, i a brighter maximum of the same component
        start = np.searchsorted(cid, cid[multi], side="left")
        cnt = multi - start
        j = np.repeat(multi, cnt)
        i = np.repeat(start, cnt) + (np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt))
        dy, dx = (pr[j] - pr[i]).astype(np.float64), (pc[j] - pc[i]).astype(np.float64)
        far = np.hypot(dx, dy) >= cfg.deblend_min_sep_px
        dip = np.full(j.size, np.inf)
        for t in (0.25, 0.5, 0.75):
            rr = np.rint(pr[i] + t * dy).astype(np.int64)
            cc = np.rint(pc[i] + t * dx).astype(np.int64)
            dip = np.minimum(dip, Z[rr, cc])
        sep = far & (dip < (1.0 - cfg.deblend_contrast) * z[j])
        bad = np.zeros(len(cid), bool)
        np.logical_or.at(bad, j, ~sep)
        accept[multi] = ~bad[multi]
    return pr[accept], pc[accept], npix_c[cid[accept]], n_large


def _measure(img, R, sig_map, Z, ratio, s, cfg, sat, fit_sigma=False):
    """Hot-pixel test, saturation and PSF fit of the candidates of one frame."""
    H, W = R.shape
    pr, pc, npix, n_large = _candidates(Z, cfg)
    K = pr.size
    e = np.zeros(0)
    if K == 0:
        return dict(x=e, y=e, flux=e, npix=np.zeros(0, np.int64), sigma_px=e, saturated=np.zeros(0, bool),
                    s=np.full(0, s), large=n_large, hot=0, snr=e, ok=np.zeros(0, bool))
    if fit_sigma:     # the PSF width: from the 25 brightest unsaturated candidates of SNR > 30 only
        z = Z[pr, pc]
        near_sat = np.zeros(K, bool)
        if sat is not None:
            for dr in range(-2, 3):
                for dc in range(-2, 3):
                    near_sat |= img[np.clip(pr + dr, 0, H - 1), np.clip(pc + dc, 0, W - 1)] >= sat
        top = np.flatnonzero((z > 30) & ~near_sat)
        if top.size:      # isolated: no other candidate within 3 PSF half-widths
            d = np.hypot(pr[top, None] - pr[None, :], pc[top, None] - pc[None, :]).astype(np.float64)
            d[np.arange(top.size), top] = np.inf
            top = top[d.min(1) > 3 * max(2, math.ceil(2.5 * s))]
        top = top[np.argsort(-z[top], kind="stable")][:25]
        pr, pc, npix = pr[top], pc[top], npix[top]
        K = pr.size
        if K == 0:
            return dict(s=np.full(0, s), ok=np.zeros(0, bool), saturated=np.zeros(0, bool), snr=e)
    # brightest R pixel of the candidate's 3 x 3 neighbourhood (within the frame)
    off = np.array([(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
    rr, cc = pr[:, None] + off[:, 0], pc[:, None] + off[:, 1]
    inside = (rr >= 0) & (rr < H) & (cc >= 0) & (cc < W)
    vals = np.where(inside, R[np.clip(rr, 0, H - 1), np.clip(cc, 0, W - 1)], -np.inf)
    best = vals.argmax(1)
    r0, c0 = pr + off[best, 0], pc + off[best, 1]
    at = lambda dr, dc: R[np.clip(r0 + dr, 0, H - 1), np.clip(c0 + dc, 0, W - 1)].astype(np.float64)
    peak = at(0, 0)
    m4 = (at(-1, 0) + at(1, 0) + at(0, -1) + at(0, 1)) / 4.0
    noise = np.maximum(sig_map[r0, c0].astype(np.float64), cfg.noise_floor_adu)
    satmask = img >= sat if sat is not None else np.zeros((H, W), bool)
    is_sat = satmask[r0, c0]
    hot_px = np.zeros(K, bool)
    keep = np.ones(K, bool)
    n_hot = 0
    if cfg.hot_pixel_k > 0:
        rmax = (1.0 + cfg.sharpness_tolerance) * sharpness_limit(s)
        stat = peak - rmax * m4
        hot_px = (stat > cfg.hot_pixel_k * noise * math.sqrt(1.0 + rmax * rmax / 4.0)) & ~is_sat
        k0 = psf_kernel_1d(s)
        k00 = float(k0[len(k0) // 2] ** 2)
        z_wo = Z[r0, c0] - (peak - m4) * k00 / (noise * ratio)        # Z at the spike without its excess
        keep = ~hot_px | (z_wo > cfg.k_sigma)
        n_hot = int((hot_px & ~keep).sum())
    pr, pc, r0, c0, npix, noise, hot_px, is_sat = (a[keep] for a in (pr, pc, r0, c0, npix, noise, hot_px, is_sat))
    K = pr.size
    valid = ~satmask
    h = max(2, int(math.ceil(2.5 * s)))
    x = np.zeros(K)
    y = np.zeros(K)
    A = np.zeros(K)
    cov = np.full((K, 4, 4), np.nan)
    ok = np.zeros(K, bool)
    sfit = np.full(K, s)
    # saturated candidates: stamp grown by the plateau radius
    sat_any = np.zeros(K, bool)
    if sat is not None and K:
        st_s, inside, _, _ = _stamps(satmask, None, r0, c0, h)
        sat_any = (st_s & (inside > 0)).reshape(K, -1).any(1)
    groups = [(~sat_any, h, False)]
    if sat_any.any():
        nsat = np.array([satmask[max(0, a - 3 * h):a + 3 * h + 1, max(0, b - 3 * h):b + 3 * h + 1].sum()
                         for a, b in zip(r0[sat_any], c0[sat_any])])   # one window per saturated star
        hs = h + int(math.ceil(math.sqrt(max(nsat.max(), 1) / math.pi))) + 1
        groups.append((sat_any, hs, True))
    frac3 = float((_Phi(1.5 / s) - _Phi(-1.5 / s)) ** 2)       # PSF fraction in a centred 3 x 3 box
    for sel, hh, saturated in groups:
        idx = np.flatnonzero(sel)
        if idx.size == 0:
            continue
        st, w0, rr0, cc0 = _stamps(R, valid, r0[idx], c0[idx], hh)
        if hot_px[idx].any():      # a kept star under a hot pixel: the spike gets weight 0
            w0[hot_px[idx], hh, hh] = 0.0
        # start: 3 x 3 intensity-weighted centroid of the positive residual
        box = (slice(None), slice(hh - 1, hh + 2), slice(hh - 1, hh + 2))
        cen = np.maximum(st[box].astype(np.float64), 0) * w0[box]
        tot = cen.sum((1, 2))
        dxs = np.where(tot > 0, (cen * np.array([-1, 0, 1])[None, None, :]).sum((1, 2)) / np.maximum(tot, 1e-12), 0)
        dys = np.where(tot > 0, (cen * np.array([-1, 0, 1])[None, :, None]).sum((1, 2)) / np.maximum(tot, 1e-12), 0)
        x0 = c0[idx] + 0.5 + dxs
        y0 = r0[idx] + 0.5 + dys
        usable = w0.reshape(idx.size, -1).sum(1)
        xf, yf, Af, _, sf_, cf, okf = _fit(st, w0, rr0, cc0, x0, y0, np.full(idx.size, s), noise[idx],
                                          cfg.gain_e_per_adu, fit_sigma=fit_sigma)
        okf &= usable >= 6
        fb = ~okf
        if fb.any():     # fallback: plateau centre (saturated) or the 3 x 3 centroid
            xf, yf = xf.copy(), yf.copy()
            xf[fb], yf[fb] = x0[fb], y0[fb]
            if saturated:
                sm, inside, _, _ = _stamps(satmask, None, r0[idx], c0[idx], hh)
                sm = sm & (inside > 0)
                ns = sm.sum((1, 2))
                gy, gx = np.mgrid[0:2 * hh + 1, 0:2 * hh + 1]
                pcx = cc0[:, None, None] + gx[None] + 0.5
                pcy = rr0[:, None, None] + gy[None] + 0.5
                have = fb & (ns > 0)
                xf[have] = ((sm * pcx).sum((1, 2)) / np.maximum(ns, 1))[have]
                yf[have] = ((sm * pcy).sum((1, 2)) / np.maximum(ns, 1))[have]
            Af = np.where(fb, np.maximum(tot, 0) / frac3, Af)
        x[idx], y[idx], A[idx], cov[idx], ok[idx], sfit[idx] = xf, yf, Af, cf, okf, sf_
    zpk = Z[pr, pc].astype(np.float64)
    sig_fb = _SQRT2 * s / np.maximum(zpk, 1e-6)
    sigma_px = np.where(ok, np.sqrt(np.maximum(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]), 0)), sig_fb)
    return dict(x=x, y=y, flux=A, npix=npix, sigma_px=sigma_px, saturated=sat_any, s=sfit, large=n_large,
                hot=n_hot, snr=zpk, ok=ok)


def _detect_frame(img: np.ndarray, cfg: LocalDetectConfig, sat) -> _Frame:
    H, W = img.shape
    level, sig = tile_background(img, cfg.tile_px, cfg.clip_sigma, cfg.clip_iters, cfg.mesh_filter)
    bg = interpolate_tiles(level, cfg.tile_px, H, W)
    sig_map = interpolate_tiles(sig, cfg.tile_px, H, W)
    R = img.astype(np.float32) - bg
    floor = np.float32(max(cfg.noise_floor_adu, 1e-6))
    s = cfg.psf_sigma_px if cfg.psf_sigma_px is not None else cfg.psf_sigma_init_px
    rcache = {}
    Z, ratio = _filter(R, sig_map.copy(), s, floor, rcache)
    if cfg.psf_sigma_px is None:     # measure the PSF width on bright, unsaturated, isolated stars
        m = _measure(img, R, sig_map, Z, ratio, s, cfg, sat, fit_sigma=True)
        use = np.flatnonzero(m["ok"] & ~m["saturated"] & (m["snr"] > 30))
        use = use[np.argsort(-m["snr"][use])][:25]
        if use.size >= 3:
            s_new = float(np.clip(np.median(m["s"][use]), 0.2, 20.0))
            if abs(s_new - s) > 0.02 * s:
                s = s_new
                Z, ratio = _filter(R, sig_map.copy(), s, floor, rcache)
    m = _measure(img, R, sig_map, Z, ratio, s, cfg, sat)
    med_sig = float(np.median(sig))
    return _Frame(x=m["x"], y=m["y"], flux=m["flux"], npix=m["npix"], sigma_px=m["sigma_px"],
                  saturated=m["saturated"], level=float(np.median(level)),
                  threshold=float(np.median(level)) + cfg.k_sigma * max(med_sig, cfg.noise_floor_adu) * ratio,
                  noise=med_sig, psf_sigma=float(s), large=m["large"], hot=m["hot"])


# ============================================================================ public API
def detect_real(images: np.ndarray, cfg: LocalDetectConfig = LocalDetectConfig(), *,
                saturation_adu=None) -> LocalDetections:
    """Detect and centroid stars in a batch of real (or realistic) frames (module docstring).

    Parameters
    ----------
    images : (B, H, W) uint8, uint16, float32 or float64 frames (ADU), not background-subtracted.
    cfg : :class:`LocalDetectConfig`.
    saturation_adu : saturation level when ``cfg.saturation_adu`` is None (e.g. the camera's 2^bits - 1);
        None = the largest value of an integer dtype, no saturation for float frames.

    Returns
    -------
    :class:`LocalDetections` sorted by (case, flux descending): ``flux`` is the fitted total flux (ADU),
    ``npix`` the pixels of the star's foreground component (Z > k_sigma), ``sigma_px`` the Cramér-Rao
    centroid uncertainty per axis (px), ``saturated`` the flag; ``background_adu`` the median tile level,
    ``threshold_adu`` that level + k_sigma x the median noise of the filtered image (the threshold of the
    filtered image, ADU).  Per-frame counters: see :class:`LocalDetections`.
    """
    images = np.asarray(images)
    if images.ndim != 3:
        raise ValueError(f"images must have shape (B, H, W), got {images.shape}")
    if images.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise ValueError(f"images must be uint8, uint16, float32 or float64, got {images.dtype}")
    B, H, W = images.shape
    sat = cfg.saturation_adu if cfg.saturation_adu is not None else saturation_adu
    if sat is None and images.dtype.kind == "u":
        sat = float(np.iinfo(images.dtype).max)
    frames = [_detect_frame(images[b], cfg, sat) for b in range(B)] if H and W else []
    cap = cfg.max_blobs_per_frame
    parts, dropped = [], np.zeros(B, np.int64)
    for b, f in enumerate(frames):
        order = np.lexsort((f.x, f.y, -f.flux))
        if order.size > cap:
            dropped[b] = order.size - cap
            order = order[:cap]
        parts.append(order)
    for b in np.flatnonzero(dropped):
        log.warning("frame %d: %d stars beyond max_blobs_per_frame=%d dropped (the faintest)", b, dropped[b], cap)
    large = np.array([f.large for f in frames], np.int64) if frames else np.zeros(B, np.int64)
    for b in np.flatnonzero(large):
        log.warning("frame %d: %d foreground regions over max_blob_pixels=%d px not centroided", b, large[b],
                    cfg.max_blob_pixels)
    cat = lambda name, dt: (np.concatenate([getattr(f, name)[o] for f, o in zip(frames, parts)]).astype(dt)
                            if frames else np.zeros(0, dt))
    counts = np.array([o.size for o in parts], np.int64) if frames else np.zeros(B, np.int64)
    offsets = np.zeros(B + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    saturated = cat("saturated", bool)
    per = lambda name: np.array([getattr(f, name) for f in frames], np.float64) if frames else np.zeros(B)
    return LocalDetections(
        case=np.repeat(np.arange(B, dtype=np.int32), counts), x=cat("x", np.float64), y=cat("y", np.float64),
        flux=cat("flux", np.float64), npix=cat("npix", np.int32), offsets=offsets,
        background_adu=per("level"), threshold_adu=per("threshold"),
        sigma_px=cat("sigma_px", np.float64), saturated=saturated,
        blobs_dropped=dropped, large_blobs=large,
        hot_pixels=np.array([f.hot for f in frames], np.int64) if frames else np.zeros(B, np.int64),
        n_saturated=np.bincount(np.repeat(np.arange(B), counts)[saturated], minlength=B).astype(np.int64),
        noise_adu=per("noise"), psf_sigma_px=per("psf_sigma"))
