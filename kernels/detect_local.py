"""Star detection for real sensors: local background and noise, matched filter, hot-pixel and saturation
handling, PSF-fit centroids with their Cramér-Rao uncertainty.

:func:`detect_real` returns the same :class:`~dualsight.kernels.detect.Detections` as
:func:`dualsight.kernels.detect.detect_stars` (as :class:`LocalDetections`, a subclass that adds per-frame
counters), so identification and attitude take either.  Every frame is processed on its own (numpy and
OpenCV; the PSF fits and the tiles' last clipping window in Taichi with ``fit_engine`` "taichi" or "auto", the default, steps
1 and 5): its detections do not depend on the batch it is in, and a star's PSF fit does not depend on the other
stars (each leaves the batched fit when it converges).

One module per stage: step 1 is :mod:`dualsight.kernels.detect_background` (tile statistics), steps 2-3
:mod:`dualsight.kernels.detect_candidates` (matched filter, candidates), the PSF and its fit (step 5)
:mod:`dualsight.kernels.detect_psf`, the candidates' brightest pixel and hot-pixel test (step 4)
:mod:`dualsight.kernels.detect_hot_pixels`; this module holds the settings, the saturation handling (step 6)
around the fit, and assembles the detections (step 7).  Per frame:

1. **Local background and noise.**  The frame is cut into ``tile_px`` squares (mirrored at the far edges
   to whole tiles).  ``clip_iters`` times, the kept pixels are those within ``clip_sigma`` standard
   deviations of the centre (3-sigma clipping).  The first window is centred on the median with sigma =
   1.4826 MAD; the following ones on the clipped mean with the clipped standard deviation corrected for the
   truncation (for a normal distribution clipped at +-c sigma the standard deviation is
   sigma sqrt(1 - 2 c phi(c) / (2 Phi(c) - 1)): 0.98657 sigma at c = 3).  All of it is computed on a quarter of
   the tile's pixels (even rows and even columns; sorted once, each window the contiguous run of sorted values;
   tiles of odd size: all pixels): the level errs by ~sigma / sqrt(T^2 / 4) (0.063 sigma for 32 px tiles) and the
   noise by ~4.4 % per tile, before the median filters below (tests/test_detect_real.py; why not every pixel:
   :func:`~dualsight.kernels.detect_background.tile_background`).
   The tile's level is the final clipped mean and its noise the corrected clipped standard deviation — not
   the median and the MAD themselves, which on integer ADU with sigma ~2-3 ADU move in 0.5-ADU steps: a 0.5
   ADU error of the level is 0.65 sigma of the matched-filtered image at PSF sigma 0.9 px.  Where the median is a
   tied value (integer counts whose noise spans 1-2 levels, or a dark-subtracted frame clamped at 0: the MAD is
   one level or 0, and a sigma of 0 never widens its window) the clipping starts from the 1-ADU lattice's
   interpolated median and interquartile range / 1.349 instead
   (:func:`~dualsight.kernels.detect_background.lattice_start`).  Tiles that keep less
   than half of their sample (a bright star, a glare) are replaced by the frame's median tile; a 3 x 3
   median filter over the tile grid (``mesh_filter``, as SExtractor's BACK_FILTERSIZE) removes the
   remaining outliers from the levels, a 5 x 5 one (``mesh_filter`` + 2) from the noise, which varies more slowly and
   sets more of the threshold's scatter. The level and the inverse noise 1 / max(sigma, ``noise_floor_adu``) are
   interpolated bilinearly between tile centres (tile (i, j)'s centre is pixel coordinate ((j + 0.5) T, (i + 0.5) T);
   constant beyond the outer centres): the pixel noise is the harmonic interpolation of the tiles'.
2. **Matched filter.**  The background-subtracted frame R is correlated with the pixel-integrated
   Gaussian PSF of standard deviation ``psf_sigma_px`` (separable kernel k_i = Phi((i + 1/2)/s) -
   Phi((i - 1/2)/s), |i| <= h, normalised, h the fewest taps that keep 0.999 of the untruncated filter's SNR:
   ``detect_psf.FILTER_SNR_EFFICIENCY``; R = 0 outside the frame).  The filtered image's own
   noise is measured: the clipped mean and standard deviation of a strided sample of F / sigma (every 8th row and column
   from 4 ceil(h / 4) px off the edges, h the kernel's half-width: ~12,000 pixels of a 1024 x 768 frame; median,
   MAD and the first two windows on every 4th sample value, the last window on all): the mean is subtracted and the
   standard deviation (the ratio sigma_F / sigma: sum_i k_i^2 for white noise, more for a noise correlated between
   pixels) scales the local noise map, so Z is in units of the filtered noise's own sigma even where the tiles' sigma
   is off (quantised, clamped); a frame clamped at its black level (over a quarter of its
   pixels at its minimum) also has the sample's upper tail checked (``detect_candidates.TAIL_P``: its noise is
   skewed to the right).  Near the edges the kernel's missing taps
   are accounted for exactly (Z's noise is evaluated at pixels on demand, not stored as a map).  Pixels of
   Z = F / sigma_F > ``k_sigma`` are foreground.  For a star of flux Fs with pixel fractions P_i on white
   noise sigma, Z at the star's pixel is (up to the pixel phase) the optimal, PSF-weighted integrated SNR
   Fs sqrt(sum_i P_i^2) / sigma ~= Fs / (sigma sqrt(4 pi (s^2 + 1/12))).  ``k_sigma`` is a threshold on
   this integrated SNR, not on the peak pixel's SNR: a pixel-centred 5-sigma star is found with
   probability ~0.5 (Z at each pixel is Gaussian with unit variance around its noise-free value;
   tests/test_detect_real.py checks the rate against that expectation), a 7-sigma star ~98 %.
3. **Candidates.**  Foreground components (connected components of the pixels of Z > ``k_sigma``, labelled over
   those pixels only by :func:`~dualsight.kernels.detect_candidates.sparse_components`; the same components as
   OpenCV's and :mod:`dualsight.kernels.labelling`'s, tests/test_hil_speed.py) larger than ``max_blob_pixels`` are not
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
   candidate is still above ``k_sigma`` without the spike's excess (Z's own noise at that pixel, the frame
   edges included; on an edge the mean is over the in-frame neighbours) it is kept (a star under a hot pixel)
   and the spike gets weight 0 in the fit; otherwise it is dropped and counted (``hot_pixels``).
5. **Centroid and uncertainty.**  A weighted least-squares fit (Levenberg-Marquardt, batched over the stars;
   each star stops when its proposed position step is under 1e-3 px, i.e. within ~1e-3 px of its minimum,
   or after 10 steps) of the pixel-integrated
   Gaussian PSF plus a constant, mu_i = A P_i(x, y) + b, to R on a (2h + 1)^2 stamp around p,
   h = max(2, ceil(2.5 s)).  Pixel variance: sigma^2 + max(mu_i - b, 0) / gain (``gain_e_per_adu``; None =
   background-limited, sigma^2).  The stated uncertainty is the Cramér-Rao bound at the fit: the inverse
   of the Fisher matrix I = sum_i grad(mu_i) grad(mu_i)^T / var_i over (x, y, A, b), ``sigma_px`` =
   sqrt((C_xx + C_yy) / 2) (Winick 1986, "Cramér-Rao lower bounds on the performance of charge-coupled-
   device optical position estimators", JOSA A 3, 1809).  Background-limited and well sampled it is
   sigma_px = sqrt(8 pi) s^2 sigma / Fs = sqrt(2) s / SNR; photon-limited, s / sqrt(N_photons).  With
   ``fit_engine`` "taichi" (or "auto", the default) the fits run as one compiled kernel (:mod:`dualsight.kernels.detect_psf_fit`:
   3-5x faster, positions equal to the numpy fit's within ~1e-12 px, not bit for bit; one launch per group of
   stamps, which also cuts the stamps from the frame, starts them at the 3 x 3 centroid and inverts the Fisher
   matrix: ``fit_frame_compiled``), and so do the tiles' last
   clipping window and the candidates' components (:mod:`dualsight.kernels.detect_passes`; float64 sums: the
   detections within ~1e-7 px of the numpy path's).  The engine is a setting of the run, never chosen by what the
   process happens to run; "numpy" starts no kernels (Taichi's start and the detector's kernels cost ~1.1 s once
   per process, which a one-image ``hil star`` pays: the price of the default's ~4 ms less on every further
   frame; tests/test_detect_psf_fit.py).  The fit
   is the maximum-likelihood estimate under that model, which reaches the bound at moderate SNR
   (measured: tests/test_detect_real.py).  A fit that does not converge falls back to the 3 x 3
   intensity-weighted centroid with sigma_px = sqrt(2) s / Z.
6. **Saturation.**  Pixels at or above the saturation level (``saturation_adu``, or the caller's, e.g.
   the camera's 2^bits - 1) get weight 0: a saturated star is fitted on its unsaturated rim (stamp grown
   by the plateau's radius); with fewer than 6 rim pixels, or a rim fit that does not converge, its
   centroid is the plateau's centre (mean of the saturated pixels' centres).  Such stars are flagged
   (``Detections.saturated``).  A saturated plateau wider than pi (6 s)^2 pixels (in the (6h + 1)^2 window
   around the candidate) is not a star but an extended object (the Moon, a planet's disk, the Earth's limb):
   a star's plateau radius is s sqrt(2 ln(F / (2 pi s^2 full well))), 6 s only at F = 4e8 full wells.  It is
   counted in ``large_blobs``, not returned.
7. **No silent caps.**  At most ``max_blobs_per_frame`` stars per frame (the highest fitted flux) are
   returned; the others are counted in ``blobs_dropped`` and a warning is logged, as for ``large_blobs``.

With ``psf_sigma_px`` None the PSF width is measured per frame.  When the camera states its width
(``psf_sigma_stated_px``, from the camera file's ``psf_sigma_px``: its calibration) the frame is filtered at that
width and the width is measured on the bright stars of that one pass (the same selection and fits as below); the
stars' fits then take the measured width, and only a frame whose measured width costs the stated width's filter
more than 1 % of its SNR (``STATED_WIDTH_MIN_EFFICIENCY``: a defocused or smeared frame) is filtered again at it:
one full-resolution pass and the width fits instead of the binned pass (1.0-1.4 ms less per 1024 x 768-1024
frame, a fifth of the detector: below).
Otherwise a first pass at ``psf_sigma_init_px``, on the
2 x 2-binned R (its matched filter at half the width in binned pixels: a quarter of a full pass; the stars' fits on
full-resolution stamps), fits the width of up to 25 bright (SNR > 30; SNR > 15 when fewer than 3 reach 30),
unsaturated, isolated stars;
their median (of one star or more; fits under ``MIN_MEASURED_SIGMA_PX`` = 0.35 px are hot-pixel clusters, not
stars) is used for the final pass, else the initial width.  (Needing 3 kept the initial 1.0 px on sparse fields of
smeared stars, whose round-PSF fits measure 1.3-1.7 px on 6 px streaks: the narrower filter and fit stated half the
along-streak error of tracked stars, star tracking's examples/star/track.toml, seed 2203, sequence 856.)  (Measured on the 8 ESA frames, 2026-11-24: widths 0.636-0.705 px;
the frame with a bright sky, which has fewer than 3 stars above SNR 30, is measured from the SNR > 15 stars
instead of keeping the initial 1.0; from the binned first pass, 2026-11-27: within 0.015 px of those.)

Centroids use the continuous pixel convention (pixel (r, c) has its centre at (c + 0.5, r + 0.5)).
Cost with a stated width (2026-11-28, ``python benchmarks/bench_detect.py --frames 48``, one core): 4.1-4.3 ms per
1024 x 768 frame against 5.1-5.2 ms measuring it in the binned first pass and 3.7-3.9 ms with the width given,
completeness, false rate and centroid rms those of the given width (to 1e-4 px).
Cost (one core, ``benchmarks/bench_detect_speed.py --against 28d26a5 --rounds 3 --rendered 20``, CPU time, load
0.2-0.5), 2026-11-28 after the five-tap filter (``detect_psf.FILTER_SNR_EFFICIENCY``), the compiled candidate screening
(:mod:`dualsight.kernels.detect_hot_pixels`) and the tiles' windows found by walks: 4.2-4.5 ms per rendered 1024 x 1024
frame (background ~1.05, filter ~1.4 for both passes, candidates ~0.45, hot pixels and fits ~0.6, other ~0.75) against
4.8-5.0 ms (median ratio 0.90), 3.8-4.2 ms per ESA frame against 4.4-4.9 (0.91).  Before that (one core,
``--against ff0fe3d --rounds 3``, CPU time, load 1.0-1.1),
2026-11-28, the tiles' windows on their quarter samples and the noise sample every 8th row and column: 5.1-5.7 ms
per rendered 1024 x 1024 frame (background ~1.2, filter ~1.8 for both passes, candidates ~0.5, fits ~0.9, other ~0.85)
against 6.4-6.7 ms (median ratio 0.80), 4.5-5.6 ms per ESA frame against 5.9-6.2 (0.91); the PSF-width pass is
~1.1 ms of a rendered frame (``psf_sigma_px`` given: 3.8 ms).  Before (``--against 306a946``, load 5.7-5.8), the
default (fit_engine "taichi"), 2026-11-27 after the one-launch fits, the compiled candidate search, the SIMD sort of
the tiles' samples and the saturation shortcut: 5.3-5.8 ms per ESA frame — background ~1.6, filter ~1.35,
candidates ~0.45, hot-pixel test and fits ~1.5 (of which the fit kernels ~0.8: ~300 stars x 2.6 us), other ~0.65 —
against 6.7-7.8 ms for 306a946 (ratios 0.75-0.83, median 0.77); 5.5-6.4 ms per rendered 1024 x 1024 frame
(background ~1.85, filter ~2.0, candidates ~0.45, fits ~0.85, other ~0.9) against 6.9-7.7 ms (median ratio 0.84).
What remained then was mostly full-frame work that the maths asks for (measured alone on a 1024 x 1024 frame, one
core: the matched filter's sepFilter2D 0.67 ms and the binned one's 0.17, the tiles' last window over every pixel
0.54, their sorted quarter samples 0.14 + clipping 0.28, the background and noise maps 0.24, the residual 0.15, Z's
scaling 0.22, the two noise samples' clipped statistics 0.30: ~2.7 ms before the first candidate) plus ~0.3-0.6 ms of
numpy calls per pass over the candidates.
Earlier the same day, at load 14-16 (CPU times there run ~1.2x those at load ~4, from 0fd2b06's): ~9.7 ms per ESA
frame (1024 x 768, 90-520 detections, width measured) — background ~2.7, matched filter ~2.0 (binned width pass and
final pass, noise samples included), candidates ~1.0, hot-pixel test and PSF fits ~3.1 (width pass included), other ~1.2;
~9.5 ms per rendered 1024 x 1024 sensor-noise frame (20-50 stars): background ~2.6, filter ~2.7, candidates ~0.8,
fits ~1.7, other ~1.5.  The code of 0fd2b06 (the numpy path, today's fit_engine "numpy") in the same runs: 14.5 and
12.7 ms (ratios 0.67 and 0.75).  Earlier (load 3.8-3.9): 0fd2b06's path ~12 and ~11 ms; 00d8bee 16.0-16.2 and
14.2-14.7 ms (a full-resolution width pass, OpenCV's full-frame labelling, the noise map and its inverse as (H, W)
maps); before that ~38-43 ms with every tile and noise-sample value sorted / partitioned, a dilation for the maxima
and fits run to 1e-4 px.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from dualsight.config import check_fields
from dualsight.kernels.detect import Detections, as_frames
from dualsight.kernels.detect_background import interpolate_tiles, tile_background
from dualsight.kernels.detect_candidates import clamped, find_candidates, matched_filter
from dualsight.kernels.detect_hot_pixels import screen_candidates, screen_candidates_compiled
from dualsight.kernels.detect_psf import cut_stamps, filter_efficiency, fit_psf, flux_fraction_3x3, psf_kernel_1d
from dualsight.kernels.detect_passes import pixel_dtype_supported
from dualsight.kernels.detect_psf_fit import MAX_STAMP, fit_frame_compiled, fit_psf_compiled
from dualsight.kernels.sensor_config import MAX_ADU

__all__ = ["BinnedView", "LocalDetectConfig", "LocalDetections", "MIN_MEASURED_SIGMA_PX",
           "STATED_WIDTH_MIN_EFFICIENCY", "detect_real", "frames_psf_width", "subtract_local_background"]

log = logging.getLogger(__name__)

_UNITS = {"k_sigma": "sigma", "psf_sigma_px": "px", "psf_sigma_init_px": "px", "psf_sigma_stated_px": "px",
          "tile_px": "px", "clip_sigma": "sigma", "hot_pixel_k": "sigma", "saturation_adu": "ADU", "gain_e_per_adu": "e-/ADU",
          "noise_floor_adu": "ADU", "max_blob_pixels": "px", "deblend_min_sep_px": "px"}


@dataclass(frozen=True)
class LocalDetectConfig:
    """Settings of :func:`detect_real` (module docstring).  Every range is part of the field's type.

    Attributes
    ----------
    k_sigma : detection threshold on the matched-filtered SNR (integrated, PSF-weighted SNR), in [1, 1000].
    psf_sigma_px : Gaussian PSF standard deviation (px) of the matched filter and the fit, in [0.2, 20];
        None = measured per frame.
    psf_sigma_init_px : first-pass width when ``psf_sigma_px`` and ``psf_sigma_stated_px`` are None, in [0.2, 20].
    psf_sigma_stated_px : the width the camera states (its camera file's ``psf_sigma_px``), in [0.2, 20], or None:
        with ``psf_sigma_px`` None the frame is filtered at it and its width measured on that pass's bright stars,
        without the first pass (module docstring); None = the first pass at ``psf_sigma_init_px``.
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
    fit_engine : "taichi", "numpy" or "auto" (default), the implementation of the PSF fits, the tiles' last clipping
        window and the candidates' components (module docstring, step 5).  "auto" runs "taichi" here; a caller that
        knows it will detect only a few frames in a fresh process resolves it to "numpy" before the call (starting
        Taichi and building these kernels costs ~2 s per process against ~4 ms saved per frame: ``hil star``
        does, ``jobs/kinds/hil_star_spec.resolve_fit_engine``), so that one image is solved in a fraction of a second.
    """

    k_sigma: Annotated[float, Field(ge=1.0, le=1000.0)] = 5.0
    psf_sigma_px: Annotated[float, Field(ge=0.2, le=20.0)] | None = None
    psf_sigma_init_px: Annotated[float, Field(ge=0.2, le=20.0)] = 1.0
    psf_sigma_stated_px: Annotated[float, Field(ge=0.2, le=20.0)] | None = None
    tile_px: Annotated[int, Field(ge=8, le=4096)] = 32
    clip_sigma: Annotated[float, Field(ge=1.5, le=10.0)] = 3.0
    clip_iters: Annotated[int, Field(ge=0, le=20)] = 3
    mesh_filter: Literal[1, 3, 5] = 3
    hot_pixel_k: Annotated[float, Field(ge=0.0, le=1000.0)] = 5.0
    sharpness_tolerance: Annotated[float, Field(ge=0.0, le=10.0)] = 0.5
    saturation_adu: Annotated[float, Field(ge=0, le=MAX_ADU)] | None = None
    gain_e_per_adu: Annotated[float, Field(ge=1e-3, le=1e4)] | None = None
    noise_floor_adu: Annotated[float, Field(ge=0, le=MAX_ADU)] = 0.29
    max_blob_pixels: Annotated[int, Field(ge=1, le=2 ** 32)] = 4096
    max_blobs_per_frame: Annotated[int, Field(ge=1, le=10 ** 6)] = 1000
    deblend_min_sep_px: Annotated[float, Field(ge=0.0, le=100.0)] = 2.0
    deblend_contrast: Annotated[float, Field(ge=0.0, le=1.0)] = 0.2
    connectivity: Literal[4, 8] = 8
    fit_engine: Literal["auto", "numpy", "taichi"] = "auto"

    def __post_init__(self):
        check_fields(self, units=_UNITS)

    @property
    def engine(self) -> str:
        """The implementation that runs: ``fit_engine`` with "auto" as "taichi"."""
        return "numpy" if self.fit_engine == "numpy" else "taichi"


@dataclass(frozen=True)
class LocalDetections(Detections):
    """:class:`~dualsight.kernels.detect.Detections` plus what :func:`detect_real` counted per frame.

    blobs_dropped : (B,) int64 stars beyond ``max_blobs_per_frame`` (the faintest), not returned.
    large_blobs : (B,) int64 extended objects, not stars, not returned: foreground components over
        ``max_blob_pixels`` and saturated plateaus wider than pi (6 s)^2 px (module docstring, 6.).
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


def subtract_local_background(images: np.ndarray, cfg: LocalDetectConfig = LocalDetectConfig()):
    """(residual (B, H, W) float32, median tile level (B,)) of frames minus the interpolated tile background
    that :func:`detect_real` uses (for overlays and reports)."""
    images = np.asarray(images)
    B, H, W = images.shape
    out = np.empty((B, H, W), np.float32)
    lev = np.zeros(B)
    for b in range(B):     # one frame at a time (bounded memory), as detect_real
        level, _ = tile_background(images[b], cfg.tile_px, cfg.clip_sigma, cfg.clip_iters, cfg.mesh_filter,
                                   cfg.engine)
        np.subtract(images[b], interpolate_tiles(level, cfg.tile_px, H, W), out=out[b], casting="unsafe")
        lev[b] = float(np.median(level))
    return out, lev


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


class BinnedView:
    """A 2 x 2-binned image seen at full-resolution pixel indices: ``view[r, c]`` is ``image[r // 2, c // 2]``
    (clipped to the binned image: the odd last row or column of the frame falls in the last bin)."""

    def __init__(self, image, shape):
        self.image = image
        self.shape = shape

    def __getitem__(self, rc):
        r, c = rc
        return self.image[np.minimum(np.asarray(r) // 2, self.shape[0] - 1),
                          np.minimum(np.asarray(c) // 2, self.shape[1] - 1)]


def _measure(img, R, inv, Z, sig_f, s, cfg, sat, fit_sigma=False, cands=None, spike_tap=None):
    """Hot-pixel test, saturation and PSF fit of the candidates of one frame (``inv``: the inverse pixel noise map;
    ``sig_f``: Z's noise map; ``cands``:
    the candidates (rows, cols, npix, large components) when not those of Z; ``spike_tap``: the weight of one
    pixel's excess in Z x sigma_F, when Z is not the full-resolution filter of width s)."""
    H, W = R.shape
    pr, pc, npix, n_large = find_candidates(Z, cfg) if cands is None else cands
    K = pr.size
    e = np.zeros(0)
    if K == 0:
        return dict(x=e, y=e, flux=e, npix=np.zeros(0, np.int64), sigma_px=e, saturated=np.zeros(0, bool),
                    s=np.full(0, s), large=n_large, hot=0, snr=e, ok=np.zeros(0, bool))
    if fit_sigma:     # the PSF width: from the brightest unsaturated candidates of SNR > 15 (the caller picks)
        z = Z[pr, pc]
        near_sat = np.zeros(K, bool)
        if sat is not None:      # a saturated pixel in the 5 x 5 square (clipped at the frame's edges)
            o5 = np.arange(-2, 3)
            near_sat = (img[np.clip(pr[:, None, None] + o5[None, :, None], 0, H - 1),
                            np.clip(pc[:, None, None] + o5[None, None, :], 0, W - 1)] >= sat).any((1, 2))
        top = np.flatnonzero((z > 15) & ~near_sat)
        if top.size:      # isolated: no other candidate within 3 PSF half-widths
            d2 = (pr[top, None] - pr[None, :]) ** 2 + (pc[top, None] - pc[None, :]) ** 2     # integers: exact
            d2[np.arange(top.size), top] = np.iinfo(d2.dtype).max
            top = top[d2.min(1) > (3 * max(2, math.ceil(2.5 * s))) ** 2]
        top = top[np.argsort(-z[top], kind="stable")]     # the 25 brightest after the hot-pixel test below
        pr, pc, npix = pr[top], pc[top], npix[top]
        K = pr.size
        if K == 0:
            return dict(s=np.full(0, s), ok=np.zeros(0, bool), saturated=np.zeros(0, bool), snr=e)
    # the brightest pixel of each candidate's 3 x 3 neighbourhood, its noise and saturation, the hot-pixel test
    # (step 4: kernels.detect_hot_pixels)
    if cfg.engine == "taichi" and pixel_dtype_supported(img.dtype):
        b = 2 if isinstance(Z, BinnedView) else 1
        Zi, nf = (Z.image, sig_f.image) if b == 2 else (Z, sig_f)
        r0, c0, noise, is_sat, hot_px, keep = screen_candidates_compiled(
            R, inv, img, pr, pc, Zi, nf.inv, nf.row, nf.col, nf.ratio, b, sat, s, cfg, spike_tap)
    else:
        r0, c0, noise, is_sat, hot_px, keep = screen_candidates(R, inv, img, pr, pc, Z, sig_f, sat, s, cfg,
                                                                spike_tap)
    n_hot = int((hot_px & ~keep).sum())
    if fit_sigma:    # the width only from candidates without a spike: clusters of hot pixels (or a cosmic
        # ray's track) keep Z above the threshold without their brightest pixel and fit a width of ~0.2 px
        keep = keep & (np.cumsum(keep) <= 25)
    pr, pc, r0, c0, npix, noise, hot_px, is_sat = (a[keep] for a in (pr, pc, r0, c0, npix, noise, hot_px, is_sat))
    K = pr.size
    h = max(2, int(math.ceil(2.5 * s)))
    # saturated candidates (a saturated pixel in the stamp): the stamp grows by the plateau radius (below)
    sat_any = np.zeros(K, bool)
    if sat is not None and K:
        st_s, inside, _, _ = cut_stamps(img, None, r0, c0, h)
        sat_any = ((st_s >= sat) & (inside > 0)).reshape(K, -1).any(1)
    if K and not sat_any.any() and cfg.engine == "taichi" and 2 * h + 1 <= MAX_STAMP \
            and pixel_dtype_supported(img.dtype):
        # one compiled fit for all the candidates: the general path below without its bookkeeping (same values)
        f = fit_frame_compiled(R, img, r0, c0, hot_px, h, sat, s, noise, cfg.gain_e_per_adu, fit_sigma=fit_sigma)
        x, y, A, ok = f["x"], f["y"], f["A"], f["ok"]
        fb = ~ok
        if fb.any():     # fallback: the 3 x 3 centroid
            x, y = np.where(fb, f["x0"], x), np.where(fb, f["y0"], y)
            A = np.where(fb, np.maximum(f["tot"], 0) / flux_fraction_3x3(s), A)
        zpk = Z[pr, pc].astype(np.float64)
        sigma_px = np.where(ok, np.sqrt(np.maximum(0.5 * (f["cxx"] + f["cyy"]), 0)),
                            math.sqrt(2.0) * s / np.maximum(zpk, 1e-6))
        return dict(x=x, y=y, flux=A, npix=npix, sigma_px=sigma_px, saturated=sat_any, s=f["s"], large=n_large,
                    hot=n_hot, snr=zpk, ok=ok)
    x = np.zeros(K)
    y = np.zeros(K)
    A = np.zeros(K)
    cov = np.full((K, 4, 4), np.nan)
    ok = np.zeros(K, bool)
    sfit = np.full(K, s)
    if sat_any.any():
        win, win_in, _, _ = cut_stamps(img, None, r0[sat_any], c0[sat_any], 3 * h)   # (6h + 1)^2 around each
        nsat = ((win >= sat) & (win_in > 0)).sum((1, 2))                                 # saturated star
        ext = nsat > math.pi * (6.0 * s) ** 2      # extended: no star's plateau is that wide (docstring, 6.)
        if ext.any():
            n_large += int(ext.sum())
            gone = np.flatnonzero(sat_any)[ext]
            keep2 = np.ones(K, bool)
            keep2[gone] = False
            pr, pc, r0, c0, npix, noise, hot_px, is_sat, sat_any = (
                a[keep2] for a in (pr, pc, r0, c0, npix, noise, hot_px, is_sat, sat_any))
            nsat = nsat[~ext]
            K = pr.size
            x, y, A, cov, ok, sfit = x[keep2], y[keep2], A[keep2], cov[keep2], ok[keep2], sfit[keep2]
    groups = [(~sat_any, h, False)]
    if sat_any.any():
        hs = h + int(math.ceil(math.sqrt(max(nsat.max(), 1) / math.pi))) + 1
        groups.append((sat_any, hs, True))
    frac3 = flux_fraction_3x3(s)                              # PSF fraction in a centred 3 x 3 box
    for sel, hh, saturated in groups:
        idx = np.flatnonzero(sel)
        if idx.size == 0:
            continue
        rr0, cc0 = r0[idx] - hh, c0[idx] - hh
        if cfg.engine == "taichi" and 2 * hh + 1 <= MAX_STAMP and pixel_dtype_supported(img.dtype):
            # stamps, start, fit and Cramér-Rao bound of all the group's stars in one kernel launch
            f = fit_frame_compiled(R, img, r0[idx], c0[idx], hot_px[idx], hh, sat, s, noise[idx],
                                   cfg.gain_e_per_adu, fit_sigma=fit_sigma)
            xf, yf, Af, sf_, okf, x0, y0, tot = (f[k] for k in ("x", "y", "A", "s", "ok", "x0", "y0", "tot"))
            cf = np.full((idx.size, 4, 4), np.nan)
            cf[:, 0, 0], cf[:, 1, 1] = f["cxx"], f["cyy"]
        else:
            st, w0, rr0, cc0 = cut_stamps(R, None, r0[idx], c0[idx], hh, img=img, sat=sat)
            if hot_px[idx].any():      # a kept star under a hot pixel: the spike gets weight 0
                w0[hot_px[idx], hh, hh] = 0.0
            # start: 3 x 3 intensity-weighted centroid of the positive residual
            box = (slice(None), slice(hh - 1, hh + 2), slice(hh - 1, hh + 2))
            cen = np.maximum(st[box].astype(np.float64), 0) * w0[box]
            tot = cen.sum((1, 2))
            dxs = np.where(tot > 0, (cen * np.array([-1, 0, 1])[None, None, :]).sum((1, 2)) / np.maximum(tot, 1e-12),
                           0)
            dys = np.where(tot > 0, (cen * np.array([-1, 0, 1])[None, :, None]).sum((1, 2)) / np.maximum(tot, 1e-12),
                           0)
            x0 = c0[idx] + 0.5 + dxs
            y0 = r0[idx] + 0.5 + dys
            usable = w0.reshape(idx.size, -1).sum(1)
            fit = fit_psf_compiled if cfg.engine == "taichi" else fit_psf          # module docstring, step 5
            xf, yf, Af, _, sf_, cf, okf = fit(st, w0, rr0, cc0, x0, y0, np.full(idx.size, s), noise[idx],
                                              cfg.gain_e_per_adu, fit_sigma=fit_sigma)
            okf &= usable >= 6
        fb = ~okf
        if fb.any():     # fallback: plateau centre (saturated) or the 3 x 3 centroid
            xf, yf = xf.copy(), yf.copy()
            xf[fb], yf[fb] = x0[fb], y0[fb]
            if saturated:
                sm, inside, _, _ = cut_stamps(img, None, r0[idx], c0[idx], hh)
                sm = (sm >= sat) & (inside > 0)
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
    sig_fb = math.sqrt(2.0) * s / np.maximum(zpk, 1e-6)
    sigma_px = np.where(ok, np.sqrt(np.maximum(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]), 0)), sig_fb)
    return dict(x=x, y=y, flux=A, npix=npix, sigma_px=sigma_px, saturated=sat_any, s=sfit, large=n_large,
                hot=n_hot, snr=zpk, ok=ok)


MIN_MEASURED_SIGMA_PX = 0.35
"""Smallest PSF width the per-frame measurement accepts from one star's fit (px): narrower fits are hot-pixel
clusters or cosmic-ray tracks (measured ~0.2 px on rendered frames with hot pixels 1e-3), and a PSF that sharp
is undersampled: its stars cannot be told from hot pixels anyway."""


STATED_WIDTH_MIN_EFFICIENCY = 0.99
"""A camera's stated PSF width (``psf_sigma_stated_px``) stays the matched filter's width on a frame when that filter
keeps at least this fraction of the SNR of the filter at the frame's measured width
(:func:`~dualsight.kernels.detect_psf.filter_efficiency`: a stated 0.9 px serves frames of 0.77-1.05 px, 0.67 px
frames of 0.58-0.78 px); else the frame is filtered again at its measured width.  1 % of SNR moves a Z = 5 star by
0.05 sigma; the fits always take the frame's measured width."""


FRAMES_WIDTH_MIN_FRAMES, FRAMES_WIDTH_MAX_SPREAD = 3, 1.15
"""A set of frames has one PSF width (:func:`frames_psf_width`) when at least this many measured it and the 90th
percentile of their widths is at most this times the 10th: one stated width then serves each of them in one pass
(:data:`STATED_WIDTH_MIN_EFFICIENCY`: +-13 % at 0.9 px)."""


def frames_psf_width(widths) -> tuple[float, int] | None:
    """(median width px, frames) of the frames' measured PSF widths ``widths`` (per frame, px; NaN or <= 0: not
    measured) when they agree (:data:`FRAMES_WIDTH_MIN_FRAMES`, :data:`FRAMES_WIDTH_MAX_SPREAD`), else None: the
    width a camera file can state (``psf_sigma_px``).  Percentiles are order statistics (nearest rank)."""
    w = np.sort(np.asarray([v for v in widths if v is not None], np.float64))
    w = w[np.isfinite(w) & (w > 0)]
    if w.size < FRAMES_WIDTH_MIN_FRAMES:
        return None
    q = lambda p: float(w[min(w.size - 1, int(p * (w.size - 1) + 0.5))])
    if q(0.9) > FRAMES_WIDTH_MAX_SPREAD * q(0.1):
        return None
    return q(0.5), int(w.size)


def _frame_width(m, s):
    """The frame's PSF width from :func:`_measure`'s width-free fits ``m`` (module docstring: the median of up to
    25 of the brightest good fits, SNR > 30, or > 15 when fewer than 3 reach 30), else (no such star) ``s``, the
    width the frame is filtered at; a median within 2 % of ``s`` keeps ``s``."""
    # fitted widths under MIN_MEASURED_SIGMA_PX are not stars' (hot-pixel clusters, cosmic-ray tracks: ~0.2 px)
    good = m["ok"] & ~m["saturated"] & (m["s"] >= MIN_MEASURED_SIGMA_PX)
    use = np.flatnonzero(good & (m["snr"] > 30))
    if use.size < 3:              # a bright sky or a sparse field: fainter stars, still well measured
        use = np.flatnonzero(good & (m["snr"] > 15))
    use = use[np.argsort(-m["snr"][use])][:25]
    if use.size >= 1:             # a sparse field: the one or two stars it has (a smeared frame's streaks
        s_new = float(np.clip(np.median(m["s"][use]), 0.2, 20.0))      # fit wider than the initial width)
        if abs(s_new - s) > 0.02 * s:
            return s_new
    return s


def _measure_width(img, R, inv, inv_tiles, s, cfg, sat, tail):
    """The PSF-width pass (module docstring): the candidates of the 2 x 2-binned residual's matched filter (PSF
    sigma s / 2 in binned pixels; a quarter of the full pass's work; its noise map ``inv_tiles``, the tiles'
    1 / sigma, interpolated at the bins' centres), each at the top-left pixel of its bin (the
    brightest pixel of R within one pixel of it is the star's), fitted with the width free on full-resolution
    stamps of R (:func:`_measure`, ``fit_sigma``; a hot pixel's excess weighs 1/4 of the binned kernel's centre
    tap in the binned Z)."""
    import cv2

    H, W = R.shape
    h2, w2 = H // 2, W // 2
    if h2 < 8 or w2 < 8:
        Z, _, sig_f = matched_filter(R, inv, s, tail)
        return _measure(img, R, inv, Z, sig_f, s, cfg, sat, fit_sigma=True)
    Rb = cv2.resize(R[:2 * h2, :2 * w2], (w2, h2), interpolation=cv2.INTER_AREA)          # 2 x 2 means
    tile = cfg.tile_px
    ib = (interpolate_tiles(inv_tiles, tile // 2, h2, w2) if tile % 2 == 0     # the scale: matched_filter
          else np.ascontiguousarray(inv[:2 * h2:2, :2 * w2:2]))                # measures its own
    Zb, _, sfb = matched_filter(Rb, ib, 0.5 * s, tail)
    prb, pcb, npix, n_large = find_candidates(Zb, cfg)
    kb = psf_kernel_1d(0.5 * s)
    return _measure(img, R, inv, BinnedView(Zb, Zb.shape), BinnedView(sfb, Zb.shape), s, cfg, sat, fit_sigma=True,
                    cands=(2 * prb, 2 * pcb, npix, n_large), spike_tap=float(kb[len(kb) // 2] ** 2) / 4.0)


def _detect_frame(img: np.ndarray, cfg: LocalDetectConfig, sat) -> _Frame:
    import cv2

    H, W = img.shape
    level, sig = tile_background(img, cfg.tile_px, cfg.clip_sigma, cfg.clip_iters, cfg.mesh_filter, cfg.engine)
    bg = interpolate_tiles(level, cfg.tile_px, H, W)
    floor = np.float32(max(cfg.noise_floor_adu, 1e-6))
    inv_tiles = 1.0 / np.maximum(sig, floor)
    inv = interpolate_tiles(inv_tiles, cfg.tile_px, H, W)    # 1 / the pixel noise (harmonic)
    if img.dtype in (np.uint8, np.uint16, np.float32):   # OpenCV's subtraction: the same float32 values, ~20 % faster
        R = cv2.subtract(img, bg, dtype=cv2.CV_32F)
    else:
        R = np.subtract(img, bg, dtype=np.float32)
    if sat is not None and not img.max() >= sat:    # no saturated pixel: every saturation test is void (one
        sat = None                                  # SIMD pass instead of the candidates' stamp gathers)
    tail = clamped(img)                   # a frame clamped at its black level: its filtered noise's tail checked
    if cfg.psf_sigma_px is not None:      # the width given: one pass
        s = cfg.psf_sigma_px
        Z, ratio, sig_f = matched_filter(R, inv, s, tail)   # sig_f: Z's noise, edges included
        m = _measure(img, R, inv, Z, sig_f, s, cfg, sat)
    elif cfg.psf_sigma_stated_px is not None:    # the camera's width: filtered at it, checked on its bright stars
        s = cfg.psf_sigma_stated_px
        Z, ratio, sig_f = matched_filter(R, inv, s, tail)
        cands = find_candidates(Z, cfg)
        k = psf_kernel_1d(s)
        tap = float(k[len(k) // 2] ** 2)             # a spike's weight in this Z (the fits below take other widths)
        # the width fits as the first pass makes them (stamps, start and hot-pixel test at psf_sigma_init_px: a real
        # PSF's wings make a Gaussian's fitted width depend on the stamp), on this pass's candidates
        m0 = _measure(img, R, inv, Z, sig_f, cfg.psf_sigma_init_px, cfg, sat, fit_sigma=True, cands=cands,
                      spike_tap=tap)
        s_meas = _frame_width(m0, s)       # no star to measure, or within 2 % of it: the stated width
        if filter_efficiency(s, s_meas) < STATED_WIDTH_MIN_EFFICIENCY:     # this frame's PSF is not the stated one:
            s = s_meas                                                      # the pass at its measured width
            Z, ratio, sig_f = matched_filter(R, inv, s, tail)
            m = _measure(img, R, inv, Z, sig_f, s, cfg, sat)
        else:                                # the stated width's filter, the measured width's fits
            m = _measure(img, R, inv, Z, sig_f, s_meas, cfg, sat, cands=cands, spike_tap=tap)
            s = s_meas
    else:                  # measure the PSF width on bright, unsaturated, isolated stars of a first, binned pass
        s = cfg.psf_sigma_init_px
        s = _frame_width(_measure_width(img, R, inv, inv_tiles, s, cfg, sat, tail), s)
        Z, ratio, sig_f = matched_filter(R, inv, s, tail)
        m = _measure(img, R, inv, Z, sig_f, s, cfg, sat)
    med_sig = float(np.median(sig))
    med_level = float(np.median(level))
    return _Frame(x=m["x"], y=m["y"], flux=m["flux"], npix=m["npix"], sigma_px=m["sigma_px"],
                  saturated=m["saturated"], level=med_level,
                  threshold=med_level + cfg.k_sigma * max(med_sig, cfg.noise_floor_adu) * ratio,
                  noise=med_sig, psf_sigma=float(s), large=m["large"], hot=m["hot"])


# ============================================================================ public API
def detect_real(images: np.ndarray, cfg: LocalDetectConfig = LocalDetectConfig(), *,
                saturation_adu=None) -> LocalDetections:
    """Detect and centroid stars in a batch of real (or realistic) frames (module docstring).

    Parameters
    ----------
    images : (B, H, W) uint8, uint16, float32 or float64 frames (ADU), not background-subtracted, finite (NaN or
        infinite pixels give meaningless detections, differently per engine: ``hil star`` replaces them first,
        ``jobs.kinds.hil_star.fill_nonfinite``).
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
    images = as_frames(images)
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
        log.warning("frame %d: %d extended objects not centroided (foreground regions over max_blob_pixels=%d px"
                    " or saturated plateaus wider than a star's)", b, large[b], cfg.max_blob_pixels)
    cat = lambda name, dt: (np.concatenate([getattr(f, name)[o] for f, o in zip(frames, parts)]).astype(dt, copy=False)
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
