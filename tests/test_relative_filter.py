"""The relative-navigation EKF (nav/relative_filter.py, issue 23 point 4) against cases with a known answer: single
range and bearing updates against the scalar Kalman formulas, the process noise against the double integrator's
closed form and a brute-force quadrature, convergence on perfect measurements, range unobservable from bearings
alone until a known manoeuvre (Woffinden & Geller 2009), NEES over 100 Monte Carlo runs against chi-square bounds,
and the chi-square bounds against the exact even-dof distribution."""

import math

import numpy as np

from dualsight.nav.relative_filter import FilterConfig
from dualsight.nav import relative_filter as rf
from dualsight.scene import relative_orbit as ro

ORBIT = ro.CircularOrbit(altitude_m=500e3, inclination_rad=math.radians(51.6), raan_rad=math.radians(120.0),
                         arg_lat_rad=math.radians(10.0))
N = ORBIT.mean_motion


def rot(axis, ang):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K


def los_icrs(truth, R):
    """(B, T, 3) ICRS lines of sight chaser -> target from Hill truth (B, T, 6) and rotations (T, 3, 3)."""
    rho = truth[..., :3]
    return -np.einsum("tij,btj->bti", R, rho / np.linalg.norm(rho, axis=-1, keepdims=True))


def perturb(u, sigma, rng):
    """Unit vectors u (..., 3) moved by isotropic Gaussian angles of sigma per axis across them."""
    e = rng.normal(size=u.shape) * sigma
    e -= np.sum(e * u, -1, keepdims=True) * u
    v = u + e
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_range_update_scalar_kalman():
    p, s, d = 25.0, 3.0, 4.0
    x = np.array([[1000.0, 0, 0, 0, 0, 0]])
    P = np.diag([p, p, p, 1e-4, 1e-4, 1e-4])[None]
    xn, Pn = rf.range_update(x, P, np.array([1000.0 + d]), s)
    assert math.isclose(xn[0, 0], 1000 + p / (p + s * s) * d, rel_tol=1e-12)
    assert math.isclose(Pn[0, 0, 0], p * s * s / (p + s * s), rel_tol=1e-12)
    assert np.allclose(xn[0, 1:], 0) and np.allclose(Pn[0, 1:, 1:], P[0, 1:, 1:])
    assert math.isclose(float(rf.range_sigma(10.0, 16.0)), 6 / math.sqrt(12), rel_tol=1e-15)


def test_bearing_update_scalar_kalman_through_rotation():
    # chaser 1000 m behind the target on V-bar: the line of sight is +y (Hill), R y^ in ICRS.  The measurement
    # shows the target delta rad towards +x (radial): the chaser sits at x = -1000 tan(delta)
    R = rot([0.3, -1.0, 0.5], 2.1)
    r, p, sig, delta = 1000.0, 4.0, 2e-3, 1e-5
    u_m = math.cos(delta) * R[:, 1] + math.sin(delta) * R[:, 0]
    x = np.array([[0.0, -r, 0, 0, 0, 0]])
    P = np.diag([p, p, p, 1e-4, 1e-4, 1e-4])[None]
    xn, Pn = rf.bearing_update(x, P, u_m[None], rf.isotropic_bearing_cov(u_m[None], sig), R)
    m2 = (r * sig) ** 2                          # measurement variance in metres across the line of sight
    assert math.isclose(xn[0, 0], -r * delta * p / (p + m2), rel_tol=1e-6)
    assert abs(xn[0, 1] + r) < 1e-6 and abs(xn[0, 2]) < 1e-9
    assert math.isclose(Pn[0, 0, 0], p * m2 / (p + m2), rel_tol=1e-6)
    assert math.isclose(Pn[0, 2, 2], p * m2 / (p + m2), rel_tol=1e-6)
    assert math.isclose(Pn[0, 1, 1], p, rel_tol=1e-9)                   # no information along the line of sight


def test_process_noise_against_double_integrator_and_quadrature():
    q, dt = 1e-10, 20.0
    Q0 = rf.process_noise(1e-12, dt, q)          # n -> 0: white acceleration on a double integrator
    I3 = np.eye(3)
    ref = q * np.block([[dt ** 3 / 3 * I3, dt ** 2 / 2 * I3], [dt ** 2 / 2 * I3, dt * I3]])
    assert np.allclose(Q0, ref, rtol=1e-9, atol=1e-10 * ref.max())
    dt = 900.0                                   # n dt ~ 1: brute-force trapezoid over 4001 nodes
    tau = np.linspace(0, dt, 4001)
    G = ro.cw_stm(N, tau)[:, :, 3:]
    f = np.einsum("kia,kja->kij", G, G)
    brute = q * (tau[1] - tau[0]) * (f.sum(0) - 0.5 * (f[0] + f[-1]))
    assert np.allclose(rf.process_noise(N, dt, q), brute, rtol=1e-6, atol=1e-9 * np.abs(brute).max())


def test_perfect_range_and_bearings_converge_to_truth():
    times = np.arange(0, 1200.0, 10.0)
    truth0 = np.array([[30.0, -150.0, 12.0, 0.02, 0.05, -0.01]])
    truth = ro.propagate(truth0, times, N)
    R = ro.hill_to_icrs(ORBIT, times)
    u = los_icrs(truth, R)
    cov = rf.isotropic_bearing_cov(u.reshape(-1, 3), 1e-9).reshape(1, -1, 3, 3)
    rng_m = np.linalg.norm(truth[..., :3], axis=-1)
    x0 = truth0 + np.array([[8.0, -20.0, -5.0, 0.01, -0.02, 0.01]])
    P0 = np.diag([30.0 ** 2] * 3 + [0.05 ** 2] * 3)[None]
    # iterated EKF: the prior is 22 m off at 150 m (8 deg), too far for one linearisation against 1 nrad bearings
    cfg = FilterConfig(accel_psd=1e-16, iterations=3)
    xs, Ps = rf.run(x0, P0, times, ORBIT, cfg, bearings=u, bearing_cov=cov, ranges=rng_m,
                    range_sig=np.full_like(rng_m, 1e-4))
    err = xs[0] - truth[0]
    assert np.linalg.norm(err[0, :3]) < 1e-6     # the first frame fixes the position ...
    assert np.linalg.norm(err[0, 3:]) > 1e-2     # ... but not the velocity
    assert np.linalg.norm(err[-1, :3]) < 1e-6 and np.linalg.norm(err[-1, 3:]) < 1e-9
    assert np.all(np.sqrt(np.diagonal(Ps[0, -1])[:3]) < 1e-4)


def los_variance(x, P):
    rh = x[:, :3] / np.linalg.norm(x[:, :3], axis=-1, keepdims=True)
    return np.einsum("bi,bij,bj->b", rh, P[:, :3, :3], rh)


def bearings_only(dv_times, dv, seed):
    """Chaser on V-bar 2 km behind, 1.5 orbits of bearings every 30 s (sigma 10 urad), no range."""
    times = np.arange(0, 1.5 * ORBIT.period_s, 30.0)
    truth0 = np.array([[0.0, -2000.0, 0.0, 0.0, 0.0, 0.0]])
    truth = ro.propagate(truth0, times, N, dv_times=dv_times, dv=dv)
    R = ro.hill_to_icrs(ORBIT, times)
    rng = np.random.default_rng([23, 4, seed])
    u = perturb(los_icrs(truth, R), 1e-5, rng)
    cov = rf.isotropic_bearing_cov(u.reshape(-1, 3), 1e-5).reshape(1, -1, 3, 3)
    x0 = truth0 * 0.8                            # 20 % short in range, on the right line of sight
    P0 = np.diag([400.0 ** 2] * 3 + [0.05 ** 2] * 3)[None]
    xs, Ps = rf.run(x0, P0, times, ORBIT, FilterConfig(accel_psd=1e-16), bearings=u, bearing_cov=cov,
                    dv_times=dv_times, dv=dv)
    return truth[0], xs[0], Ps[0]


def test_range_unobservable_from_bearings_until_a_known_manoeuvre():
    truth, xs, Ps = bearings_only((), None, 1)
    sd_end = math.sqrt(los_variance(xs[-1:], Ps[-1:])[0])
    assert sd_end > 100.0                        # still ~ the prior 400 m along the line of sight
    r_err = abs(np.linalg.norm(xs[-1, :3]) - np.linalg.norm(truth[-1, :3]))
    assert r_err > 100.0                         # and the 20 % range error stays
    # one known hop (0.1 m/s along-track at t = 1000 s) makes the range observable
    truth, xs, Ps = bearings_only([1000.0], np.array([[0.0, 0.1, 0.0]]), 1)
    sd_end = math.sqrt(los_variance(xs[-1:], Ps[-1:])[0])
    rng_end = np.linalg.norm(truth[-1, :3])
    assert sd_end < 0.02 * rng_end
    assert abs(np.linalg.norm(xs[-1, :3]) - rng_end) < 3 * sd_end + 1.0


def test_nees_over_100_runs_within_chi2_bounds():
    runs, q, dt = 100, 1e-10, 10.0
    times = np.arange(0, 600.0, dt)
    rng = np.random.default_rng([23, 4, 100])
    nominal = np.array([20.0, -120.0, 10.0, 0.0, 0.06, 0.0])
    P0 = np.diag([10.0 ** 2] * 3 + [0.02 ** 2] * 3)
    x0 = nominal + rng.normal(size=(runs, 6)) @ np.linalg.cholesky(P0).T   # filter starts at the nominal
    # truth with the process noise the filter assumes
    Lq = np.linalg.cholesky(rf.process_noise(N, dt, q))
    Phi = ro.cw_stm(N, dt)
    truth = np.empty((runs, times.size, 6))
    truth[:, 0] = x0
    for k in range(1, times.size):
        truth[:, k] = truth[:, k - 1] @ Phi.T + rng.normal(size=(runs, 6)) @ Lq.T
    R = ro.hill_to_icrs(ORBIT, times)
    sig_b = 2e-4
    u = perturb(los_icrs(truth, R), sig_b, rng)
    cov = rf.isotropic_bearing_cov(u.reshape(-1, 3), sig_b).reshape(runs, -1, 3, 3)
    w = 8.0                                      # the blobber's interval: the truth uniform inside [min, min + w]
    rmin = np.linalg.norm(truth[..., :3], axis=-1) - rng.uniform(0, w, (runs, times.size))
    rmax = rmin + w
    rng_m = 0.5 * (rmin + rmax)
    xs, Ps = rf.run(np.broadcast_to(nominal, (runs, 6)), np.broadcast_to(P0, (runs, 6, 6)), times, ORBIT,
                    FilterConfig(accel_psd=q, iterations=3), bearings=u, bearing_cov=cov, ranges=rng_m,
                    range_sig=rf.range_sigma(rmin, rmax))
    mean_nees = rf.nees(xs, Ps, truth).mean(0)    # (T,)
    lo, hi = rf.chi2_mean_bounds(6, runs, 0.95)
    after = mean_nees[10:]                        # after convergence (100 s)
    inside = (after > lo) & (after < hi)
    assert inside.mean() >= 0.9, (lo, hi, after)  # 95 % bounds per frame: a few frames outside by chance
    assert 5.4 < after.mean() < 6.6


def chi2_quantile_even(p, k):
    """Exact chi-square quantile for even k: CDF 1 - exp(-x/2) sum_{j<k/2} (x/2)^j / j! (log space), bisection."""
    def cdf(x):
        j = np.arange(k // 2)
        logt = j * math.log(x / 2) - np.array([math.lgamma(i + 1) for i in j]) - x / 2
        return 1 - np.exp(logt).sum()
    lo, hi = 0.0, 10.0 * k
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
    return lo


def test_chi2_mean_bounds_against_exact_distribution():
    assert math.isclose(chi2_quantile_even(0.975, 6), 14.4494, rel_tol=1e-4)   # table value (Abramowitz-Stegun)
    assert math.isclose(chi2_quantile_even(0.025, 6), 1.2373, rel_tol=1e-3)
    lo, hi = rf.chi2_mean_bounds(6, 100, 0.95)
    assert math.isclose(lo, chi2_quantile_even(0.025, 600) / 100, rel_tol=1e-4)
    assert math.isclose(hi, chi2_quantile_even(0.975, 600) / 100, rel_tol=1e-4)
    # the NEES of a consistent estimate is chi-square: brute force
    rng = np.random.default_rng([23, 4, 7])
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    e = rng.normal(size=(200000, 2)) @ np.linalg.cholesky(P).T
    assert abs(rf.nees(e, np.broadcast_to(P, (200000, 2, 2)), np.zeros(2)).mean() - 2.0) < 0.02


def test_filter_config_refuses_values_out_of_range():
    """FilterConfig (nav/relative_filter.py): one ConfigError naming the field and its range."""
    import pytest

    from dualsight.errors import ConfigError

    for kw, text in [({"accel_psd": -1e-12}, "filter.accel_psd"), ({"iterations": 0}, "filter.iterations"),
                     ({"dv_sigma_frac": 1.5}, "filter.dv_sigma_frac"), ({"dv_sigma_m_s": float("nan")}, "dv_sigma_m_s")]:
        with pytest.raises(ConfigError, match=text.replace(".", r"\.")):
            FilterConfig(**kw)
    assert FilterConfig(accel_psd=0.0, iterations=20).iterations == 20
