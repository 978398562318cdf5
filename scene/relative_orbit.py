"""Relative motion near a circular orbit: Clohessy-Wiltshire (issue 23, point 4).

A circular reference orbit (the target's) of radius ``a = R_E + altitude`` about a spherical Earth
(``MU_EARTH`` = 3.986004418e14 m^3/s^2, ``R_EARTH`` = 6378137 m), mean motion ``n = sqrt(mu / a^3)`` (rad/s).
The chaser's state relative to the target, ``(x, y, z, vx, vy, vz)`` (m, m/s), lives in the target's Hill frame
(LVLH): x radial (away from the Earth), y along-track (with the velocity), z cross-track (along the orbit normal
``h = r x v``).  Its linearised motion (Clohessy & Wiltshire, J. Aerospace Sci. 27(9), 1960; Curtis, *Orbital
Mechanics for Engineering Students*, Sec. 7.4-7.5; Vallado, *Fundamentals of Astrodynamics*, Sec. 6.8):

    x'' = 3 n^2 x + 2 n y',    y'' = -2 n x',    z'' = -n^2 z,

solved in closed form by the state transition matrix ``Phi(t)`` (:func:`cw_stm`, Curtis Eq. 7.53 / Vallado
Eq. 6-66 with s = sin nt, c = cos nt):

    Phi_rr = [[4 - 3c, 0, 0], [6 (s - nt), 1, 0], [0, 0, c]]
    Phi_rv = [[s / n, 2 (1 - c) / n, 0], [-2 (1 - c) / n, (4 s - 3 nt) / n, 0], [0, 0, s / n]]
    Phi_vr = [[3 n s, 0, 0], [-6 n (1 - c), 0, 0], [0, 0, -n s]]
    Phi_vv = [[c, 2 s, 0], [-2 s, 4 c - 3, 0], [0, 0, c]]

Impulsive manoeuvres (delta-v in the Hill frame at given times) add to the velocity at their instant; a state at a
time equal to a manoeuvre's is the state just after it.

The Hill frame's axes in the inertial frame (ICRS / GCRS: z the Earth's pole, x the equinox) at time t follow from
the reference orbit's position and velocity: ``x^ = r / |r|``, ``z^ = (r x v) / |r x v|``, ``y^ = z^ x x^``.  The
orbit is placed by inclination i, right ascension of the ascending node Omega and argument of latitude u(t) =
u0 + n t (Vallado Sec. 2.5, circular orbit: ``r = a (cos O cos u - sin O sin u cos i, sin O cos u + cos O sin u
cos i, sin u sin i)``).

Units: metres, seconds, radians.  Pure numpy, no loop over states or times (the manoeuvres, a handful, are
visited in order).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MU_EARTH", "R_EARTH", "CircularOrbit", "cw_stm", "propagate", "hill_to_icrs", "hill_state_to_icrs"]

MU_EARTH = 3.986004418e14
"""Earth's gravitational parameter (m^3/s^2, EGM96 / WGS-84)."""
R_EARTH = 6378137.0
"""Earth's equatorial radius (m, WGS-84)."""


@dataclass(frozen=True)
class CircularOrbit:
    """A circular reference orbit: ``altitude_m`` above ``R_EARTH``, ``inclination_rad``, ``raan_rad`` (right
    ascension of the ascending node) and ``arg_lat_rad`` (argument of latitude, from the node) at t = 0."""

    altitude_m: float
    inclination_rad: float = 0.0
    raan_rad: float = 0.0
    arg_lat_rad: float = 0.0

    @property
    def radius_m(self) -> float:
        """Orbit radius a = R_EARTH + altitude (m)."""
        return R_EARTH + float(self.altitude_m)

    @property
    def mean_motion(self) -> float:
        """Mean motion n = sqrt(mu / a^3) (rad/s)."""
        return math.sqrt(MU_EARTH / self.radius_m ** 3)

    @property
    def period_s(self) -> float:
        """Orbital period 2 pi / n (s)."""
        return 2.0 * math.pi / self.mean_motion


def cw_stm(n: float, t) -> np.ndarray:
    """Clohessy-Wiltshire state transition matrices.

    n : mean motion (rad/s); t : scalar or (T,) elapsed times (s, any sign).  Returns (T, 6, 6) (or (6, 6) for a
    scalar t) with ``x(t0 + t) = Phi(t) x(t0)`` for Hill-frame states (x, y, z, vx, vy, vz) (m, m/s)
    (Curtis Eq. 7.53; Vallado Eq. 6-66)."""
    t = np.asarray(t, np.float64)
    nt = n * t
    s, c = np.sin(nt), np.cos(nt)
    z = np.zeros_like(nt)
    o = np.ones_like(nt)
    rows = [
        [4 - 3 * c, z, z, s / n, 2 * (1 - c) / n, z],
        [6 * (s - nt), o, z, -2 * (1 - c) / n, (4 * s - 3 * nt) / n, z],
        [z, z, c, z, z, s / n],
        [3 * n * s, z, z, c, 2 * s, z],
        [-6 * n * (1 - c), z, z, -2 * s, 4 * c - 3, z],
        [z, z, -n * s, z, z, c],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def propagate(states, times, n: float, *, t0: float = 0.0, dv_times=None, dv=None) -> np.ndarray:
    """Hill-frame states over time under Clohessy-Wiltshire motion with impulsive manoeuvres.

    states : (N, 6) at ``t0`` (m, m/s); times : (T,) s, each >= t0; n : mean motion (rad/s); dv_times : (M,) s and
    dv : (M, 3) m/s (Hill frame) the manoeuvres of every state (the same for all N), or (N, M, 3) per state.
    Returns (N, T, 6); at a time equal to a manoeuvre's the state includes it."""
    x0 = np.atleast_2d(np.asarray(states, np.float64))
    times = np.asarray(times, np.float64)
    if np.any(times < t0):
        raise ValueError("propagate: times before t0")
    tm = np.zeros(0) if dv_times is None else np.asarray(dv_times, np.float64).reshape(-1)
    dvs = np.zeros((x0.shape[0], 0, 3)) if dv is None else np.asarray(dv, np.float64)
    if dvs.ndim == 2:
        dvs = np.broadcast_to(dvs[None], (x0.shape[0],) + dvs.shape)
    order = np.argsort(tm, kind="stable")
    tm, dvs = tm[order], dvs[:, order]
    # state at the start of each segment: t0, then just after each manoeuvre
    seg_t = np.concatenate([[t0], tm])
    seg_x = [x0]
    for k in range(tm.size):
        xk = seg_x[-1] @ cw_stm(n, tm[k] - seg_t[k]).T
        xk = xk.copy()
        xk[:, 3:] += dvs[:, k]
        seg_x.append(xk)
    seg_x = np.stack(seg_x, 1)                                    # (N, M+1, 6)
    seg = np.searchsorted(tm, times, side="right")                # (T,) segment of each time
    Phi = cw_stm(n, times - seg_t[seg])                           # (T, 6, 6)
    return np.einsum("tij,ntj->nti", Phi, seg_x[:, seg])


def _reference_rv(orbit: CircularOrbit, t):
    """(T, 3) position (m) and velocity (m/s) of the reference orbit in the inertial frame at times t (s)."""
    t = np.atleast_1d(np.asarray(t, np.float64))
    a, n = orbit.radius_m, orbit.mean_motion
    u = orbit.arg_lat_rad + n * t
    cO, sO = math.cos(orbit.raan_rad), math.sin(orbit.raan_rad)
    ci, si = math.cos(orbit.inclination_rad), math.sin(orbit.inclination_rad)
    cu, su = np.cos(u), np.sin(u)
    P = np.array([cO, sO, 0.0])              # towards the ascending node
    Q = np.array([-sO * ci, cO * ci, si])    # 90 deg ahead in the orbit plane
    r = a * (cu[:, None] * P + su[:, None] * Q)
    v = a * n * (-su[:, None] * P + cu[:, None] * Q)
    return r, v


def hill_to_icrs(orbit: CircularOrbit, t) -> np.ndarray:
    """(T, 3, 3) rotations from the Hill frame to the inertial frame at times t ((T,) s): columns are x^ (radial),
    y^ (along-track), z^ (orbit normal) in ICRS, so ``v_icrs = R @ v_hill``."""
    r, v = _reference_rv(orbit, t)
    xh = r / np.linalg.norm(r, axis=-1, keepdims=True)
    h = np.cross(r, v)
    zh = h / np.linalg.norm(h, axis=-1, keepdims=True)
    yh = np.cross(zh, xh)
    return np.stack([xh, yh, zh], -1)


def hill_state_to_icrs(orbit: CircularOrbit, t, states) -> np.ndarray:
    """(T, 6) relative states in the inertial frame (not rotating) from (T, 6) Hill-frame states at times (T,) s:
    ``rho_I = R rho``, ``rho_I' = R (rho' + omega x rho)`` with omega = (0, 0, n) the Hill frame's rate."""
    R = hill_to_icrs(orbit, t)
    x = np.asarray(states, np.float64)
    w = np.array([0.0, 0.0, orbit.mean_motion])
    vel = x[:, 3:] + np.cross(np.broadcast_to(w, x[:, :3].shape), x[:, :3])
    return np.concatenate([np.einsum("tij,tj->ti", R, x[:, :3]), np.einsum("tij,tj->ti", R, vel)], -1)
