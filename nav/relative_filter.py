"""Relative navigation: an extended Kalman filter on the chaser's position and velocity relative to the target
(issue 23, point 4).

State ``x = (x, y, z, vx, vy, vz)`` (m, m/s): the chaser relative to the target in the target's Hill frame (x
radial, y along-track, z cross-track; ``scene/relative_orbit.py``), covariance ``P`` (6, 6).  Every function is
batched over a leading B (independent filters, e.g. Monte Carlo runs): x (B, 6), P (B, 6, 6).

Prediction (:func:`predict`): the Clohessy-Wiltshire transition ``x <- Phi(dt) x``, ``P <- Phi P Phi^T + Q(dt)``
with ``Q(dt) = q int_0^dt Phi_v(tau) Phi_v(tau)^T dtau`` for white acceleration noise of spectral density q
(m^2/s^3 per axis; ``Phi_v`` the velocity columns of Phi; 8-point Gauss-Legendre, exact to rounding for
n dt < 1) (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001,
Sec. 6.2).  A known manoeuvre adds its delta-v to the velocity, and its execution error covariance to P.

Updates (Joseph form, Bar-Shalom Eq. 5.2.3-18; optionally iterated, Bar-Shalom Sec. 10.3.2):

- **inertial bearing** (:func:`bearing_update`): the measured line of sight from chaser to target ``u_m`` (ICRS
  unit vector) with its covariance C (3, 3), rank 2 across u_m (``nav/target_bearing.inertial_bearing``).  The
  predicted line of sight is ``u(x) = -R rho / |rho|`` (R the Hill-to-ICRS rotation, ``relative_orbit.
  hill_to_icrs``).  The measurement is the tangent-plane component: with E (2, 3) an orthonormal basis across
  u_m, ``z = E u_m = 0`` and ``h(x) = E u(x)``, ``H = -E R (I - rho^ rho^T) / |rho|`` on the position,
  noise ``E C E^T`` (2, 2): two angles, well posed whatever the direction.
- **range** (:func:`range_update`): ``h(x) = |rho|``, ``H = [rho^T / |rho|, 0]``; a blobber's [min, max] range is
  a uniform uncertainty, sigma = (max - min) / sqrt(12) (:func:`range_sigma`); the rendezvous kind gives the
  blobber's range with its known bias removed and its spread over orientations instead
  (``nav/blobber_range_error.py``).

Correlated centre-of-brightness error (:func:`bias_propagate`, ``bias`` of :func:`bearing_update`, ``n_bias`` of
:func:`run`): the bearing measures the line of sight to the target's centre of brightness, whose offset from the
body's centre after the mean phase correction is not white: the target spins about one axis, so the photocentre
averaged over a spin differs from the mean over all attitudes by an offset that changes only as the viewing
geometry does (``scene/target_photometry.photocentre_statistics``).  The filter appends nb states beta of unit
variance, each a first-order Gauss-Markov process (Gelb, *Applied Optimal Estimation*, 1974, Table 4.4-1;
Brown & Hwang, *Introduction to Random Signals and Applied Kalman Filtering*, 4th ed., 2012, Sec. 4.2 and 9.2):
``beta_k = d beta_{k-1} + w``, ``var w = 1 - d^2`` (stationary unit variance; d = exp(-dpsi / psi_c) from the
caller); the offset in ICRS is ``G beta`` with G (3, nb) metres per unit state across the line of sight, so the
predicted line of sight becomes ``u = (-R rho + G beta) / |-R rho + G beta|`` and its Jacobian gains
``E (I - u u^T) G / |.|`` on beta.  The NEES stays the 6 relative states' (the marginal of the augmented P).

Bearings alone do not observe the range under linear relative dynamics (a scaled trajectory gives the same
bearings) until a known manoeuvre breaks the scaling (Woffinden & Geller, IEEE TAES 45(3), 2009).

Consistency: :func:`nees` (normalised estimation error squared, chi-square with 6 dof when P holds) and
:func:`chi2_mean_bounds`, the two-sided bounds of its mean over M runs (chi-square with 6 M dof over M).

Units: metres, seconds, radians.  Pure numpy; the loop in :func:`run` is over frames (a filter is sequential),
never over runs.
"""

from __future__ import annotations

import dataclasses
import typing
import math
from statistics import NormalDist

import pydantic
import numpy as np

from dualsight.config import check_fields
from dualsight.errors import ConfigError
from dualsight.scene.relative_orbit import CircularOrbit, cw_stm, hill_to_icrs


_FILTER_UNITS = {"accel_psd": "m^2/s^3", "dv_sigma_m_s": "m/s", "dv_sigma_frac": "of |dv|"}


@dataclasses.dataclass(frozen=True)
class FilterConfig:
    """Noise settings of the relative-navigation EKF (``nav/relative_filter.py``; a rendezvous spec's filter comes
    from its ``RendezvousConfig``: ``jobs/kinds/rendezvous_filter.filter_config``).  Checked when built (ConfigError
    naming ``filter.<field>``, the value and the range).

    accel_psd : white acceleration noise spectral density per Hill axis, in [0, 1e-3] m^2/s^3 (1e-12 ~ 1 um/s^2
        over 1 s; default 1e-12).
    dv_sigma_frac : 1-sigma execution error of a manoeuvre per axis, as a fraction of |dv|, in [0, 1] (default 0).
    dv_sigma_m_s : 1-sigma execution error of a manoeuvre per axis, in [0, 1] m/s, added in quadrature (default 0).
    iterations : linearisations per measurement update, in [1, 20] (1: the EKF; more: the iterated EKF, which stays
        consistent when the first bearings meet a prior whose error across the line of sight is a large angle)."""

    accel_psd: typing.Annotated[float, pydantic.Field(ge=0.0, le=1e-3)] = 1e-12
    dv_sigma_frac: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 0.0
    dv_sigma_m_s: typing.Annotated[float, pydantic.Field(ge=0.0, le=1.0)] = 0.0
    iterations: typing.Annotated[int, pydantic.Field(ge=1, le=20)] = 1

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"filter.{name}"), _FILTER_UNITS)

__all__ = ["process_noise", "predict", "apply_manoeuvre", "tangent_basis", "isotropic_bearing_cov", "bearing_update",
           "bias_propagate",
           "range_sigma", "range_update", "nees", "chi2_mean_bounds", "run"]


def process_noise(n: float, dt: float, q: float) -> np.ndarray:
    """(6, 6) discrete process noise ``q int_0^dt Phi(tau)[:, 3:] Phi(tau)[:, 3:]^T dtau`` (m^2, m^2/s, m^2/s^2)
    of white acceleration noise (spectral density q, m^2/s^3) under CW motion (mean motion n, rad/s)."""
    if dt <= 0 or q == 0:
        return np.zeros((6, 6))
    nodes, weights = np.polynomial.legendre.leggauss(8)
    tau = 0.5 * dt * (nodes + 1.0)
    G = cw_stm(n, tau)[:, :, 3:]                                   # (8, 6, 3)
    return q * 0.5 * dt * np.einsum("k,kia,kja->ij", weights, G, G)


def predict(x, P, dt: float, n: float, cfg: FilterConfig):
    """Propagate (B, 6 + nb) states and (B, 6 + nb, 6 + nb) covariances over dt (s) by CW (mean motion n, rad/s);
    bias states (:func:`bias_propagate`) are held."""
    Phi = np.eye(x.shape[-1])
    Phi[:6, :6] = cw_stm(n, dt)
    Q = np.zeros_like(Phi)
    Q[:6, :6] = process_noise(n, dt, cfg.accel_psd)
    return x @ Phi.T, Phi @ P @ Phi.T + Q


def apply_manoeuvre(x, P, dv, cfg: FilterConfig):
    """Add a known delta-v (3,) or (B, 3) (m/s, Hill frame) to the velocity, and its execution error variance
    ``(dv_sigma_frac |dv|)^2 + dv_sigma_m_s^2`` per axis to the velocity block of P."""
    dv = np.broadcast_to(np.asarray(dv, np.float64), x[..., 3:6].shape)
    x = x.copy()
    x[:, 3:6] += dv
    var = (cfg.dv_sigma_frac * np.linalg.norm(dv, axis=-1)) ** 2 + cfg.dv_sigma_m_s ** 2
    P = P.copy()
    P[:, 3:6, 3:6] += var[:, None, None] * np.eye(3)
    return x, P


def tangent_basis(u) -> np.ndarray:
    """(B, 2, 3) orthonormal rows across (B, 3) unit vectors u (e1 = u x ref / |.|, e2 = u x e1; ref the x axis,
    or y where u is within 26 deg of x)."""
    u = np.asarray(u, np.float64)
    ref = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    e1 = np.cross(u, ref)
    e1 /= np.linalg.norm(e1, axis=-1, keepdims=True)
    return np.stack([e1, np.cross(u, e1)], -2)


def isotropic_bearing_cov(u, sigma_rad) -> np.ndarray:
    """(B, 3, 3) covariance sigma^2 (I - u u^T) of a line of sight u (B, 3) with sigma_rad (rad, scalar or (B,))
    per axis across it."""
    u = np.asarray(u, np.float64)
    s2 = np.broadcast_to(np.asarray(sigma_rad, np.float64) ** 2, u.shape[:-1])
    return s2[:, None, None] * (np.eye(3) - u[:, :, None] * u[:, None, :])


def _update(x, P, fn, Rm, iterations: int):
    """Iterated Kalman update (Gauss-Newton on the measurement; Bar-Shalom Sec. 10.3.2; ``iterations`` = 1 is the
    plain EKF) of (B, 6) x, (B, 6, 6) P; ``fn(x_i) -> (z - h(x_i) (B, m), H(x_i) (B, m, 6))``, noise (B, m, m).
    Covariance in Joseph form at the last linearisation point."""
    xi = x
    for _ in range(max(int(iterations), 1)):
        resid, H = fn(xi)
        Ht = np.swapaxes(H, -1, -2)
        S = H @ P @ Ht + Rm
        K = np.swapaxes(np.linalg.solve(S, H @ P), -1, -2)          # P H^T S^-1 (P, S symmetric)
        xi = x + np.einsum("bim,bm->bi", K, resid - np.einsum("bmi,bi->bm", H, x - xi))
    IKH = np.eye(x.shape[-1]) - K @ H
    P = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ Rm @ np.swapaxes(K, -1, -2)
    return xi, 0.5 * (P + np.swapaxes(P, -1, -2))


def bearing_update(x, P, u_meas, cov_meas, R_hill, iterations: int = 1, bias=None):
    """Update by an inertial bearing: u_meas (B, 3) ICRS unit line of sight from chaser to target, cov_meas
    (B, 3, 3) its covariance (rad^2, rank 2 across u_meas), R_hill (3, 3) or (B, 3, 3) the Hill-to-ICRS rotation
    at the measurement time.  Two tangent-plane angles (module docstring); ``iterations`` > 1 iterates the
    linearisation (an iterated EKF: needed when the prior's error across the line of sight is a sizeable angle).
    x (B, 6 + nb), P (B, 6 + nb, 6 + nb): with bias (B, 3, nb) m per unit bias state (the centre of brightness's
    correlated offset, ICRS; module docstring) the line of sight is to ``-R rho + bias beta``, beta =
    x[:, 6:6 + nb]."""
    u_meas = np.asarray(u_meas, np.float64)
    R = np.broadcast_to(np.asarray(R_hill, np.float64), (x.shape[0], 3, 3))
    E = tangent_basis(u_meas)
    G = None if bias is None or np.size(bias) == 0 else np.asarray(bias, np.float64).reshape(x.shape[0], 3, -1)
    nb = 0 if G is None else G.shape[-1]

    def fn(xi):
        s = -np.einsum("bij,bj->bi", R, xi[:, :3])                # chaser -> target body origin (ICRS, m)
        if G is not None:
            s = s + np.einsum("bij,bj->bi", G, xi[:, 6:6 + nb])   # -> its centre of brightness
        r = np.linalg.norm(s, axis=-1)
        sh = s / r[:, None]
        resid = -np.einsum("bij,bj->bi", E, sh)                    # z - h = E u_meas - E s^ = 0 - E s^
        Ep = E @ ((np.eye(3) - sh[:, :, None] * sh[:, None, :]) / r[:, None, None])
        H = np.zeros((xi.shape[0], 2, xi.shape[1]))
        H[:, :, :3] = -Ep @ R
        if G is not None:
            H[:, :, 6:6 + nb] = Ep @ G
        return resid, H

    Rm = E @ np.asarray(cov_meas, np.float64) @ np.swapaxes(E, -1, -2)
    return _update(x, P, fn, Rm, iterations)


def bias_propagate(x, P, decay, nb: int | None = None):
    """First-order Gauss-Markov step of the unit-variance bias states x[:, 6:] (module docstring): beta <- d beta,
    P's beta rows and columns scaled by d and ``1 - d^2`` added to its diagonal (Brown & Hwang Sec. 4.2: the
    discrete model of exp(-|tau| / T) autocorrelation, unit variance).  decay (B, nb) or (nb,) in [0, 1]; the
    bias states are x[:, 6:6 + nb] (nb: default all after the 6 relative states)."""
    nb = x.shape[1] - 6 if nb is None else int(nb)
    if nb == 0:
        return x, P
    d = np.broadcast_to(np.asarray(decay, np.float64), (x.shape[0], nb))
    f = np.concatenate([np.ones((x.shape[0], 6)), d, np.ones((x.shape[0], x.shape[1] - 6 - nb))], -1)
    x = x * f
    P = P * f[:, :, None] * f[:, None, :]
    idx = np.arange(6, 6 + nb)
    P[:, idx, idx] += 1.0 - d ** 2
    return x, P


def range_sigma(range_min_m, range_max_m):
    """1-sigma (m) of a range known to lie uniformly in [min, max]: (max - min) / sqrt(12)."""
    return (np.asarray(range_max_m, np.float64) - np.asarray(range_min_m, np.float64)) / math.sqrt(12.0)


def range_update(x, P, range_m, sigma_m, iterations: int = 1):
    """Update by a measured range (B,) m with 1-sigma (B,) or scalar m (``iterations`` as in
    :func:`bearing_update`); x (B, 6 + nb) (bias states untouched but through their correlations)."""
    z = np.asarray(range_m, np.float64)

    def fn(xi):
        rho = xi[:, :3]
        r = np.linalg.norm(rho, axis=-1)
        H = np.zeros((xi.shape[0], 1, xi.shape[1]))
        H[:, 0, :3] = rho / r[:, None]
        return (z - r)[:, None], H

    s2 = np.broadcast_to(np.asarray(sigma_m, np.float64) ** 2, z.shape)
    return _update(x, P, fn, s2[:, None, None], iterations)


def nees(x_est, P, x_true) -> np.ndarray:
    """(...,) normalised estimation error squared ``e^T P^-1 e``, e = x_est - x_true; x (..., k), P (..., k, k)
    (any k: pass ``x[..., :3], P[..., :3, :3]`` for position only)."""
    e = np.asarray(x_est, np.float64) - np.asarray(x_true, np.float64)
    return np.einsum("...i,...i->...", e, np.linalg.solve(P, e[..., None])[..., 0])


def chi2_mean_bounds(dof: int, runs: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval of the mean of ``runs`` independent chi-square(dof) variables: chi-square
    quantiles with k = dof * runs degrees of freedom, divided by runs (Bar-Shalom Sec. 5.4.2).  Quantiles by the
    Wilson-Hilferty approximation ``k (1 - 2/(9k) + z sqrt(2/(9k)))^3`` (relative error < 1e-3 for k >= 100)."""
    k = float(dof * runs)
    out = []
    for p in ((1 - prob) / 2, (1 + prob) / 2):
        z = NormalDist().inv_cdf(p)
        out.append(k * (1 - 2 / (9 * k) + z * math.sqrt(2 / (9 * k))) ** 3 / runs)
    return out[0], out[1]


def run(x0, P0, times, orbit: CircularOrbit, cfg: FilterConfig, *, bearings=None, bearing_cov=None,
        ranges=None, range_sig=None, dv_times=(), dv=None, adjust=None, select=None, n_bias: int = 0,
        bias_decay=None, range_sig_frac=None):
    """The filter over a sequence of frames, batched over B runs.

    x0 (B, 6), P0 (B, 6, 6) at ``times[0]``; times (T,) s increasing; bearings (B, T, 3) ICRS lines of sight with
    bearing_cov (B, T, 3, 3), NaN rows where a frame has none; ranges and range_sig (B, T) m, NaN where none;
    range_sig_frac: optional (B, T) 1-sigma of a range as a fraction of the range, in place of range_sig: the sigma
    is that fraction of the predicted range |rho| at the update (a multiplicative error, as the blobber's: a sigma
    taken from the measured range itself weights the short measurements more and biases the estimate short, by
    about 2 s^2 for a fraction s: -0.85 % at s = 6.5 %, inverse-variance weights 1/z^2 give E[1/z] / E[1/z^2]);
    dv_times (M,) s in (times[0], times[-1]] and dv (M, 3) or (B, M, 3) m/s the known manoeuvres (a manoeuvre at a
    frame's time is applied before that frame's measurements); adjust: optional ``adjust(k, x, P, u, C) -> (u, C)``
    called at frame k after the prediction with the predicted states x (K, 6), covariances P (K, 6, 6), bearings
    u (K, 3) and covariances C (K, 3, 3) of the K runs that have a bearing there, returning the bearings and
    covariances to update with (e.g. a centre-of-brightness correction at the predicted range); select: optional
    ``select(k, x, P, R_k) -> (u (B, 3), C (B, 3, 3))`` called at frame k after the prediction with every run's
    predicted state and covariance and the Hill-to-ICRS rotation, returning the bearing to update with (NaN rows:
    none), in place of ``bearings``/``adjust`` (the flight way to pick the target among candidates and gate
    outliers by the innovation: ``nav/target_finding.py``); it may return a third element G (B, 3, n_bias), the
    centre of brightness's correlated offset per unit bias state (ICRS, m; :func:`bearing_update`).  n_bias: the
    number of unit-variance Gauss-Markov bias states appended to the state (zero mean, unit variance at
    ``times[0]``; module docstring), propagated at frame k by ``bias_decay(k, x, R_k) -> (B, n_bias)`` (the
    correlation with frame k - 1; not called at frame 0; None: held constant).  Returns the updated relative
    states (B, T, 6) and their covariances (B, T, 6, 6) at every frame (the bias states' marginal left out)."""
    times = np.asarray(times, np.float64)
    n = orbit.mean_motion
    x, P = np.array(x0, np.float64), np.array(P0, np.float64)
    B, T = x.shape[0], times.size
    nb = int(n_bias)
    if nb:
        x = np.concatenate([x, np.zeros((B, nb))], -1)
        P = np.block([[P, np.zeros((B, 6, nb))], [np.zeros((B, nb, 6)), np.broadcast_to(np.eye(nb), (B, nb, nb))]])
    tm = np.asarray(dv_times, np.float64).reshape(-1)
    if tm.size and (np.any(tm <= times[0]) or np.any(tm > times[-1])):
        raise ValueError("run: manoeuvre times must lie in (times[0], times[-1]]")
    dvs = np.zeros((B, 0, 3)) if dv is None else np.asarray(dv, np.float64)
    if dvs.ndim == 2:
        dvs = np.broadcast_to(dvs[None], (B,) + dvs.shape)
    order = np.argsort(tm, kind="stable")
    tm, dvs = tm[order], dvs[:, order]
    R = hill_to_icrs(orbit, times)
    xs, Ps = np.empty((B, T, 6)), np.empty((B, T, 6, 6))
    t_now, k_dv = times[0], 0
    for k in range(T):
        while k_dv < tm.size and tm[k_dv] <= times[k]:
            x, P = predict(x, P, tm[k_dv] - t_now, n, cfg)
            x, P = apply_manoeuvre(x, P, dvs[:, k_dv], cfg)
            t_now, k_dv = tm[k_dv], k_dv + 1
        if times[k] > t_now:
            x, P = predict(x, P, times[k] - t_now, n, cfg)
            t_now = times[k]
        if nb and k > 0 and bias_decay is not None:
            x, P = bias_propagate(x, P, bias_decay(k, x, R[k]), nb)
        if select is not None:
            b, bc, *g = select(k, x, P, R[k])
            ok = np.all(np.isfinite(b), axis=-1)
            if ok.any():
                G = np.asarray(g[0])[ok][..., :nb] if g and nb else None
                x[ok], P[ok] = bearing_update(x[ok], P[ok], b[ok], np.asarray(bc)[ok], R[k], cfg.iterations, G)
        elif bearings is not None:
            b = np.asarray(bearings[:, k], np.float64)
            ok = np.all(np.isfinite(b), axis=-1)
            if ok.any():
                bu, bc = b[ok], np.asarray(bearing_cov[:, k])[ok]
                if adjust is not None:
                    bu, bc = adjust(k, x[ok], P[ok], bu, bc)
                x[ok], P[ok] = bearing_update(x[ok], P[ok], bu, bc, R[k], cfg.iterations)
        if ranges is not None:
            r = np.asarray(ranges[:, k], np.float64)
            ok = np.isfinite(r)
            if ok.any():
                if range_sig_frac is not None:
                    sig = np.asarray(range_sig_frac[:, k], np.float64)[ok] * np.linalg.norm(x[ok, :3], axis=-1)
                else:
                    sig = np.asarray(range_sig[:, k], np.float64)[ok]
                x[ok], P[ok] = range_update(x[ok], P[ok], r[ok], sig, cfg.iterations)
        xs[:, k], Ps[:, k] = x[:, :6], P[:, :6, :6]
    return xs, Ps
