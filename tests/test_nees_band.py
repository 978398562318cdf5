"""The simultaneous band of a mean NEES over a run of frames (nav/nees_band.py), against independent truth: Sidak's
level for independent frames, the one-frame bounds for fully persistent ones, the identity corr(x^2, y^2) = c^2 for
correlated normals, and a brute-force simulation of consistent filters' chi-square NEES."""

import numpy as np
from hypothesis import given, settings, strategies as st

from dualsight.nav.nees_band import inside_probability, lag1_correlation, simultaneous_level, simultaneous_mean_bounds
from dualsight.nav.relative_filter import chi2_mean_bounds


def ar1_nees(rng, runs, approaches, frames, rho, dof=6):
    """(runs, approaches, frames) NEES of exactly Gaussian unit errors, each an AR(1) with correlation rho."""
    e = rng.normal(size=(runs, approaches, dof))
    out = np.empty((runs, approaches, frames))
    for k in range(frames):
        if k:
            e = rho * e + np.sqrt(1.0 - rho * rho) * rng.normal(size=e.shape)
        out[..., k] = (e * e).sum(-1)
    return out


def test_independent_frames_give_sidaks_level():
    for frames in (10, 54):
        sidak = 1.0 - 0.95 ** (1.0 / frames)
        assert abs(simultaneous_level(frames, 0.0) / sidak - 1.0) < 0.08


def test_fully_persistent_frames_give_the_one_frame_level():
    assert abs(simultaneous_level(54, 1.0) - 0.05) < 0.004
    lo, hi, _ = simultaneous_mean_bounds(6, 100, 54, 1.0)
    lo1, hi1 = chi2_mean_bounds(6, 100, 0.95)
    assert abs(lo - lo1) < 0.02 and abs(hi - hi1) < 0.02


def test_lag1_correlation_of_ar1_chi_square_is_rho_squared():
    rng = np.random.default_rng(4)
    nees = ar1_nees(rng, 1, 20_000, 6, 0.9)[0]
    assert abs(lag1_correlation(nees) - 0.81) < 0.015
    nees = ar1_nees(rng, 1, 20_000, 6, 0.0)[0]
    assert abs(lag1_correlation(nees)) < 0.02


def test_a_consistent_filter_stays_inside_the_band_at_every_frame_95_percent_of_the_time():
    rng = np.random.default_rng(9)
    runs, M, F, rho = 4000, 100, 30, np.sqrt(0.85)
    means = ar1_nees(rng, runs, M, F, rho).mean(1)                 # (runs, F) a campaign's mean NEES per frame
    lag1 = lag1_correlation(ar1_nees(rng, 1, 20_000, F, rho)[0])
    lo, hi, a = simultaneous_mean_bounds(6, M, F, lag1)
    inside_all = np.mean(np.all((means >= lo) & (means <= hi), axis=1))
    assert abs(inside_all - 0.95) < 0.015                          # 4000 runs: 1 sigma 0.0034
    lo1, hi1 = chi2_mean_bounds(6, M, 0.95)                        # the one-frame bounds at every frame: far less
    p1 = np.mean(np.all((means >= lo1) & (means <= hi1), axis=1))
    assert p1 < 0.75 and abs(inside_probability(F, lag1) - p1) < 0.03
    assert lo < lo1 and hi > hi1 and 0.0 < a < 0.05


@settings(max_examples=15, deadline=None)
@given(frames=st.integers(2, 60), lag1=st.floats(0.0, 0.999))
def test_the_level_lies_between_sidaks_and_the_one_frame_level(frames, lag1):
    a = simultaneous_level(frames, lag1, samples=4000)
    sidak = 1.0 - 0.95 ** (1.0 / frames)
    assert 0.8 * sidak <= a <= 0.05 * 1.2


def test_the_one_frame_bounds_hold_independent_frames_095_to_the_power_f_and_persistent_ones_095():
    for frames in (5, 20):
        assert abs(inside_probability(frames, 0.0) - 0.95 ** frames) < 0.006
    assert abs(inside_probability(54, 1.0) - 0.95) < 0.004
