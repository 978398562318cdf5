"""Sun, Earth and Moon keep-out of a star camera in orbit, and the Earth's shadow (issue 23, point 1).

For a spacecraft at ``r`` (km, GCRS: origin the Earth's centre, ICRS axes) with camera boresights ``b`` (ICRS unit
vectors) and the geocentric Sun and Moon (km; ``scene/ephemeris.py``), batched over B frames:

* Sun and Moon angles: between ``b`` and the direction *from the spacecraft*, ``(X - r) / |X - r|``: the Moon's
  parallax from low Earth orbit reaches asin(|r| / |moon|) ~ 1 deg, the Sun's 10 arcsec.
* Earth: its angular radius seen from the spacecraft ``rho = asin(R_E / |r|)``, the angle from ``b`` to the Earth's
  centre ``theta = angle(b, -r)``, and the angle from ``b`` to the nearest point of the Earth's limb,
  ``theta - rho`` (negative: the boresight is on the Earth's disk).
* keep-out flags: Sun / Moon angle < its half-angle, Earth limb angle < its half-angle (cones about the boresight).
* the lit Earth in the Earth keep-out cone: whether any sunlit point of the Earth's visible disk lies within the
  Earth half-angle of the boresight.  The disk is sampled on a fixed grid of lines of sight (:data:`LIT_RINGS`
  rings x :data:`LIT_AZIMUTHS` azimuths, the limb included) plus the disk's point nearest the boresight; each line
  of sight meets the sphere at a surface point, lit when its outward normal has a positive component towards the
  Sun.  A lit sliver narrower than the grid (about rho / 16 across) can be missed.
* shadow: conical (Vallado, *Fundamentals of Astrodynamics*, Sec. 5.3, the umbra / penumbra cones), by the
  apparent disks seen from the spacecraft: the Sun's angular radius ``a_s = asin(R_SUN / |s - r|)``, the Earth's
  ``rho``, their separation ``theta_s``; umbra when ``rho > a_s`` and ``theta_s <= rho - a_s`` (no part of the
  Sun visible), penumbra when ``theta_s < rho + a_s`` otherwise.  A spherical Earth (R_E = 6378.137 km, no
  atmosphere: refraction and the ~50 km of twilight are left out).

Half-angle defaults (``scene/environment_config.EnvironmentConfig``): Sun 30 deg, Earth limb 20 deg, Moon 10 deg, chosen
as the usual order of small star trackers' exclusion angles (Sun 25-45 deg, lit Earth 15-30 deg, Moon 5-15 deg),
not a particular data sheet's.  Units: km, radians.  Pure numpy, no loop over frames or samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.scene.ephemeris import R_EARTH_KM

__all__ = ["R_SUN_KM", "LIT_RINGS", "LIT_AZIMUTHS", "KeepOut", "angle_between", "earth_disk_lit_in_cone",
           "keep_out"]

R_SUN_KM = 695700.0
"""The Sun's nominal radius (km, IAU 2015 Resolution B3)."""
LIT_RINGS = 12
"""Rings of lines of sight (from nadir to the limb) sampling the Earth's visible disk."""
LIT_AZIMUTHS = 48
"""Azimuths per ring."""


@dataclass(frozen=True)
class KeepOut:
    """Each frame's view of the Sun, Earth and Moon (all (B,)).

    sun_angle_rad, moon_angle_rad: boresight to the body's centre seen from the spacecraft; earth_limb_angle_rad:
    boresight to the nearest point of the limb (negative on the disk); earth_radius_rad: the Earth's angular radius;
    earth_lit_in_cone: a sunlit point of the Earth within the Earth half-angle; sun_keepout, earth_keepout,
    moon_keepout: inside the half-angle cones; umbra, penumbra: the spacecraft in the Earth's shadow (no Sun / part
    of it)."""

    sun_angle_rad: np.ndarray
    moon_angle_rad: np.ndarray
    earth_limb_angle_rad: np.ndarray
    earth_radius_rad: np.ndarray
    earth_lit_in_cone: np.ndarray
    sun_keepout: np.ndarray
    earth_keepout: np.ndarray
    moon_keepout: np.ndarray
    umbra: np.ndarray
    penumbra: np.ndarray


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def angle_between(a, b) -> np.ndarray:
    """(...,) angle (rad) between vectors a and b (..., 3) (any lengths), by atan2 of |a x b| and a . b (accurate
    near 0 and pi)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...k,...k->...", a, b))


def earth_disk_lit_in_cone(r_km, boresight, sun_dir, half_rad: float) -> np.ndarray:
    """(B,) bool: a sunlit point of the Earth's visible disk lies within ``half_rad`` of the boresight.

    r_km (B, 3) spacecraft (GCRS, km); boresight (B, 3) unit; sun_dir (B, 3) unit vectors from the Earth's centre
    towards the Sun.  Sampled lines of sight (module doc)."""
    r = np.asarray(r_km, np.float64)
    b = _unit(np.asarray(boresight, np.float64))
    rn = np.linalg.norm(r, axis=-1)
    nadir = -r / rn[:, None]
    rho = np.arcsin(np.clip(R_EARTH_KM / rn, 0.0, 1.0))
    # a frame (p, q) about nadir
    ref = np.where(np.abs(nadir[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    p = _unit(np.cross(nadir, ref))
    q = np.cross(nadir, p)
    frac = np.concatenate([[0.0], np.sqrt((np.arange(1, LIT_RINGS) + 0.0) / (LIT_RINGS - 1))])   # 0 .. 1 (limb)
    phi = 2 * np.pi * np.arange(LIT_AZIMUTHS) / LIT_AZIMUTHS
    alpha = rho[:, None, None] * frac[None, :, None] * (1.0 - 1e-9)                          # (B, K, 1)
    ca, sa = np.cos(alpha), np.sin(alpha)
    d = (ca[..., None] * nadir[:, None, None, :]
         + sa[..., None] * (np.cos(phi)[None, None, :, None] * p[:, None, None, :]
                            + np.sin(phi)[None, None, :, None] * q[:, None, None, :]))
    d = d.reshape(len(r), -1, 3)                                                              # (B, K*M, 3)
    # the disk's point nearest the boresight: the boresight itself on the disk, else the limb towards it
    theta = angle_between(b, nadir)
    w = b - np.cos(theta)[:, None] * nadir
    wn = np.linalg.norm(w, axis=-1, keepdims=True)
    toward = np.where(wn > 1e-12, w / np.maximum(wn, 1e-300), p)          # any direction when b is +-nadir
    near_a = np.minimum(theta, rho * (1.0 - 1e-9))
    d_near = np.cos(near_a)[:, None] * nadir + np.sin(near_a)[:, None] * toward
    d = np.concatenate([d, d_near[:, None]], 1)
    in_cone = np.einsum("bnk,bk->bn", d, b) >= np.cos(half_rad)
    rd = np.einsum("bk,bnk->bn", r, d)
    t = -rd - np.sqrt(np.maximum(rd * rd - (rn * rn - R_EARTH_KM ** 2)[:, None], 0.0))     # first hit of the sphere
    surf = r[:, None, :] + t[..., None] * d
    lit = np.einsum("bnk,bk->bn", surf, np.asarray(sun_dir, np.float64)) > 0.0
    return np.any(in_cone & lit, axis=1)


def keep_out(r_km, boresight, sun_km, moon_km, *, sun_half_rad: float, earth_half_rad: float,
             moon_half_rad: float) -> KeepOut:
    """The Sun, Earth and Moon seen from spacecraft positions ``r_km`` (B, 3) (GCRS, km) along ``boresight``
    (B, 3) ICRS unit vectors, with the geocentric Sun ``sun_km`` and Moon ``moon_km`` (B, 3) (km) and the keep-out
    half-angles (rad).  See the module doc for the geometry."""
    r = np.atleast_2d(np.asarray(r_km, np.float64))
    b = np.atleast_2d(np.asarray(boresight, np.float64))
    sun = np.atleast_2d(np.asarray(sun_km, np.float64))
    moon = np.atleast_2d(np.asarray(moon_km, np.float64))
    to_sun = sun - r
    sun_angle = angle_between(b, to_sun)
    moon_angle = angle_between(b, moon - r)
    rn = np.linalg.norm(r, axis=-1)
    rho = np.arcsin(np.clip(R_EARTH_KM / rn, 0.0, 1.0))
    limb = angle_between(b, -r) - rho
    # conical shadow from the apparent disks
    a_s = np.arcsin(np.clip(R_SUN_KM / np.linalg.norm(to_sun, axis=-1), 0.0, 1.0))
    sep = angle_between(to_sun, -r)
    umbra = (rho > a_s) & (sep <= rho - a_s)
    penumbra = ~umbra & (sep < rho + a_s)
    lit = earth_disk_lit_in_cone(r, b, _unit(sun), earth_half_rad)
    return KeepOut(sun_angle, moon_angle, limb, rho, lit, sun_angle < sun_half_rad, limb < earth_half_rad,
                   moon_angle < moon_half_rad, umbra, penumbra)
