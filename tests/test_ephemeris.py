"""Low-precision Sun and Moon (scene/ephemeris.py, issue 23 point 1) against astropy's ``get_body`` (GCRS, the
built-in ephemeris: VSOP87 Earth, ELP2000-82 Moon) over 1,000 random times 2000-2040, and the precession matrix
against astropy's own precession (FK5 of date -> ICRS-aligned J2000)."""

import warnings

import numpy as np
import pytest

from dualsight.scene import ephemeris as ep

UNIX_2000, UNIX_2040 = 946684800.0, 2208988800.0


@pytest.fixture(scope="module")
def astropy_truth():
    from astropy.utils import iers
    iers.conf.auto_download = False
    from astropy.coordinates import get_body
    from astropy.time import Time

    u = np.random.default_rng(7).uniform(UNIX_2000, UNIX_2040, 1000)
    t = Time(u, format="unix", scale="utc")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")        # ERFA's "dubious year" after the last known leap second
        out = {b: get_body(b, t).cartesian.xyz.to("km").value.T for b in ("sun", "moon")}
        out["jd_tt"] = t.tt.jd
    out["unix"] = u
    return out


def _angle_deg(a, b):
    c = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def test_tt_from_unix(astropy_truth):
    # TT - UTC = 69.184 s since 2017; 64.184-69.184 s over 2000-2016: within 5 s of astropy's leap-second table
    d = (ep.jd_tt_from_unix(astropy_truth["unix"]) - astropy_truth["jd_tt"]) * 86400.0
    assert np.all(np.abs(d) <= 5.001)
    late = astropy_truth["unix"] > 1483228800.0 + 1.0          # after 2017-01-01
    assert np.all(np.abs(d[late]) < 1e-3)


def test_sun_direction_and_distance(astropy_truth):
    m = ep.sun_position(ep.jd_tt_from_unix(astropy_truth["unix"]))
    c = astropy_truth["sun"]
    ang = _angle_deg(m, c)
    assert ang.max() < 0.012                   # Almanac: 0.01 deg (measured max 0.011, median 0.0027)
    assert np.median(ang) < 0.004
    assert np.max(np.abs(np.linalg.norm(m, axis=1) / np.linalg.norm(c, axis=1) - 1)) < 2e-4


def test_moon_direction_and_distance(astropy_truth):
    m = ep.moon_position(ep.jd_tt_from_unix(astropy_truth["unix"]))
    c = astropy_truth["moon"]
    ang = _angle_deg(m, c)
    assert ang.max() < 0.35                    # Almanac: 0.3 deg in longitude (measured max 0.31, median 0.086)
    assert np.median(ang) < 0.12
    assert np.max(np.abs(np.linalg.norm(m, axis=1) / np.linalg.norm(c, axis=1) - 1)) < 5e-3


def test_precession_against_astropy():
    from astropy import units as u
    from astropy.coordinates import FK5, SkyCoord
    from astropy.time import Time

    rng = np.random.default_rng(3)
    v = rng.normal(size=(50, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    jd = 2451545.0 + 365.25 * 40 * rng.random(50)
    ra, dec = np.degrees(np.arctan2(v[:, 1], v[:, 0])), np.degrees(np.arcsin(v[:, 2]))
    of_date = SkyCoord(ra * u.deg, dec * u.deg, frame=FK5(equinox=Time(jd, format="jd", scale="tt")))
    truth = of_date.transform_to(FK5(equinox="J2000")).cartesian.xyz.value.T
    mine = np.einsum("bij,bj->bi", ep.precession_to_j2000(jd), v)
    assert _angle_deg(mine, truth).max() < 1e-4      # astropy: IAU 2006 precession, within 0.12 arcsec of 1976
    assert _angle_deg(v, truth).max() > 0.1          # the test would see a missing precession
