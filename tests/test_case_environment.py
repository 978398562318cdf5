"""Each case's epoch, orbit position and view of the Sun, Earth and Moon (scene/case_environment.py, issue 23
point 1) against independent truth: numpy's own ``default_rng([seed, i])`` stepped by hand past the star job's and
the target's draws, the orbit built by elementary rotations, astropy's Sun, and the target's Sun taken from it."""

import math
import warnings

import numpy as np

from dualsight.scene.environment_config import EnvironmentConfig
from dualsight.scene.target_config import TargetConfig
from dualsight.scene import case_environment as ce
from dualsight.scene.camera import Camera
from dualsight.scene.ephemeris import R_EARTH_KM
from dualsight.scene.target_in_field import draw_targets

CFG = EnvironmentConfig(epoch_utc=("2030-03-01T00:00:00", "2030-09-01T00:00:00"), altitude_km=700.0,
                        inclination_deg=60.0, earth_keepout_deg=25.0, moon_keepout_deg=12.0)


def _rot(axis, a):
    c, s = math.cos(a), math.sin(a)
    return {3: np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), 1: np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])}[axis]


def _attitudes(n, seed=1):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], -1),
                     np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], -1),
                     np.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def test_draws_and_orbit_against_numpy_and_rotations():
    ids = np.array([0, 1, 7, 1000, 123456])
    A = _attitudes(len(ids))
    env = ce.draw_environment(CFG, 42, ids, A, math.radians(30))
    t0, t1 = CFG.epoch_unix_s
    for k, i in enumerate(ids):
        g = np.random.default_rng([42, int(i)])
        g.bit_generator.random_raw(4 + 9)                  # the star job's four draws, the target's nine
        u_epoch, u_node, u_lat = g.random(3)
        assert env.epoch_unix_s[k] == t0 + (t1 - t0) * u_epoch
        r = _rot(3, 2 * math.pi * u_node) @ _rot(1, math.radians(60.0)) @ _rot(3, 2 * math.pi * u_lat) \
            @ np.array([R_EARTH_KM + 700.0, 0, 0])
        assert np.allclose(env.r_km[k], r, rtol=0, atol=1e-8)
    # the boresight is the camera's +z: the Sun angle is the angle between A[2] and the Sun from the spacecraft
    cosang = np.einsum("bk,bk->b", A[:, 2], env.sun_dir)
    assert np.allclose(np.cos(env.view.sun_angle_rad), cosang, atol=1e-12)


def test_sun_against_astropy_and_into_the_target():
    from astropy.utils import iers
    iers.conf.auto_download = False
    from astropy.coordinates import get_body
    from astropy.time import Time

    ids = np.arange(40)
    A = _attitudes(len(ids), 2)
    env = ce.draw_environment(CFG, 5, ids, A, math.radians(30))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sun = get_body("sun", Time(env.epoch_unix_s, format="unix", scale="utc")).cartesian.xyz.to("km").value.T
    d = sun - env.r_km
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(np.sum(d * env.sun_dir, 1), -1, 1))).max() < 0.012
    # the target's Sun is the environment's, seen through the attitude; its phase follows from it
    cam = Camera(width=512, height=512, fx=1000.0, fy=1000.0, cx=256.0, cy=256.0, pixel_pitch_m=5.5e-6)
    tcfg = TargetConfig(satellite="examples/satellites/cubesat_3u.toml", sun_icrs=(0.0, 0.0, 1.0))
    tc = draw_targets(tcfg, 5, ids, A, cam, sun_icrs=env.sun_dir)
    assert np.allclose(tc.sun_icrs, env.sun_dir, atol=1e-12)
    assert np.allclose(tc.sun_cam, np.einsum("bij,bj->bi", A, env.sun_dir), atol=1e-12)
    o = -tc.pos_cam / np.linalg.norm(tc.pos_cam, axis=1, keepdims=True)
    assert np.allclose(np.cos(tc.phase_rad), np.sum(o * tc.sun_cam, 1), atol=1e-9)
    # everything else of the target is the same draw as without the environment
    tc0 = draw_targets(tcfg, 5, ids, A, cam)
    assert np.array_equal(tc.range_m, tc0.range_m) and np.array_equal(tc.pos_cam, tc0.pos_cam)


def test_keepout_flags_follow_the_half_angles():
    ids = np.arange(500)
    env = ce.draw_environment(CFG, 3, ids, _attitudes(len(ids), 3), math.radians(30))
    v = env.view
    assert np.array_equal(v.earth_keepout, np.degrees(v.earth_limb_angle_rad) < 25.0)
    assert np.array_equal(v.moon_keepout, np.degrees(v.moon_angle_rad) < 12.0)
    assert np.array_equal(v.sun_keepout, np.degrees(v.sun_angle_rad) < 30.0)
    # random attitudes from 700 km: the Earth (radius 64 deg) fills a large part of the sky
    rho = math.asin(R_EARTH_KM / (R_EARTH_KM + 700.0))
    assert np.allclose(v.earth_radius_rad, rho)
    share = np.mean(v.earth_keepout)
    cap = (1 - math.cos(rho + math.radians(25.0))) / 2            # solid-angle share of the Earth cone + 25 deg
    assert abs(share - cap) < 0.07
    assert 0 < v.umbra.sum() < len(ids)
