"""The close preset's blobber range model (issue 23 point 6 c): the calibration's kernel regression
(nav/blobber_range_error.RangeRatioCalibration) against a brute-force loop and a known conditional mean; the filter's
multiplicative range sigma (relative_filter.run, range_sig_frac) unbiased where a sigma from the measured range is
short by the analytic 2 s^2; the kind's range model and its cut-blob test (jobs/kinds/rendezvous_measure, rendezvous_context) against hand-built
expectations."""

import math

import numpy as np

from dualsight.nav.relative_filter import FilterConfig
from dualsight.jobs.kinds import rendezvous_context, rendezvous_measure
from dualsight.nav import relative_filter as rf
from dualsight.nav.blobber_range_error import RangeRatioCalibration
from dualsight.scene import relative_orbit as ro


def test_kernel_regression_against_a_brute_force_loop():
    rng = np.random.default_rng([23, 1])
    n, r, q = 10 ** rng.uniform(1, 4, 300), rng.uniform(1, 3, 300), 1 + 0.05 * rng.normal(size=300)
    q[5] = np.nan                                          # ignored
    cal = RangeRatioCalibration(n, r, q, bw_log_n=0.3, bw_ratio=0.2, chunk=7)
    nq, rq = np.array([30.0, 500.0, 2000.0, np.nan]), np.array([1.5, 2.2, 2.9, 2.0])
    m, s, ne = cal.at(nq, rq)
    ok = np.isfinite(q)
    for j in range(3):
        w = np.array([math.exp(-0.5 * (((math.log10(n[i]) - math.log10(nq[j])) / 0.3) ** 2
                                       + ((r[i] - rq[j]) / 0.2) ** 2)) for i in range(300) if ok[i]])
        qs = q[ok]
        mm = np.sum(w * qs) / np.sum(w)
        assert math.isclose(m[j], mm, rel_tol=1e-12)
        assert math.isclose(s[j], math.sqrt(np.sum(w * (qs - mm) ** 2) / np.sum(w)), rel_tol=1e-9)
        assert math.isclose(ne[j], np.sum(w) ** 2 / np.sum(w ** 2), rel_tol=1e-9)
    assert np.isnan(m[3]) and np.isnan(s[3]) and np.isnan(ne[3])


def test_kernel_regression_recovers_a_known_conditional_mean_and_spread():
    """q = 1 + 0.03 (ratio - 2) - 0.01 log10(n / 100) + N(0, 0.04): linear, so the kernel estimate in the
    interior is the line (symmetric kernel over a uniform density) and the spread is 0.04."""
    rng = np.random.default_rng([23, 2])
    M = 40000
    n, r = 10 ** rng.uniform(1, 4, M), rng.uniform(1, 3, M)
    q = 1 + 0.03 * (r - 2) - 0.01 * np.log10(n / 100) + 0.04 * rng.normal(size=M)
    m, s, ne = RangeRatioCalibration(n, r, q).at(np.array([50.0, 300.0, 3000.0]), np.array([1.6, 2.0, 2.4]))
    truth = 1 + 0.03 * (np.array([1.6, 2.0, 2.4]) - 2) - 0.01 * np.log10(np.array([50.0, 300.0, 3000.0]) / 100)
    se = 0.04 / np.sqrt(ne)
    assert np.all(np.abs(m - truth) < 4 * se + 2e-4), (m, truth, se)
    np.testing.assert_allclose(s, 0.04, rtol=0.15)


def test_range_sigma_from_the_predicted_range_is_unbiased_and_from_the_measured_one_is_not():
    """A stationary chaser 50 m behind on V-bar (a CW equilibrium), 40 ranges with a 10 % multiplicative error:
    with the sigma a fraction of the predicted range the mean estimate over 4000 runs is the truth (within 4
    standard errors); with the sigma that fraction of each measured range it is short by about 2 s^2 = 2 % (weights
    1 / z^2: E[1/z] / E[1/z^2] = rho (1 - 2 s^2) to second order)."""
    orbit = ro.CircularOrbit(altitude_m=500e3)
    B, T, s = 4000, 40, 0.10
    rng = np.random.default_rng([23, 3])
    truth = np.array([0.0, -50.0, 0.0, 0.0, 0.0, 0.0])
    z = 50.0 * (1 + s * rng.normal(size=(B, T)))
    x0 = np.broadcast_to(truth, (B, 6)).copy()
    P0 = np.broadcast_to(np.diag([1e-6, 25.0, 1e-6, 1e-12, 1e-12, 1e-12]), (B, 6, 6)).copy()
    times = np.arange(T) * 1.0
    cfg = FilterConfig(accel_psd=0.0)
    xs, Ps = rf.run(x0, P0, times, orbit, cfg, ranges=z, range_sig_frac=np.full((B, T), s))
    est = -xs[:, -1, 1]
    se = np.std(est) / math.sqrt(B)
    assert abs(est.mean() - 50.0) < 4 * se, (est.mean(), se)
    xs2, _ = rf.run(x0, P0, times, orbit, cfg, ranges=z, range_sig=s * z)
    bias = -xs2[:, -1, 1].mean() / 50.0 - 1
    assert -0.026 < bias < -0.014, bias
    # the stated sigma matches the scatter (consistency)
    assert 0.85 < np.std(est) / math.sqrt(Ps[:, -1, 1, 1].mean()) < 1.15


def test_range_model_takes_the_calibration_at_the_blobs_coverage_and_ratio():
    cal = RangeRatioCalibration(np.array([100.0, 100.0, 100.0]), np.array([2.0, 2.0, 2.0]),
                                np.array([0.96, 0.98, 1.00]))     # mean 0.98, sd sqrt(2/3) 0.02
    ctx = rendezvous_context.RendezvousContext(None, None, (), range_ratio=(np.array([1.0, 3.0]), np.array([0.5, 0.5]),
                                                            np.array([0.5, 0.5])), range_calibration=cal)
    m = {"range_used": np.array([True, False]), "range": np.array([10.0, np.nan]),
         "axis_ratio": np.array([2.0, np.nan]), "n_blob": np.array([100.0, np.nan])}
    rendezvous_measure.range_model(ctx, m)
    sd = math.sqrt(2 / 3) * 0.02
    np.testing.assert_allclose(m["range_filter"][0], 10.0 / 0.98)
    np.testing.assert_allclose(m["range_sigma_frac"][0], sd / 0.98)
    np.testing.assert_allclose(m["range_sigma"][0], 10.0 * sd / 0.98 ** 2)
    assert np.isnan(m["range_filter"][1]) and np.isnan(m["range_sigma_frac"][1])


def test_touches_edge_at_the_first_and_last_rows_and_columns():
    class Cam:
        width, height = 100, 80
    box = np.array([[0, 10, 20, 30], [10, 0, 20, 30], [10, 10, 99, 30], [10, 10, 20, 79], [1, 1, 98, 78]])
    np.testing.assert_array_equal(rendezvous_context.touches_edge(box, Cam()), [True, True, True, True, False])
