"""Attitude trajectories of tracking sequences (scene/attitude_trajectory.py).

Independent truths: the rotation angle and axis of ``A(t) A0^T`` from the trace and the antisymmetric part (plain
numpy here), Rodrigues' formula of the test helpers, the analytic trapezoid (duration ``angle / w + w / a``), rates
by central finite differences of the attitudes, the variance of a sum of sinusoids (``sum a^2 / 2``) and of a PSD
(its integral), and the sample mean / spread of the gyro's error against its stated bias and noise.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dualsight.scene.attitude import euler123_to_dcm, random_euler123
from dualsight.scene.attitude_trajectory import (BLANK, BLINDED, DROPPED, NORMAL, add_jitter, constant_rate,
                                                 eigenaxis_slew, frame_events, gyro_rates, jitter_from_psd,
                                                 sinusoid_jitter, slew_duration, slew_profile)
from helpers import rotation, unit


def angle_axis(R):
    """Rotation angle (rad) and axis of the passive rotations R (..., 3, 3): the angle from the trace, the axis
    from the antisymmetric part (R = I - sin t [u x] + ...)."""
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)
    s = 0.5 * np.stack([R[..., 1, 2] - R[..., 2, 1], R[..., 2, 0] - R[..., 0, 2], R[..., 0, 1] - R[..., 1, 0]], -1)
    with np.errstate(invalid="ignore"):
        return np.arccos(c), unit(s)


def fd_rate(A, times):
    """Body rates at the inner samples by central differences: dA/dt A^T = -[omega x]."""
    h = times[2:] - times[:-2]
    W = -np.einsum("tij,tkj->tik", A[2:] - A[:-2], A[1:-1]) / h[:, None, None]
    return 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], -1)


def test_constant_rate_turns_by_rate_times_time():
    rng = np.random.default_rng(1)
    A0 = euler123_to_dcm(random_euler123(rng, 1))[0]
    w = unit(np.array([0.2, -0.5, 1.0])) * math.radians(1.5)
    t = np.linspace(0, 100, 1001)                               # up to 150 deg
    A, om = constant_rate(t, A0, w)
    ang, ax = angle_axis(A @ A0.T)
    np.testing.assert_allclose(ang, np.linalg.norm(w) * t, atol=1e-12)
    np.testing.assert_allclose(ax[1:], np.broadcast_to(unit(w), (1000, 3)), atol=1e-12)
    np.testing.assert_allclose(A[500], rotation(w, np.linalg.norm(w) * 50).T @ A0, atol=1e-14)
    np.testing.assert_allclose(fd_rate(A, t), om[1:-1], atol=1e-7)
    np.testing.assert_allclose(np.einsum("tij,tkj->tik", A, A), np.broadcast_to(np.eye(3), A.shape), atol=1e-14)


@pytest.mark.parametrize("angle_deg, w_deg, a_deg", [(30.0, 2.0, 0.5), (3.0, 2.0, 0.5), (0.4, 1.0, 4.0)])
def test_slew_reaches_the_target_with_the_limits_held(angle_deg, w_deg, a_deg):
    """Trapezoid (30 deg: 4 s ramps) and triangles (3 deg, 0.4 deg): the target attitude at the end, rate and
    acceleration (finite differences) within the limits, the analytic duration, rest before and after."""
    rng = np.random.default_rng(2)
    A0 = euler123_to_dcm(random_euler123(rng, 1))[0]
    axis = unit(rng.normal(size=3))
    angle, w, a = math.radians(angle_deg), math.radians(w_deg), math.radians(a_deg)
    A1 = rotation(axis, angle).T @ A0
    T = slew_duration(angle, w, a)
    want_T = angle / w + w / a if angle >= w * w / a else 2 * math.sqrt(angle / a)
    assert T == pytest.approx(want_T, rel=1e-12)
    t = np.linspace(-1.0, T + 1.0, 20001) + 0.5
    A, om = eigenaxis_slew(t, A0, A1, w, a, t_start=0.5)
    np.testing.assert_allclose(A[-1], A1, atol=1e-12)
    np.testing.assert_allclose(A[0], A0, atol=1e-15)
    np.testing.assert_allclose(fd_rate(A, t), om[1:-1], atol=2e-4 * w + 1e-9)
    speed = np.linalg.norm(om, axis=1)
    assert speed.max() <= w * (1 + 1e-12)
    acc = np.abs(np.diff(speed) / np.diff(t))
    assert acc.max() <= a * (1 + 1e-6)
    end = t - 0.5 >= T
    assert np.all(speed[(t < 0.5) | end] == 0)
    theta, rate = slew_profile(t, angle, w, a, 0.5)
    np.testing.assert_allclose(np.cumsum(rate[:-1] * np.diff(t))[-1], angle, rtol=1e-3)      # rate integrates
    if angle >= w * w / a:
        assert speed.max() == pytest.approx(w)


def test_jitter_rates_match_finite_differences_and_the_spectrum():
    """Sinusoids of 0.03-0.6 deg on a 2 deg/s base: the exact rate of the composition against central differences
    with h = 1e-6 s (the Jacobian's nonlinear terms are ~1e-3 of the rate here, far above the 1e-8 checked)."""
    rng = np.random.default_rng(3)
    t = np.linspace(0, 20, 40001)
    f = np.array([0.7, 3.0, 11.0])
    amp = np.radians(np.array([[0.3, 0.1, 0.6], [0.1, 0.05, 0.1], [0.03, 0.02, 0.05]]))
    d, dd = sinusoid_jitter(t, f, amp, rng)
    np.testing.assert_allclose(np.var(d, axis=0), 0.5 * np.sum(amp ** 2, axis=0), rtol=0.02)
    h, tk = 1e-6, np.linspace(0, 20, 2001)
    d, dd = sinusoid_jitter(np.concatenate([tk - h, tk, tk + h]), f, amp, np.random.default_rng(3))
    A0 = euler123_to_dcm(random_euler123(rng, 1))[0]
    Ab, wb = constant_rate(np.concatenate([tk - h, tk, tk + h]), A0, np.radians([0.5, 0.0, 2.0]))
    A, om = add_jitter(Ab, wb, d, dd)
    n = tk.size
    W = -np.einsum("tij,tkj->tik", A[2 * n:] - A[:n], A[n:2 * n]) / (2 * h)             # -[omega x]
    fd = 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], -1)
    np.testing.assert_allclose(fd, om[n:2 * n], atol=1e-8)
    assert np.abs(om[n:2 * n] - (dd[n:2 * n] + wb[n:2 * n])).max() > 1e-5         # the exact terms matter
    # a flat PSD of 1e-10 rad^2/Hz over 1-50 Hz: variance = integral = 4.9e-9 rad^2 per axis
    fg = np.arange(1.0, 50.0 + 1e-9, 0.5)
    d, _ = jitter_from_psd(t, fg, np.full(fg.size, 1e-10), np.random.default_rng(4))
    np.testing.assert_allclose(np.var(d, axis=0), 1e-10 * 0.5 * fg.size, rtol=0.05)


def test_gyro_bias_and_noise():
    rng = np.random.default_rng(5)
    T, dt = 20000, 0.1
    w = np.tile(np.radians([0.1, -0.2, 0.3]), (T, 1))
    bias = np.radians([0.01, -0.02, 0.005])
    sig = math.radians(0.003)
    g, b = gyro_rates(w, dt, rng, bias=bias, noise_rad_s=sig)
    err = g - w
    assert np.all(np.abs(err.mean(0) - bias) < 4 * sig / math.sqrt(T))
    np.testing.assert_allclose(err.std(0), sig, rtol=0.03)
    np.testing.assert_array_equal(b, np.broadcast_to(bias, (T, 3)))
    # bias random walk: the bias' increments over dt have sigma_b sqrt(dt)
    g, b = gyro_rates(w, dt, rng, bias=bias, bias_walk_rad_s2_rthz=1e-5)
    np.testing.assert_allclose(np.diff(b, axis=0).std(0), 1e-5 * math.sqrt(dt), rtol=0.03)
    assert np.array_equal(b[0], bias)


def test_frame_events():
    ev = frame_events(10, blank=[1], blinded=[4, 5], dropped=[9])
    assert ev.tolist() == [NORMAL, BLANK, 0, 0, BLINDED, BLINDED, 0, 0, 0, DROPPED]
    ev = frame_events(100000, np.random.default_rng(6), p_blank=0.01, p_blinded=0.02, p_dropped=0.03)
    frac = np.bincount(ev, minlength=4) / ev.size
    np.testing.assert_allclose(frac[1:], [0.01, 0.02, 0.03], atol=0.002)
    a = frame_events(50, np.random.default_rng([3, 7]), p_dropped=0.5)
    assert np.array_equal(a, frame_events(50, np.random.default_rng([3, 7]), p_dropped=0.5))   # the case's rng only
