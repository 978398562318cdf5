"""Truth attitude for real night-sky photos: from time, site and the mount's altitude/azimuth.

This is the reference method's tripod test ("it was important to make sure that the tripod was level,
to enable the calculation of the true attitude"): a camera on a levelled alt/az mount at a known site
and time looks at a known (alt, az); astropy turns that horizontal direction into ICRS
(``AltAz -> ICRS``: Earth rotation and orientation from the IERS tables, precession-nutation,
aberration, and optionally refraction).  It also reads the independent plate-solved truth of the ESA
tetra3 frames (:func:`load_truth_json`).

Conventions
    Altitude above the horizon, azimuth from north through east (so "Azi-45" = 315 deg, north-west).
    The camera frame is dualsight's (+x along increasing column, +y along increasing row, +z out
    through the lens); attitude matrices map ICRS unit vectors into it (``v_cam = A @ v_icrs``).
    At roll 0 the image's "up" (decreasing row, -y) points toward the zenith, i.e. the camera is
    level: +x (image right) is horizontal, to the right when facing the azimuth (east when facing north).

Offline
    Importing the astropy parts sets ``astropy.utils.iers.conf.auto_download = False``: nothing is
    downloaded at run time; the IERS tables bundled with astropy (astropy-iers-data) cover past dates
    such as 2019.  Dates beyond them fall back to predictions with a warning from astropy.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from dualsight.errors import ConfigError
from dualsight.scene.attitude import radec_to_unit, rot_axis, unit_to_radec
from dualsight.scene.units import angle_between

_FILENAME = re.compile(
    r"(?P<date>\d{4}-\d{2}-\d{2})T(?P<h>\d{2}):?(?P<m>\d{2}):?(?P<s>\d{2}(?:\.\d+)?)"
    r".*?Alt(?P<alt>[-+]?\d+(?:\.\d+)?)_?Azi?(?P<az>[-+]?\d+(?:\.\d+)?)", re.IGNORECASE)

_UP_STEP_DEG = 0.01  # offset along the vertical used to find "up" (deg); see attitude_from_altaz


def _astropy():
    """Import astropy's coordinate machinery with downloads switched off."""
    from astropy.utils import iers

    iers.conf.auto_download = False
    import astropy.units as u
    from astropy.coordinates import ICRS, AltAz, EarthLocation, SkyCoord
    from astropy.time import Time

    return u, ICRS, AltAz, EarthLocation, SkyCoord, Time


def _altaz_to_icrs_unit(time_utc, lat_deg, lon_deg, alt_m, alt_deg, az_deg, pressure_hpa, temperature_c,
                        relative_humidity, wavelength_um) -> np.ndarray:
    """(..., 3) ICRS unit vectors of horizontal directions (broadcast over all array arguments)."""
    u, ICRS, AltAz, EarthLocation, SkyCoord, Time = _astropy()
    t = time_utc if isinstance(time_utc, Time) else Time(time_utc, scale="utc")
    tv = np.asarray(t.mjd)
    shape = np.broadcast_shapes(tv.shape, *(np.shape(x) for x in (lat_deg, lon_deg, alt_m, alt_deg, az_deg)))
    lat, lon, h, alt, az = (np.broadcast_to(np.asarray(x, dtype=np.float64), shape)
                            for x in (lat_deg, lon_deg, alt_m, alt_deg, az_deg))
    if t.shape != shape:
        t = Time(np.broadcast_to(t.jd1, shape), np.broadcast_to(t.jd2, shape), format="jd", scale=t.scale)
    site = EarthLocation.from_geodetic(lon=lon * u.deg, lat=lat * u.deg, height=h * u.m)
    frame = AltAz(obstime=t, location=site, pressure=pressure_hpa * u.hPa, temperature=temperature_c * u.deg_C,
                  relative_humidity=relative_humidity, obswl=wavelength_um * u.um)
    icrs = SkyCoord(az=np.mod(az, 360.0) * u.deg, alt=alt * u.deg, frame=frame).transform_to(ICRS())
    return radec_to_unit(icrs.ra.rad, icrs.dec.rad)


def boresight_from_altaz(time_utc, lat_deg, lon_deg, alt_m, alt_deg, az_deg, *, pressure_hpa: float = 0.0,
                         temperature_c: float = 10.0, relative_humidity: float = 0.5,
                         wavelength_um: float = 0.55):
    """ICRS direction of a horizontal (alt, az) pointing at a site and time.

    Parameters
    ----------
    time_utc : ISO string ("2019-07-29T20:47:26"), datetime (naive = UTC) or astropy Time; scalar or array.
    lat_deg, lon_deg : geodetic latitude (north +) and longitude (east +), deg (WGS84).
    alt_m : height of the site above the ellipsoid, m.
    alt_deg : altitude of the pointing above the horizon, deg.
    az_deg : azimuth from north through east, deg (any range; -45 == 315).
    pressure_hpa : 0 (default) gives the geometric direction, no refraction; pass the site pressure
        (about 1013 hPa at sea level) to treat (alt, az) as the *observed* (refracted) direction, which
        is what a camera sees: that moves the ICRS direction by ~1.2 arcmin at 40 deg altitude.
    temperature_c, relative_humidity, wavelength_um : refraction inputs (used only when pressure > 0).

    Returns
    -------
    (ra_deg in [0, 360), dec_deg): floats for scalar inputs, else arrays of the broadcast shape.
    """
    v = _altaz_to_icrs_unit(time_utc, lat_deg, lon_deg, alt_m, alt_deg, az_deg, pressure_hpa, temperature_c,
                            relative_humidity, wavelength_um)
    ra, dec = unit_to_radec(v)
    ra, dec = np.degrees(ra), np.degrees(dec)
    if ra.ndim == 0:
        return float(ra), float(dec)
    return ra, dec


def attitude_from_altaz(time_utc, lat_deg, lon_deg, alt_m, alt_deg, az_deg, roll_deg=0.0, *,
                        pressure_hpa: float = 0.0, temperature_c: float = 10.0, relative_humidity: float = 0.5,
                        wavelength_um: float = 0.55) -> np.ndarray:
    """Inertial (ICRS) -> camera matrix of a camera on a levelled alt/az mount.

    The camera's +z is the (alt, az) direction; at ``roll_deg = 0`` its image "up" (-y, decreasing
    row) points toward the zenith and +x (increasing column) is horizontal, to the right of the
    pointing (east when facing north).  A nonzero roll turns the camera frame about its boresight:
    ``A = R_3(roll) @ A_level`` (frame rotation of +x toward +y by ``roll``, ``attitude.rot_axis``),
    so the direction to the zenith, straight up (0, -1) in (col, row) in the level image, appears
    along (-sin roll, -cos roll).

    "Up" is taken as the ICRS direction from a point ``0.01`` deg *below* the boresight on the same
    vertical to the boresight itself, both transformed by astropy, so the frame includes the same
    aberration/refraction as the boresight and stays defined at the zenith (alt = 90: up points away
    from ``az``).  Parameters as :func:`boresight_from_altaz` (``alt_deg`` must be > -89.99).

    Returns
    -------
    (3, 3) matrix for scalar inputs, else (..., 3, 3) over the broadcast shape; rows are the camera
    axes x, y, z in ICRS.
    """
    alt = np.asarray(alt_deg, dtype=np.float64)
    if np.any(alt > 90.0) or np.any(alt - _UP_STEP_DEG < -90.0):
        raise ConfigError(f"altitude must be in (-89.99, 90] deg, got {alt_deg!r}", field="alt_deg")
    stacked_alt = np.stack(np.broadcast_arrays(alt, alt - _UP_STEP_DEG))
    v = _altaz_to_icrs_unit(time_utc, lat_deg, lon_deg, alt_m, stacked_alt, az_deg, pressure_hpa, temperature_c,
                            relative_humidity, wavelength_um)
    z, below = v[0], v[1]
    up = z - below
    up = up - np.sum(up * z, axis=-1, keepdims=True) * z
    up /= np.linalg.norm(up, axis=-1, keepdims=True)
    y = -up
    x = np.cross(y, z)
    A = np.stack([x, y, z], axis=-2)
    roll = np.asarray(roll_deg, dtype=np.float64)
    if np.any(roll != 0):
        shape = np.broadcast_shapes(A.shape[:-2], roll.shape)
        R = rot_axis(3, np.radians(np.broadcast_to(roll, shape)).ravel()).reshape(shape + (3, 3))
        A = R @ A
    return A


def altaz_from_filename(name: str | Path) -> tuple[str, float, float]:
    """(UTC ISO time, alt_deg, az_deg in [0, 360)) from a file name such as tetra3's
    ``2019-07-29T204726_Alt40_Azi-135_Try1.tiff`` -> ("2019-07-29T20:47:26", 40.0, 225.0).

    Raises ConfigError when the name carries no time and Alt/Azi fields.
    """
    m = _FILENAME.search(Path(name).name)
    if m is None:
        raise ConfigError("file name carries no 'YYYY-MM-DDTHHMMSS ... Alt<deg>_Azi<deg>'", source=str(name))
    t = f"{m['date']}T{m['h']}:{m['m']}:{m['s']}"
    return t, float(m["alt"]), float(np.mod(float(m["az"]), 360.0))


def load_truth_json(path: str | Path) -> dict[str, dict]:
    """Read a plate-solved truth file (format of ``shared/data/real/esa_tetra3/truth.json``).

    Returns
    -------
    {image file name: entry}, where each entry holds the file's fields with
      ``ra_deg``, ``dec_deg`` : float, boresight (ICRS, deg);
      ``R_icrs_to_cam`` : (3, 3) float64 ndarray (checked orthonormal with det +1 to 1e-6);
      ``boresight_from_R_deg`` : (2,) ndarray, if present;
      ``matched`` : dict of (N,) float64 arrays ``row``, ``col`` (px, from the top-left corner),
                    ``ra_deg``, ``dec_deg``, ``mag``;
    and the other fields (``fov_deg``, ``focal_length_px``, ``rmse_arcsec``, ...) as stored.

    Raises
    ------
    ConfigError naming the file and the entry/key when the file is missing or malformed.
    """
    path = Path(path)
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError("file not found", source=str(path)) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ConfigError(f"is not readable JSON: {e}", source=str(path)) from None
    if not isinstance(raw, dict) or not raw:
        raise ConfigError("must be a non-empty JSON object {image name: entry}", source=str(path))
    out = {}
    for name, e in raw.items():
        if not isinstance(e, dict):
            raise ConfigError("entry must be an object", source=str(path), field=name)
        entry = dict(e)
        try:
            entry["ra_deg"] = float(e["ra_deg"])
            entry["dec_deg"] = float(e["dec_deg"])
            R = np.asarray(e["R_icrs_to_cam"], dtype=np.float64)
        except KeyError as k:
            raise ConfigError(f"missing key {k}", source=str(path), field=name) from None
        except (TypeError, ValueError) as err:
            raise ConfigError(f"bad value: {err}", source=str(path), field=name) from None
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise ConfigError("R_icrs_to_cam must be a 3x3 rotation matrix", source=str(path),
                              field=f"{name}.R_icrs_to_cam")
        entry["R_icrs_to_cam"] = R
        if "boresight_from_R_deg" in e:
            entry["boresight_from_R_deg"] = np.asarray(e["boresight_from_R_deg"], dtype=np.float64)
        stars = e.get("matched", [])
        if not isinstance(stars, list):
            raise ConfigError("must be a list of stars", source=str(path), field=f"{name}.matched")
        try:
            entry["matched"] = {k: np.array([float(s[k]) for s in stars], dtype=np.float64)
                                for k in ("row", "col", "ra_deg", "dec_deg", "mag")}
        except (KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"each star needs numeric row, col, ra_deg, dec_deg, mag ({err})", source=str(path),
                              field=f"{name}.matched") from None
        out[name] = entry
    return out


def angle_deg(ra1_deg, dec1_deg, ra2_deg, dec2_deg):
    """Great-circle angle (deg) between two RA/Dec directions given in degrees (truth files, CLI).

    Arrays broadcast; returns float64 degrees of the broadcast shape, from
    :func:`dualsight.scene.units.angle_between` (atan2 of |a x b| and a . b).
    """
    a = radec_to_unit(np.radians(ra1_deg), np.radians(dec1_deg))
    b = radec_to_unit(np.radians(ra2_deg), np.radians(dec2_deg))
    return np.degrees(angle_between(a, b))

