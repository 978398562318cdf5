"""Attitude trajectories of a star camera over an image sequence: the truth of a tracking case (issue 22, point 1).

Pure functions of ``(times (T,), parameters) -> (A (T, 3, 3), omega (T, 3))``: the attitude ``A`` maps inertial
(ICRS) vectors into the camera frame (docs/architecture.md) and ``omega`` is the true body rate (rad/s, camera
frame) with ``dA/dt = -[omega x] A`` (``scene/rotation_vector.py``).  Pieces:

* :func:`constant_rate`: ``A(t) = exp(-[omega (t - t0) x]) A0``;
* :func:`slew_profile` / :func:`eigenaxis_slew`: a rest-to-rest rotation about one axis with a trapezoidal rate
  profile (constant acceleration ``a`` up to the rate limit ``w``, coast, constant deceleration; a triangle when
  the angle is shorter than ``w^2 / a``);
* :func:`sinusoid_jitter` (a sum of sinusoids, phases drawn from the case's generator) and
  :func:`jitter_from_psd` (amplitudes from a one-sided power spectral density, ``a_k = sqrt(2 S(f_k) df)``);
  a PSD tabulated at arbitrary increasing frequencies (piecewise linear between them, zero outside) is put on an
  even grid by :func:`psd_bins` (each bin's exact mean, so the variance is the PSD's integral exactly) and drawn
  by :func:`jitter_from_psd_table`,
  laid over a base motion by :func:`add_jitter` with the exact rate of the composition
  (``omega = J_r(delta) d(delta)/dt + R(delta) omega_base``, ``J_r`` the right Jacobian of SO(3), Markley &
  Crassidis 2014, Sec. 2.9 / Barfoot 2017, Eq. 7.77);
* :func:`gyro_rates`: what a rate gyro reports, ``omega + b + n`` with a constant bias, white noise and an optional
  bias random walk;
* :func:`frame_events`: per-frame events (a blank frame, the Sun or the Earth blinding the camera, a dropped frame);
  :func:`crossing_paths`: bright objects crossing the image on straight lines over a few frames.

Random draws come only from the ``numpy.random.Generator`` handed in (the case's ``default_rng([seed, i])``), never
from global state.  Radians, seconds and hertz throughout.
"""

from __future__ import annotations

import numpy as np

from dualsight.scene.rotation_vector import cross_matrix, frame_rotation, frame_rotation_vector

__all__ = ["constant_rate", "slew_profile", "slew_duration", "eigenaxis_slew", "sinusoid_jitter", "jitter_from_psd",
           "PSD_BINS", "psd_integral", "psd_bins", "jitter_from_psd_table", "add_jitter", "right_jacobian", "gyro_rates", "EVENT_NAMES", "NORMAL", "BLANK", "BLINDED", "DROPPED",
           "CROSSING", "frame_events", "crossing_paths"]

EVENT_NAMES = ("normal", "blank", "blinded", "dropped", "crossing")
"""Per-frame event codes (index = code): a normal frame; a blank frame (no star visible: eclipse exit, lens cap,
shutter fault); a blinded frame (the Sun or the Earth in the field: saturated background); a dropped frame (no
image delivered); a bright object (a planet, the Moon: not a catalog star) crossing the field
(:func:`crossing_paths`)."""
NORMAL, BLANK, BLINDED, DROPPED, CROSSING = range(len(EVENT_NAMES))


def constant_rate(times: np.ndarray, A0: np.ndarray, omega: np.ndarray, t0: float = 0.0):
    """Rotation at a constant body rate.  times : (T,) s.  A0 : (3, 3) attitude at ``t0``.  omega : (3,) rad/s.
    Returns A (T, 3, 3) = ``exp(-[omega (t - t0) x]) A0`` and omega (T, 3)."""
    t = np.asarray(times, np.float64)
    w = np.asarray(omega, np.float64)
    A = frame_rotation((t - t0)[:, None] * w[None, :]) @ np.asarray(A0, np.float64)
    return A, np.broadcast_to(w, (t.size, 3)).copy()


def slew_duration(angle: float, rate_max: float, accel_max: float) -> float:
    """Duration (s) of a rest-to-rest slew of ``angle`` rad under the limits: ``angle / w + w / a`` when the rate
    limit is reached (``angle >= w^2 / a``), else ``2 sqrt(angle / a)`` (triangle)."""
    angle, w, a = abs(float(angle)), float(rate_max), float(accel_max)
    return angle / w + w / a if angle >= w * w / a else 2.0 * np.sqrt(angle / a)


def slew_profile(times: np.ndarray, angle: float, rate_max: float, accel_max: float, t_start: float = 0.0):
    """Angle and angular rate of a rest-to-rest slew with a trapezoidal rate profile.

    times : (T,) s.  angle : rad (>= 0).  rate_max : rad/s (> 0).  accel_max : rad/s^2 (> 0).  t_start : s.
    Returns theta (T,) rad (0 before ``t_start``, ``angle`` after the end) and theta_dot (T,) rad/s.
    The peak rate is ``min(w, sqrt(angle a))``; acceleration phase ``t_a = peak / a``, coast
    ``t_c = angle / peak - t_a``.
    """
    angle, w, a = abs(float(angle)), float(rate_max), float(accel_max)
    if not (w > 0 and a > 0):
        raise ValueError(f"rate_max and accel_max must be > 0, got {w}, {a}")
    t = np.asarray(times, np.float64) - float(t_start)
    peak = min(w, np.sqrt(angle * a))
    if peak == 0:
        return np.zeros_like(t), np.zeros_like(t)
    ta = peak / a
    tc = angle / peak - ta
    T = 2 * ta + tc
    s = np.clip(t, 0.0, T)
    up = s < ta
    down = s > ta + tc
    sd = T - s
    theta = np.where(up, 0.5 * a * s * s, np.where(down, angle - 0.5 * a * sd * sd, 0.5 * a * ta * ta + peak * (s - ta)))
    rate = np.where(up, a * s, np.where(down, a * sd, peak))
    rate = np.where((t <= 0) | (t >= T), 0.0, rate)
    return theta, rate


def eigenaxis_slew(times: np.ndarray, A0: np.ndarray, A1: np.ndarray, rate_max: float, accel_max: float,
                   t_start: float = 0.0):
    """Rest-to-rest slew from ``A0`` to ``A1`` about the fixed eigenaxis ``e`` of ``A1 A0^T`` (the shortest
    rotation), with :func:`slew_profile`'s rate and acceleration limits.  The axis is the same in the camera frame
    throughout, so the body rate is ``e theta_dot``.
    Returns A (T, 3, 3), omega (T, 3) rad/s."""
    A0 = np.asarray(A0, np.float64)
    phi = frame_rotation_vector(np.asarray(A1, np.float64) @ A0.T)
    angle = float(np.linalg.norm(phi))
    e = phi / angle if angle > 0 else np.zeros(3)
    theta, rate = slew_profile(times, angle, rate_max, accel_max, t_start)
    return frame_rotation(theta[:, None] * e[None, :]) @ A0, rate[:, None] * e[None, :]


def sinusoid_jitter(times: np.ndarray, freqs_hz: np.ndarray, amplitudes_rad: np.ndarray, rng: np.random.Generator):
    """Jitter as a sum of sinusoids: ``delta(t) = sum_k a_k sin(2 pi f_k t + p_k)`` per axis, phases ``p_k``
    uniform in [0, 2 pi) from ``rng`` (one per frequency and axis).

    freqs_hz : (K,) Hz.  amplitudes_rad : (K, 3) rad per axis (camera frame).
    Returns delta (T, 3) rad and its time derivative (T, 3) rad/s.
    """
    t = np.asarray(times, np.float64)
    f = np.asarray(freqs_hz, np.float64).reshape(-1)
    amp = np.asarray(amplitudes_rad, np.float64).reshape(f.size, 3)
    ph = rng.uniform(0.0, 2 * np.pi, size=(f.size, 3))
    arg = 2 * np.pi * f[None, :, None] * t[:, None, None] + ph[None]            # (T, K, 3)
    delta = np.sum(amp[None] * np.sin(arg), axis=1)
    ddot = np.sum(amp[None] * (2 * np.pi * f)[None, :, None] * np.cos(arg), axis=1)
    return delta, ddot


def jitter_from_psd(times: np.ndarray, freqs_hz: np.ndarray, psd_rad2_hz: np.ndarray, rng: np.random.Generator):
    """Jitter with a given one-sided power spectral density, as a sum of sinusoids on a frequency grid.

    freqs_hz : (K,) evenly spaced frequencies (Hz, the grid's step ``df`` = their spacing; one frequency: df = 1).
    psd_rad2_hz : (K,) or (K, 3) rad^2/Hz per axis.  Amplitude ``a_k = sqrt(2 S(f_k) df)``, so each axis' variance
    is ``sum_k S(f_k) df`` (the integral of the PSD).  Returns as :func:`sinusoid_jitter`.
    """
    f = np.asarray(freqs_hz, np.float64).reshape(-1)
    df = float(np.mean(np.diff(f))) if f.size > 1 else 1.0
    S = np.broadcast_to(np.asarray(psd_rad2_hz, np.float64).reshape(f.size, -1), (f.size, 3))
    return sinusoid_jitter(times, f, np.sqrt(2.0 * S * df), rng)


PSD_BINS = 256
"""Sinusoids of :func:`jitter_from_psd_table` per axis: the tabulated band cut into this many equal bins."""


def _cumulative_psd(f: np.ndarray, S: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``F(x) = integral from f[0] to x`` of the piecewise-linear PSD through ``(f, S)`` (zero outside the table).
    f : (K,) increasing; S : (K, A); x : (M,).  Returns (M, A)."""
    x = np.clip(np.asarray(x, np.float64), f[0], f[-1])
    Fk = np.concatenate([np.zeros((1, S.shape[1])), np.cumsum(0.5 * (S[1:] + S[:-1]) * np.diff(f)[:, None], axis=0)])
    i = np.clip(np.searchsorted(f, x, side="right") - 1, 0, f.size - 2)
    slope = (S[i + 1] - S[i]) / (f[i + 1] - f[i])[:, None]
    h = (x - f[i])[:, None]
    return Fk[i] + S[i] * h + 0.5 * slope * h * h


def psd_integral(freqs_hz: np.ndarray, psd: np.ndarray) -> np.ndarray:
    """Variance (the PSD's units x Hz) of a one-sided PSD tabulated at ``freqs_hz`` (K,) increasing, piecewise
    linear between the points and zero outside: the trapezoid sum, per column of ``psd`` (K,) or (K, A)."""
    f = np.asarray(freqs_hz, np.float64)
    S = np.asarray(psd, np.float64).reshape(f.size, -1)
    return np.sum(0.5 * (S[1:] + S[:-1]) * np.diff(f)[:, None], axis=0)


def psd_bins(freqs_hz: np.ndarray, psd: np.ndarray, n_bins: int = PSD_BINS):
    """A tabulated one-sided PSD on an even grid: the band ``[f_0, f_{K-1}]`` cut into ``n_bins`` equal bins of
    width ``df``; each bin's value is the exact mean of the piecewise-linear PSD over it, so ``sum S_m df`` is the
    PSD's integral (:func:`psd_integral`) exactly.

    freqs_hz : (K,) strictly increasing, K >= 2.  psd : (K,) or (K, A), >= 0.
    Returns (bin centres (n_bins,) Hz, bin means (n_bins, A))."""
    f = np.asarray(freqs_hz, np.float64).reshape(-1)
    if f.size < 2 or np.any(np.diff(f) <= 0):
        raise ValueError(f"a PSD table needs >= 2 strictly increasing frequencies, got {f.tolist()}")
    S = np.asarray(psd, np.float64).reshape(f.size, -1)
    edges = np.linspace(f[0], f[-1], int(n_bins) + 1)
    F = _cumulative_psd(f, S, edges)
    df = edges[1] - edges[0]
    return 0.5 * (edges[1:] + edges[:-1]), np.maximum(np.diff(F, axis=0) / df, 0.0)


def jitter_from_psd_table(times: np.ndarray, freqs_hz: np.ndarray, psd_rad2_hz: np.ndarray,
                          rng: np.random.Generator, n_bins: int = PSD_BINS):
    """Jitter whose one-sided PSD per axis is tabulated at increasing frequencies (piecewise linear between them,
    zero outside): :func:`psd_bins` then :func:`jitter_from_psd` (``n_bins`` sinusoids per axis, random phases from
    ``rng``).  Over the phases each axis' variance is ``psd_integral`` exactly and its autocorrelation
    ``R(tau) = sum_m S_m df cos(2 pi f_m tau)`` (the Wiener-Khinchin integral on the bins).

    times : (T,) s.  freqs_hz : (K,) Hz.  psd_rad2_hz : (K,) (all axes) or (K, 3) rad^2/Hz.
    Returns delta (T, 3) rad and its time derivative (T, 3) rad/s."""
    fm, Sm = psd_bins(freqs_hz, psd_rad2_hz, n_bins)
    return jitter_from_psd(times, fm, np.broadcast_to(Sm, (fm.size, 3)), rng)


def right_jacobian(delta: np.ndarray) -> np.ndarray:
    """(..., 3, 3) ``J`` with ``omega = J(delta) d(delta)/dt`` the body rate of ``R = exp(-[delta x])``:
    ``J = I - (1 - cos t) / t^2 [delta x] + (t - sin t) / t^3 [delta x]^2`` (the right Jacobian of SO(3) in this
    passive convention; Taylor series below t = 1e-4 rad)."""
    d = np.asarray(delta, np.float64)
    t2 = np.sum(d * d, axis=-1)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    c1 = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / (ts * ts))
    c2 = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / (ts ** 3))
    K = cross_matrix(d)
    return np.eye(3) - c1[..., None, None] * K + c2[..., None, None] * (K @ K)


def add_jitter(A_base: np.ndarray, omega_base: np.ndarray, delta: np.ndarray, delta_dot: np.ndarray):
    """Lay a small rotation ``delta(t)`` (camera frame) over a base motion: ``A = exp(-[delta x]) A_base``.

    A_base : (T, 3, 3); omega_base : (T, 3) rad/s; delta : (T, 3) rad; delta_dot : (T, 3) rad/s.
    Returns A (T, 3, 3) and the exact body rate ``J(delta) delta_dot + R(delta) omega_base`` (T, 3)
    (:func:`right_jacobian`; from ``dA/dt = (dR/dt R^T - [R omega_base x]) A``).
    """
    R = frame_rotation(delta)
    w = np.einsum("tij,tj->ti", right_jacobian(delta), delta_dot) + np.einsum("tij,tj->ti", R, omega_base)
    return R @ np.asarray(A_base, np.float64), w


def gyro_rates(omega: np.ndarray, dt: float, rng: np.random.Generator, bias=(0.0, 0.0, 0.0), noise_rad_s: float = 0.0,
               bias_walk_rad_s2_rthz: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Rate-gyro outputs at the frames: ``omega + b_k + n_k``.

    omega : (T, 3) true body rate (rad/s).  dt : s between samples (for the bias walk).  bias : (3,) rad/s
    initial bias.  noise_rad_s : 1-sigma white noise per axis and sample (rad/s; an angle random walk
    ``N`` rad/sqrt(s) averaged over dt gives ``N / sqrt(dt)``).  bias_walk_rad_s2_rthz : rate random walk
    (rad/s^2/sqrt(Hz)): ``b_{k+1} = b_k + sigma_b sqrt(dt) w_k``.
    Returns (measured (T, 3) rad/s, bias (T, 3) rad/s).
    """
    w = np.asarray(omega, np.float64)
    T = w.shape[0]
    steps = rng.normal(size=(T, 3)) * float(bias_walk_rad_s2_rthz) * np.sqrt(float(dt))
    steps[0] = 0.0
    b = np.asarray(bias, np.float64)[None, :] + np.cumsum(steps, axis=0)
    return w + b + rng.normal(size=(T, 3)) * float(noise_rad_s), b


def frame_events(n_frames: int, rng: np.random.Generator | None = None, *, blank=(), blinded=(), dropped=(),
                 p_blank: float = 0.0, p_blinded: float = 0.0, p_dropped: float = 0.0) -> np.ndarray:
    """(T,) int8 event code of each frame (:data:`EVENT_NAMES`): the listed frame indices, and with ``rng`` each
    other frame independently blank / blinded / dropped with the given probabilities (one uniform draw per frame).
    A frame listed twice takes the later of blank, blinded, dropped."""
    ev = np.zeros(int(n_frames), np.int8)
    if rng is not None and (p_blank or p_blinded or p_dropped):
        u = rng.random(int(n_frames))
        c1, c2, c3 = p_blank, p_blank + p_blinded, p_blank + p_blinded + p_dropped
        ev = np.select([u < c1, u < c2, u < c3], [BLANK, BLINDED, DROPPED], NORMAL).astype(np.int8)
    for code, idx in ((BLANK, blank), (BLINDED, blinded), (DROPPED, dropped)):
        ev[np.asarray(idx, np.int64)] = code
    return ev


def crossing_paths(n_frames: int, n_crossings: int, length: int, width: int, height: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bright objects crossing the image on straight lines, each over ``length`` consecutive frames.

    Per crossing (draw order): a start frame uniform in [1, n_frames - length] (so the first frame never has one),
    a centre point uniform in the image's central half (px), a direction angle uniform in [0, 2 pi); the object
    moves by ``diagonal / length`` px per frame, so that over its ``length`` frames it covers the image's diagonal,
    at the centre point halfway.  Positions may fall outside the image (the object entering or leaving).
    Returns frame (C,) int64, xy (C, 2) px (col, row) and crossing index (C,) int64, C = n_crossings * length
    (frames beyond the sequence are dropped)."""
    L = int(length)
    fr, xy, idx = [], [], []
    diag = float(np.hypot(width, height))
    for c in range(int(n_crossings)):
        start = int(rng.integers(1, max(2, int(n_frames) - L + 1)))
        centre = np.array([width, height], np.float64) * (0.25 + 0.5 * rng.random(2))
        phi = rng.uniform(0.0, 2.0 * np.pi)
        j = np.arange(L)
        step = (diag / L) * np.array([np.cos(phi), np.sin(phi)])
        p = centre[None, :] + (j - 0.5 * (L - 1))[:, None] * step[None, :]
        keep = start + j < int(n_frames)
        fr.append(start + j[keep])
        xy.append(p[keep])
        idx.append(np.full(int(keep.sum()), c, np.int64))
    if not fr:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64)
    return np.concatenate(fr).astype(np.int64), np.concatenate(xy), np.concatenate(idx)
