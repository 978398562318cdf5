"""Attitude from identified stars (SVD, Markley 1988) and the reference's error metrics (Eqs. 4-7), against
analytic rotations, Markley's covariance and the definitions written out literally."""

from __future__ import annotations

import numpy as np
import pytest

from dualsight.nav.attitude import svd_attitude
from dualsight.nav.errors import (CONFIDENT_WRONG, NO_SOLUTION, STATUS_NAMES, SUCCESS, axis_errors, classify,
                                  total_error_angle)
from dualsight.scene.attitude import quat_to_dcm, random_quaternions, rot_axis
from dualsight.scene.units import ARCSEC

from helpers import rotation, unit


# ------------------------------------------------------------------------------------------ SVD


def test_svd_recovers_rotation_from_noiseless_vectors():
    rng = np.random.default_rng(1)
    B, S = 64, 7
    A_true = quat_to_dcm(random_quaternions(rng, B))
    ref = unit(rng.normal(size=(B, S, 3)))
    obs = np.einsum("bij,bsj->bsi", A_true, ref)
    w = rng.uniform(0.1, 2.0, (B, S))
    A, ok = svd_attitude(obs, ref, w)
    assert ok.all()
    np.testing.assert_allclose(A, A_true, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(A), 1.0, atol=1e-12)


def test_svd_padding_and_degenerate_cases():
    rng = np.random.default_rng(2)
    A_true = quat_to_dcm(random_quaternions(rng, 4))
    ref = unit(rng.normal(size=(4, 5, 3)))
    obs = np.einsum("bij,bsj->bsi", A_true, ref)
    w = np.ones((4, 5))
    w[0, 3:] = 0.0
    obs[0, 3:] = np.nan                                   # padding may hold NaN
    w[1, 1:] = 0.0                                        # one vector: undetermined
    ref[2, 1] = ref[2, 0]                                  # two parallel vectors: undetermined
    obs[2, 1] = obs[2, 0]
    w[2, 2:] = 0.0
    w[3, 2:] = 0.0                                        # two vectors: enough
    A, ok = svd_attitude(obs, ref, w)
    assert ok.tolist() == [True, False, False, True]
    np.testing.assert_allclose(A[[0, 3]], A_true[[0, 3]], atol=1e-12)
    assert np.isnan(A[1]).all() and np.isnan(A[2]).all()


def test_svd_non_finite_case_fails_alone():
    """A case whose profile matrix is not finite (an infinite weight, a NaN vector with weight) has no attitude;
    the other cases of the batch are solved as alone, and nothing is raised or warned."""
    import warnings

    rng = np.random.default_rng(3)
    A_true = quat_to_dcm(random_quaternions(rng, 3))
    ref = unit(rng.normal(size=(3, 6, 3)))
    obs = np.einsum("bij,bsj->bsi", A_true, ref)
    w = np.ones((3, 6))
    w[0, 2] = np.inf
    obs[2, 4] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        A, ok = svd_attitude(obs, ref, w)
    assert ok.tolist() == [False, True, False]
    assert np.isnan(A[[0, 2]]).all()
    np.testing.assert_allclose(A[1], A_true[1], atol=1e-12)


def test_svd_noise_matches_markley_covariance():
    """Monte Carlo errors of noisy observations against Markley's covariance (QUEST noise model)."""
    rng = np.random.default_rng(3)
    B, S, sigma = 4000, 8, 2e-4
    A_true = quat_to_dcm(random_quaternions(rng, 1))[0]
    # a fixed field of 8 stars within ~8 deg of the boresight, re-observed with fresh noise each trial
    r_cam = unit(np.concatenate([rng.uniform(-0.14, 0.14, (S, 2)), np.ones((S, 1))], axis=1))
    ref = np.broadcast_to(r_cam @ A_true, (B, S, 3)).copy()       # ICRS: A^T b
    noise = rng.normal(scale=sigma, size=(B, S, 3))
    noise -= np.sum(noise * r_cam, axis=-1, keepdims=True) * r_cam  # perpendicular to b (QUEST model)
    obs = unit(r_cam + noise)
    A, ok, cov = svd_attitude(obs, ref, np.full((B, S), sigma**-2), return_cov=True)
    assert ok.all()
    Th = A_true @ np.swapaxes(A, 1, 2)                     # camera-frame error rotation
    phi = 0.5 * np.stack([Th[:, 2, 1] - Th[:, 1, 2], Th[:, 0, 2] - Th[:, 2, 0], Th[:, 1, 0] - Th[:, 0, 1]], -1)
    emp = phi.T @ phi / B
    pred = cov[0]
    np.testing.assert_allclose(np.diag(emp), np.diag(pred), rtol=0.1)
    assert np.abs(phi.mean(axis=0)).max() < 4 * np.sqrt(np.diag(pred).max() / B)
    # the roll (about the boresight z) is the weakest axis for a narrow field
    assert pred[2, 2] > 5 * max(pred[0, 0], pred[1, 1])


# ------------------------------------------------------------------------------------------ errors


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("arcsec", [50.0, -50.0, 3.0])
def test_axis_errors_small_rotation(axis, arcsec):
    rng = np.random.default_rng(4)
    A_true = quat_to_dcm(random_quaternions(rng, 5))
    a = arcsec * ARCSEC
    # Theta = A_est^T A_true = active rotation by +a about the axis  <=>  A_est = A_true R_axis(a)
    A_est = A_true @ rot_axis(axis + 1, a)
    eps = axis_errors(A_est, A_true) / ARCSEC
    expect = np.zeros(3)
    expect[axis] = arcsec
    np.testing.assert_allclose(eps, np.broadcast_to(expect, eps.shape), atol=1e-6)
    # camera frame: the same error applied on the camera side
    A_est_c = rot_axis(axis + 1, a) @ A_true
    np.testing.assert_allclose(axis_errors(A_est_c, A_true, frame="camera") / ARCSEC,
                               np.broadcast_to(expect, eps.shape), atol=1e-6)
    np.testing.assert_allclose(total_error_angle(A_est, A_true) / ARCSEC, abs(arcsec), rtol=1e-6)


def test_axis_errors_are_eqs_4_to_7_literally():
    rng = np.random.default_rng(5)
    A_true = quat_to_dcm(random_quaternions(rng, 20))
    A_est = quat_to_dcm(random_quaternions(rng, 20))
    Th = np.linalg.inv(A_est) @ A_true                  # R_calc^-1 R_actual
    phi = np.stack([Th[:, 2, 1], Th[:, 0, 2], Th[:, 1, 0]], -1)
    np.testing.assert_allclose(axis_errors(A_est, A_true), np.pi / 2 - np.arccos(phi), atol=1e-12)


def test_total_angle_and_180_degree_trap():
    rng = np.random.default_rng(6)
    A_true = quat_to_dcm(random_quaternions(rng, 4))
    angles = np.array([1e-7, 0.3, 2.0, np.pi])
    axes = unit(rng.normal(size=(4, 3)))
    Th = np.stack([rotation(ax, t) for ax, t in zip(axes, angles)])
    A_est = A_true @ np.swapaxes(Th, 1, 2)                 # so that A_est^T A_true = Th
    np.testing.assert_allclose(total_error_angle(A_est, A_true), angles, rtol=1e-7, atol=1e-9)
    # 180 deg about x: every phi is ~0, yet the case must fail
    flip = A_true[:1] @ rot_axis(1, np.pi)
    e = axis_errors(flip, A_true[:1])
    assert np.abs(e).max() < 1e-9
    tot = total_error_angle(flip, A_true[:1])
    assert classify(e, tot, np.array([5]))[0] == CONFIDENT_WRONG
    assert classify(e, tot, np.array([0]))[0] == NO_SOLUTION


def test_classify_codes():
    lim = 100 * ARCSEC
    err = np.array([[10, -20, 30], [0, 0, 101], [0, 0, 101], [np.nan] * 3, [99, -99, 99]]) * ARCSEC
    tot = np.linalg.norm(err, axis=1)
    T = np.array([3, 2, 0, 0, 1])
    st = classify(err, tot, T)
    assert st.tolist() == [SUCCESS, CONFIDENT_WRONG, NO_SOLUTION, NO_SOLUTION, SUCCESS]
    assert [STATUS_NAMES[k] for k in st[:3]] == ["success", "confident_wrong", "no_solution"]
    assert classify(err[:1] * 0, np.array([2 * lim]), np.array([1]))[0] == CONFIDENT_WRONG


