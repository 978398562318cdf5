"""The rendezvous job's filter wiring (:mod:`dualsight.jobs.kinds.rendezvous`): the EKF's settings, the
centre-of-brightness bias model it carries as states (:class:`CobBias`; the product's, :func:`gauss_markov_cob`),
the target picked and its bearing corrected frame by frame (:func:`target_selector`), and the run over one
approach (:func:`run_filter`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from dualsight.nav.relative_filter import FilterConfig
from dualsight.jobs.kinds.rendezvous_spec import RendezvousConfig
from dualsight.nav import relative_filter as rf
from dualsight.nav.target_finding import FOUND_BY, chi2_gate_2dof, innovation_d2, pick, predicted_bearing
from dualsight.nav.target_bearing import sphere_phase_correction
from dualsight.scene.relative_orbit import hill_to_icrs
from dualsight.jobs.kinds.rendezvous_spec import RendezvousSpec
from dualsight.jobs.kinds.rendezvous_context import RendezvousContext
from dualsight.jobs.kinds.rendezvous_truth import sun_icrs


GATE_PROB = 0.99999
"""Probability of the chi-square(2) validation gate on the bearing innovation (``nav/target_finding.py``): a
bearing farther from the filter's prediction than this (wrong identification or attitude, a false detection) is
not used.  The candidates are already the detections no catalog star explains that move against the stars, so the
gate guards against identification and attitude failures only; the true target's bearings had heavier tails than
a Gaussian (1.3-1.6 % of the far preset's frames beyond the 2-dof 99.73 % point against 0.27 %, seeds 1-4, before
the point target's centroid sigma came from its calibration: at most 0.14 % since, below 400 m 1.6-2 %), and a
filter without process noise (the truth has none) that rejects two or three of them in a row can stay locked out
(0.999: seed 2 case 83 and seed 4 case 89 gated out for 41 and 55 frames), so the gate is wide (d2 < 23.0)."""


def filter_config(cfg: RendezvousConfig) -> FilterConfig:
    """The EKF's settings of a spec."""
    return FilterConfig(accel_psd=cfg.accel_psd, dv_sigma_frac=cfg.dv_error_frac, dv_sigma_m_s=cfg.dv_error_m_s,
                           iterations=cfg.iterations)


COB_BIAS_STATES = 2
"""Bias states of the filter (``nav/relative_filter.py``): the centre of brightness's correlated offset along the
Sun's direction in the plane of the sky and across it (``scene/photocentre_bias.py``)."""


def cob_axes(u: np.ndarray, s: np.ndarray) -> np.ndarray:
    """(K, 3, 2) unit vectors across lines of sight u (K, 3): the Sun's direction s (3,) projected across u, and
    u x that (any pair across u where the Sun is along u)."""
    d = s[None] - (u @ s)[:, None] * u
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    alt = rf.tangent_basis(u)[:, 0]
    d = np.where(n > 1e-9, d / np.where(n > 1e-9, n, 1.0), alt)
    return np.stack([d, np.cross(u, d)], -1)


@dataclass(frozen=True)
class CobBias:
    """A model of what the mean phase correction leaves of the centre of brightness, as ``n`` unit-variance bias
    states of the filter (``nav/relative_filter.run``'s ``n_bias``).  ``columns(k, v, D, alpha, r) -> (G, white)``
    for frame k's candidates: G (K, 3, n) m per unit state (``bearing_update``'s ``bias``) and white (K, 2) m the
    1-sigma of the rest along D's two axes, from their corrected lines of sight v (K, 3), the axes D (K, 3, 2) of
    :func:`cob_axes` (the Sun's side across v, and v x that), the phase angles alpha (K,) rad and the predicted range
    r m; ``decay(k, x, R_k) -> (1, n)`` the states' correlation with frame k - 1 and ``start(x, R_k)`` its first
    line of sight (:func:`cob_bias_decay`).  The product's is :func:`gauss_markov_cob`;
    ``benchmarks/bench_rendezvous_bias_models.py`` compares others."""

    n: int
    columns: Callable
    decay: Callable
    start: Callable


def gauss_markov_cob(spec: RendezvousSpec, ctx: RendezvousContext) -> CobBias | None:
    """The filter's model (:func:`target_selector`'s docstring): :data:`COB_BIAS_STATES` first-order Gauss-Markov
    states, ``sigma_sun`` and ``sigma_cross`` at the phase angle, decaying as :func:`cob_bias_decay`; the scatter
    about the spin average white.  None where :func:`cob_bias_states` is 0."""
    nb = cob_bias_states(spec, ctx)
    if not nb:
        return None
    pb = ctx.photocentre_bias

    def columns(k, v, D, alpha, r):
        s_sun, s_cross, w_sun, w_cross, _, _ = pb.at(alpha)
        return D * np.stack([s_sun, s_cross], -1)[:, None, :], np.stack([w_sun, w_cross], -1)

    decay, start = cob_bias_decay(spec, ctx)
    return CobBias(nb, columns, decay, start)


def cob_states(spec: RendezvousSpec, ctx: RendezvousContext, cob: CobBias | None) -> tuple[CobBias | None, int]:
    """The bias model the filter runs with (``cob``, or the product's :func:`gauss_markov_cob` for None) and its
    number of states (0 without ``phase_correction``, and so for a silhouette bearing: the photocentre's whole
    spread is then white)."""
    cob = gauss_markov_cob(spec, ctx) if cob is None else cob
    return cob, (cob.n if (cob is not None and spec.cfg.phase_correction) else 0)


def silhouette_cov(ctx: RendezvousContext, C_centre: np.ndarray, v: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """(K, 3, 3) rad^2: the covariance a filter takes for a silhouette centre's error (``bearing_point``
    "silhouette") at lines of sight v (K, 3): the calibrated white covariance ``C_centre`` (3, 3) rad^2 (ICRS,
    across the line of sight: along the blob's own axes, ``nav/blob_centre_error.CentreErrorCalibration.cov_px``)
    scaled by the error's sequence gain g along the orbit normal ``normal`` (3,) projected across v (the line of
    sight of an approach in the orbit plane turns about it) and across that (``ctx.silhouette_gain``: its
    frame-to-frame correlation under the target's spin and the observer's turn,
    ``rendezvous_context.silhouette_sequence_gain``): D S D^T C D S D^T with D those two axes (``cob_axes``) and
    S = diag(sqrt(g))."""
    D = cob_axes(v, normal)                                               # (K, 3, 2)
    DS = D * np.sqrt(np.asarray(ctx.silhouette_gain, np.float64))[None, None, :]
    M = DS @ np.swapaxes(D, -1, -2)                                       # (K, 3, 3): D S D^T
    return M @ np.asarray(C_centre, np.float64)[None] @ np.swapaxes(M, -1, -2)


def target_selector(spec: RendezvousSpec, ctx: RendezvousContext, m: dict, cob: CobBias | None = None):
    """The filter's ``select`` hook (``nav/relative_filter.run``): at frame k, each of the frame's candidates
    (``m["cand"]``: the moving unmatched detections of a star frame, the resolved blob of a proximity frame) is
    corrected for the centre of brightness at the predicted range r = |rho_pred| (with ``phase_correction``: moved
    towards the body's centre by the target's mean photocentre offset over attitudes at the phase angle between the
    Sun and its line of sight, ``scene/target_photometry.photocentre_table`` /
    ``nav/target_bearing.sphere_phase_correction``), then
    the one nearest the predicted bearing inside the chi-square(2) gate of probability :data:`GATE_PROB` is the
    target (``nav/target_finding.py``).

    What the correction leaves (``scene/photocentre_bias.py``): the spin-averaged photocentre's offset from the
    mean, correlated from frame to frame, goes to the filter's :data:`COB_BIAS_STATES` bias states (the third
    element returned: G (1, 3, 2) = the Sun's projection across the line of sight and its perpendicular, times
    ``sigma_sun`` and ``sigma_cross`` at the phase angle; propagated by :func:`cob_bias_decay`), and only the
    scatter about the spin average (``white_sun``, ``white_cross`` along the same two axes) joins the bearing's
    white covariance, with
    ``(cob_sigma_frac x 2 bounding_radius / r)^2`` in any case.  Without ``phase_correction`` the mean offset is
    not removed and the table's whole spread is white (no bias states: :func:`cob_bias_states`).  A bearing through
    the silhouette centre (``bearing_point`` "silhouette") has no centre of brightness to correct: its error is
    white, :func:`silhouette_cov` (with the ``cob_sigma_frac`` term).

    Records per frame the raw and used bearing and covariance (``u``, ``C``, ``u_used``, ``C_used``),
    ``bearing_used``, ``found_by`` (``FOUND_BY`` code) and ``found_true`` (the pick is the true target's
    detection: scored after the pick).  ``cob``: another model of those bias states (:class:`CobBias`; None: the
    product's, :func:`gauss_markov_cob`)."""
    c = spec.cfg
    extra = c.cob_sigma_frac * 2.0 * ctx.shape.bounding_radius
    s = sun_icrs(spec)
    grid, mean, spread = ctx.photocentre
    cob, nb = cob_states(spec, ctx, cob)
    cand = m["cand"]
    gate = chi2_gate_2dof(GATE_PROB)
    hit_code = 1 if spec.is_star else FOUND_BY.index("resolved_blob")

    def select(k, x, P, R_k):
        u_out, C_out, G_out = np.full((1, 3), np.nan), np.zeros((1, 3, 3)), np.zeros((1, 3, max(nb, 1)))
        idx = np.flatnonzero(cand["frame"] == k)
        if idx.size == 0:
            return u_out, C_out, G_out
        u, C = cand["u"][idx], cand["C"][idx]
        r = float(np.linalg.norm(x[0, :3]))
        var = np.full(len(u), extra ** 2)
        v = u
        G = np.zeros((len(u), 3, max(nb, 1)))
        if c.bearing_point == "silhouette":        # no centre of brightness: the silhouette centre's own error
            C = C + silhouette_cov(ctx, m["centre_cov"][k], v, R_k[:, 2])
        elif c.phase_correction:
            alpha = np.arccos(np.clip(-(u @ s), -1.0, 1.0))          # Sun - target - chaser
            v = sphere_phase_correction(u, np.broadcast_to(s, u.shape), np.interp(alpha, grid, mean), r)
            if nb:
                D = cob_axes(v, s)
                G, white = cob.columns(k, v, D, alpha, r)
                Dw = D * white[:, None, :] / r
                C = C + Dw @ np.swapaxes(Dw, -1, -2)
            else:
                var = var + np.interp(alpha, grid, spread) ** 2
        Cv = C + rf.isotropic_bearing_cov(v, np.sqrt(var) / r)
        up, Cp = predicted_bearing(x[:1], P[:1], R_k)
        if nb:                                       # the bias's part of the prediction (its current estimate)
            Gb = G @ P[0, 6:6 + nb, 6:6 + nb] @ np.swapaxes(G, -1, -2) / r ** 2
            proj = np.eye(3) - up[0][:, None] * up[0][None, :]
            Cp = Cp + proj @ Gb[0] @ proj
            off = G[:1] @ x[0, 6:6 + nb] / r
            up = up + off - (off @ up[0])[:, None] * up
            up = up / np.linalg.norm(up, axis=-1, keepdims=True)
        j, code = pick(innovation_d2(v, Cv, up[0], Cp[0]), gate)
        m["found_by"][k] = hit_code if code == 1 else code
        if j < 0:
            return u_out, C_out, G_out
        m["u"][k], m["C"][k], m["u_used"][k], m["C_used"][k] = u[j], C[j], v[j], Cv[j]
        m["target_xy"][k] = cand["xy"][idx[j]]
        m["bearing_used"][k] = True
        m["found_true"][k] = cand["true"][idx[j]]
        return v[j:j + 1], Cv[j:j + 1], G[j:j + 1]

    return select


def cob_bias_states(spec: RendezvousSpec, ctx: RendezvousContext) -> int:
    """:data:`COB_BIAS_STATES` where the mean phase correction is applied and the photocentre statistics are known,
    else 0 (then the table's whole spread is white, as before the bias states)."""
    return COB_BIAS_STATES if (spec.cfg.phase_correction and ctx.photocentre_bias is not None) else 0


def cob_bias_decay(spec: RendezvousSpec, ctx: RendezvousContext):
    """The filter's ``bias_decay`` hook: the correlation ``exp(-dpsi / psi_c)`` of the two bias states between
    frame k - 1 and k, dpsi the angle between the predicted lines of sight of the two frames (ICRS; the target's
    spin axis is fixed in ICRS, so this is the turn of the viewing direction relative to the body's spin) and
    psi_c the correlation's integral scale along the Sun and across at the phase angle
    (``scene/photocentre_bias.correlation_angle``; its 1/e angle is ~3x longer and made the filter
    underconfident on 4 of 6 seeds of the far preset, docs/rendezvous.md).  The statistics turn the observer
    about the Sun; a turn of another axis is taken as the same turn."""
    s = sun_icrs(spec)
    pb = ctx.photocentre_bias
    turn, start = line_of_sight_turn()

    def decay(k, x, R_k):
        dpsi, u = turn(x, R_k)
        if dpsi is None:
            return np.ones((1, COB_BIAS_STATES))
        alpha = float(np.arccos(np.clip(-(u @ s), -1.0, 1.0)))
        *_, c_sun, c_cross = pb.at(alpha)
        return np.exp(-dpsi / np.array([[c_sun, c_cross]]))

    return decay, start


def line_of_sight_turn():
    """A pair ``(turn(x, R_k) -> (dpsi, u), start(x, R_k))`` following the predicted line of sight u = -R_k rho /
    |rho| (ICRS; x (1, >= 3) the predicted state, R_k Hill -> ICRS) from call to call: dpsi the angle (rad) it
    turned since the last call (None at the first, unless ``start`` gave one)."""
    last = {}

    def los(x, R_k):
        rho = x[0, :3]
        return -(R_k @ rho) / np.linalg.norm(rho)

    def turn(x, R_k):
        u = los(x, R_k)
        prev = last.get("u")
        last["u"] = u
        if prev is None:
            return None, u
        return float(np.arctan2(np.linalg.norm(np.cross(prev, u)), prev @ u)), u

    return turn, lambda x, R_k: last.__setitem__("u", los(x, R_k))


def run_filter(spec: RendezvousSpec, ctx: RendezvousContext, draw: dict, m: dict,
               cob: CobBias | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(T, 6) estimates and (T, 6, 6) covariances of the EKF (one approach) from the nominal initial state and the
    spec's prior, with the measurements ``m`` (the target picked and its bearing corrected by
    :func:`target_selector`, its centre-of-brightness bias states by ``cob``, None: the product's) and the nominal
    manoeuvres."""
    c = spec.cfg
    P0 = np.diag(np.array(list(c.prior_position_m) + list(c.prior_velocity_m_s)) ** 2)
    rng = np.where(m["range_used"], m["range_filter"], np.nan)
    cob, nb = cob_states(spec, ctx, cob)
    if nb:
        cob.start(draw["x0_nominal"][None], hill_to_icrs(spec.orbit, spec.times[:1])[0])
    xs, Ps = rf.run(draw["x0_nominal"][None], P0[None], spec.times, spec.orbit, filter_config(c), ranges=rng[None],
                    range_sig_frac=np.nan_to_num(m["range_sigma_frac"], nan=1.0)[None],
                    dv_times=np.asarray(c.manoeuvre_times_s), dv=draw["dv_nominal"] if len(c.manoeuvre_times_s)
                    else None, select=target_selector(spec, ctx, m, cob), n_bias=nb,
                    bias_decay=cob.decay if nb else None)
    return xs[0], Ps[0]


def burn_frames(spec: RendezvousSpec) -> tuple[np.ndarray, int]:
    """(time since the first manoeuvre per frame (s; -1 before it or without one), the frame nearest one orbital
    period after it (-1: none, or beyond the last frame by more than half a frame))."""
    t = spec.times
    c = spec.cfg
    if not c.manoeuvre_times_s:
        return np.full(len(t), -1.0), -1
    t_b = min(c.manoeuvre_times_s)
    since = np.where(t >= t_b, t - t_b, -1.0)
    k = int(np.argmin(np.abs(t - (t_b + spec.orbit.period_s))))
    return since, (k if abs(t[k] - t_b - spec.orbit.period_s) <= 0.5 * c.frame_interval_s else -1)
