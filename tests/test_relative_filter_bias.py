"""The relative-navigation filter's correlated centre-of-brightness bias states (nav/relative_filter.py,
issue 23 point 6 c) and the error models behind them (scene/photocentre_bias.py, nav/blobber_range_error.py),
against independent answers: the scalar Kalman update through G, the stationary Gauss-Markov moments in closed
form, a Monte Carlo of a truth with a Gauss-Markov photocentre bias (NEES in its chi-square bounds with the states,
beyond them without), the law of total variance against photocentre_table, the shaded photocentre against the
Lambertian one and the silhouette's centre, and the range-ratio moments against a brute-force loop."""

import math

import numpy as np
import pytest

from dualsight.nav.relative_filter import FilterConfig
from dualsight.nav import relative_filter as rf
from dualsight.nav.blobber_range_error import range_ratio_at, range_ratio_statistics
from dualsight.scene import relative_orbit as ro
from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms
from dualsight.scene.photocentre_bias import (facet_materials, photocentre_statistics, shaded_photocentre_offset)
from dualsight.scene.satellite import load_satellite
from dualsight.scene.target_photometry import photocentre_offset, photocentre_table, target_shape

ORBIT = ro.CircularOrbit(altitude_m=500e3, inclination_rad=math.radians(51.6), raan_rad=math.radians(120.0),
                         arg_lat_rad=math.radians(10.0))


def test_bearing_update_moves_the_bias_state_by_the_scalar_kalman_gain():
    # chaser 1000 m behind on V-bar, position known to 1 um: a bearing delta rad off along d (across the line of
    # sight) can only be the bias, beta+ = K delta, K = (s / r) / ((s / r)^2 + sm^2), P+ = 1 - K s / r
    R = np.eye(3)
    r, s, sm, delta = 1000.0, 0.02, 1e-5, 3e-5
    u0 = np.array([0.0, 1.0, 0.0])                              # -R rho^ for rho = (0, -r, 0)
    d = np.array([0.0, 0.0, 1.0])
    u_m = math.cos(delta) * u0 + math.sin(delta) * d
    x = np.array([[0.0, -r, 0.0, 0.0, 0.0, 0.0, 0.0]])
    P = np.diag([1e-12] * 3 + [1e-8] * 3 + [1.0])[None]
    G = (s * d)[None, :, None]                                   # (1, 3, 1): 1 unit of beta = s metres along d
    xn, Pn = rf.bearing_update(x, P, u_m[None], rf.isotropic_bearing_cov(u_m[None], sm), R, bias=G)
    h = s / r
    K = h / (h * h + sm * sm)
    assert xn[0, 6] == pytest.approx(K * delta, rel=1e-4)
    assert Pn[0, 6, 6] == pytest.approx(1.0 - K * h, rel=1e-4)
    assert np.allclose(xn[0, :3], x[0, :3], atol=1e-5)           # the known position stays


def test_bias_propagate_is_the_stationary_gauss_markov_step():
    x = np.array([[1.0, 2, 3, 4, 5, 6, 0.5, -2.0]])
    P = np.eye(8)[None] * 0.5
    P[0, 0, 6] = P[0, 6, 0] = 0.3
    d = np.array([0.8, 0.25])
    xn, Pn = rf.bias_propagate(x, P, d)
    np.testing.assert_allclose(xn[0, :6], x[0, :6])
    np.testing.assert_allclose(xn[0, 6:], d * x[0, 6:])
    np.testing.assert_allclose(np.diag(Pn[0])[6:], d ** 2 * 0.5 + 1 - d ** 2)   # var -> d^2 var + (1 - d^2)
    assert Pn[0, 0, 6] == pytest.approx(0.8 * 0.3)                             # cross terms decay with d
    # k steps from a unit variance stay at unit variance; the correlation with the start is d^k
    x1, P1 = np.zeros((1, 7)), np.eye(7)[None]
    P1[0, 0, 6] = P1[0, 6, 0] = 0.5
    for _ in range(5):
        x1, P1 = rf.bias_propagate(x1, P1, [0.9])
    assert P1[0, 6, 6] == pytest.approx(1.0) and P1[0, 0, 6] == pytest.approx(0.5 * 0.9 ** 5)


def _gm_campaign(n_bias: int, runs: int = 100, seed: int = 1):
    """Bearings and ranges of chasers on V-bar ~300 m behind whose bearings carry a first-order Gauss-Markov offset
    of the target's centre of brightness (sigma 0.2 m along orbit normal, decay 0.9 per frame) plus white noise;
    the filter with ``n_bias`` states of that model.  Returns the (runs, T) NEES."""
    times = np.arange(0, 4000.0, 50.0)
    T = times.size
    rng = np.random.default_rng([23, 6, seed])
    nominal = np.array([0.0, -300.0, 0.0, 0.0, 0.0, 0.0])
    P0 = np.diag([1.0] * 3 + [1e-3] * 3) ** 2
    x0 = nominal + rng.normal(size=(runs, 6)) @ np.linalg.cholesky(P0).T
    truth = ro.propagate(x0, times, ORBIT.mean_motion)
    R = ro.hill_to_icrs(ORBIT, times)
    sb, dec, sw = 0.2, 0.9, 2e-4
    beta = np.empty((runs, T))
    beta[:, 0] = rng.normal(size=runs)
    for k in range(1, T):
        beta[:, k] = dec * beta[:, k - 1] + math.sqrt(1 - dec * dec) * rng.normal(size=runs)
    z_icrs = R[:, :, 2]                                          # the orbit normal in ICRS (T, 3)
    s = -np.einsum("tij,btj->bti", R, truth[..., :3]) + sb * beta[..., None] * z_icrs[None]
    u = s / np.linalg.norm(s, axis=-1, keepdims=True)
    e = rng.normal(size=u.shape) * sw
    e -= np.sum(e * u, -1, keepdims=True) * u
    u = (u + e) / np.linalg.norm(u + e, axis=-1, keepdims=True)
    C = rf.isotropic_bearing_cov(u.reshape(-1, 3), sw).reshape(runs, T, 3, 3)
    rng_m = np.linalg.norm(truth[..., :3], axis=-1)
    rs = 3.0
    rmeas = rng_m + rng.normal(size=rng_m.shape) * rs

    def select(k, x, P, R_k):
        G = np.broadcast_to((sb * z_icrs[k])[None, :, None], (runs, 3, 1))
        return u[:, k], C[:, k], G

    xs, Ps = rf.run(np.broadcast_to(nominal, (runs, 6)), np.broadcast_to(P0, (runs, 6, 6)), times, ORBIT,
                    FilterConfig(accel_psd=0.0, iterations=2), ranges=rmeas, range_sig=np.full_like(rmeas, rs),
                    select=select, n_bias=n_bias, bias_decay=lambda k, x, R_k: np.full((runs, 1), dec))
    return rf.nees(xs, Ps, truth)


def test_bias_states_make_a_gauss_markov_photocentre_consistent_and_their_absence_does_not():
    lo, hi = rf.chi2_mean_bounds(6, 100, 0.95)
    with_states = _gm_campaign(1).mean(0)[10:]
    assert ((with_states > lo) & (with_states < hi)).mean() >= 0.9, with_states
    assert 5.4 < with_states.mean() < 6.6
    without = _gm_campaign(0).mean(0)[10:]
    assert without.mean() > 2 * hi                                # the bias ignored: far overconfident


@pytest.fixture(scope="module")
def cubesat():
    sat = load_satellite("examples/satellites/cubesat_3u.toml")
    return sat, target_shape(sat.components)


def test_bias_and_white_parts_add_up_to_the_tables_spread(cubesat):
    _, shape = cubesat
    st = photocentre_statistics(shape, n_axes=120, n_phases=16)
    a, mean, spread = photocentre_table(shape, n=4000)
    inner = (st.alpha > 0.2) & (st.alpha < math.radians(91))      # beyond, the table keeps lit attitudes only
    total = np.sqrt(st.spread_white ** 2 + 0.5 * (st.sigma_sun ** 2 + st.sigma_cross ** 2))
    np.testing.assert_allclose(total[inner], np.interp(st.alpha[inner], a, spread), rtol=0.08)
    np.testing.assert_allclose(st.mean_sun[inner], np.interp(st.alpha[inner], a, mean), rtol=0.08, atol=1e-3)
    assert np.all(st.sigma_sun[inner] > 0.1 * total[inner])                   # a spinning cuboid keeps a bias
    held = photocentre_statistics(shape, spinning=False, n_axes=120)
    np.testing.assert_allclose(held.spread_white, 0.0, atol=1e-12)            # held: all of it is the bias


def test_shaded_photocentre_is_lambertian_without_ambient_and_specular_and_central_with_ambient_only(cubesat):
    sat, shape = cubesat
    rng = np.random.default_rng([23, 6, 9])
    u = rng.random((3, 50))
    Rb = quat_to_dcm(quaternions_from_uniforms(u[0], u[1], u[2]))
    sun = np.tile([0.6, 0.0, 0.8], (50, 1))
    obs = np.tile([0.0, 0.0, 1.0], (50, 1))
    mats = facet_materials(sat.components)
    lamb = mats.copy()
    lamb[:, 0] = 0.0
    lamb[:, 2] = 0.0
    np.testing.assert_allclose(shaded_photocentre_offset(shape, lamb, 0.0, 1.0, Rb, sun, obs),
                               photocentre_offset(shape, Rb, sun, obs), atol=1e-12)
    # ambient light only: every visible facet shines by its projected area, whose weighted centres of a closed
    # convex body's front faces are the silhouette's centroid: the body's centre for a centred cuboid
    np.testing.assert_allclose(shaded_photocentre_offset(shape, mats, 0.3, 0.0, Rb, sun, obs), 0.0, atol=1e-12)


def test_range_ratio_moments_against_a_brute_force_loop():
    rng = np.random.default_rng([23, 6, 11])
    ratio = 1.0 + 2.0 * rng.random(3000)
    area = 1.0 + ratio + 0.5 * rng.random(3000)
    lo = 1.0 + 0.5 * np.arange(4)
    hi = lo + 0.5
    ac = np.array([2.5, 3.1, 3.6, 4.2])
    m, s = range_ratio_statistics(ratio, area, lo, hi, ac)
    for k in range(4):
        sel = (ratio >= lo[k]) & ((ratio < hi[k]) if k < 3 else (ratio <= hi[k]))
        q = [math.sqrt(ac[k] / a) for a in area[sel]]
        assert m[k] == pytest.approx(np.mean(q), rel=1e-12)
        assert s[k] == pytest.approx(np.std(q), rel=1e-9)
    # the relopt area (E[A^-1/2] / E[A^-1])^2 is biased short: m_q = E[A^-1/2]^2 / E[A^-1] <= 1
    sel = (ratio >= lo[1]) & (ratio < hi[1])
    rel = (np.mean(area[sel] ** -0.5) / np.mean(1 / area[sel])) ** 2
    m2, _ = range_ratio_statistics(ratio, area, lo, hi, np.full(4, rel))
    assert m2[1] == pytest.approx(np.mean(area[sel] ** -0.5) ** 2 / np.mean(1 / area[sel]), rel=1e-12)
    assert m2[1] < 1.0
    mq, sq = range_ratio_at(np.array([1.25, np.nan]), 0.5 * (lo + hi), m, s)
    assert mq[0] == pytest.approx(m[0]) and math.isnan(mq[1])
