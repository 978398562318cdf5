"""Each case's place in orbit and time, and what its camera sees of the Sun, Earth and Moon (issue 23, point 1).

Stage of the star job with ``[target.environment]`` (``scene/environment_config.EnvironmentConfig``), before the target's
draw (``scene/target_in_field.draw_targets`` takes the Sun from here).  Per case, from its own generator
``default_rng([seed, i])`` after the star job's four draws and the target's nine (so the attitude, the noise seed
and the target of every case are those of the same run without an environment): the epoch (uniform in
``epoch_utc``), the right ascension of the ascending node and the argument of latitude (each uniform in
[0, 2 pi)) of a point on the circular orbit of ``altitude_km`` and ``inclination_deg`` (Vallado, *Fundamentals of
Astrodynamics*, Sec. 2.5: ``r = a (cos O cos u - sin O sin u cos i, sin O cos u + cos O sin u cos i,
sin u sin i)``).  Then the Sun and Moon at the epoch (``scene/ephemeris.py``) and the boresight's keep-out and the
Earth's shadow (``scene/keepout.py``); the boresight is the camera's +z axis in ICRS, row 2 of the attitude
``A`` (ICRS -> camera).

Units: km, s, rad.  Vectorised over the cases.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dualsight.scene.environment_config import EnvironmentConfig
from dualsight.scene.case_rng import streams as case_streams
from dualsight.scene.ephemeris import R_EARTH_KM, jd_tt_from_unix, moon_position, sun_position
from dualsight.scene.keepout import KeepOut, keep_out
from dualsight.scene.target_in_field import STAR_JOB_DRAWS

__all__ = ["DRAWS_BEFORE", "CaseEnvironment", "orbit_position", "draw_environment"]

DRAWS_BEFORE = STAR_JOB_DRAWS + 9
"""Raw 64-bit draws each case takes before its environment's: the star job's four and the target's nine
(``scene/target_in_field.draw_targets``: presence, range, x, y, three for its attitude, phase, azimuth)."""


@dataclass(frozen=True)
class CaseEnvironment:
    """Each case's environment: epoch_unix_s (B,) POSIX seconds (UTC); r_km (B, 3) spacecraft position (GCRS);
    sun_km, moon_km (B, 3) geocentric Sun and Moon (km); sun_dir (B, 3) unit vector from the spacecraft to the
    Sun (ICRS); view: the boresight's :class:`~dualsight.scene.keepout.KeepOut`."""

    epoch_unix_s: np.ndarray
    r_km: np.ndarray
    sun_km: np.ndarray
    moon_km: np.ndarray
    sun_dir: np.ndarray
    view: KeepOut


def orbit_position(radius_km: float, inclination_rad: float, raan_rad, arg_lat_rad) -> np.ndarray:
    """(B, 3) position (km, inertial) on a circular orbit of ``radius_km`` and inclination at nodes ``raan_rad``
    and arguments of latitude ``arg_lat_rad`` ((B,) rad; Vallado Sec. 2.5)."""
    O, u = np.asarray(raan_rad, np.float64), np.asarray(arg_lat_rad, np.float64)
    ci, si = math.cos(inclination_rad), math.sin(inclination_rad)
    return radius_km * np.stack([np.cos(O) * np.cos(u) - np.sin(O) * np.sin(u) * ci,
                                 np.sin(O) * np.cos(u) + np.cos(O) * np.sin(u) * ci,
                                 np.sin(u) * si], -1)


def draw_environment(cfg: EnvironmentConfig, seed: int, case_ids, A_true, sun_keepout_rad: float) -> CaseEnvironment:
    """The environment of each case from ``default_rng([seed, case_id])`` (its three draws after
    :data:`DRAWS_BEFORE`: epoch, node, argument of latitude) and the view along each attitude's boresight.

    A_true : (B, 3, 3) ICRS -> camera; sun_keepout_rad : the Sun's keep-out half-angle (the target's)."""
    rng = case_streams(seed, np.asarray(case_ids, np.int64))
    for _ in range(DRAWS_BEFORE):
        rng.next_uint64()
    u_epoch, u_node, u_lat = rng.random(), rng.random(), rng.random()
    t0, t1 = cfg.epoch_unix_s
    epoch = t0 + (t1 - t0) * u_epoch
    r = orbit_position(R_EARTH_KM + cfg.altitude_km, math.radians(cfg.inclination_deg), 2 * np.pi * u_node,
                       2 * np.pi * u_lat)
    jd = jd_tt_from_unix(epoch)
    sun, moon = sun_position(jd), moon_position(jd)
    boresight = np.asarray(A_true, np.float64)[:, 2, :]
    view = keep_out(r, boresight, sun, moon, sun_half_rad=sun_keepout_rad,
                    earth_half_rad=math.radians(cfg.earth_keepout_deg),
                    moon_half_rad=math.radians(cfg.moon_keepout_deg))
    to_sun = sun - r
    return CaseEnvironment(epoch, r, sun, moon, to_sun / np.linalg.norm(to_sun, axis=-1, keepdims=True), view)
