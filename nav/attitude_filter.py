"""A gyroless attitude and rate filter over a star tracker's frame solutions (issue 22, points 2, 3 and 6).

One frame's attitude from a handful of smeared stars is weak about the boresight (roll): at 1 deg/s through the
reference's star camera (56 arcsec/px, 100 ms exposure) its stated 1-sigma reaches 20-60 arcsec.  A flight tracker
does not throw those frames away; it fuses every verified solution with the prediction from the last ones.  This
module is that filter: an *interacting multiple model* (IMM) estimator of the attitude and the body rate with two
motion models, both "constant rate with a random angular acceleration held over each frame interval" (discrete white
noise acceleration, DWNA), one *steady* (small acceleration: a fixed rate, jitter) and one *manoeuvre* (the slew's
acceleration limit), mixed by their likelihoods every frame (Bar-Shalom, Li & Kirubarajan, "Estimation with
Applications to Tracking and Navigation", Wiley 2001: DWNA Sec. 6.3.2, IMM Sec. 11.6.6).

State and conventions (the ones of ``nav/tracking.py`` and ``nav/angular_rate.py``):

* a reference attitude ``A_ref`` (3, 3), inertial -> camera, and per model ``x = [dtheta, omega]`` (6,):
  the attitude is ``exp(-[dtheta x]) A_ref`` (``scene/rotation_vector.frame_rotation``), ``omega`` the body rate in
  the camera frame (rad/s, ``dA/dt = -[omega x] A``); ``P`` (6, 6) their error covariance (rad^2, rad^2/s, (rad/s)^2).
* propagation over ``dt`` with the mixed rate ``w``: ``A_ref <- exp(-[w dt x]) A_ref`` and per model
  ``dtheta <- Phi dtheta + dt (omega - w)``, ``F = [[Phi, dt I], [0, I]]``, ``P <- F P F^T + Q``,
  ``Q = s_a^2 [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]`` (DWNA, Bar-Shalom Eq. 6.3.2-4; ``Phi = exp(-[w dt x])``;
  the error kinematics of Markley & Crassidis 2014, Eq. 3.21, to first order).  With a gyro the rate is the
  gyro's: ``omega = w = gyro``, its covariance the gyro's, no cross terms.
* measurement: a frame's verified attitude ``A_m`` with covariance ``R`` (3, 3) rad^2 (tracking's or
  lost-in-space's, ``nav/tracking.solve_pairs``), as the rotation vector ``z = log(A_m A_ref^T)``
  (``nav/angular_rate.log_rotation``), ``H = [I 0]``; Kalman update in Joseph form per model.

The combined estimate is the probability-weighted mean of the models with the spread of their means added to the
covariance (Bar-Shalom Eq. 11.6.6-20/21).  A measurement whose normalised innovation squared against the combined
prediction exceeds ``gate`` (chi-square, 3 degrees of freedom) does not fit the track: the caller restarts the filter
at that measurement (a verified lost-in-space fix after a manoeuvre the models did not follow).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.nav.angular_rate import log_rotation
from dualsight.scene.rotation_vector import frame_rotation

__all__ = ["FilterState", "start", "predict", "combined", "rate", "innovation", "update"]

_I3 = np.eye(3)


@dataclass(frozen=True)
class FilterState:
    """The IMM's state after a step.  A_ref : (3, 3) reference attitude (inertial -> camera).  x : (M, 9) per model
    ``[dtheta (rad), omega (rad/s), alpha (rad/s^2)]`` relative to ``A_ref`` (``alpha`` the angular acceleration,
    zero in a constant-rate model).  P : (M, 9, 9) their covariances.  mu : (M,) model probabilities (sum 1).
    t : s, the time of the state."""

    A_ref: np.ndarray
    x: np.ndarray
    P: np.ndarray
    mu: np.ndarray
    t: float
    P_free: np.ndarray | None = None
    """After :func:`predict`: (M, 9, 9) the covariances without this step's random acceleration (the constant-rate
    extrapolation that the tracking windows follow, :func:`combined` with ``free=True``); None after an update."""


def start(A: np.ndarray, cov: np.ndarray, t: float, rate_sigma_rad_s: float, n_models: int = 2,
          omega: np.ndarray | None = None, omega_cov: np.ndarray | None = None,
          accel_sigma_rad_s2: np.ndarray | None = None) -> FilterState:
    """A filter started at one verified attitude ``A`` (3, 3) with covariance ``cov`` (3, 3) rad^2 at time ``t`` s;
    the rate ``omega`` (3,) rad/s with ``omega_cov`` (3, 3), or unknown: zero with ``rate_sigma_rad_s`` per axis;
    the angular acceleration zero with ``accel_sigma_rad_s2`` (M,) per model (None: zero, every model constant-rate).
    Every model starts with equal probability."""
    x = np.zeros((n_models, 9))
    P = np.zeros((n_models, 9, 9))
    P[:, :3, :3] = cov
    if omega is not None:
        x[:, 3:6] = omega
        P[:, 3:6, 3:6] = omega_cov
    else:
        P[:, 3:6, 3:6] = _I3 * rate_sigma_rad_s ** 2
    if accel_sigma_rad_s2 is not None:
        P[:, 6:, 6:] = _I3 * (np.asarray(accel_sigma_rad_s2, np.float64) ** 2)[:, None, None]
    return FilterState(np.asarray(A, np.float64), x, P, np.full(n_models, 1.0 / n_models), float(t))


def _moments(x: np.ndarray, P: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (9,) and covariance (9, 9) of a Gaussian mixture: weights w (M,), means x (M, 9), covariances P."""
    m = w @ x
    d = x - m
    return m, (w @ P.reshape(len(w), -1)).reshape(P.shape[1:]) + (d.T * w) @ d


def _kron_i3(g: np.ndarray) -> np.ndarray:
    """(9, 9) ``kron(outer(g, g), I3)`` for g (3,): one 3 x 3 block per pair of the state's three parts."""
    return (np.multiply.outer(g, g)[:, None, :, None] * _I3[None, :, None, :]).reshape(9, 9)


def rate(s: FilterState) -> np.ndarray:
    """(3,) rad/s the combined rate (the probability-weighted mean of the models'), without the covariance."""
    return s.mu @ s.x[:, 3:6]


def predict(s: FilterState, t: float, noise: np.ndarray, switch: np.ndarray, const_accel: np.ndarray | None = None,
            gyro: np.ndarray | None = None, gyro_cov: np.ndarray | None = None) -> FilterState:
    """The IMM's mixing and each model's propagation to time ``t`` s (module docstring).

    noise : (M,) each model's 1-sigma per axis: a constant-rate model's angular acceleration (rad/s^2) held over
    the interval (DWNA), a constant-acceleration model's jerk (rad/s^3) held over the interval (discrete Wiener
    process acceleration, Bar-Shalom Sec. 6.3.3).  switch : (M, M) Markov transition probabilities ``p_ij``
    (row i -> column j; rows sum to 1).  const_accel : (M,) bool, the model carries the angular acceleration
    (default: none does).  gyro : (3,) rad/s measured mean rate over the interval with ``gyro_cov`` (3, 3), or None.
    """
    dt = float(t) - s.t
    M = len(s.mu)
    ca = np.zeros(M, bool) if const_accel is None else np.asarray(const_accel, bool)
    c = s.mu @ switch                                   # predicted model probabilities (Eq. 11.6.6-6)
    mix = (switch * s.mu[:, None]) / np.where(c > 0, c, 1.0)[None, :]     # mu_{i|j}
    xs, Ps = s.x, s.P
    if ca.any() and not ca.all():
        # unbiased mixing of models of different order (Li & Jilkov, "Survey of maneuvering target tracking.
        # Part V: multiple-model methods", IEEE TAES 41(4), 2005, Sec. 4.2): a constant-rate model has no
        # acceleration estimate, so it lends the constant-acceleration models' one, not a certain zero
        w_ca = s.mu[ca] / s.mu[ca].sum()
        a_m, a_C = _moments(s.x[ca][:, 6:], s.P[ca][:, 6:, 6:], w_ca)
        xs, Ps = s.x.copy(), s.P.copy()
        xs[~ca, 6:] = a_m
        Ps[~ca, 6:, :] = 0.0
        Ps[~ca, :, 6:] = 0.0
        Ps[~ca, 6:, 6:] = a_C
    x0 = mix.T @ xs
    d = xs[None, :, :] - x0[:, None, :]                 # (j, i, 9): model i's mean from model j's mixed one
    P0 = (mix.T @ Ps.reshape(M, -1)).reshape(Ps.shape) + np.swapaxes(d * mix.T[:, :, None], 1, 2) @ d
    x0[~ca, 6:] = 0.0                                   # a constant-rate model has no acceleration
    P0[~ca, 6:, :] = 0.0
    P0[~ca, :, 6:] = 0.0
    if gyro is not None:
        x0[:, 3:6] = gyro
        x0[:, 6:] = 0.0
        P0[:, 3:, :] = 0.0
        P0[:, :, 3:] = 0.0
        P0[:, 3:6, 3:6] = gyro_cov
        w = np.asarray(gyro, np.float64)
    else:
        w = c @ x0[:, 3:6]
    Phi = frame_rotation(w * dt)
    F = np.zeros((9, 9))
    F[:3, :3] = Phi
    F[:3, 3:6] = _I3 * dt
    F[:3, 6:] = _I3 * (0.5 * dt * dt)
    F[3:6, 3:6] = F[6:, 6:] = _I3
    F[3:6, 6:] = _I3 * dt
    x = x0 @ F.T
    x[:, :3] -= w * dt
    g_cv = np.array([0.5 * dt * dt, dt, 0.0])           # DWNA: acceleration held over the interval
    g_ca = np.array([dt ** 3 / 6.0, 0.5 * dt * dt, dt])  # DWPA: jerk held over the interval
    P_free = F @ P0 @ F.T
    q = np.where(ca[:, None, None], _kron_i3(g_ca), _kron_i3(g_cv)) if ca.any() else _kron_i3(g_cv)
    P = P_free + (np.asarray(noise, np.float64) ** 2)[:, None, None] * q
    if gyro is not None:                                # the gyro's rate: no random acceleration on it
        for Q in (P, P_free):
            Q[:, 3:, :] = 0.0
            Q[:, :, 3:] = 0.0
            Q[:, 3:6, 3:6] = gyro_cov
            Q[:, :3, :3] = Phi @ P0[:, :3, :3] @ Phi.T + (dt * dt) * gyro_cov
    return FilterState(Phi @ s.A_ref, x, 0.5 * (P + np.swapaxes(P, 1, 2)), c, float(t),
                       0.5 * (P_free + np.swapaxes(P_free, 1, 2)))


def combined(s: FilterState, free: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The combined estimate: attitude (3, 3), its covariance (3, 3) rad^2, rate (3,) rad/s and its covariance
    (3, 3) (rad/s)^2 (Bar-Shalom Eq. 11.6.6-20/21); ``free``: with the covariances of :attr:`FilterState.P_free`."""
    m, C = _moments(s.x, s.P_free if free else s.P, s.mu)
    return frame_rotation(m[:3]) @ s.A_ref, C[:3, :3], m[3:6], C[3:6, 3:6]


def innovation(s: FilterState, A_m: np.ndarray, R: np.ndarray) -> float:
    """Normalised innovation squared (chi-square, 3 dof) of a measured attitude ``A_m`` (3, 3) with covariance
    ``R`` (3, 3) rad^2 against the combined prediction."""
    m, C = _moments(s.x, s.P, s.mu)
    nu = log_rotation(A_m @ s.A_ref.T) - m[:3]
    S = C[:3, :3] + R
    return float(nu @ np.linalg.solve(S, nu))


def update(s: FilterState, A_m: np.ndarray, R: np.ndarray) -> FilterState:
    """Each model's Kalman update with the measured attitude ``A_m`` (3, 3), covariance ``R`` (3, 3) rad^2, the
    model probabilities by the innovations' likelihoods (Bar-Shalom Eq. 11.6.6-14/15), and the combined attitude
    folded into ``A_ref`` (every model's ``dtheta`` shifted by it, first order)."""
    z = log_rotation(A_m @ s.A_ref.T)
    M = len(s.mu)
    nu = z - s.x[:, :3]                                 # (M, 3) innovations
    S = s.P[:, :3, :3] + R
    Si = np.linalg.inv(S)
    K = s.P[:, :, :3] @ Si                              # (M, 9, 3)
    x = s.x + np.einsum("mij,mj->mi", K, nu)
    IKH = np.broadcast_to(np.eye(9), (M, 9, 9)).copy()
    IKH[:, :, :3] -= K
    P = IKH @ s.P @ np.swapaxes(IKH, 1, 2) + K @ R @ np.swapaxes(K, 1, 2)      # Joseph form
    loglik = -0.5 * (np.einsum("mi,mij,mj->m", nu, Si, nu) + np.log(np.maximum(np.linalg.det(S), 1e-300)))
    lw = loglik + np.log(np.maximum(s.mu, 1e-300))
    mu = np.exp(lw - lw.max())
    mu /= mu.sum()
    m = mu @ x[:, :3]
    x[:, :3] -= m
    return FilterState(frame_rotation(m) @ s.A_ref, x, 0.5 * (P + np.swapaxes(P, 1, 2)), mu, s.t)
