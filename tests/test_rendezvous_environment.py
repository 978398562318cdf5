"""Sun, Earth and Moon per rendezvous frame (``[rendezvous.environment]``, issue 23 point 1): each frame's angles
against astropy's Sun and Moon seen from the chaser (rebuilt here from the reference orbit by elementary rotations
and the frame's true Hill offset), the keep-out flags against their half-angles, the shadow, the epoch's Sun for
the target, the columns null without the table and a hostile value one line."""

import math
import warnings

import numpy as np
import pytest

from dualsight.errors import ConfigError
from dualsight.jobs.kinds import rendezvous as rz, rendezvous_spec
from helpers import angle_deg, sky_geometry

ENV = {"epoch_utc": "2032-06-01T03:00:00", "sun_keepout_deg": 40.0, "earth_keepout_deg": 25.0,
       "moon_keepout_deg": 15.0}
FAR = {"rendezvous": {"duration_s": 6000.0, "frame_interval_s": 500.0, "manoeuvre_times_s": [500.0],
                      "environment": ENV}}


def _spec(config):
    d, _ = rendezvous_spec.resolve_spec(None, config)
    return rz.spec_from_dict(d)


@pytest.fixture(scope="module")
def case():
    spec = _spec(FAR)
    return spec, rz.compute_case(spec, rz.make_context(spec), 0)


def test_frames_against_astropy(case):
    from astropy.utils import iers
    iers.conf.auto_download = False
    from astropy.coordinates import get_body
    from astropy.time import Time

    spec, out = case
    rows = out["frames"].to_pydict()
    c = spec.cfg
    t = spec.times
    # the reference orbit by rotations: R3(node) R1(inclination) R3(argument of latitude + n t) [a, 0, 0]
    a_km = 6378.137 + c.altitude_km
    n = math.sqrt(3.986004418e14 / (a_km * 1e3) ** 3)
    O, i = math.radians(c.raan_deg), math.radians(c.inclination_deg)
    u = math.radians(c.arg_lat_deg) + n * t
    R3 = lambda x: np.array([[math.cos(x), -math.sin(x), 0], [math.sin(x), math.cos(x), 0], [0, 0, 1.0]])  # noqa
    R1 = np.array([[1.0, 0, 0], [0, math.cos(i), -math.sin(i)], [0, math.sin(i), math.cos(i)]])
    r_ref = np.stack([R3(O) @ R1 @ R3(uk) @ np.array([a_km, 0, 0]) for uk in u])
    # the chaser: its Hill offset (radial, along-track, normal) in km on those axes
    radial = r_ref / a_km
    normal = np.array(R3(O) @ R1 @ np.array([0, 0, 1.0]))
    along = np.cross(normal, radial)
    x = out["truth"][:, :3] / 1e3
    r = r_ref + x[:, :1] * radial + x[:, 1:2] * along + x[:, 2:3] * normal
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tm = Time(ENV["epoch_utc"], scale="utc") + t / 86400.0
        sun = get_body("sun", tm).cartesian.xyz.to("km").value.T
        moon = get_body("moon", tm).cartesian.xyz.to("km").value.T
    b = out["geo"]["A_true"][:, 2, :]
    g = sky_geometry(b, r, sun, moon)
    sun_deg, limb, umbra, clear = g["sun_deg"], g["limb_deg"], g["umbra"], g["clear"]
    assert np.max(np.abs(np.array(rows["sun_angle_deg"]) - sun_deg)) < 0.012
    assert np.max(np.abs(np.array(rows["moon_angle_deg"]) - g["moon_deg"])) < 0.35
    assert np.max(np.abs(np.array(rows["earth_limb_angle_deg"]) - limb)) < 1e-6
    assert rows["sun_keepout"] == (sun_deg < 40.0).tolist()
    assert rows["earth_keepout"] == (limb < 25.0).tolist()
    ecl = np.array(rows["eclipse"])
    assert np.array_equal(ecl[clear | umbra], umbra[clear | umbra])
    assert 0 < ecl.sum() < len(t)                      # an orbit: some frames in the shadow, some not
    # the target is lit by the epoch's Sun
    assert angle_deg(out["geo"]["targets"].sun_icrs[0], sun[0]).max() < 0.012


def test_without_the_table_null():
    spec = _spec({"rendezvous": {k: v for k, v in FAR["rendezvous"].items() if k != "environment"}})
    out = rz.compute_case(spec, rz.make_context(spec), 0)
    f = out["frames"]
    for name in ("sun_angle_deg", "earth_limb_angle_deg", "moon_angle_deg", "sun_keepout", "earth_keepout",
                 "moon_keepout", "earth_lit_in_cone", "eclipse", "penumbra"):
        assert f.column(name).null_count == f.num_rows
    assert "environment" not in spec.to_dict()["rendezvous"]      # the run's identity without the table unchanged


def test_hostile_value_is_one_line():
    bad = {"rendezvous": dict(FAR["rendezvous"], environment=dict(ENV, epoch_utc="2077-01-01T00:00:00"))}
    with pytest.raises(ConfigError, match=r"rendezvous\.environment\.epoch_utc.*1950.*2050") as e:
        _spec(bad)
    assert "\n" not in str(e.value)
