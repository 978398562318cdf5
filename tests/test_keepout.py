"""Sun / Earth / Moon keep-out and the Earth's shadow (scene/keepout.py, issue 23 point 1) against independent
truth: astropy's Sun and Moon (get_body, GCRS) seen from the spacecraft, brute-force sampling of the Earth's
surface (limb angle, lit Earth in the cone) and of the Sun's disk (umbra / penumbra), and closed-form cases."""

import math
import warnings

import numpy as np

from dualsight.scene import ephemeris as ep
from dualsight.scene import keepout as ko

RE = ep.R_EARTH_KM


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _acos_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(_unit(a) * _unit(b), -1), -1, 1)))


def _leo(rng, n, lo=400.0, hi=1200.0):
    return _unit(rng.normal(size=(n, 3))) * (RE + rng.uniform(lo, hi, n))[:, None]


def _sphere_points(rng, n):
    return _unit(rng.normal(size=(n, 3))) * RE


def test_sun_and_moon_angles_from_the_spacecraft_against_astropy():
    from astropy.utils import iers
    iers.conf.auto_download = False
    from astropy.coordinates import get_body
    from astropy.time import Time

    rng = np.random.default_rng(11)
    n = 300
    unix = rng.uniform(1.5e9, 2.1e9, n)
    t = Time(unix, format="unix", scale="utc")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sun_t = get_body("sun", t).cartesian.xyz.to("km").value.T
        moon_t = get_body("moon", t).cartesian.xyz.to("km").value.T
    r = _leo(rng, n, 300.0, 2000.0)
    moon_from_r = moon_t - r
    # boresights near the Moon so the angles are small (parallax matters most there) and random elsewhere
    b = _unit(np.where(np.arange(n)[:, None] % 2 == 0, _unit(moon_from_r) + 0.05 * rng.normal(size=(n, 3)),
                       rng.normal(size=(n, 3))))
    jd = ep.jd_tt_from_unix(unix)
    k = ko.keep_out(r, b, ep.sun_position(jd), ep.moon_position(jd), sun_half_rad=math.radians(30),
                    earth_half_rad=math.radians(20), moon_half_rad=math.radians(10))
    moon_truth = _acos_deg(b, moon_from_r)
    assert np.max(np.abs(np.degrees(k.moon_angle_rad) - moon_truth)) < 0.35
    assert np.max(np.abs(np.degrees(k.sun_angle_rad) - _acos_deg(b, sun_t - r))) < 0.012
    # the parallax is there: the geocentric direction would be off by up to ~1 deg from LEO
    assert np.max(np.abs(_acos_deg(b, moon_t) - moon_truth)) > 0.5
    assert np.array_equal(k.moon_keepout, np.degrees(k.moon_angle_rad) < 10)
    assert np.array_equal(k.sun_keepout, np.degrees(k.sun_angle_rad) < 30)


def test_earth_limb_angle_against_surface_sampling():
    rng = np.random.default_rng(5)
    n = 40
    r = _leo(rng, n)
    b = _unit(rng.normal(size=(n, 3)))
    k = ko.keep_out(r, b, np.tile([ep.AU_KM, 0, 0], (n, 1)), np.tile([384400.0, 0, 0], (n, 1)),
                    sun_half_rad=0.5, earth_half_rad=math.radians(20), moon_half_rad=0.2)
    pts = _sphere_points(rng, 400_000)
    for i in range(n):
        vis = np.einsum("nk,k->n", pts, r[i]) > RE * RE           # points that face the spacecraft
        ang = _acos_deg(pts[vis] - r[i], np.broadcast_to(b[i], (vis.sum(), 3)))
        on_disk = np.degrees(k.earth_limb_angle_rad[i]) < 0
        if on_disk:
            continue
        assert abs(ang.min() - np.degrees(k.earth_limb_angle_rad[i])) < 0.6     # sampling spacing ~0.5 deg
    # closed form: nadir pointing sits rho inside the limb; pointing along the horizon is on the limb
    r0 = np.array([[RE + 500.0, 0.0, 0.0]] * 2)
    rho = math.asin(RE / (RE + 500.0))
    b0 = np.array([[-1.0, 0.0, 0.0], [-math.cos(rho), math.sin(rho), 0.0]])
    k0 = ko.keep_out(r0, b0, np.tile([0, ep.AU_KM, 0], (2, 1)), np.tile([0, 384400.0, 0], (2, 1)),
                     sun_half_rad=0.5, earth_half_rad=0.3, moon_half_rad=0.2)
    assert np.allclose(k0.earth_limb_angle_rad, [-rho, 0.0], atol=1e-12)
    assert np.allclose(k0.earth_radius_rad, rho)
    assert k0.earth_keepout.all()


def test_lit_earth_in_the_cone_against_surface_sampling():
    rng = np.random.default_rng(8)
    n = 200
    r = _leo(rng, n)
    sun = _unit(rng.normal(size=(n, 3)))
    # boresights within ~60 deg of nadir: most cones meet the disk, the terminator crosses many of them
    b = _unit(-_unit(r) + 0.9 * rng.normal(size=(n, 3)))
    half = math.radians(20)
    got = ko.earth_disk_lit_in_cone(r, b, sun, half)
    pts = _sphere_points(rng, 600_000)
    hits = np.zeros(n, np.int64)
    hits_wide = np.zeros(n, np.int64)         # a cone 1 deg wider: slivers the surface sampling is too coarse for
    for i in range(n):
        vis = np.einsum("nk,k->n", pts, r[i]) > RE * RE
        p = pts[vis]
        ang = _acos_deg(p - r[i], np.broadcast_to(b[i], p.shape))
        lit = p @ sun[i] > 0
        hits[i] = np.count_nonzero((ang < math.degrees(half)) & lit)
        hits_wide[i] = np.count_nonzero((ang < math.degrees(half) + 1.0) & lit)
    assert np.all(got[hits >= 30])            # a lit patch of ~1 deg^2 or more is seen
    assert not np.any(got & (hits_wide == 0))  # nothing lit near the cone: never flagged
    assert 20 < got.sum() < n - 20            # both answers occur
    assert np.mean(got == (hits > 0)) > 0.95


def test_umbra_and_penumbra_against_sun_disk_sampling():
    rng = np.random.default_rng(9)
    n = 400
    sun_dir = _unit(rng.normal(size=(n, 3)))
    sun = sun_dir * ep.AU_KM
    # spacecraft behind the Earth near the shadow's edge, and anywhere
    back = -sun_dir * (RE + rng.uniform(300, 3000, n))[:, None]
    side = _unit(np.cross(sun_dir, rng.normal(size=(n, 3))))
    off = np.where(np.arange(n) % 2 == 0, rng.uniform(-1.1, 1.1, n) * RE, RE + rng.uniform(-20, 20, n))
    r = back + side * off[:, None]
    r = np.where(np.arange(n)[:, None] % 4 == 0, _leo(rng, n), r)
    k = ko.keep_out(r, np.tile([0, 0, 1.0], (n, 1)), sun, np.tile([384400.0, 0, 0], (n, 1)),
                    sun_half_rad=0.5, earth_half_rad=0.3, moon_half_rad=0.2)
    # brute force: points of the Sun's sphere, rays from the spacecraft, blocked by the Earth sphere
    m = 4000
    frac = np.zeros(n)
    for i in range(n):
        s = sun[i] + _unit(rng.normal(size=(m, 3))) * ko.R_SUN_KM
        s = s[np.einsum("mk,mk->m", s - sun[i], r[i] - s) > 0]            # the hemisphere facing the spacecraft
        d = _unit(s - r[i])
        rd = d @ r[i]
        disc = rd * rd - (r[i] @ r[i] - RE * RE)
        blocked = (disc > 0) & (-rd - np.sqrt(np.maximum(disc, 0)) > 0)
        frac[i] = blocked.mean()
    assert np.all(k.umbra[frac == 1.0] | k.penumbra[frac == 1.0])
    assert np.all(~k.umbra[frac < 1.0 - 0.01])
    shadow = k.umbra | k.penumbra
    assert not np.any(shadow & (frac == 0.0) & ~_near_penumbra_edge(k, r, sun))
    assert np.all((k.umbra | k.penumbra)[(frac > 0.01)])
    assert k.umbra.sum() > 20 and k.penumbra.sum() > 5 and (~k.umbra & ~k.penumbra).sum() > 20
    # a cylindrical shadow agrees away from the penumbra
    cyl = (np.einsum("bk,bk->b", r, sun_dir) < 0) & (np.linalg.norm(np.cross(r, sun_dir), axis=1) < RE)
    assert np.array_equal(cyl[~k.penumbra], k.umbra[~k.penumbra])


def _near_penumbra_edge(k, r, sun):
    """A sampled Sun disk can miss a sliver of the penumbra: within 0.01 deg of its outer edge."""
    a_s = np.arcsin(ko.R_SUN_KM / np.linalg.norm(sun - r, axis=1))
    sep = ko.angle_between(sun - r, -r)
    return np.abs(sep - (k.earth_radius_rad + a_s)) < math.radians(0.01)


def test_one_frame_as_flat_vectors():
    # one frame given as flat vectors works like a batch of one
    k = ko.keep_out([RE + 500.0, 0, 0], [1.0, 0, 0], [ep.AU_KM, 0, 0], [384400.0, 0, 0], sun_half_rad=0.5,
                    earth_half_rad=0.3, moon_half_rad=0.2)
    assert k.sun_angle_rad.shape == (1,) and k.sun_keepout[0] and k.moon_keepout[0] and not k.earth_keepout[0]
    assert not k.umbra[0] and not k.penumbra[0] and not k.earth_lit_in_cone[0]
