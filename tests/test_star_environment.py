"""The star job with ``[target.environment]`` (issue 23 point 1): each row's epoch, Earth / Moon / Sun angles,
keep-out flags and shadow against astropy's Sun and Moon seen from the case's own orbit position (rebuilt here
from numpy's ``default_rng([seed, i])``), the target's Sun taken from the epoch, the rows without the table null
and the same as before, and hostile values refused in one line."""

import math
import subprocess
import sys
import warnings

import numpy as np
import pytest

from dualsight.errors import ConfigError
from dualsight.jobs.engine.specs import preset_and_config
from dualsight.jobs.kinds import star
from helpers import angle_deg, sky_geometry

SAT = "examples/satellites/cubesat_3u.toml"
ENV = {"epoch_utc": ["2031-01-01T00:00:00", "2031-12-31T00:00:00"], "altitude_km": 600.0, "inclination_deg": 45.0,
       "earth_keepout_deg": 22.0, "moon_keepout_deg": 11.0}
IDS = np.arange(24, dtype=np.int64)


@pytest.fixture(scope="module")
def runs():
    d, _ = preset_and_config(star.PRESETS, "paper", None)
    d["target"] = {"satellite": SAT, "range_m": [2000.0, 5000.0], "sun_keepout_deg": 35.0}
    plain = star.spec_from_dict(d, source="test")
    d["target"] = dict(d["target"], environment=ENV)
    spec = star.spec_from_dict(d, source="test")
    ctx = star.make_context(spec)
    return (spec, star.compute_batch(spec, ctx, IDS), star.compute_batch(plain, ctx, IDS))


def _truth_positions(seed):
    """Each case's epoch (POSIX s) and position (km) from numpy's generator: 13 draws skipped, then 3."""
    t0, t1 = 1924992000.0, 1956441600.0                       # 2031-01-01, 2031-12-31 UTC
    out_t, out_r = [], []
    inc = math.radians(45.0)
    for i in IDS:
        g = np.random.default_rng([seed, int(i)])
        g.bit_generator.random_raw(13)
        ue, un, ul = g.random(3)
        O, u = 2 * math.pi * un, 2 * math.pi * ul
        # the orbit written as the node's rotation of the in-plane position (the test's own form)
        p = np.array([math.cos(u), math.sin(u) * math.cos(inc), math.sin(u) * math.sin(inc)]) * (6378.137 + 600.0)
        Rz = np.array([[math.cos(O), -math.sin(O), 0], [math.sin(O), math.cos(O), 0], [0, 0, 1.0]])
        out_t.append(t0 + (t1 - t0) * ue)
        out_r.append(Rz @ p)
    return np.array(out_t), np.array(out_r)


def test_rows_against_astropy(runs):
    from astropy.utils import iers
    iers.conf.auto_download = False
    from astropy.coordinates import get_body
    from astropy.time import Time

    spec, out, _ = runs
    rows = out["tables"]["star_cases"].to_pydict()
    t_unix, r = _truth_positions(spec.seed)
    got_t = np.array([x.timestamp() for x in rows["epoch_utc"]])
    assert np.max(np.abs(got_t - t_unix)) < 1e-5
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t = Time(t_unix, format="unix", scale="utc")
        sun = get_body("sun", t).cartesian.xyz.to("km").value.T
        moon = get_body("moon", t).cartesian.xyz.to("km").value.T
    b = np.asarray(out["draw"]["A_true"])[:, 2, :]            # the camera's +z in ICRS
    g = sky_geometry(b, r, sun, moon)
    sun_deg, limb, umbra, clear = g["sun_deg"], g["limb_deg"], g["umbra"], g["clear"]
    assert np.max(np.abs(np.degrees(rows["sun_angle_rad"]) - sun_deg)) < 0.012
    assert np.max(np.abs(np.degrees(rows["moon_angle_rad"]) - g["moon_deg"])) < 0.35
    assert np.max(np.abs(np.degrees(rows["earth_limb_angle_rad"]) - limb)) < 1e-6
    assert rows["sun_keepout"] == (sun_deg < 35.0).tolist()
    assert rows["earth_keepout"] == (limb < 22.0).tolist()
    # shadow: the Sun (0.27 deg) wholly behind the Earth's disk from the spacecraft
    assert np.array_equal(np.array(rows["eclipse"])[clear | umbra], umbra[clear | umbra])
    # a target in the umbra is dark: no light, no detection of it
    ecl = np.array(rows["eclipse"])
    assert ecl.any() and not np.array(rows["target_present"])[ecl].any()
    assert np.array(rows["target_present"])[~ecl].mean() > 0.5
    # the target's Sun is the epoch's: its RA/Dec column is the Sun seen from the spacecraft
    s = np.stack([np.cos(rows["sun_dec_rad"]) * np.cos(rows["sun_ra_rad"]),
                  np.cos(rows["sun_dec_rad"]) * np.sin(rows["sun_ra_rad"]), np.sin(rows["sun_dec_rad"])], -1)
    assert angle_deg(s, sun - r).max() < 0.012


def test_without_environment_null_and_unchanged(runs):
    _, out, plain = runs
    p = plain["tables"]["star_cases"]
    e = out["tables"]["star_cases"]
    for name in ("epoch_utc", "earth_limb_angle_rad", "moon_angle_rad", "earth_keepout", "moon_keepout",
                 "earth_lit_in_cone", "eclipse", "penumbra"):
        assert p.column(name).null_count == len(IDS)
        assert e.column(name).null_count == 0
    # the attitude, noise and target draws are the same cases; only the Sun (and what it lights) differs
    for name in ("theta1_rad", "theta2_rad", "theta3_rad", "target_range_m", "target_x_px", "target_y_px"):
        assert p.column(name).to_pylist() == e.column(name).to_pylist()
    assert p.column("sun_ra_rad").to_pylist() != e.column("sun_ra_rad").to_pylist()
    assert plain["environment"] is None


@pytest.mark.parametrize("key, value, match", [
    ("altitude_km", 100.0, r"target\.environment\.altitude_km.*150"),
    ("epoch_utc", ["2049-01-01T00:00:00", "2051-01-01T00:00:00"], r"target\.environment\.epoch_utc\[1\].*1950.*2050"),
    ("epoch_utc", ["2030-02-01", "2030-01-01"], r"target\.environment\.epoch_utc.*first <= last"),
    ("moon_keepout_deg", 95.0, r"target\.environment\.moon_keepout_deg.*90"),
    ("inclination", 10.0, r"target\.environment\.inclination.*unknown key"),
])
def test_hostile_values_are_one_line(key, value, match):
    d, _ = preset_and_config(star.PRESETS, "paper", None)
    d["target"] = {"satellite": SAT, "environment": dict(ENV, **{key: value})}
    with pytest.raises(ConfigError, match=match) as e:
        star.spec_from_dict(d, source="cfg.toml")
    assert "\n" not in str(e.value) and "cfg.toml" in str(e.value)


def test_command_line_refuses_in_one_line(tmp_path):
    cfg = tmp_path / "env.toml"
    cfg.write_text(f'[target]\nsatellite = "{SAT}"\n[target.environment]\naltitude_km = 1e6\n')
    p = subprocess.run([sys.executable, "-m", "dualsight.jobs.cli.main", "star", "run", "--config", str(cfg),
                        "--cases", "2", "--lake", str(tmp_path / "lake")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2
    err = p.stderr.strip().splitlines()
    assert len(err) == 1 and "target.environment.altitude_km" in err[0] and "40000" in err[0], p.stderr
