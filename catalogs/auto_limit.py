"""The catalog magnitude limit that follows the camera: enough catalog stars per field, no tuning.

:func:`auto_mag_limit` picks the faintest Johnson V the star catalog is cut at from

1. the camera's field: the solid angle Omega of the image rectangle seen through the pinhole model with
   its distortion (:func:`field_solid_angle`);
2. the catalog's whole-sky cumulative counts N(<= V) (:func:`hipparcos_vmag`: every hip2 star's V,
   117,955 stars to V 14.4): a field pointed at random holds on average ``N(<= V) Omega / (4 pi)`` stars;
3. the target, ``target_per_field`` stars per field on average (default 15).

The limit is the smallest V on a 0.1 mag grid whose mean count per field reaches the target, then

* capped by the sensor's sensitivity when known (``sensor_v``: the faintest V it detects, e.g.
  :func:`sensor_limit_v` for a simulated :class:`~dualsight.kernels.sensor_config.SensorConfig`): stars the
  camera cannot see only add false catalog pairs;
* capped by the catalog's completeness (``complete_v``, default :data:`HIPPARCOS_COMPLETE_V` = 8.0): beyond
  it the camera sees stars the catalog lacks, and a fainter cut adds stars unevenly over the sky;
* capped by the catalog's own cut when the counts come from a catalog built to a limit, and by
  :data:`~dualsight.catalogs.stars.MAG_LIMIT_RANGE`;
* raised, whatever the caps, to hold at least :data:`~dualsight.catalogs.stars.MIN_STARS` stars over the
  whole sky (the star catalog's own minimum).

``dualsight hil star`` uses it by default (``--mag-limit`` not given, or ``mag_limit = "auto"`` in the
``[catalog]`` table; resolved when the spec is built, jobs/kinds/hil_star_spec.py) with
:data:`HIL_TARGET_PER_FIELD` = 35 stars per field.

When a cap binds, the field holds fewer than the target on average; :class:`AutoLimit` says which cap and
how many stars a field then holds (:meth:`AutoLimit.describe`).

Completeness assumed (:data:`HIPPARCOS_COMPLETE_V`): the Hipparcos survey is complete to
V = 7.9 + 1.1 |sin b| for spectral types earlier than G5 and V = 7.3 + 1.1 |sin b| for later types
(b = galactic latitude; Perryman et al. 1997, A&A 323, L49; ESA 1997, The Hipparcos and Tycho Catalogues,
Vol. 1), i.e. 7.3-9.0 depending on the sky and the colour.  In hip2 itself the differential counts grow like a complete
sample's (x1.2-1.3 per 0.25 mag) up to V ~ 8 and flatten after (x1.14 at 8.0-8.25, x1.02 at 8.5-8.75, falling
beyond 8.75), so the whole sky is taken as complete to V 8.0: the late-type limit averaged over the sphere
(7.3 + 1.1 <|sin b|> = 7.85), rounded.
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualsight.catalogs.cache import resolve_cache_dir, short_hash

__all__ = ["HIPPARCOS_COMPLETE_V", "GRID_MAG", "DEFAULT_TARGET", "HIL_TARGET_PER_FIELD", "AutoLimit", "is_auto",
           "describe_mag_limit", "auto_mag_limit", "auto_limit", "field_solid_angle",
           "field_size_deg", "hipparcos_vmag", "sensor_limit_v", "stars_per_field"]

HIPPARCOS_COMPLETE_V = 8.0
"""Johnson V to which the Hipparcos catalog is taken as complete over the whole sky (module docstring)."""

GRID_MAG = 0.1
"""The limit is rounded up to a multiple of this (mag): few distinct limits, so few cached catalogs."""

DEFAULT_TARGET = 15.0
"""Mean catalog stars per field aimed at by default (the reference's setup, V 5.5 over a 15.9 x 12.0 deg
field, holds 13 on average)."""

HIL_TARGET_PER_FIELD = 35.0
"""Mean catalog stars per field aimed at for real frames (``hil star``'s ``mag_limit = "auto"``).  More than
:data:`DEFAULT_TARGET` because a real camera sees more stars than the catalog holds: the ``max_stars`` (25)
brightest detections vote, ranked by the sensor's band, not by V, and fields differ (over 3,000 random
pointings of the ESA camera at V 7.0: mean 36.9 stars, 10th percentile 22, fewest 12), so 35 on average puts
about as many catalog stars as voters in 9 fields out of 10.  Measured on the eight ESA tetra3 frames
(tests/test_hil_star.py, the one real camera at hand): a target of 15 gives V 6.3 and solves 7 of 8 (the paper
method 6; the hardest frame identifies 8 stars); 25 gives V 6.7, all 8 (paper 7); 30 gives V 6.9, all 8 by
both methods (the hardest frame 15 stars identified, 18 at V 7.0); 35 gives V 7.0, the limit measured best on
these frames before it was automatic, so their results are unchanged."""

_EDGE_SAMPLES = 256
"""Boundary points per image side for :func:`field_solid_angle` (exact without distortion)."""


# ============================================================================================ the field
def _boundary_px(camera, n: int) -> np.ndarray:
    """(4 n, 2) pixel coordinates around the image rectangle [0, W] x [0, H] (the outer pixels' outer
    edges), counter-clockwise in (col, row): top edge left to right, right edge down, bottom, left up."""
    W, H = float(camera.width), float(camera.height)
    t = np.arange(n, dtype=np.float64) / n
    top = np.stack([t * W, np.zeros(n)], axis=1)
    right = np.stack([np.full(n, W), t * H], axis=1)
    bottom = np.stack([W - t * W, np.full(n, H)], axis=1)
    left = np.stack([np.zeros(n), H - t * H], axis=1)
    return np.concatenate([top, right, bottom, left])


def field_solid_angle(camera, n_edge: int = _EDGE_SAMPLES) -> float:
    """Solid angle (sr) of the sky the image rectangle sees.

    The rectangle's boundary (the outer edges of the outer pixels, ``n_edge`` points per side) is
    back-projected through the camera (``Camera.backproject``: pinhole and distortion) and the solid angle
    of the spherical polygon through those directions is summed over the triangles it makes with the
    direction of the image centre (Van Oosterom & Strackee 1983, IEEE Trans. Biomed. Eng. 30, 125:
    ``tan(Omega_t / 2) = a . (b x c) / (1 + a.b + b.c + c.a)``).  Without distortion the image edges are
    great circles, so the result is exact (for a centred pinhole, ``4 arcsin(sin a sin b)`` with a, b
    the half-angles of the sides); with distortion the error falls as 1 / n_edge^2.
    """
    v = camera.backproject(_boundary_px(camera, int(n_edge)))
    c = camera.backproject(np.array([camera.width / 2.0, camera.height / 2.0]))
    a, b = v, np.roll(v, -1, axis=0)
    num = np.einsum("ij,ij->i", np.broadcast_to(c, a.shape), np.cross(a, b))
    den = 1.0 + a @ c + b @ c + np.einsum("ij,ij->i", a, b)
    return float(abs(np.sum(2.0 * np.arctan2(num, den))))


def field_size_deg(camera) -> tuple[float, float]:
    """(horizontal, vertical) angular size (deg) of the image through its centre: the angle between the
    back-projected midpoints of the left and right (top and bottom) edges, distortion included."""
    W, H = camera.width, camera.height
    p = camera.backproject(np.array([[0.0, H / 2], [W, H / 2], [W / 2, 0.0], [W / 2, H]], np.float64))
    h = math.atan2(np.linalg.norm(np.cross(p[0], p[1])), float(p[0] @ p[1]))
    v = math.atan2(np.linalg.norm(np.cross(p[2], p[3])), float(p[2] @ p[3]))
    return math.degrees(h), math.degrees(v)


# ============================================================================================ the counts
@functools.lru_cache(maxsize=2)
def hipparcos_vmag(path: str | None = None) -> np.ndarray:
    """(117955,) float64 Johnson V of every hip2 star, ascending (the catalog's whole-sky counts:
    ``N(<= V) = searchsorted(vmag, V, "right")``).  The V of :func:`dualsight.catalogs.stars.johnson_v`,
    the very values the star catalog is cut on.  Parsing hip2.dat takes ~0.5 s, so the array is kept per
    process and cached as ``<cache>/hip2-vmag-<key>.npy``, keyed by the file's path, size and mtime (a
    damaged cache file is rebuilt)."""
    from dualsight.catalogs.stars import hip2_path, johnson_v, read_hip2    # pyarrow: deferred

    src = hip2_path() if path is None else Path(path)
    st = src.stat()
    key = short_hash({"file": str(src.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns, "v": 1})
    cache = resolve_cache_dir(None) / f"hip2-vmag-{key}.npy"
    out = None
    try:
        out = np.load(cache)
        if out.ndim != 1 or out.dtype != np.float64 or not np.all(np.isfinite(out)) or np.any(np.diff(out) < 0):
            out = None
    except (OSError, ValueError):
        out = None
    if out is None:
        v, _ = johnson_v(read_hip2(src))
        out = np.sort(v)
        try:
            cache.parent.mkdir(parents=True, exist_ok=True)
            tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp")
            with open(tmp, "wb") as f:
                np.save(f, out)
            os.replace(tmp, cache)
        except OSError:
            pass                # a read-only cache only costs the parse next time
    out.flags.writeable = False
    return out


def _magnitudes(counts) -> tuple[np.ndarray, float | None]:
    """(ascending V of every star, the catalog's own cut or None) from a StarCatalog, an array of V or None."""
    if counts is None:
        return hipparcos_vmag(), None
    if hasattr(counts, "vmag"):
        cut = getattr(getattr(counts, "config", None), "mag_limit", None)
        return np.sort(np.asarray(counts.vmag, np.float64)), (float(cut) if cut is not None else None)
    v = np.sort(np.asarray(counts, np.float64).ravel())
    if not np.all(np.isfinite(v)):
        raise ValueError("star magnitudes must be finite")
    return v, None


def stars_per_field(vmag_sorted: np.ndarray, mag_limit: float, field_sr: float) -> float:
    """Mean catalog stars in a field of ``field_sr`` sr pointed at random: N(<= mag_limit) Omega / (4 pi)."""
    return float(np.searchsorted(vmag_sorted, mag_limit, side="right")) * field_sr / (4.0 * math.pi)


def _grid_up(v: float) -> float:
    """The smallest multiple of :data:`GRID_MAG` >= v (rounded to 1e-9 first: 6.3 stays 6.3)."""
    return round(math.ceil(round(v / GRID_MAG, 9)) * GRID_MAG, 6)


def _fmt_mag(v: float) -> str:
    """6.9 -> "6.9", 7.0 -> "7.0", 7.25 -> "7.25"."""
    return f"{v:.1f}" if round(v, 1) == v else f"{v:g}"


def _grid_down(v: float) -> float:
    return round(math.floor(round(v / GRID_MAG, 9)) * GRID_MAG, 6)


# ============================================================================================ the sensor
def sensor_limit_v(sensor, k_sigma: float = 5.0, min_pixels: int = 3, threshold_adu: float = 0.0) -> float | None:
    """Faintest Johnson V a simulated sensor detects (:class:`~dualsight.kernels.sensor_config.SensorConfig`
    with the detector's ``k_sigma``, ``min_pixels``, ``threshold_adu``), None when unbounded (no noise).

    A star of magnitude V gives F(V) = ``zero_mag_rate_e_per_s`` 10^(-0.4 V) ``exposure_s`` electrons
    (:func:`~dualsight.kernels.sensor_config.flux_from_magnitude`).  Centred on a pixel, its Gaussian PSF
    (sigma s = ``psf_sigma_px``) puts the fraction p_ab = q_a q_b in pixel (a, b) from the centre, with
    q_0 = 2 Phi(1/(2s)) - 1 and q_a = Phi((|a| + 1/2)/s) - Phi((|a| - 1/2)/s); p_m is the ``min_pixels``-th
    largest of them (the detector drops smaller blobs).  The sky noise the detector measures, in electrons,
    is sigma_e = sqrt(read_noise^2 + base_e [shot noise on] + gain^2 / 12 [quantised]) (base_e = dark
    current x exposure + sky background); the detector's threshold above the background, in electrons, is
    T = max(k_sigma sigma_e, threshold_adu gain, gain [quantised: at least one ADU step]).  The star is
    detected when F(V) p_m > T, so

        V_sensor = -2.5 log10(T / (zero_mag_rate_e_per_s exposure_s p_m)).

    The star's own shot noise and the pixel phase (a star between pixels spreads its light, about 0.5 mag
    fainter at s ~ 0.8) are left out: this is the faintest V detected at best, a cap, not a promise.
    With no noise, no ADU step and no absolute threshold the sensor sees every star: None.
    """
    s = float(sensor.psf_sigma_px)
    phi = lambda x: 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))          # noqa: E731
    r = max(3, int(math.ceil(4 * s)) + 1)
    q = np.array([phi((abs(a) + 0.5) / s) - phi((abs(a) - 0.5) / s) for a in range(-r, r + 1)])
    p = np.sort(np.outer(q, q).ravel())[::-1]
    p_m = float(p[min(max(int(min_pixels), 1), p.size) - 1])
    gauss = float(sensor.read_noise_e) ** 2 + (float(sensor.base_e) if sensor.shot_noise else 0.0)
    gain = float(sensor.gain_e_per_adu)
    sigma_e = math.sqrt(gauss + (gain * gain / 12.0 if sensor.quantize else 0.0)) if gauss > 0 else 0.0
    T = max(float(k_sigma) * sigma_e, float(threshold_adu) * gain, gain if sensor.quantize else 0.0)
    rate = float(sensor.zero_mag_rate_e_per_s) * float(sensor.exposure_s) * p_m
    if rate <= 0:
        return -math.inf                                    # no light: nothing is detected
    if T <= 0:
        return None
    return -2.5 * math.log10(T / rate)


# ============================================================================================ the limit
@dataclass(frozen=True)
class AutoLimit:
    """What :func:`auto_limit` chose and why.

    mag_limit : the chosen Johnson V limit (mag, a multiple of :data:`GRID_MAG`).
    stars_per_field : mean catalog stars per field at ``mag_limit``.
    target : the stars per field aimed at.  wanted : the limit the target alone asks for (mag).
    field_sr : the field's solid angle (sr).  field_deg : (horizontal, vertical) size (deg).
    capped_by : None (the target decided), "sensor", "completeness", "catalog" (the counts' own cut) or
        "range" (:data:`~dualsight.catalogs.stars.MAG_LIMIT_RANGE`); "min_stars" when raised to
        :data:`~dualsight.catalogs.stars.MIN_STARS` stars over the sky.
    sensor_v, complete_v : the caps given (mag; sensor_v None = unknown).
    """

    mag_limit: float
    stars_per_field: float
    target: float
    wanted: float
    field_sr: float
    field_deg: tuple[float, float]
    capped_by: str | None
    sensor_v: float | None
    complete_v: float

    def describe(self) -> str:
        """One line, e.g. ``catalog to V 7.0 (auto: 37.0 stars per 11.4 x 8.6 deg field)``."""
        w, h = self.field_deg
        why = f"auto: {self.stars_per_field:.1f} stars per {w:.1f} x {h:.1f} deg field"
        if self.capped_by == "sensor":
            why += f"; capped by the sensor's faintest detectable V {self.sensor_v:.2f} (target {self.target:g})"
        elif self.capped_by == "completeness":
            why += f"; capped at the catalog's completeness V {self.complete_v:g} (target {self.target:g} " \
                   f"needs V {self.wanted:.1f})"
        elif self.capped_by in ("catalog", "range"):
            why += f"; capped by the catalog's faintest V (target {self.target:g} needs V {self.wanted:.1f})"
        elif self.capped_by == "min_stars":
            why += "; raised to hold the catalog's minimum number of stars"
        return f"catalog to V {_fmt_mag(self.mag_limit)} ({why})"


def auto_limit(camera, counts=None, target_per_field: float = DEFAULT_TARGET, *, sensor_v: float | None = None,
               complete_v: float = HIPPARCOS_COMPLETE_V, field_sr: float | None = None) -> AutoLimit:
    """:func:`auto_mag_limit` with its reasons (:class:`AutoLimit`); same arguments."""
    from dualsight.catalogs.stars import MAG_LIMIT_RANGE, MIN_STARS         # pyarrow: deferred

    if not (isinstance(target_per_field, (int, float)) and math.isfinite(target_per_field) and target_per_field > 0):
        raise ValueError(f"target_per_field must be a finite number > 0, got {target_per_field!r}")
    omega = field_solid_angle(camera) if field_sr is None else float(field_sr)
    if not (omega > 0 and math.isfinite(omega)):
        raise ValueError(f"the field's solid angle must be > 0 sr, got {omega!r}")
    v, cut = _magnitudes(counts)
    if v.size == 0:
        raise ValueError("no star magnitudes to count")
    lo, hi = MAG_LIMIT_RANGE
    # the target: N(<= V) >= target 4 pi / Omega, N counting stars with V <= limit (as the catalog keeps them)
    need = int(math.ceil(target_per_field * 4.0 * math.pi / omega - 1e-9))
    wanted = _grid_up(float(v[min(max(need, 1), v.size) - 1])) if need <= v.size else math.inf
    caps = [(hi, "range"), (complete_v, "completeness")]
    if cut is not None:
        caps.append((cut, "catalog"))
    if sensor_v is not None:
        caps.append((max(float(sensor_v), lo), "sensor"))
    mag, capped = max(lo, wanted), None
    for c, why in caps:                                     # the tightest cap wins (first listed on a tie)
        if _grid_down(c) < mag:
            mag, capped = _grid_down(c), why
    floor = _grid_up(float(v[min(MIN_STARS, v.size) - 1]))
    if mag < floor:
        mag, capped = floor, "min_stars"
    mag = min(max(mag, lo), hi)
    return AutoLimit(mag_limit=float(mag), stars_per_field=stars_per_field(v, mag, omega),
                     target=float(target_per_field), wanted=float(wanted), field_sr=omega,
                     field_deg=field_size_deg(camera), capped_by=capped, sensor_v=sensor_v,
                     complete_v=float(complete_v))


def auto_mag_limit(camera, counts=None, target_per_field: float = DEFAULT_TARGET, *, sensor_v: float | None = None,
                   complete_v: float = HIPPARCOS_COMPLETE_V, field_sr: float | None = None) -> float:
    """The catalog magnitude limit (Johnson V) for ``camera`` (module docstring).

    Parameters
    ----------
    camera : :class:`~dualsight.scene.camera.Camera` (its field: :func:`field_solid_angle`).
    counts : the catalog's whole-sky magnitudes: None = every hip2 star (:func:`hipparcos_vmag`), a
        :class:`~dualsight.catalogs.stars.StarCatalog` (its ``vmag``; its own cut caps the answer) or an
        array of V (mag), one per star.
    target_per_field : mean catalog stars per field aimed at (> 0).
    sensor_v : faintest V the sensor detects (mag; e.g. :func:`sensor_limit_v`), None = unknown.
    complete_v : V to which the catalog is complete (mag; default :data:`HIPPARCOS_COMPLETE_V`).
    field_sr : the field's solid angle (sr) if already known; None = :func:`field_solid_angle`.

    Returns
    -------
    The smallest multiple of :data:`GRID_MAG` with ``N(<= V) Omega / (4 pi) >= target_per_field``, then
    capped and floored as the module docstring says (float, mag).
    """
    return auto_limit(camera, counts, target_per_field, sensor_v=sensor_v, complete_v=complete_v,
                      field_sr=field_sr).mag_limit


def is_auto(value) -> bool:
    """Whether a ``mag_limit`` setting asks for the automatic limit: None or the string "auto" (any case)."""
    return value is None or (isinstance(value, str) and value.strip().lower() == "auto")


def describe_mag_limit(camera, mag_limit: float, target_per_field: float = HIL_TARGET_PER_FIELD, **kw) -> str:
    """One line saying what a catalog limit gives ``camera``: the :meth:`AutoLimit.describe` line when
    ``mag_limit`` is the automatic limit for ``target_per_field``, else e.g. ``catalog to V 7.5 (50.6 stars
    per 11.4 x 8.6 deg field)``.  ``kw``: the other arguments of :func:`auto_limit`."""
    a = auto_limit(camera, target_per_field=target_per_field, **kw)
    if float(mag_limit) == a.mag_limit:
        return a.describe()
    w, h = a.field_deg
    v, _ = _magnitudes(kw.get("counts"))
    n = stars_per_field(v, float(mag_limit), a.field_sr)
    return f"catalog to V {_fmt_mag(float(mag_limit))} ({n:.1f} stars per {w:.1f} x {h:.1f} deg field)"
