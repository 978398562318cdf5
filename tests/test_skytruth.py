"""Truth attitude from time, site and alt/az (scene/skytruth.py), against the plate-solved ESA frames.

Truths: truth.json of the ESA tetra3 frames (an independent lost-in-space solver), textbook sidereal
time (Meeus, Astronomical Algorithms, Eq. 12.4) and Bennett's refraction formula.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dualsight.errors import ConfigError
from dualsight.scene.attitude import radec_to_unit
from dualsight.scene.skytruth import (altaz_from_filename, angle_deg, attitude_from_altaz, boresight_from_altaz,
                                      load_truth_json)
from dualsight.scene.units import angle_between
from helpers import shared_real

TRUTH = shared_real() / "esa_tetra3" / "truth.json"
SITE = dict(lat_deg=52.08, lon_deg=4.37, alt_m=0.0)  # esa_tetra3/README.md: fitted, unpublished site
HARD = "2019-07-29T204726_Alt40_Azi45_Try1.tiff"  # README: poorer solution

ESA_NAMES = sorted(json.loads(TRUTH.read_text())) if TRUTH.exists() else []


@pytest.fixture(scope="module")
def truth() -> dict:
    if not TRUTH.exists():
        pytest.skip(f"ESA tetra3 truth not found at {TRUTH}")
    return load_truth_json(TRUTH)


# ---------------------------------------------------------------------------------------------- truth reader
def test_load_truth_json_types(truth):
    assert len(truth) == 8
    for name, e in truth.items():
        assert name.endswith(".tiff")
        R = e["R_icrs_to_cam"]
        assert isinstance(R, np.ndarray) and R.shape == (3, 3)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
        m = e["matched"]
        assert set(m) == {"row", "col", "ra_deg", "dec_deg", "mag"}
        assert all(isinstance(v, np.ndarray) and v.shape == (e["matches"],) for v in m.values())
        assert np.all((m["row"] >= 0) & (m["row"] <= 768) & (m["col"] >= 0) & (m["col"] <= 1024))


def test_truth_third_row_is_the_boresight(truth):
    """R's third row is the boresight: exactly boresight_from_R_deg (1e-8), and ra/dec to 1e-5 rad for the
    frames where the two solutions agree; the file's ra/dec and R differ by up to 7.4 arcsec (3.6e-5) on
    three frames and by 63 arcsec (3e-4) on the hard frame Alt40_Azi45, so those get looser bounds."""
    for name, e in truth.items():
        row = e["R_icrs_to_cam"][2]
        b_R = radec_to_unit(*np.radians(e["boresight_from_R_deg"]))
        np.testing.assert_allclose(row, b_R, atol=1e-8, err_msg=name)
        b = radec_to_unit(np.radians(e["ra_deg"]), np.radians(e["dec_deg"]))
        tol = 4e-4 if name == HARD else 5e-5
        np.testing.assert_allclose(row, b, atol=tol, err_msg=name)
    tight = [n for n, e in truth.items()
             if np.abs(e["R_icrs_to_cam"][2] - radec_to_unit(np.radians(e["ra_deg"]), np.radians(e["dec_deg"]))).max()
             < 1e-5]
    assert len(tight) >= 4


def test_truth_matched_stars_project_through_R(truth):
    """The matched stars' catalog directions, through R and a 5119 px pinhole centred at (512, 384),
    land on their centroids within 2 px (one pixel ~ 40 arcsec) -- the reader keeps rows/cols/R consistent."""
    for name, e in truth.items():
        m = e["matched"]
        v = radec_to_unit(np.radians(m["ra_deg"]), np.radians(m["dec_deg"])) @ e["R_icrs_to_cam"].T
        f = e["focal_length_px"]
        col = f * v[:, 0] / v[:, 2] + 512.0
        row = f * v[:, 1] / v[:, 2] + 384.0
        err = np.hypot(col - m["col"], row - m["row"])
        assert np.median(err) < (3.0 if name == HARD else 1.0), name


def test_load_truth_json_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_truth_json(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ConfigError, match="JSON"):
        load_truth_json(bad)
    bad.write_text(json.dumps({"a.tiff": {"ra_deg": 1.0, "dec_deg": 2.0}}))
    with pytest.raises(ConfigError, match="R_icrs_to_cam"):
        load_truth_json(bad)
    bad.write_text(json.dumps({"a.tiff": {"ra_deg": 1.0, "dec_deg": 2.0, "R_icrs_to_cam": np.eye(3).tolist(),
                                          "matched": [{"row": 1}]}}))
    with pytest.raises(ConfigError, match=r"a.tiff.matched"):
        load_truth_json(bad)
    bad.write_text(json.dumps({"a.tiff": {"ra_deg": 1.0, "dec_deg": 2.0, "R_icrs_to_cam": (2 * np.eye(3)).tolist()}}))
    with pytest.raises(ConfigError, match="rotation"):
        load_truth_json(bad)


# ---------------------------------------------------------------------------------------------- file names
def test_altaz_from_filename():
    assert altaz_from_filename("2019-07-29T204726_Alt40_Azi-135_Try1.tiff") == ("2019-07-29T20:47:26", 40.0, 225.0)
    assert altaz_from_filename(Path("/x/2019-07-29T204726_Alt60_Azi-45_Try1.tiff"))[1:] == (60.0, 315.0)
    assert altaz_from_filename("2019-07-29T204726_Alt60_Azi135_Try1.tiff")[2] == 135.0
    with pytest.raises(ConfigError, match="Alt"):
        altaz_from_filename("left01.jpg")


# ---------------------------------------------------------------------------------------------- ESA frames
@pytest.mark.parametrize("name", ESA_NAMES or ["(ESA truth absent)"])
def test_esa_boresight_from_nominal_altaz_within_2_deg(truth, name):
    t, alt, az = altaz_from_filename(name)
    ra, dec = boresight_from_altaz(t, alt_deg=alt, az_deg=az, **SITE)
    e = truth[name]
    err = angle_deg(ra, dec, e["ra_deg"], e["dec_deg"])
    assert err < 2.0, f"{name}: alt/az boresight {ra:.3f}, {dec:.3f} is {err:.3f} deg from the plate solution"


def test_esa_attitude_within_2_5_deg_of_plate_solution(truth):
    """Whole-attitude check (boresight and roll): the level-camera attitude is within 2.5 deg (rotation
    angle) of each plate-solved R, i.e. the frames were taken with image-up toward the zenith."""
    names = sorted(truth)
    ts, alts, azs = zip(*(altaz_from_filename(n) for n in names))
    A = attitude_from_altaz(list(ts), SITE["lat_deg"], SITE["lon_deg"], SITE["alt_m"], np.array(alts),
                            np.array(azs))
    assert A.shape == (8, 3, 3)
    np.testing.assert_allclose(A @ A.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (8, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(A), 1.0, atol=1e-12)
    for n, a in zip(names, A):
        D = truth[n]["R_icrs_to_cam"] @ a.T
        rot = np.degrees(np.arccos(np.clip((np.trace(D) - 1) / 2, -1, 1)))
        assert rot < 2.5, f"{n}: {rot:.2f} deg"
    # the batch's boresights are the scalar function's
    ra, dec = boresight_from_altaz(list(ts), alt_deg=np.array(alts), az_deg=np.array(azs), **SITE)
    b = radec_to_unit(np.radians(ra), np.radians(dec))
    np.testing.assert_allclose(A[:, 2, :], b, atol=1e-12)


# ---------------------------------------------------------------------------------------------- geometry
T0 = "2019-07-29T20:47:26"


def _gmst_deg(iso_utc: str) -> float:
    """Greenwich mean sidereal time (deg), Meeus Eq. 12.4 (UT1 ~ UTC to 1 s)."""
    from datetime import datetime, timezone

    t = datetime.fromisoformat(iso_utc).replace(tzinfo=timezone.utc)
    jd = t.timestamp() / 86400.0 + 2440587.5
    d = jd - 2451545.0
    T = d / 36525.0
    return (280.46061837 + 360.98564736629 * d + 0.000387933 * T * T - T ** 3 / 38710000.0) % 360.0


def test_zenith_is_local_sidereal_time_and_latitude():
    """Pointing at the zenith: RA = local mean sidereal time, Dec = latitude, up to precession since
    J2000 (~0.27 deg in 2019) -- an independent check of the astropy path and its sign conventions."""
    ra, dec = boresight_from_altaz(T0, 52.08, 4.37, 0.0, 90.0, 0.0)
    lst = (_gmst_deg(T0) + 4.37) % 360.0
    assert abs(((ra - lst + 180) % 360) - 180) < 0.5
    assert abs(dec - 52.08) < 0.3


def test_pole_and_cardinal_directions():
    # north at altitude = latitude is the celestial pole (ICRS pole vs pole of date: ~0.1 deg in 2019)
    assert boresight_from_altaz(T0, 52.08, 4.37, 0.0, 52.08, 0.0)[1] > 89.75
    # due south at altitude 90 - lat is the celestial equator on the meridian: Dec ~ 0, RA ~ LST
    ra, dec = boresight_from_altaz(T0, 52.08, 4.37, 0.0, 90.0 - 52.08, 180.0)
    assert abs(dec) < 0.3 and abs(((ra - (_gmst_deg(T0) + 4.37) + 180) % 360) - 180) < 0.5
    # azimuth -45 is 315 (north-west)
    a = boresight_from_altaz(T0, 52.08, 4.37, 0.0, 40.0, -45.0)
    b = boresight_from_altaz(T0, 52.08, 4.37, 0.0, 40.0, 315.0)
    assert a == pytest.approx(b, abs=1e-9)


def test_image_up_is_toward_the_zenith_and_right_is_east_facing_north():
    zen = radec_to_unit(*np.radians(boresight_from_altaz(T0, 52.08, 4.37, 0.0, 90.0, 0.0)))
    for alt, az in [(40.0, 225.0), (60.0, 45.0), (10.0, 0.0)]:
        A = attitude_from_altaz(T0, 52.08, 4.37, 0.0, alt, az)
        z_cam = A @ zen
        # zenith straight up in the image (-y), x ~ 0; x is 1e-4 rad at most (20 arcsec): annual aberration
        # (~20 arcsec) shifts the far zenith and the boresight's neighbourhood slightly differently
        assert z_cam[1] < -0.1 and abs(z_cam[0]) < 1e-4
        assert np.degrees(angle_between(A[2], zen)) == pytest.approx(90.0 - alt, abs=0.01)
    east = radec_to_unit(*np.radians(boresight_from_altaz(T0, 52.08, 4.37, 0.0, 0.0, 90.0)))
    A = attitude_from_altaz(T0, 52.08, 4.37, 0.0, 10.0, 0.0)  # facing north
    assert (A @ east)[0] > 0.99


def test_roll_turns_the_frame_about_the_boresight():
    A0 = attitude_from_altaz(T0, 52.08, 4.37, 0.0, 40.0, 225.0)
    A90 = attitude_from_altaz(T0, 52.08, 4.37, 0.0, 40.0, 225.0, roll_deg=90.0)
    np.testing.assert_allclose(A90[2], A0[2], atol=1e-15)
    np.testing.assert_allclose(A90[0], A0[1], atol=1e-12)  # R_3(90): new x = old y
    np.testing.assert_allclose(A90[1], -A0[0], atol=1e-12)
    zen = radec_to_unit(*np.radians(boresight_from_altaz(T0, 52.08, 4.37, 0.0, 90.0, 0.0)))
    r = np.radians(30.0)
    v = attitude_from_altaz(T0, 52.08, 4.37, 0.0, 40.0, 225.0, roll_deg=30.0) @ zen
    np.testing.assert_allclose(v[:2] / np.hypot(*v[:2]), [-np.sin(r), -np.cos(r)], atol=1e-5)


def test_zenith_pointing_is_defined_and_bad_altitude_rejected():
    A = attitude_from_altaz(T0, 52.08, 4.37, 0.0, 90.0, 0.0)
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-12)
    with pytest.raises(ConfigError, match="altitude"):
        attitude_from_altaz(T0, 52.08, 4.37, 0.0, 91.0, 0.0)


def test_refraction_option_matches_bennett():
    """With pressure, (alt, az) is the observed direction: the true direction is lower by the refraction,
    Bennett (1982): R = cot(h + 7.31 / (h + 4.4)) arcmin (~1.2' at 40 deg, 1013 hPa, 10 C)."""
    h = 40.0
    bennett = 1.0 / np.tan(np.radians(h + 7.31 / (h + 4.4)))  # arcmin
    geo = boresight_from_altaz(T0, 52.08, 4.37, 0.0, h, 225.0)
    obs = boresight_from_altaz(T0, 52.08, 4.37, 0.0, h, 225.0, pressure_hpa=1010.0, temperature_c=10.0)
    sep = angle_deg(*geo, *obs) * 60.0
    assert sep == pytest.approx(bennett, abs=0.05)
    below = boresight_from_altaz(T0, 52.08, 4.37, 0.0, h - bennett / 60.0, 225.0)
    assert angle_deg(*obs, *below) * 3600 < 3.0


def test_no_download_configured():
    from astropy.utils import iers

    boresight_from_altaz(T0, 52.08, 4.37, 0.0, 45.0, 0.0)
    assert iers.conf.auto_download is False
