"""Batched star-field rendering on the CPU (Taichi): exact pixel-integrated Gaussian PSFs plus sensor effects.

Coordinates (DESIGN.md): continuous pixel coordinates (col, row) = (x, y) measured from the image's
top-left *corner*; pixel (r, c) covers [c, c+1) x [r, r+1) and has its centre at (c + 0.5, r + 0.5).

Signal model (electrons, per pixel (r, c) of case b)::

    S      = sum_s  F_s * [Phi((c+1-x_s)/sigma) - Phi((c-x_s)/sigma)] * [Phi((r+1-y_s)/sigma) - Phi((r-y_s)/sigma)]
    e      = S + dark_current * exposure + sky_background  (+ hot_pixel_e on hot pixels)
    e      = Poisson(e)                       if shot_noise
    e      = min(e, full_well)
    e      = e + read_noise * N(0, 1)
    ADU    = clip(floor(e / gain + bias_adu + 1e-9), 0, 2^bit_depth - 1)   (no floor if not quantize)

Stage 1, the signal S (Gaussian PSFs of standard deviation ``psf_sigma_px`` integrated exactly over each
pixel, in a window of half-width ``ceil(psf_window_sigma * sigma + 1)`` px, so at most 2 * Phi(-psf_window_sigma)
of the flux (6.3e-5 for 4 sigma) falls outside per axis), is :mod:`dualsight.kernels.star_psf`.  This module
holds the sensor model (:class:`SensorConfig`), stage 2 (the ``finalize`` kernel: charge, noise, ADC) and
:func:`render_star_fields`, which runs both.

Random numbers come from :mod:`dualsight.kernels.rng` (a counter-based hash of (case seed, stream,
pixel index)), never from ``ti.random``: a case renders bit-identically whatever batch, position or
thread computes it.  Shot noise is exact Poisson: inversion of a tabulated CDF for pixels at the sky level
(most of a star field), otherwise sequential inversion below 10 e- and PTRS rejection (Hörmann 1993) above.
Read noise is N(0, 1) by inversion (Wichura's AS241).  Without shot noise, dark current and sky
background are their means only.

Magnitudes: ``flux_from_magnitude`` uses ``F = zero_mag_rate_e_per_s * 10^(-0.4 m) * exposure_s``.  The
default zero point, 1.5e6 e-/s for a V = 0 star, is a round figure for a ~1 cm^2 clear aperture
(e.g. 17 mm f/1.4): about 1000 photons s^-1 cm^-2 A^-1 at V = 0 (Bessell, Castelli & Plez 1998, A&A 333,
231: 3.63e-9 erg s^-1 cm^-2 A^-1 at 550 nm) over a ~3000 A silicon pass band at ~50 % quantum efficiency.
It is a config field; set it from your optics.

Noise-free frames never need to be materialised for detection: see
``dualsight.kernels.detect.render_and_detect_ideal`` (same pixels, only the patches around stars).

Taichi is initialised lazily (``dualsight.kernels._runtime.ensure_init``) on the first call.
"""


import math
import threading
from dataclasses import dataclass, fields
from typing import Annotated

import numpy as np
import taichi as ti
from pydantic import Field

from dualsight.kernels import rng, star_psf
from dualsight.config import check_fields
from dualsight.kernels._runtime import KernelCache

__all__ = ["SensorConfig", "flux_from_magnitude", "render_star_fields", "false_star_lists",
           "append_false_stars", "release_scratch"]

MAX_CHUNK_PIXELS = 1 << 26  # pixels per kernel call: 256 MB float32 scratch at most, indices fit in int32
_QUANT_EPS = 1e-9  # ADU; keeps exact multiples of the gain from flooring one count low


# ============================================================================ configuration
MAX_CHARGE_E = 1e12
"""Largest charge (e-) any charge field may hold: 1e6 above the deepest real full wells (~1e6 e-), so
``full_well_e = 1e12`` still means "never saturates", while float32/float64 arithmetic stays exact enough."""
MAX_ADU = 2 ** 24
"""Largest ADU magnitude of any ADU field: the full scale of the deepest ADC allowed (``bit_depth`` 24)."""

_Charge = Annotated[float, Field(ge=0, le=MAX_CHARGE_E)]
_SENSOR_UNITS = {"psf_sigma_px": "px", "exposure_s": "s", "gain_e_per_adu": "e-/ADU", "full_well_e": "e-",
                 "bit_depth": "bits", "bias_adu": "ADU", "zero_mag_rate_e_per_s": "e-/s", "psf_window_sigma": "sigma",
                 "read_noise_e": "e- rms", "dark_current_e_per_s": "e-/s/px", "sky_background_e": "e-/px",
                 "hot_pixel_e": "e-", "false_star_flux_min_e": "e-", "false_star_flux_max_e": "e-"}


@dataclass(frozen=True)
class SensorConfig:
    """Optics + detector model for star-field rendering.  The defaults describe an *ideal* sensor
    (every noise source off) that still quantises to 12-bit ADU.

    Every field's range is part of its type (pydantic ``Field``), checked both when a TOML table is
    validated (``dualsight.jobs.config.validate``) and when the dataclass is built in Python
    (:func:`dualsight.config.check_fields`).

    Attributes
    ----------
    psf_sigma_px : Gaussian PSF standard deviation (px), in [0.05, 50]; 0.8 = slight defocus (FWHM 1.9 px).
        Below 0.05 px the PSF is a delta (the pixel integral is exact anyway); above 50 px a star is a
        ~400 px wide disc and each window costs (2 * psf_window_sigma * sigma)^2 pixel evaluations.
    exposure_s : exposure time (s), in (0, 3600]: star trackers expose ms to ~1 s; an hour is the
        longest astronomical exposure worth modelling (and bounds the Poisson means).
    gain_e_per_adu : electrons per ADU (conversion gain), in [1e-3, 1e4] e-/ADU (real sensors: ~0.1-20).
    full_well_e : pixel saturation charge (e-), in (0, 1e12]; charge is clipped here before read noise
        (real wells hold 1e3-1e6 e-; 1e12 = never saturates).
    bit_depth : ADC bits, an integer in [1, 24]; ADU are clipped to [0, 2^bit_depth - 1] (<= 16 for
        uint16 output; 24 keeps every ADU exact in float32).
    bias_adu : constant ADC offset (ADU) added before quantisation (lets read noise go below zero), in
        [-2^24, 2^24] ADU (the full scale of a 24-bit ADC).
    quantize : floor to integer ADU (True for a real ADC; False gives continuous ADU).
    zero_mag_rate_e_per_s : electrons per second collected from a magnitude-0 star (see module doc), in
        [0, 1e12] e-/s (1e12 is ~1e4 times a 1 m^2 aperture's rate).
    psf_window_sigma : render each PSF out to this many sigma (+1 px) from the star, in [1, 10]: at 10
        sigma the flux outside (2 Phi(-10) ~ 1.5e-23) is below float64 resolution; the window has
        (2 ceil(psf_window_sigma * sigma + 1) + 1)^2 pixels, at most 1003^2 with the bounds.
    read_noise_e : Gaussian read noise standard deviation (e- rms), in [0, 1e12]; 0 = off.
    dark_current_e_per_s : mean dark current (e-/s/px), in [0, 1e12]; 0 = off.
    sky_background_e : mean sky background (e-/px per exposure), in [0, 1e12]; 0 = off.
    shot_noise : Poisson noise on signal + dark + background (+ hot pixel charge).
    hot_pixel_fraction : probability that a pixel is hot, in [0, 1]; 0 = off.
    hot_pixel_e : extra charge of a hot pixel (e- per exposure), in [0, 1e12].
    hot_pixel_seed : None = hot pixels drawn per case from the case seed; an integer in [0, 2^64) = one
        fixed hot-pixel map (a property of the sensor) shared by every case.
    false_stars_per_frame : number of spurious point sources (glints, debris, planets) added to every
        frame at uniform random positions, an integer in [0, 10000] (bounds the star lists); 0 = off.
    false_star_flux_min_e, false_star_flux_max_e : their flux is log-uniform in this range (e-), each in
        (0, 1e12], and max >= min (the one cross-field rule, checked in ``__post_init__``).
    """

    psf_sigma_px: Annotated[float, Field(ge=0.05, le=50.0)] = 0.8
    exposure_s: Annotated[float, Field(gt=0, le=3600.0)] = 0.1
    gain_e_per_adu: Annotated[float, Field(ge=1e-3, le=1e4)] = 5.0
    full_well_e: Annotated[float, Field(gt=0, le=MAX_CHARGE_E)] = 20000.0
    bit_depth: Annotated[int, Field(ge=1, le=24)] = 12
    bias_adu: Annotated[float, Field(ge=-MAX_ADU, le=MAX_ADU)] = 0.0
    quantize: bool = True
    zero_mag_rate_e_per_s: _Charge = 1.5e6
    psf_window_sigma: Annotated[float, Field(ge=1.0, le=10.0)] = 4.0
    read_noise_e: _Charge = 0.0
    dark_current_e_per_s: _Charge = 0.0
    sky_background_e: _Charge = 0.0
    shot_noise: bool = False
    hot_pixel_fraction: Annotated[float, Field(ge=0.0, le=1.0)] = 0.0
    hot_pixel_e: _Charge = 5000.0
    hot_pixel_seed: Annotated[int, Field(ge=0, lt=2 ** 64)] | None = None
    false_stars_per_frame: Annotated[int, Field(ge=0, le=10_000)] = 0
    false_star_flux_min_e: Annotated[float, Field(gt=0, le=MAX_CHARGE_E)] = 500.0
    false_star_flux_max_e: Annotated[float, Field(gt=0, le=MAX_CHARGE_E)] = 20000.0

    def __post_init__(self):
        check_fields(self, units=_SENSOR_UNITS)
        if self.false_star_flux_max_e < self.false_star_flux_min_e:
            raise ValueError(f"SensorConfig.false_star_flux_max_e must be >= false_star_flux_min_e "
                             f"({self.false_star_flux_min_e!r}), got {self.false_star_flux_max_e!r}")

    # ------------------------------------------------------------------ derived
    @property
    def max_adu(self) -> int:
        """Largest ADU value, 2^bit_depth - 1."""
        return (1 << self.bit_depth) - 1

    @property
    def base_e(self) -> float:
        """Mean charge every pixel collects without stars: dark * exposure + sky background (e-)."""
        return self.dark_current_e_per_s * self.exposure_s + self.sky_background_e

    @property
    def has_pixel_noise(self) -> bool:
        """True if any per-pixel random effect is on (shot, read or hot pixels)."""
        return self.shot_noise or self.read_noise_e > 0 or self.hot_pixel_fraction > 0

    @property
    def needs_seeds(self) -> bool:
        """True if rendering draws random numbers (pixel noise or false stars)."""
        return self.has_pixel_noise or self.false_stars_per_frame > 0

    @property
    def is_ideal(self) -> bool:
        """No random effect at all (the image is a deterministic function of the star list)."""
        return not self.needs_seeds

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def empty_pixel_adu(self) -> float:
        """ADU value of a star-free pixel of a noise-free frame (same arithmetic as the kernels)."""
        e = min(np.float64(np.float32(0.0)) + self.base_e, self.full_well_e)
        adu = e / self.gain_e_per_adu + self.bias_adu
        if self.quantize:
            adu = math.floor(adu + _QUANT_EPS)
        return float(min(max(adu, 0.0), float(self.max_adu)))


def flux_from_magnitude(vmag, cfg: SensorConfig = SensorConfig()) -> np.ndarray:
    """Electrons collected from stars of visual magnitude ``vmag`` during one exposure.

    F = cfg.zero_mag_rate_e_per_s * 10^(-0.4 vmag) * cfg.exposure_s   (Pogson's ratio; any shape, float64).
    """
    m = np.asarray(vmag, dtype=np.float64)
    return cfg.zero_mag_rate_e_per_s * np.power(10.0, -0.4 * m) * cfg.exposure_s


# ============================================================================ Taichi funcs
@ti.func
def ideal_adu(s, base_e, full_well, gain, bias, max_adu, quantize):
    """ADU of a pixel holding f32 star signal ``s`` (e-) without random effects (f64 result)."""
    e = ti.min(ti.cast(s, ti.f64) + base_e, full_well)
    adu = e / gain + bias
    if quantize != 0:
        adu = ti.floor(adu + ti.f64(_QUANT_EPS))
    return ti.min(ti.max(adu, ti.f64(0.0)), max_adu)


# ============================================================================ kernels (built lazily)
_KERNELS = KernelCache()      # builders registered at the end of the module


def _get(name: str, dtype=None):
    return _KERNELS.get(name, dtype)


def _build_finalize(dtype):
    tdt = {np.dtype(np.uint16).str: ti.u16, np.dtype(np.float32).str: ti.f32}[np.dtype(dtype).str]

    @ti.kernel
    def finalize(buf: ti.types.ndarray(dtype=ti.f32, ndim=1), out: ti.types.ndarray(dtype=tdt, ndim=1),
                 B: ti.i32, H: ti.i32, W: ti.i32,
                 seeds: ti.types.ndarray(dtype=ti.u64, ndim=1), hot_seed: ti.u64, use_hot_seed: ti.i32,
                 base_e: ti.f64, full_well: ti.f64, gain: ti.f64, bias: ti.f64, max_adu: ti.f64,
                 quantize: ti.i32, shot: ti.i32, read_e: ti.f64, hot_frac: ti.f64, hot_e: ti.f64,
                 cdf: ti.types.ndarray(dtype=ti.f64, ndim=1), guide: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 use_table: ti.i32):
        # flat (B*H*W,) arrays: 3-D external-array stores cost ~2x more in Taichi 1.7 CPU code
        for b, r in ti.ndrange(B, H):  # (frame, row) outer loop, columns serial
            seed = seeds[b]
            hseed = seed
            if use_hot_seed != 0:
                hseed = hot_seed
            k_hot = rng.stream_key(hseed, rng.STREAM_HOT, 0)
            k_read = rng.stream_key(seed, rng.STREAM_READ, 0)
            k_shot0 = rng.stream_key(seed, rng.STREAM_SHOT, 0)
            k_shot1 = rng.stream_key(seed, rng.STREAM_SHOT, 1)
            row0 = ti.cast(r, ti.u64) * ti.cast(W, ti.u64)
            p0 = (b * H + r) * W
            if shot == 0 and read_e <= ti.f64(0.0) and hot_frac <= ti.f64(0.0):
                # noise-free: empty pixels (most of a star field) take the precomputed sky value and
                # leave the scratch untouched; others go through the same ideal_adu arithmetic
                sky = ti.cast(ideal_adu(ti.f32(0.0), base_e, full_well, gain, bias, max_adu, quantize), tdt)
                for c in range(W):
                    s = buf[p0 + c]
                    if s == ti.f32(0.0):
                        out[p0 + c] = sky
                    else:
                        buf[p0 + c] = ti.f32(0.0)  # restore the all-zero scratch invariant
                        out[p0 + c] = ti.cast(ideal_adu(s, base_e, full_well, gain, bias, max_adu, quantize),
                                               tdt)
            else:
                lam_c = base_e  # Poisson constants cached for the last lambda (the sky's, mostly)
                cst = rng.poisson_consts(lam_c)
                for c in range(W):
                    s = buf[p0 + c]
                    if s != ti.f32(0.0):
                        buf[p0 + c] = ti.f32(0.0)
                    idx = row0 + ti.cast(c, ti.u64)
                    e = ti.cast(s, ti.f64) + base_e
                    if hot_frac > ti.f64(0.0):
                        if rng.u01_key(k_hot, idx) < hot_frac:
                            e += hot_e
                    if shot != 0:
                        k = ti.f64(-1.0)
                        if use_table != 0 and e == base_e:  # the sky's lambda: tabulated CDF
                            k = rng.poisson_table(rng.u01_key(k_shot0, idx), cdf, guide)
                        if k < ti.f64(0.0):
                            if e != lam_c:
                                lam_c = e
                                cst = rng.poisson_consts(e)
                            k = rng.poisson_keyed(e, cst, k_shot0, k_shot1, seed, rng.STREAM_SHOT, idx)
                        e = k
                    e = ti.min(e, full_well)
                    if read_e > ti.f64(0.0):
                        e += read_e * rng.normal_key(k_read, idx)
                    adu = e / gain + bias
                    if quantize != 0:
                        adu = ti.floor(adu + ti.f64(_QUANT_EPS))
                    adu = ti.min(ti.max(adu, ti.f64(0.0)), max_adu)
                    out[p0 + c] = ti.cast(adu, tdt)
    return finalize


_KERNELS.builders.update({"finalize": _build_finalize})


# ============================================================================ scratch buffer
class _Scratch:
    """One process-wide float32 signal buffer that is all zero between calls.

    The finalize pass zeroes every pixel right after reading it, so the buffer never needs a
    separate clearing pass and its pages stay mapped (no page faults on reuse).
    """

    def __init__(self):
        self.lock = threading.Lock()
        self.buf: np.ndarray | None = None

    def get(self, n: int) -> np.ndarray:
        if self.buf is None or self.buf.size < n:
            self.buf = None
            self.buf = np.zeros(n, dtype=np.float32)
        return self.buf[:n]

    def drop(self):
        self.buf = None


_scratch = _Scratch()


def release_scratch() -> None:
    """Free the cached float32 signal buffer (it is re-created on the next render)."""
    with _scratch.lock:
        _scratch.drop()


# ============================================================================ helpers
def check_star_arrays(x, y, flux_e, valid=None):
    """Validate and convert star lists: returns contiguous (x, y, flux float64, ok uint8), each (B, S).

    ``valid`` may be None (all valid) or a bool array broadcastable to (B, S).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"x must have shape (B, S), got {x.shape}")
    y = np.asarray(y, dtype=np.float64)
    f = np.asarray(flux_e, dtype=np.float64)
    if y.shape != x.shape or f.shape != x.shape:
        raise ValueError(f"x, y, flux_e must share shape (B, S); got {x.shape}, {y.shape}, {f.shape}")
    if valid is None:
        ok = np.ones(x.shape, dtype=np.uint8)
    else:
        v = np.asarray(valid)
        if v.dtype != np.bool_:
            raise ValueError(f"valid must be a bool array, got dtype {v.dtype}")
        try:
            ok = np.broadcast_to(v, x.shape).astype(np.uint8)
        except ValueError:
            raise ValueError(f"valid must have shape {x.shape}, got {v.shape}") from None
    return (np.ascontiguousarray(x), np.ascontiguousarray(y), np.ascontiguousarray(f),
            np.ascontiguousarray(ok))


def false_star_lists(seeds: np.ndarray, width: int, height: int, cfg: SensorConfig):
    """The false stars of each case: (x, y, flux_e) each (B, F), F = cfg.false_stars_per_frame.

    Positions uniform over the frame, flux log-uniform in [false_star_flux_min_e, false_star_flux_max_e];
    drawn from the counter-based hash of (case seed, STREAM_FALSE_STAR, draw 0/1/2, star index).
    """
    n = cfg.false_stars_per_frame
    s = np.asarray(seeds, dtype=np.uint64)[:, None]
    k = np.arange(n, dtype=np.uint64)[None, :]
    fx = rng.uniform_np(s, rng.STREAM_FALSE_STAR, 0, k) * width
    fy = rng.uniform_np(s, rng.STREAM_FALSE_STAR, 1, k) * height
    lo, hi = math.log(cfg.false_star_flux_min_e), math.log(cfg.false_star_flux_max_e)
    ff = np.exp(lo + rng.uniform_np(s, rng.STREAM_FALSE_STAR, 2, k) * (hi - lo))
    return fx, fy, ff


def append_false_stars(x, y, f, ok, seeds, width, height, cfg: SensorConfig):
    """Star arrays with the case's false stars appended as extra columns (no-op if none)."""
    if cfg.false_stars_per_frame == 0:
        return x, y, f, ok
    fx, fy, ff = false_star_lists(seeds, width, height, cfg)
    cat = lambda a, b: np.ascontiguousarray(np.concatenate([a, b.astype(a.dtype)], axis=1))
    return cat(x, fx), cat(y, fy), cat(f, ff), cat(ok, np.ones(fx.shape, np.uint8))


def check_size(width, height):
    for name, v in (("width", width), ("height", height)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or not 1 <= int(v) <= 65536:
            raise ValueError(f"{name} must be an integer in [1, 65536], got {v!r}")
    if int(width) * int(height) > 1 << 30:
        raise ValueError(f"frame of {width} x {height} px is larger than 2^30 pixels")
    return int(width), int(height)


def prepare_stars(x, y, flux_e, valid, width, height, cfg, seeds):
    """Shared input handling of the renderers: validated arrays, false stars appended, uint64 seeds."""
    width, height = check_size(width, height)
    x, y, f, ok = check_star_arrays(x, y, flux_e, valid)
    B = x.shape[0]
    if seeds is None:
        if cfg.needs_seeds:
            raise ValueError("seeds (one uint64 per case) are required when noise or false stars are on")
        seeds = np.zeros(B, dtype=np.uint64)
    else:
        seeds = rng.as_seeds(seeds, B)
    x, y, f, ok = append_false_stars(x, y, f, ok, seeds, width, height, cfg)
    if x.shape[1] == 0:  # Taichi wants non-empty arrays: one invalid star
        x = np.zeros((B, 1)); y = np.zeros((B, 1)); f = np.zeros((B, 1)); ok = np.zeros((B, 1), np.uint8)
    return x, y, f, ok, seeds, width, height


# ============================================================================ public API
def render_star_fields(x, y, flux_e, valid, width: int, height: int, cfg: SensorConfig = SensorConfig(),
                       seeds=None, *, dtype=np.uint16, out: np.ndarray | None = None) -> np.ndarray:
    """Render a batch of star-field frames (dense, full frame, all sensor effects).

    Parameters
    ----------
    x, y : (B, S) float, star positions in continuous pixel coordinates (col, row) from the top-left
        corner (the top-left pixel's centre is (0.5, 0.5)); stars may lie partly or fully off the image.
    flux_e : (B, S) float, total electrons of each star during the exposure (see :func:`flux_from_magnitude`).
    valid : (B, S) bool (or None = all); invalid, non-finite or non-positive-flux stars are skipped.
    width, height : frame size (px).
    cfg : :class:`SensorConfig`.
    seeds : (B,) uint64 per-case seeds; required when any random effect is on (else ignored).
    dtype : np.uint16 (default) or np.float32 output; both hold ADU (integers when cfg.quantize).
    out : optional preallocated (B, H, W) C-contiguous array of ``dtype`` to write into.

    Returns
    -------
    (B, H, W) images in ADU (see the module docstring for the pixel model).

    Cost: one serial-per-case splat of each star's window plus one (frame, row) pass over every pixel
    (1024 x 768, one core: ~1 ms/frame noise-free, ~10-15 ms/frame with shot or read noise).  For
    noise-free frames prefer ``dualsight.kernels.detect.render_and_detect_ideal``, which never touches
    the empty sky.  Memory: a process-wide float32 scratch of up to 2^26 pixels (256 MB) is kept zeroed
    between calls (batches are processed in chunks of that size); :func:`release_scratch` frees it.
    """
    x, y, f, ok, seeds, W, H = prepare_stars(x, y, flux_e, valid, width, height, cfg, seeds)
    dt = np.dtype(dtype)
    if dt not in (np.dtype(np.uint16), np.dtype(np.float32)):
        raise ValueError(f"dtype must be uint16 or float32, got {dt}")
    if dt == np.uint16 and cfg.bit_depth > 16:
        raise ValueError(f"uint16 output needs bit_depth <= 16, got {cfg.bit_depth}")
    B = x.shape[0]
    if out is None:
        out = np.empty((B, H, W), dtype=dt)
    elif out.shape != (B, H, W) or out.dtype != dt or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous {dt} array of shape {(B, H, W)}, "
                         f"got {out.dtype} {out.shape}")
    if B == 0:
        return out
    fin = _get("finalize", dt)
    hot_seed = cfg.hot_pixel_seed
    # Poisson CDF table of the sky level (dark + background), shared by most pixels; exact inversion
    use_table = cfg.shot_noise and 0.0 < cfg.base_e <= 1e6
    cdf, guide = rng.poisson_table_np(cfg.base_e) if use_table else (np.ones(1), np.zeros(1, np.int32))
    chunk = max(1, min(B, MAX_CHUNK_PIXELS // (H * W)))  # frames per kernel call (bounded scratch, i32 indices)
    with _scratch.lock:
        try:
            for b0 in range(0, B, chunk):  # loop over chunks of frames, not over pixels or stars
                sl = slice(b0, min(B, b0 + chunk))
                n = sl.stop - sl.start
                buf = _scratch.get(n * H * W)
                star_psf.splat_stars(x[sl], y[sl], f[sl], ok[sl], buf.reshape(n, H, W), cfg.psf_sigma_px,
                                     cfg.psf_window_sigma)
                fin(buf, out[sl].reshape(-1), n, H, W, seeds[sl], np.uint64(hot_seed or 0),
                    int(hot_seed is not None), float(cfg.base_e), float(cfg.full_well_e), float(cfg.gain_e_per_adu),
                    float(cfg.bias_adu), float(cfg.max_adu), int(cfg.quantize), int(cfg.shot_noise),
                    float(cfg.read_noise_e), float(cfg.hot_pixel_fraction), float(cfg.hot_pixel_e), cdf, guide,
                    int(use_table))
        except BaseException:
            _scratch.drop()  # the zero invariant may be broken
            raise
    return out
