"""Low-precision geocentric Sun and Moon (issue 23, point 1): directions and distances as pure vectorised
functions of time, in the ICRS / GCRS axes (the equator and equinox of J2000, origin the Earth's centre).

Source: *The Astronomical Almanac*, low-precision formulae, Section C ("Sun", precision 0.01 deg in right ascension
and declination, 1950-2050) and Section D ("Moon", 0.3 deg in ecliptic longitude, 0.2 deg in latitude, 0.003 deg
in horizontal parallax, 1950-2050); the same formulae are printed in Montenbruck & Pfleger, *Astronomy on the
Personal Computer*, and in Vallado, *Fundamentals of Astrodynamics*, Algorithms 29 (Sun) and 31 (Moon).  With
n = JD(TT) - 2451545.0 days and T = n / 36525 centuries:

Sun:   L = 280.460 + 0.9856474 n,  g = 357.528 + 0.9856003 n  (deg)
       lambda = L + 1.915 sin g + 0.020 sin 2g,  beta = 0,
       R = 1.00014 - 0.01671 cos g - 0.00014 cos 2g  (au)
Moon:  lambda = 218.32 + 481267.881 T + 6.29 sin(135.0 + 477198.87 T) - 1.27 sin(259.3 - 413335.36 T)
                + 0.66 sin(235.7 + 890534.22 T) + 0.21 sin(269.9 + 954397.74 T)
                - 0.19 sin(357.5 + 35999.05 T) - 0.11 sin(186.5 + 966404.03 T)
       beta   = 5.13 sin(93.3 + 483202.02 T) + 0.28 sin(228.2 + 960400.89 T)
                - 0.28 sin(318.3 + 6003.15 T) - 0.17 sin(217.6 - 407332.21 T)
       pi     = 0.9508 + 0.0518 cos(135.0 + 477198.87 T) + 0.0095 cos(259.3 - 413335.36 T)
                + 0.0078 cos(235.7 + 890534.22 T) + 0.0028 cos(269.9 + 954397.74 T)
       distance = R_EARTH / sin(pi)
Both:  ecliptic of date -> equator of date by the obliquity eps = 23.439 - 0.0000004 n (deg).

The Almanac's coordinates are referred to the equinox *of date*; 40 years of precession move them ~0.56 deg from
the J2000 axes, so this module rotates them to J2000 by the IAU 1976 precession angles (Lieske et al., A&A 58, 1,
1977: zeta, z, theta; P = R3(-z) R2(theta) R3(-zeta) maps J2000 to the mean equator of date, its transpose back).
Nutation (< 0.005 deg) and the Sun's annual aberration (0.0057 deg, already in the Almanac's lambda) are left in
the error budget.  Measured against astropy ``get_body(..., GCRS)`` over 1,000 random times 2000-2040
(tests/test_ephemeris.py, seed 7): Sun max 0.011 deg (median 0.0027), Moon max 0.31 deg (median 0.086), distances
Sun 8.5e-5 and Moon 3.3e-3 relative.

Times: JD in TT; :func:`jd_tt_from_unix` turns POSIX seconds (UTC) into it with TT - UTC = 69.184 s (TAI - UTC =
37 s since 2017; the 5 s less of 2000-2016 move the Moon by < 0.001 deg).  Units: km, degrees only inside the
formulae.  No astropy here (it is the tests' truth).
"""

from __future__ import annotations

import numpy as np

__all__ = ["AU_KM", "R_EARTH_KM", "TT_MINUS_UTC_S", "jd_tt_from_unix", "precession_to_j2000", "sun_position",
           "moon_position"]

AU_KM = 149597870.7
"""Astronomical unit (km, IAU 2012)."""
R_EARTH_KM = 6378.137
"""Earth's equatorial radius (km, WGS-84), the Almanac's unit of the Moon's parallax."""
TT_MINUS_UTC_S = 69.184
"""TT - UTC (s) since 2017-01-01 (TAI - UTC = 37 s, TT - TAI = 32.184 s)."""
_J2000 = 2451545.0
_ARCSEC = np.pi / (180.0 * 3600.0)


def jd_tt_from_unix(unix_s) -> np.ndarray:
    """Julian date (TT) of POSIX times ``unix_s`` (s since 1970-01-01 UTC, any shape), TT - UTC = 69.184 s."""
    return (np.asarray(unix_s, np.float64) + TT_MINUS_UTC_S) / 86400.0 + 2440587.5


def precession_to_j2000(jd_tt) -> np.ndarray:
    """(..., 3, 3) rotations from the mean equator and equinox of date to J2000 (IAU 1976, Lieske et al. 1977):
    ``v_J2000 = P @ v_date``."""
    T = (np.asarray(jd_tt, np.float64) - _J2000) / 36525.0
    zeta = (2306.2181 * T + 0.30188 * T ** 2 + 0.017998 * T ** 3) * _ARCSEC
    z = (2306.2181 * T + 1.09468 * T ** 2 + 0.018203 * T ** 3) * _ARCSEC
    theta = (2004.3109 * T - 0.42665 * T ** 2 - 0.041833 * T ** 3) * _ARCSEC
    cz, sz, cZ, sZ, ct, st = np.cos(zeta), np.sin(zeta), np.cos(z), np.sin(z), np.cos(theta), np.sin(theta)
    # P(J2000 -> date) = R3(-z) R2(theta) R3(-zeta) written out (Lieske Eq. 12); its transpose goes back
    m = np.stack([
        np.stack([cZ * ct * cz - sZ * sz, -cZ * ct * sz - sZ * cz, -cZ * st], -1),
        np.stack([sZ * ct * cz + cZ * sz, -sZ * ct * sz + cZ * cz, -sZ * st], -1),
        np.stack([st * cz, -st * sz, ct], -1),
    ], -2)
    return np.swapaxes(m, -1, -2)


def _ecliptic_of_date_to_j2000(lam_deg, beta_deg, dist_km, n_days) -> np.ndarray:
    """(..., 3) J2000 equatorial position (km) of ecliptic-of-date longitude / latitude (deg) and distance."""
    lam, beta = np.radians(lam_deg), np.radians(beta_deg)
    eps = np.radians(23.439 - 0.0000004 * n_days)
    x = np.cos(beta) * np.cos(lam)
    y_e, z_e = np.cos(beta) * np.sin(lam), np.sin(beta)
    y = np.cos(eps) * y_e - np.sin(eps) * z_e
    z = np.sin(eps) * y_e + np.cos(eps) * z_e
    v_date = np.stack([x, y, z], -1) * np.asarray(dist_km)[..., None]
    return np.einsum("...ij,...j->...i", precession_to_j2000(n_days + _J2000), v_date)


def sun_position(jd_tt) -> np.ndarray:
    """(..., 3) geocentric position of the Sun (km, GCRS/ICRS axes) at Julian dates ``jd_tt`` (TT, any shape).

    The Astronomical Almanac's low-precision Sun (module doc): 0.01 deg, 1950-2050."""
    n = np.asarray(jd_tt, np.float64) - _J2000
    L = 280.460 + 0.9856474 * n
    g = np.radians(357.528 + 0.9856003 * n)
    lam = L + 1.915 * np.sin(g) + 0.020 * np.sin(2 * g)
    R = (1.00014 - 0.01671 * np.cos(g) - 0.00014 * np.cos(2 * g)) * AU_KM
    return _ecliptic_of_date_to_j2000(lam, np.zeros_like(lam), R, n)


def moon_position(jd_tt) -> np.ndarray:
    """(..., 3) geocentric position of the Moon (km, GCRS/ICRS axes) at Julian dates ``jd_tt`` (TT, any shape).

    The Astronomical Almanac's low-precision Moon (module doc): 0.3 deg, 1950-2050; distance from the
    horizontal parallax, R_EARTH_KM / sin(pi)."""
    n = np.asarray(jd_tt, np.float64) - _J2000
    T = n / 36525.0

    def s(a, b):
        return np.sin(np.radians(a + b * T))

    def c(a, b):
        return np.cos(np.radians(a + b * T))

    lam = (218.32 + 481267.881 * T + 6.29 * s(135.0, 477198.87) - 1.27 * s(259.3, -413335.36)
           + 0.66 * s(235.7, 890534.22) + 0.21 * s(269.9, 954397.74) - 0.19 * s(357.5, 35999.05)
           - 0.11 * s(186.5, 966404.03))
    beta = (5.13 * s(93.3, 483202.02) + 0.28 * s(228.2, 960400.89) - 0.28 * s(318.3, 6003.15)
            - 0.17 * s(217.6, -407332.21))
    par = (0.9508 + 0.0518 * c(135.0, 477198.87) + 0.0095 * c(259.3, -413335.36) + 0.0078 * c(235.7, 890534.22)
           + 0.0028 * c(269.9, 954397.74))
    return _ecliptic_of_date_to_j2000(lam, beta, R_EARTH_KM / np.sin(np.radians(par)), n)
