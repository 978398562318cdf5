"""The star renderer's sensor model: :class:`SensorConfig` (every field's range in its type) and the
magnitude-to-electrons conversion; importable without the render kernels (no Taichi:
:mod:`dualsight.kernels.starfield` renders with it; the formulas and sources are in that module's docstring).
Nothing here reads a file: a measured PSF (``psf_image``) is read by :mod:`dualsight.scene.psf_file` and
handed to the renderer as an array."""

import math
from dataclasses import dataclass, fields
from typing import Annotated, Literal

import numpy as np
from pydantic import ConfigDict, Field
from typing_extensions import TypedDict

from dualsight.config import check_fields
from dualsight.kernels.psf_image import check_psf

QUANT_EPS_ADU = 1e-9
"""ADU added before the ADC's floor, ADU = floor(e / gain + bias + QUANT_EPS_ADU): keeps a charge that is an exact
multiple of the gain from flooring one count low through rounding.  Every evaluation of the ADC uses it (the
render kernels of :mod:`dualsight.kernels.starfield`, the sky tables of :mod:`dualsight.kernels.sky_noise`,
:meth:`SensorConfig.empty_pixel_adu`), so they agree bit for bit."""


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
    validated (``dualsight.config.validate``) and when the dataclass is built in Python
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
        4096 characters; relative to the working directory).  Read and checked by
        :func:`dualsight.scene.psf_file.with_psf_digest` (where the job layer builds the spec) and loaded by
        :func:`dualsight.scene.psf_file.sensor_psf` for the renderer (its ``psf`` argument), never by the
        constructor or the kernels.
    psf_image_sha256 : SHA-256 of the PSF's content (:func:`dualsight.kernels.psf_image.psf_image_sha256`),
        filled in by :func:`dualsight.scene.psf_file.with_psf_digest` and kept in the spec, so a run's identity
        covers the file's
        content: a spec that states it (a stored run being resumed or replayed) fails in one line there if
        the file has changed since.
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
    psf_image_sha256: Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")] | None = None
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
        if self.psf_image is None and self.psf_image_sha256 is not None:
            raise ValueError("SensorConfig.psf_image_sha256 is only allowed with psf_image")

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

    def psf_reach_px(self, psf: np.ndarray | None = None) -> float:
        """How far (px) from a star's (mid-exposure) position its PSF puts light, smear excluded.

        psf : the measured PSF, a (ny, nx) float64 array of unit sum (fraction of a star's electrons per
            pixel; :func:`dualsight.scene.psf_file.sensor_psf`), needed with ``psf_model = "image"`` (its
            half-size sets the reach), else ignored."""
        g = self.psf_window_sigma * self.psf_sigma_px + 1.0
        if self.psf_model == "defocus":
            return self.defocus_radius_px + (g if self.defocus_gaussian else 1.0)
        if self.psf_model == "image":
            img = check_psf(psf, self.psf_model)
            return max(img.shape) // 2 + 1.0
        return g

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def empty_pixel_adu(self) -> float:
        """ADU value of a star-free pixel of a noise-free frame (same arithmetic as the kernels)."""
        e = min(np.float64(np.float32(0.0)) + self.base_e, self.full_well_e)
        adu = e / self.gain_e_per_adu + self.bias_adu
        if self.quantize:
            adu = math.floor(adu + QUANT_EPS_ADU)
        return float(min(max(adu, 0.0), float(self.max_adu)))


def flux_from_magnitude(vmag, cfg: SensorConfig = SensorConfig()) -> np.ndarray:
    """Electrons collected from stars of visual magnitude ``vmag`` during one exposure.

    F = cfg.zero_mag_rate_e_per_s * 10^(-0.4 vmag) * cfg.exposure_s   (Pogson's ratio; any shape, float64).
    """
    m = np.asarray(vmag, dtype=np.float64)
    return cfg.zero_mag_rate_e_per_s * np.power(10.0, -0.4 * m) * cfg.exposure_s
