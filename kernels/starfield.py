"""Batched star-field rendering on the CPU (Taichi): exact pixel-integrated Gaussian PSFs plus sensor effects.

Coordinates (DESIGN.md): continuous pixel coordinates (col, row) = (x, y) measured from the image's
top-left *corner*; pixel (r, c) covers [c, c+1) x [r, r+1) and has its centre at (c + 0.5, r + 0.5).

Signal model (electrons, per pixel (r, c) of case b)::

    S      = sum_s  F_s * [Phi((c+1-x_s)/sigma) - Phi((c-x_s)/sigma)] * [Phi((r+1-y_s)/sigma) - Phi((r-y_s)/sigma)]
             (or the PSF model, smear and bright objects of :mod:`dualsight.kernels.psf_models`)
    e      = S + dark_current * exposure + sky_background  (+ hot_pixel_e on hot pixels)
             + max(0, e0 + gx (c + 0.5 - W/2) + gy (r + 0.5 - H/2))      (stray light, stray_light_e = [e0, gx, gy])
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
thread computes it.  Sky pixels (no star light, not hot, no stray light: most of a star field) with
quantised ADU draw their final value in one uniform, by inversion of the tabulated exact CDF of shot noise +
read noise + ADC (:func:`sky_adu_table`, through a direct guide table: no transcendental call per pixel).
Other pixels: shot noise is exact Poisson, by inversion of a tabulated CDF for pixels at the sky level,
otherwise sequential inversion below 10 e- and PTRS rejection (Hörmann 1993) above; read noise is N(0, 1) by
inversion (Wichura's AS241).  Without shot noise, dark current and sky background are their means only.
Hot pixels (fraction p <= HOT_GEOMETRIC_MAX) are drawn along each row by the geometric gaps of their
Bernoulli process (one draw per hot pixel), above that by one draw per pixel.

Magnitudes: ``flux_from_magnitude`` uses ``F = zero_mag_rate_e_per_s * 10^(-0.4 m) * exposure_s``.  The
default zero point, 1.5e6 e-/s for a V = 0 star, is a round figure for a ~1 cm^2 clear aperture
(e.g. 17 mm f/1.4): about 1000 photons s^-1 cm^-2 A^-1 at V = 0 (Bessell, Castelli & Plez 1998, A&A 333,
231: 3.63e-9 erg s^-1 cm^-2 A^-1 at 550 nm) over a ~3000 A silicon pass band at ~50 % quantum efficiency.
It is a config field; set it from your optics.

Noise-free frames never need to be materialised for detection: see
``dualsight.kernels.detect.render_and_detect_ideal`` (same pixels, only the patches around stars).

Taichi is initialised lazily (``dualsight.kernels._runtime.ensure_init``) on the first call.
"""


import functools
import math
import threading
from dataclasses import dataclass, fields
from typing import Annotated, Literal

import numpy as np
import taichi as ti
from pydantic import ConfigDict, Field
from typing_extensions import TypedDict

from dualsight.kernels import psf_models, rng, star_psf
from dualsight.config import check_fields
from dualsight.kernels._runtime import KernelCache

__all__ = ["SensorConfig", "flux_from_magnitude", "render_star_fields", "false_star_lists",
           "append_false_stars", "release_scratch"]

MAX_CHUNK_PIXELS = 1 << 26  # pixels per kernel call: 256 MB float32 scratch at most, indices fit in int32
_QUANT_EPS = 1e-9  # ADU; keeps exact multiples of the gain from flooring one count low
_FRAC_DRAW = 4095  # STREAM_SHOT draw of the stray light's sub-grid Poisson part (PTRS uses draws < 2000)
MAX_STRAY_TABLE_ENTRIES = 1 << 21  # Poisson CDF entries tabulated for stray light (24 MB at most)
HOT_GEOMETRIC_MAX = 0.02  # hot-pixel fractions up to this are drawn by geometric gaps (one draw per hot pixel)
MAX_SKY_ADU_WORK = 1 << 19  # (Poisson terms) x (ADU values) evaluated for the sky's ADU table (~0.1 s, once)
_SKY_ADU_SIGMAS = 12.0  # the sky ADU table spans the charge range +- 12 read-noise sigmas (Phi(-12) = 1.8e-33)


# ============================================================================ configuration
MAX_CHARGE_E = 1e12
"""Largest charge (e-) any charge field may hold: 1e6 above the deepest real full wells (~1e6 e-), so
``full_well_e = 1e12`` still means "never saturates", while float32/float64 arithmetic stays exact enough."""
MAX_ADU = 2 ** 24
"""Largest ADU magnitude of any ADU field: the full scale of the deepest ADC allowed (``bit_depth`` 24)."""

_Charge = Annotated[float, Field(ge=0, le=MAX_CHARGE_E)]
_Gradient = Annotated[float, Field(ge=-1e9, le=1e9)]  # e-/px: 1e9 e- across a 65536 px frame is ~MAX_CHARGE_E
_Rate = Annotated[float, Field(ge=-100.0, le=100.0)]  # deg/s: beyond any tumbling rate a star camera could use
_SENSOR_UNITS = {"psf_sigma_px": "px", "exposure_s": "s", "gain_e_per_adu": "e-/ADU", "full_well_e": "e-",
                 "bit_depth": "bits", "bias_adu": "ADU", "zero_mag_rate_e_per_s": "e-/s", "psf_window_sigma": "sigma",
                 "read_noise_e": "e- rms", "dark_current_e_per_s": "e-/s/px", "sky_background_e": "e-/px",
                 "hot_pixel_e": "e-", "false_star_flux_min_e": "e-", "false_star_flux_max_e": "e-",
                 "defocus_radius_px": "px", "rate_deg_s": "deg/s", "stray_light_e": "e-, e-/px"}
MAX_BRIGHT_OBJECTS = 64


class BrightObject(TypedDict):
    """One bright object in the sky (``[sensor] bright_objects = [{ra_deg, dec_deg, vmag, radius_px}, ...]``).

    ra_deg in [0, 360), dec_deg in [-90, 90] (ICRS); vmag in [-30, 30] (Sun -26.7, full Moon -12.7, Venus
    down to -4.9); radius_px in [0, 4096]: 0 = a point (rendered with the star PSF), > 0 = a uniform disk
    of that radius (the Moon: its angular radius (~0.26 deg) times the focal length in px).
    """

    __pydantic_config__ = ConfigDict(extra="forbid")
    ra_deg: Annotated[float, Field(ge=0.0, lt=360.0)]
    dec_deg: Annotated[float, Field(ge=-90.0, le=90.0)]
    vmag: Annotated[float, Field(ge=-30.0, le=30.0)]
    radius_px: Annotated[float, Field(ge=0.0, le=4096.0)]


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
        (0, 1e12], and max >= min (a cross-field rule, checked in ``__post_init__``).
    psf_model : "gaussian" (default: the pixel-integrated Gaussian of ``psf_sigma_px``), "defocus" (a uniform
        disk of ``defocus_radius_px``, exact pixel areas; convolved with the Gaussian when
        ``defocus_gaussian``) or "image" (the measured PSF of ``psf_image``); see
        :mod:`dualsight.kernels.psf_models`.
    defocus_radius_px : radius of the defocus disk (px), in [0.1, 50] (used by psf_model "defocus").
    defocus_gaussian : convolve the defocus disk with the Gaussian of ``psf_sigma_px`` (lens blur,
        diffraction, charge diffusion).
    psf_image : path of the measured PSF (psf_model "image", and only then): a ``.npy`` array or a PNG,
        TIFF or FITS image, 2-D, odd sides <= 64 px, finite, >= 0, sampled on the sensor's pixels (1 to
        4096 characters; relative to the working directory).  Read and checked when the config is built.
    rate_deg_s : body rate [wx, wy, wz] of the camera frame during the exposure (deg/s), each in [-100, 100];
        stars smear along their path (straight segments, see :mod:`dualsight.kernels.psf_models`).  Needs
        the camera model at render time.  [0, 0, 0] = off.
    stray_light_e : [e0, gx, gy]: stray light of e0 electrons (in [0, 1e12]) at the frame centre with
        gradients gx, gy (e-/px along columns and rows, each in [-1e9, 1e9]), clipped at 0 e- where the
        plane goes negative; added to the charge before shot noise.  [0, 0, 0] = off.
    bright_objects : up to 64 planets or the Moon (:class:`BrightObject`: ra_deg, dec_deg, vmag,
        radius_px), projected with each case's attitude and the camera; they saturate like stars (full
        well, then the ADC).  Needs the camera and attitudes at render time.  () = none.

    The sparse noise-free detector (``dualsight.kernels.detect.render_and_detect_ideal``) renders only
    Gaussian star windows over a constant sky: every effect beyond that (pixel noise, another PSF
    model, smear, stray light, bright objects) makes :attr:`has_pixel_noise` True and :attr:`is_ideal`
    False, so those frames are rendered whole.
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
    psf_model: Literal["gaussian", "defocus", "image"] = "gaussian"
    defocus_radius_px: Annotated[float, Field(ge=0.1, le=50.0)] = 1.5
    defocus_gaussian: bool = False
    psf_image: Annotated[str, Field(min_length=1, max_length=4096)] | None = None
    rate_deg_s: Annotated[tuple[_Rate, _Rate, _Rate], Field(min_length=3, max_length=3)] = (0.0, 0.0, 0.0)
    stray_light_e: Annotated[tuple[_Charge, _Gradient, _Gradient], Field(min_length=3, max_length=3)] = (0.0, 0.0, 0.0)
    bright_objects: Annotated[tuple[BrightObject, ...], Field(max_length=MAX_BRIGHT_OBJECTS)] = ()

    def __post_init__(self):
        check_fields(self, units=_SENSOR_UNITS)
        if self.false_star_flux_max_e < self.false_star_flux_min_e:
            raise ValueError(f"SensorConfig.false_star_flux_max_e must be >= false_star_flux_min_e "
                             f"({self.false_star_flux_min_e!r}), got {self.false_star_flux_max_e!r}")
        for name in ("rate_deg_s", "stray_light_e"):  # numbers as floats (ints are allowed in a table)
            object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
        object.__setattr__(self, "bright_objects", tuple({k: float(o[k]) for k in BrightObject.__annotations__}
                                                         for o in self.bright_objects))
        if (self.psf_model == "image") != (self.psf_image is not None):
            raise ValueError("SensorConfig.psf_image must be given with psf_model = \"image\" and only then "
                             f"(psf_model {self.psf_model!r}, psf_image {self.psf_image!r})")
        if self.psf_image is not None:
            psf_models.load_psf_image(self.psf_image)  # read and checked now (cached: once per process)

    def __hash__(self):  # bright_objects holds dicts (plain JSON in to_dict)
        return hash(tuple((k, tuple(tuple(sorted(o.items())) for o in v) if k == "bright_objects" else v)
                          for k, v in self.to_dict().items()))

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
    def has_random_pixels(self) -> bool:
        """True if any per-pixel random effect is on (shot, read or hot pixels)."""
        return self.shot_noise or self.read_noise_e > 0 or self.hot_pixel_fraction > 0

    @property
    def has_smear(self) -> bool:
        return any(v != 0.0 for v in self.rate_deg_s)

    @property
    def has_stray_light(self) -> bool:
        return any(v != 0.0 for v in self.stray_light_e)

    @property
    def gaussian_windows_only(self) -> bool:
        """True if all light is Gaussian star windows over a constant sky (what the sparse path renders):
        Gaussian PSF, no smear, no stray light, no bright objects."""
        return (self.psf_model == "gaussian" and not self.has_smear and not self.has_stray_light
                and not self.bright_objects)

    @property
    def has_pixel_noise(self) -> bool:
        """True if some pixel is more than the sparse path's Gaussian windows over a constant sky: a per-pixel
        random effect (shot, read or hot pixels) or light elsewhere or otherwise shaped (PSF model
        "defocus"/"image", smear, stray light, bright objects).  The sparse detector refuses such sensors."""
        return self.has_random_pixels or not self.gaussian_windows_only

    @property
    def needs_seeds(self) -> bool:
        """True if rendering draws random numbers (pixel noise or false stars)."""
        return self.has_random_pixels or self.false_stars_per_frame > 0

    @property
    def is_ideal(self) -> bool:
        """No random effect and nothing but Gaussian star windows over a constant sky (the sparse
        noise-free path reproduces the frame exactly)."""
        return not self.needs_seeds and self.gaussian_windows_only

    @property
    def needs_camera(self) -> bool:
        """True if rendering needs the camera model (smear) or also the attitudes (bright objects)."""
        return self.has_smear or bool(self.bright_objects)

    def psf_reach_px(self) -> float:
        """How far (px) from a star's (mid-exposure) position its PSF puts light, smear excluded."""
        g = self.psf_window_sigma * self.psf_sigma_px + 1.0
        if self.psf_model == "defocus":
            return self.defocus_radius_px + (g if self.defocus_gaussian else 1.0)
        if self.psf_model == "image":
            img = psf_models.load_psf_image(self.psf_image)
            return max(img.shape) // 2 + 1.0
        return g

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


@ti.func
def _table_sample(u, cdf: ti.template(), guide: ti.template(), o0, o1):
    """Poisson sample by inversion of the tabulated CDF cdf[o0:o1] with its guide table guide[o0:o1] (local
    indices, as :func:`dualsight.kernels.rng.poisson_table`); -1.0 beyond the table's last entry."""
    K = ti.cast(o1 - o0, ti.i32)
    j = ti.min(ti.cast(u * ti.cast(K, ti.f64), ti.i32), K - 1)
    k = guide[o0 + j]
    while k < K and cdf[o0 + k] < u:
        k += 1
    res = ti.f64(-1.0)
    if k < K:
        res = ti.cast(k, ti.f64)
    return res


@ti.func
def _next_hot(c, W, log1m, u):
    """Column of the next hot pixel after column c (W: none in the row): c + 1 + G, G = floor(ln u / ln(1 - p))
    the geometric number of cool pixels before it, P(G >= g) = (1 - p)^g (log1m = ln(1 - p) < 0)."""
    g = ti.floor(ti.log(u) / log1m)
    nxt = W
    if g < ti.cast(W - c - 1, ti.f64):
        nxt = c + 1 + ti.cast(g, ti.i32)
    return nxt


@ti.func
def _small_poisson(lam, u):
    """Poisson(lam) for 0 <= lam < 1 by sequential inversion of the uniform u."""
    p = ti.exp(-lam)
    cum = p
    n = 0
    while u > cum and n < 60:
        n += 1
        p *= lam / ti.cast(n, ti.f64)
        cum += p
    return ti.cast(n, ti.f64)


@functools.lru_cache(maxsize=8)
def _stray_tables_for(base_e: float, m0: int, m1: int, step: float):
    parts = [rng.poisson_table_np(base_e + m * step) for m in range(m0, m1 + 1)]  # per grid value, not per pixel
    off = np.zeros(len(parts) + 1, np.int64)
    np.cumsum([len(c) for c, _ in parts], out=off[1:])
    return (np.ascontiguousarray(np.concatenate([c for c, _ in parts])),
            np.ascontiguousarray(np.concatenate([g for _, g in parts])), off)


def _stray_tables(cfg: SensorConfig, W: int, H: int):
    """Poisson CDF tables of the sky pixels' lambdas under stray light, on a grid: (cdf, guide, offsets, m0,
    1 / step) for lambda = base_e + m * step, m = m0 .. floor(max stray / step) over the stray plane's range
    in the frame.  The step is the finest of 1/16, 1/4, 1 e- whose tables hold at most
    MAX_STRAY_TABLE_ENTRIES entries (finer grids cost more in cache misses than they save: measured on 1024 x
    768 frames, 1/16 e- adds ~3 ms/frame to the plain sky's table sampler, 1/64 and 1 e- ~35); none (one
    dummy entry) when shot noise or stray light is off or even 1 e- is too fine (then every pixel takes the
    PTRS sampler)."""
    none = (np.ones(1), np.zeros(1, np.int32), np.zeros(1, np.int64), 0, 1.0)
    if not (cfg.shot_noise and cfg.has_stray_light):
        return none
    e0, gx, gy = cfg.stray_light_e
    corners = [max(0.0, e0 + gx * (cx - 0.5 * W) + gy * (ry - 0.5 * H)) for cx in (0.5, W - 0.5) for ry in (0.5, H - 0.5)]
    lam_hi = cfg.base_e + max(corners) + 1.0
    per_table = lam_hi + 12.0 * math.sqrt(lam_hi) + 31.0
    if lam_hi > 1e6:
        return none
    for inv_step in (16, 4, 1):
        m0, m1 = math.floor(min(corners) * inv_step), math.floor(max(corners) * inv_step)
        if (m1 - m0 + 1) * per_table <= MAX_STRAY_TABLE_ENTRIES:
            cdf, guide, off = _stray_tables_for(float(cfg.base_e), int(m0), int(m1), 1.0 / inv_step)
            return cdf, guide, off, int(m0), float(inv_step)
    return none


_erfc = np.frompyfunc(math.erfc, 1, 1)


@functools.lru_cache(maxsize=8)
def _sky_adu_table_for(base_e: float, shot: bool, read_e: float, full_well: float, gain: float, bias: float,
                       max_adu: float):
    """(cdf, guide, a0) of the ADU value of a sky pixel, or None when too costly; see :func:`sky_adu_table`."""
    if shot and base_e > 0.0:
        K = int(base_e + 12.0 * math.sqrt(base_e) + 30.0)   # as rng.poisson_table_np: tail beyond < 1e-20
        k = np.arange(K, dtype=np.float64)
        logp = -base_e + np.concatenate([[0.0], np.cumsum(math.log(base_e) - np.log(k[1:]))])
        p = np.exp(logp)
        keep = p > 0.0
        k, p = k[keep], p[keep]
    else:
        k, p = np.array([base_e if not shot else 0.0]), np.ones(1)
    e = np.minimum(k, full_well)                              # the kernel: e = min(e, full_well)
    if read_e <= 0.0:   # ADU a function of the charge: the kernel's own f64 arithmetic
        adu = np.minimum(np.maximum(np.floor(e / gain + bias + _QUANT_EPS), 0.0), max_adu)
        a0 = float(adu.min())
        pa = np.bincount((adu - a0).astype(np.int64), weights=p)
        cdf = np.cumsum(pa)
    else:
        half = _SKY_ADU_SIGMAS * read_e / gain
        lo = max(0.0, math.floor(e.min() / gain + bias - half) - 1.0)
        hi = min(max_adu, math.ceil(e.max() / gain + bias + half) + 1.0)
        if lo > hi or (hi - lo + 1) * k.size > MAX_SKY_ADU_WORK:
            return None
        a = np.arange(lo, hi + 1.0)
        # P(ADU <= a) = P(e + R z < (a + 1 - bias - eps) g) = sum_k p_k Phi(((a + 1 - bias - eps) g - e_k) / R)
        # for a < max_adu (the clip at 0 ADU is included: every y < 1 floors to <= 0); 1 at max_adu
        zc = (e[None, :] - (a[:, None] + 1.0 - bias - _QUANT_EPS) * gain) / (read_e * math.sqrt(2.0))
        cdf = (0.5 * _erfc(zc).astype(np.float64)) @ p         # Phi(x) = erfc(-x / sqrt 2) / 2
        cdf[a >= max_adu] = 1.0
        a0 = float(lo)
    # a direct guide table (Chen & Asau 1974) of >= 16 cells per entry: ~94 % of the cells hold no CDF step
    # and give the ADU in one load (rng.inverse_table)
    return np.ascontiguousarray(cdf), rng.inverse_table_np(cdf), a0


def sky_adu_table(cfg: SensorConfig):
    """Tabulated CDF of the final ADU value of a sky pixel (no star light, not hot, no stray light):
    (cdf (A,) float64, guide (A,) int32, a0) with cdf[j] = P(ADU <= a0 + j), or None (no table: the pixel goes
    through the per-effect samplers).

    The pixel model of the module docstring with S = 0: e = min(Poisson(base_e), full_well) (base_e itself
    without shot noise), e + read_noise * N(0, 1), ADU = clip(floor(e / gain + bias + 1e-9), 0, max_adu).  Its
    distribution is exactly P(ADU <= a) = sum_k P(e = k) Phi(((a + 1 - bias - 1e-9) gain - k) / read_noise)
    (read noise on), or the ADU of each charge by the kernel's own arithmetic (read noise off): one uniform
    inverted through this table replaces the Poisson and the normal draw of every sky pixel (most of a star
    field), with no transcendental call per pixel.  The table spans the charges' range +- 12 read-noise
    sigmas (the mass beyond, Phi(-12) ~ 2e-33, is below the resolution of the 53-bit uniforms).  Only for
    quantised ADU (continuous ADU have no finite table) and when the table costs at most
    MAX_SKY_ADU_WORK normal-CDF evaluations; built once per sensor (cached).
    """
    if not cfg.quantize or not (cfg.shot_noise or cfg.read_noise_e > 0.0) or cfg.base_e > 1e6:
        return None
    return _sky_adu_table_for(float(cfg.base_e), bool(cfg.shot_noise), float(cfg.read_noise_e),
                              float(cfg.full_well_e), float(cfg.gain_e_per_adu), float(cfg.bias_adu),
                              float(cfg.max_adu))


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
                 use_table: ti.i32, stray: ti.i32, stray_e0: ti.f64, stray_gx: ti.f64, stray_gy: ti.f64,
                 tcdf: ti.types.ndarray(dtype=ti.f64, ndim=1), tguide: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 toff: ti.types.ndarray(dtype=ti.i64, ndim=1), tm0: ti.i32, tinv: ti.f64,
                 acdf: ti.types.ndarray(dtype=ti.f64, ndim=1), aguide: ti.types.ndarray(dtype=ti.i32, ndim=1),
                 use_adu: ti.i32, adu0: ti.f64, hot_log1m: ti.f64):
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
            k_frac = rng.stream_key(seed, rng.STREAM_SHOT, _FRAC_DRAW)
            k_sky = rng.stream_key(seed, rng.STREAM_SKY_ADU, 0)
            k_geo = rng.stream_key(hseed, rng.STREAM_HOT, 1)
            ntab = toff.shape[0] - 1
            row0 = ti.cast(r, ti.u64) * ti.cast(W, ti.u64)
            p0 = (b * H + r) * W
            # stray light of this row at column c: max(0, stray_row + stray_gx * (c + 0.5 - W/2))
            stray_row = stray_e0 + stray_gy * (ti.cast(r, ti.f64) + ti.f64(0.5) - ti.f64(0.5) * ti.cast(H, ti.f64))
            stray_x0 = ti.f64(0.5) - ti.f64(0.5) * ti.cast(W, ti.f64)
            if shot == 0 and read_e <= ti.f64(0.0) and hot_frac <= ti.f64(0.0) and stray == 0:
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
                # sparse hot pixels (hot_log1m < 0): the row's hot columns as a Bernoulli process drawn by its
                # geometric gaps, one draw per hot pixel (+ one per row) instead of one per pixel
                rkey = ti.cast(r, ti.u64) << ti.u64(32)
                n_hot = 0
                next_hot = W
                if hot_log1m < ti.f64(0.0):
                    next_hot = _next_hot(-1, W, hot_log1m, rng.u01_key(k_geo, rkey))
                for c in range(W):
                    s = buf[p0 + c]
                    if s != ti.f32(0.0):
                        buf[p0 + c] = ti.f32(0.0)
                    idx = row0 + ti.cast(c, ti.u64)
                    hot = 0
                    if hot_log1m < ti.f64(0.0):
                        if c == next_hot:
                            hot = 1
                            n_hot += 1
                            next_hot = _next_hot(c, W, hot_log1m, rng.u01_key(k_geo, rkey | ti.cast(n_hot, ti.u64)))
                    elif hot_frac > ti.f64(0.0):
                        if rng.u01_key(k_hot, idx) < hot_frac:
                            hot = 1
                    j = -1
                    if use_adu != 0 and s == ti.f32(0.0) and hot == 0:
                        # a sky pixel (no star light, not hot; use_adu implies no stray light): its ADU value
                        # by inversion of the tabulated CDF of shot + read noise + ADC (sky_adu_table)
                        j = rng.inverse_table(rng.u01_key(k_sky, idx), acdf, aguide)
                    if j >= 0:
                        out[p0 + c] = ti.cast(adu0 + ti.cast(j, ti.f64), tdt)
                        continue
                    e = ti.cast(s, ti.f64) + base_e
                    st = ti.f64(0.0)
                    sky_px = 0  # 1: only sky, dark current and stray light (for the stray tables)
                    if s == ti.f32(0.0):
                        sky_px = 1
                    if stray != 0:
                        st = ti.max(stray_row + stray_gx * (ti.cast(c, ti.f64) + stray_x0), ti.f64(0.0))
                        e += st
                    if hot != 0:
                        e += hot_e
                        sky_px = 0
                    if shot != 0:
                        k = ti.f64(-1.0)
                        if use_table != 0 and e == base_e:  # the sky's lambda: tabulated CDF
                            k = rng.poisson_table(rng.u01_key(k_shot0, idx), cdf, guide)
                        if k < ti.f64(0.0) and stray != 0 and sky_px != 0 and ntab > 0:
                            # stray light: Poisson(base + st) = Poisson(base + q step) (tabulated CDF of that
                            # grid value, q = floor(st / step)) + Poisson(st - q step) (inversion, its own draw;
                            # independent).  The remainder is < step (<= 1/16 e-): u <= 1 - d <= exp(-d) means 0
                            # without computing exp(-d), the same result as the full inversion.
                            q = ti.floor(st * tinv)
                            ti_ = ti.cast(q, ti.i32) - tm0
                            if ti_ >= 0 and ti_ < ntab:
                                k = _table_sample(rng.u01_key(k_shot0, idx), tcdf, tguide, toff[ti_], toff[ti_ + 1])
                                d = st - q / tinv
                                if k >= ti.f64(0.0) and d > ti.f64(0.0):
                                    u2 = rng.u01_key(k_frac, idx)
                                    if u2 > ti.f64(1.0) - d:
                                        k += _small_poisson(d, u2)
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
                       seeds=None, *, dtype=np.uint16, out: np.ndarray | None = None, camera=None,
                       attitude=None) -> np.ndarray:
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
    camera : ``dualsight.scene.camera.Camera`` of the frames; needed when ``cfg.rate_deg_s`` (smear) or
        ``cfg.bright_objects`` is set (``cfg.needs_camera``), else ignored.
    attitude : (B, 3, 3) inertial -> camera rotation of each case; needed for ``cfg.bright_objects``.

    Returns
    -------
    (B, H, W) images in ADU (see the module docstring for the pixel model).

    Cost: one serial-per-case splat of each star's window plus one (frame, row) pass over every pixel
    (1024 x 768, one core: ~1 ms/frame noise-free, ~3-4 ms/frame with shot and read noise and hot pixels on
    the tabulated sky path, ~18 ms/frame with continuous ADU (``quantize=False``: per-effect samplers)).  Another PSF
    model or smear renders each star as several sub-sources (:mod:`dualsight.kernels.psf_models`), each
    within its own window: the defocus quadrature of the "realistic" preset (255 Gaussians per star) adds
    ~3 ms per frame of 13 stars, a smear multiplies that part by ~5 L (L px long).  Stray light is computed
    per pixel inside the same pass, its shot noise from tabulated CDFs (~3 ms/frame more).  For
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
    tcdf, tguide, toff, tm0, tinv = _stray_tables(cfg, W, H)
    cdf, guide = rng.poisson_table_np(cfg.base_e) if use_table else (np.ones(1), np.zeros(1, np.int32))
    sky = None if cfg.has_stray_light else sky_adu_table(cfg)   # the sky pixels' ADU in one draw
    # hot pixels up to HOT_GEOMETRIC_MAX: by their geometric gaps along each row; above, one draw per pixel
    p_hot = cfg.hot_pixel_fraction
    hot_log1m = math.log1p(-p_hot) if 0.0 < p_hot <= HOT_GEOMETRIC_MAX else 0.0
    acdf, aguide, adu0 = sky if sky is not None else (np.ones(1), np.zeros(1, np.int32), 0.0)
    src = None
    if cfg.psf_model != "gaussian" or cfg.needs_camera:  # sub-sources (psf_models); else the plain Gaussian splat
        src = psf_models.prepare_sources(x, y, f, ok, cfg, camera, attitude)
    stray = (int(cfg.has_stray_light),) + tuple(float(v) for v in cfg.stray_light_e)
    chunk = max(1, min(B, MAX_CHUNK_PIXELS // (H * W)))  # frames per kernel call (bounded scratch, i32 indices)
    with _scratch.lock:
        try:
            for b0 in range(0, B, chunk):  # loop over chunks of frames, not over pixels or stars
                sl = slice(b0, min(B, b0 + chunk))
                n = sl.stop - sl.start
                buf = _scratch.get(n * H * W)
                if src is None:
                    star_psf.splat_stars(x[sl], y[sl], f[sl], ok[sl], buf.reshape(n, H, W), cfg.psf_sigma_px,
                                         cfg.psf_window_sigma)
                else:
                    psf_models.splat_sources(src, sl, buf.reshape(n, H, W), cfg.psf_sigma_px)
                fin(buf, out[sl].reshape(-1), n, H, W, seeds[sl], np.uint64(hot_seed or 0),
                    int(hot_seed is not None), float(cfg.base_e), float(cfg.full_well_e), float(cfg.gain_e_per_adu),
                    float(cfg.bias_adu), float(cfg.max_adu), int(cfg.quantize), int(cfg.shot_noise),
                    float(cfg.read_noise_e), float(cfg.hot_pixel_fraction), float(cfg.hot_pixel_e), cdf, guide,
                    int(use_table), *stray, tcdf, tguide, toff, tm0, tinv, acdf, aguide, int(sky is not None),
                    float(adu0), hot_log1m)
        except BaseException:
            _scratch.drop()  # the zero invariant may be broken
            raise
    return out
