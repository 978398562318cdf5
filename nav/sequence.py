"""One image sequence through a flight star tracker's state machine: lost-in-space until a verified fix, then
tracking, lock lost by rule, fallback, re-acquisition (issue 22, points 1-3).

Per frame ``k`` (in time order), with the last fix (attitude ``A_f``, covariance ``P_f``, frame ``f``) of either mode:

1. no image (a dropped frame): mode ``none``, reason ``no_image``; nothing runs.
2. a prior exists (the filter fused a solution at most ``max_coast_frames`` frames ago): **tracking**
   (``nav/tracking.py``) from the filtered state (``nav/attitude_filter.py``: an IMM of a steady and a manoeuvre
   motion model over the attitude and the body rate) extrapolated at its rate with its covariance (no random
   acceleration in the windows; with a gyro, its rates propagate: the mean of its two samples, covariance
   ``gyro_sigma^2 I / 2``; frames more than ``cfg.filter_max_gap_s`` apart, e.g. a ground camera's 30 s apart, are
   fused at a constant rate, every model without acceleration: the models' random acceleration is a spacecraft's at a few frames per second):
   predict the stars (with ``exposure_s`` and ``cfg.smear_sigma_per_px``, the centroid of the detection each
   predicted star pairs with gains the round-PSF fit's model error along and across the star's predicted streak, a
   2 x 2 covariance: ``nav/smear_weights.py``), leave out the stars whose predicted streak is not whole inside
   the image (``cfg.edge_margin_px``: a cut streak's centroid is biased), match in windows, solve with the centroid
   weights, verify.  Without the filter (``cfg.attitude_filter`` false) the last output fix is propagated with the
   rate from the last two fixes (``nav/angular_rate.rate_between``; else zero with ``cfg.rate_sigma_rad_s``).
3. no prior, or tracking lost lock (its reason is kept in the row): **lost-in-space** on the same frame: geometric
   voting (``nav/star_solution.identify``, as the star job calls it) and the weighted SVD attitude
   (``nav/attitude.solve_identified``).  A fix is *verified* when the attitude is solved from at least
   ``lis_min_stars`` accepted stars, the match threshold ``T > 0`` and the chance-match probability is at most
   ``cfg.max_p_chance`` (when the voting states it).
4. a verified solution of either mode is fused in the filter (update; a restart at the solution when its
   normalised innovation exceeds ``cfg.filter_gate`` or no prior exists) and the filtered attitude is the frame's
   answer.  An answer whose covariance has a principal 1-sigma above ``cfg.max_sigma_rad`` is *degraded*: mode
   ``none`` (tracking's: reason ``degraded``), not output; the filter keeps what it learnt from it.  Without the
   filter the answer is the frame's own solution, and a degraded one is no prior.  A lost-in-space fix that
   restarts an established filter (two solutions or more fused; tracking lost lock on the frame and the fix
   contradicts the track) is *unconfirmed*: mode ``none``, reason ``unconfirmed``; the next frame tracks from it
   and, locked, confirms it (a fix that contradicts an unconfirmed restart is output).  (On 10^5 frames
   at up to 1 deg/s, the one false lock of lost-in-space was such a fix: tracking had rejected the frame by its
   residuals, lost-in-space solved it 6 sigma off.)
5. with an output at ``k``: the rate from the two last output attitudes (``rate_between``, over ``t_k - t_f``)
   and from the displacements of the stars identified in both frames (``rate_from_star_pairs``, Crassidis 2002),
   each with its covariance (the filter's own rate is in ``rate_filter``).

The loop runs over frames (a sequence is causal); every step inside is vectorised over stars.  Latency per stage
is measured with ``time.perf_counter_ns`` around each call (ns; -1 where the stage did not run).  Optionally
(``shadow_lis``) lost-in-space also runs on every frame with an image without touching the state machine, so that
tracking's identities and speed can be compared with it on the same frames: after the loop, in a pass of its own
over the frames (with the camera each frame was tracked with), so that each mode is timed in a loop of its own as a
tracker running only that mode would run it.

Angles in radians, rates in rad/s in the camera frame (``dA/dt = -[omega x] A``), pixels in the (col, row)
convention of docs/architecture.md.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from dualsight.nav.tracking_config import TrackingConfig
from dualsight.nav import attitude_filter as filt
from dualsight.nav.angular_rate import pair_by_identity, rate_between, rate_from_star_pairs
from dualsight.nav.attitude import solve_identified
from dualsight.nav.observations import MAX_OBS, Observations
from dualsight.nav.smear_weights import along_gain, smear_axes, streak_inside
from dualsight.nav.star_solution import identify
from dualsight.nav.tracking import (DEGRADED, LOCK_REASONS, NO_PRIOR, max_sigma, predict, propagate,
                                    track)
from dualsight.scene.starfield_geometry import field_half_angle

__all__ = ["MODE_NAMES", "NO_FIX", "LOST_IN_SPACE", "TRACKING", "REASON_NAMES", "NO_IMAGE", "UNCONFIRMED", "LisFix",
           "lost_in_space", "SequenceResult", "run_sequence"]

_NEAR_MARGIN = math.radians(2.0)
"""Tracking predicts from the catalog stars within the field's half-angle + this of a recent boresight, refreshed
when the boresight has moved by half of it (:data:`_COS_NEAR_STEP`): the cone test over those (68 of 8,916 stars of
a V 6.5 catalog in the reference camera's field) instead of the whole catalog every frame."""
_COS_NEAR_STEP = math.cos(0.5 * _NEAR_MARGIN)

MODE_NAMES = ("none", "lost_in_space", "tracking")
"""Names of :attr:`SequenceResult.mode` (index = code): no valid attitude, a verified lost-in-space fix, a lock."""
NO_FIX, LOST_IN_SPACE, TRACKING = range(len(MODE_NAMES))
REASON_NAMES = LOCK_REASONS + ("no_image", "unconfirmed")
"""Names of :attr:`SequenceResult.reason`: ``nav.tracking.LOCK_REASONS`` (``locked``: tracking held; ``no_prior``:
tracking did not run; else why it lost lock), ``no_image`` (a dropped frame) and ``unconfirmed`` (a verified
lost-in-space fix that contradicts the filter's live track: the filter restarts at it, the frame has no output)."""
NO_IMAGE, UNCONFIRMED = len(LOCK_REASONS), len(LOCK_REASONS) + 1


@dataclass(frozen=True)
class LisFix:
    """One frame's lost-in-space answer.  A (3, 3), cov (3, 3) rad^2 (NaN when not solved); verified : bool;
    rows : (D,) int64 catalog row of each detection (-1 unidentified); n_used : accepted stars; T : match
    threshold; p_chance : chance-match probability (NaN when not computed).  cov is scaled by the a posteriori
    variance factor ``max(1, chi^2 / (2 n - 3))`` of the accepted stars' residuals, as tracking's."""

    A: np.ndarray
    cov: np.ndarray
    verified: bool
    rows: np.ndarray
    n_used: int
    T: int
    p_chance: float


def lost_in_space(xy: np.ndarray, sigma_px: np.ndarray, camera, cat_unit: np.ndarray, index, voting,
                  cat_vmag: np.ndarray | None, max_p_chance: float, min_stars: int = 3,
                  engine: str = "taichi") -> LisFix:
    """Geometric voting and the weighted SVD attitude of one frame (the star job's chain, one frame per call).

    xy : (D, 2) centroids (px), brightest first (the first ``MAX_OBS`` vote).  sigma_px : (D,) 1-sigma centroid
    error per axis (px, > 0): weights ``w = f^2 / sigma^2`` (rad^-2), so the covariance is in rad^2 (Markley 1988).
    index : the pair catalog or its ``nav.pair_index.VotingIndex``.  voting : ``VotingConfig``.  engine : the
    voting's ``"taichi"`` or ``"numpy"`` (bit-identical).
    """
    D = len(xy)
    nan3 = np.full((3, 3), np.nan)
    rows = np.full(D, -1, np.int64)
    if D < max(3, min_stars):
        return LisFix(nan3, nan3.copy(), False, rows, 0, 0, np.nan)
    S = min(D, MAX_OBS)
    xs = np.asarray(xy[:S], np.float64)
    vec = camera.backproject(xs)[None]
    obs = Observations(vec, np.ones((1, S), bool), xs[None, :, 0], xs[None, :, 1])
    ident = identify(obs, cat_unit, index, voting, cat_vmag=cat_vmag, engine=engine)
    f = 0.5 * (camera.fx + camera.fy)
    w = (f / np.asarray(sigma_px[:S], np.float64))[None] ** 2
    A, ok, P = solve_identified(obs.vec, ident.ids, ident.accepted, cat_unit, w, return_cov=True)
    acc = ident.accepted[0] & (ident.ids[0] >= 0)
    n = int(acc.sum())
    T = int(ident.T[0])
    p = float(ident.p_chance[0])
    verified = bool(ok[0]) and n >= min_stars and T > 0 and not (np.isfinite(p) and p > max_p_chance)
    rows[:S] = np.where(acc, ident.ids[0], -1)
    cov = P[0]
    if verified:                          # the a posteriori variance factor, as tracking's (nav/tracking.track)
        r = cat_unit[ident.ids[0][acc]] @ A[0].T
        z2 = np.sum((r - vec[0][acc]) ** 2, axis=1) * w[0][acc]
        f2 = float(np.sum(z2)) / max(1, 2 * n - 3)
        if f2 > 1.0:
            cov = cov * f2
    return LisFix(A[0], cov, verified, rows, n, T, p)


@dataclass(frozen=True)
class SequenceResult:
    """Per frame (T,) of :func:`run_sequence`, and per detection (K,) in the input's ragged layout.

    mode : int8 :data:`MODE_NAMES`.  reason : int8 :data:`REASON_NAMES`.  A, cov : (T, 3, 3) the frame's attitude
    (inertial -> camera) and its error covariance (rad^2), NaN without a fix.  n_predicted, n_matched : tracking's
    predicted stars and unique window pairs (0 where it did not run); n_used : stars in the answer (tracking's
    final solution or lost-in-space's accepted stars).  two_star : bool, the lock rests on two stars.
    rms_sigma : tracking's post-fit RMS per degree of freedom (centroid sigmas; NaN elsewhere).
    p_chance : the answer's chance-match probability.  T_lis : lost-in-space's match threshold (0 where it did
    not run).  degraded : (T,) bool, a verified answer (tracking's or lost-in-space's) whose largest principal
    1-sigma exceeds ``cfg.max_sigma_rad``: mode ``none`` (tracking's: reason ``degraded``), not a prior; its
    attitude and covariance in A_degraded, cov_degraded (T, 3, 3) (NaN elsewhere).  sigma_max : (T,) rad that
    largest principal 1-sigma of every verified answer (NaN elsewhere; the filtered attitude's with
    ``cfg.attitude_filter``).  frame_sigma_max : (T,) rad the same of the frame's own solution (before the filter).
    rate_filter, rate_filter_cov : (T, 3) rad/s, (T, 3, 3) (rad/s)^2 the filter's rate at the frame and its
    covariance with ``cfg.rate_jitter_rad_s`` added (NaN without the filter or a fused solution).  p_manoeuvre : (T,) the filter's probability of not being in its steady model
    (the accelerating and the manoeuvre models; NaN as above).  rate_att, rate_star : (T, 3) rad/s rate from the last two fixes / from the stars seen in both, with
    rate_att_cov, rate_star_cov (T, 3, 3) (rad/s)^2 (NaN where not available); rate_pairs : stars of rate_star.
    t_predict_ns (propagate + predict, and the predicted streaks; with the filter, no propagation), t_track_ns
    (match + solve + verify),
    t_lis_ns (voting + attitude), t_rate_ns (both rates), t_filter_ns (the attitude filter's prediction, fusion and
    estimate: it runs after either mode), t_total_ns : int64 wall time (-1 where the stage did not run).
    det_row : (K,) int64 catalog row of each detection in the answer (-1 none).  shadow_rows : (K,) int64
    lost-in-space's identities on every frame (``shadow_lis``; else None), shadow_verified : (T,) bool,
    t_shadow_ns : (T,) int64.  predictions : {frame: ``nav.tracking.Prediction``} of every frame tracking ran on,
    as matched (after the edge cut; ``keep_predictions``), else None.
    """

    mode: np.ndarray
    reason: np.ndarray
    A: np.ndarray
    cov: np.ndarray
    n_predicted: np.ndarray
    n_matched: np.ndarray
    n_used: np.ndarray
    two_star: np.ndarray
    rms_sigma: np.ndarray
    p_chance: np.ndarray
    T_lis: np.ndarray
    rate_att: np.ndarray
    rate_att_cov: np.ndarray
    rate_star: np.ndarray
    rate_star_cov: np.ndarray
    rate_pairs: np.ndarray
    degraded: np.ndarray
    sigma_max: np.ndarray
    frame_sigma_max: np.ndarray
    rate_filter: np.ndarray
    rate_filter_cov: np.ndarray
    p_manoeuvre: np.ndarray
    A_degraded: np.ndarray
    cov_degraded: np.ndarray
    t_predict_ns: np.ndarray
    t_track_ns: np.ndarray
    t_lis_ns: np.ndarray
    t_rate_ns: np.ndarray
    t_filter_ns: np.ndarray
    t_total_ns: np.ndarray
    det_row: np.ndarray
    shadow_rows: np.ndarray | None
    shadow_verified: np.ndarray | None
    t_shadow_ns: np.ndarray | None
    predictions: dict | None = None


def run_sequence(times: np.ndarray, det_xy: np.ndarray, det_sigma_px: np.ndarray | None, offsets: np.ndarray,
                 camera, cat_unit: np.ndarray, index, voting, cfg: TrackingConfig, *,
                 available: np.ndarray | None = None, gyro: np.ndarray | None = None, gyro_sigma_rad_s: float = 0.0,
                 cat_vmag: np.ndarray | None = None, max_coast_frames: int = 10, lis_min_stars: int = 3,
                 shadow_lis: bool = False, engine: str = "taichi", focal=None,
                 exposure_s: float = 0.0, keep_predictions: bool = False) -> SequenceResult:
    """Run one sequence through the state machine of the module docstring.

    times : (T,) s, increasing.  det_xy : (K, 2) centroids (px) of every frame, frame k's in
    ``offsets[k]:offsets[k + 1]`` (offsets (T + 1,)), brightest first within a frame.  det_sigma_px : (K,) 1-sigma
    centroid error per axis (px) or None (non-finite entries too) = ``cfg.centroid_sigma_px``.
    camera : ``scene.camera.Camera``.  cat_unit : (N, 3) ICRS unit vectors, brightest first; index : the pair
    catalog or its ``VotingIndex``; voting : lost-in-space's ``VotingConfig``; cfg : ``TrackingConfig``.
    available : (T,) bool, the frame delivered an image (default all).  gyro : (T, 3) measured body rates (rad/s,
    camera frame) or None; gyro_sigma_rad_s : their 1-sigma error per axis.  cat_vmag : (N,) for the blend test.
    max_coast_frames : a fix older than this many frames is no prior.  lis_min_stars : fewest accepted stars of a
    verified lost-in-space fix.  shadow_lis : also run lost-in-space on every frame (comparison only).
    engine : the voting's engine, ``"taichi"`` or ``"numpy"``.  focal : a ``nav.focal_refine.FocalFuser`` or None:
    after every fix it refines the focal length, and the next frames use its camera.
    exposure_s : the frames' exposure (s): with the filter's rate, a tracked detection's centroid variance gains
    ``cfg.smear_sigma_per_px`` times its predicted star's streak length, squared, along the streak and
    ``cfg.smear_cross_per_px`` times it across (``nav/smear_weights.py``; 0: neither).
    """
    t = np.asarray(times, np.float64)
    T = t.size
    off = np.asarray(offsets, np.int64)
    xy_all = np.asarray(det_xy, np.float64).reshape(-1, 2)
    K = xy_all.shape[0]
    sig_all = np.full(K, cfg.centroid_sigma_px) if det_sigma_px is None else np.asarray(det_sigma_px, np.float64)
    sig_all = np.where(np.isfinite(sig_all) & (sig_all > 0), sig_all, cfg.centroid_sigma_px)
    avail = np.ones(T, bool) if available is None else np.asarray(available, bool)
    f = 0.5 * (camera.fx + camera.fy)
    nan3, nan33 = np.full((T, 3), np.nan), np.full((T, 3, 3), np.nan)
    out = dict(mode=np.zeros(T, np.int8), reason=np.full(T, NO_PRIOR, np.int8), A=nan33.copy(), cov=nan33.copy(),
               n_predicted=np.zeros(T, np.int32), n_matched=np.zeros(T, np.int32), n_used=np.zeros(T, np.int32),
               two_star=np.zeros(T, bool), rms_sigma=np.full(T, np.nan), p_chance=np.full(T, np.nan),
               T_lis=np.zeros(T, np.int32), rate_att=nan3.copy(), rate_att_cov=nan33.copy(), rate_star=nan3.copy(),
               rate_star_cov=nan33.copy(), rate_pairs=np.zeros(T, np.int32), degraded=np.zeros(T, bool),
               sigma_max=np.full(T, np.nan), frame_sigma_max=np.full(T, np.nan), rate_filter=nan3.copy(),
               rate_filter_cov=nan33.copy(), p_manoeuvre=np.full(T, np.nan),
               A_degraded=nan33.copy(), cov_degraded=nan33.copy(),
               **{k: np.full(T, -1, np.int64) for k in ("t_predict_ns", "t_track_ns", "t_lis_ns", "t_rate_ns",
                                                        "t_filter_ns",
                                                        "t_total_ns")})
    det_row = np.full(K, -1, np.int64)
    shadow_rows = np.full(K, -1, np.int64) if shadow_lis else None
    shadow_ok = np.zeros(T, bool) if shadow_lis else None
    t_shadow = np.full(T, -1, np.int64) if shadow_lis else None
    shadow_cams = {}                   # frame -> the camera lost-in-space runs with on it (shadow_lis)
    clock = time.perf_counter_ns

    def lis(xy, sg, cam=None):
        return lost_in_space(xy, sg, camera if cam is None else cam, cat_unit, index, voting, cat_vmag,
                             cfg.max_p_chance, lis_min_stars, engine)

    fix = None                         # (A, P, frame) of the last output attitude, either mode
    rate = None                        # (omega, cov) from the last two fixes (without the filter)
    state, last_fused = None, -1       # the attitude filter (nav/attitude_filter.py) and its last fused frame
    n_fused, doubtful = 0, False       # solutions fused since the filter's start; started at an unconfirmed fix
    predictions = {} if keep_predictions else None
    near_axis = near_camera = near_rows = near_cat = None     # the catalog near the boresight (see the loop)
    use_filter = cfg.attitude_filter
    # the filter's motion models: steady (constant rate), accelerating (constant acceleration), manoeuvre
    # (constant rate, large random acceleration)
    noise = np.array([cfg.accel_steady_rad_s2, cfg.jerk_rad_s3, cfg.accel_manoeuvre_rad_s2])
    const_accel = np.array([False, True, False])
    accel0 = np.array([0.0, cfg.accel_manoeuvre_rad_s2, 0.0])
    zero_noise = np.zeros(3)
    ps = cfg.model_switch_prob
    switch = np.full((3, 3), 0.5 * ps) + np.eye(3) * (1.0 - 1.5 * ps)
    for k in range(T):
        s = slice(int(off[k]), int(off[k + 1]))
        xy, sg = xy_all[s], sig_all[s]
        if not avail[k]:
            out["reason"][k] = NO_IMAGE
            continue
        if shadow_lis:
            shadow_cams[k] = camera
        c_start = clock()
        meas = None                    # (A, cov, mode, rows) of the frame's verified solution
        if fix is not None and k - fix[2] > max_coast_frames:
            fix = rate = None
        if state is not None and k - last_fused > max_coast_frames:
            state = None
        pstate = None
        t_filt = 0
        if (state if use_filter else fix) is not None:
            c0 = clock()
            if use_filter:
                g = gc = None
                if gyro is not None:
                    g = 0.5 * (np.asarray(gyro[last_fused], np.float64) + np.asarray(gyro[k], np.float64))
                    gc = np.eye(3) * (0.5 * gyro_sigma_rad_s ** 2)
                long_gap = t[k] - state.t > cfg.filter_max_gap_s
                pstate = (filt.predict(state, t[k], zero_noise, switch, None, g, gc) if long_gap
                          else filt.predict(state, t[k], noise, switch, const_accel, g, gc))
                # the windows follow the constant-rate extrapolation of the filtered state (its attitude, rate and
                # their covariance, no random acceleration): the motion models are for fusing, and their
                # acceleration held over a long gap (frames 30 s apart) would open every window to its maximum
                Ap, Pp, _, _ = filt.combined(pstate, free=True)
                t_filt = clock() - c0
                c0 = clock()
            else:
                dt = t[k] - t[fix[2]]
                if gyro is not None:
                    om = 0.5 * (np.asarray(gyro[fix[2]], np.float64) + np.asarray(gyro[k], np.float64))
                    C = np.eye(3) * (0.5 * gyro_sigma_rad_s ** 2)
                elif rate is not None:
                    om, C = rate
                else:
                    om, C = np.zeros(3), np.eye(3) * cfg.rate_sigma_rad_s ** 2
                Ap, Pp = propagate(fix[0], fix[1], om, C, dt)
            if near_axis is None or float(Ap[2] @ near_axis) < _COS_NEAR_STEP or camera is not near_camera:
                # the catalog stars within the field's half-angle + 2 deg of this boresight: the prediction runs
                # over them alone (valid while the boresight stays within 1 deg of near_axis)
                near_axis, near_camera = Ap[2].copy(), camera
                half = field_half_angle(camera)
                near_rows = np.flatnonzero(cat_unit @ near_axis > math.cos(half + _NEAR_MARGIN))
                near_cat = cat_unit[near_rows]
                # all of them in front of the camera while the boresight is within 1 deg: no cone test needed
                near_front = half + 1.5 * _NEAR_MARGIN < 0.5 * math.pi
            pred = predict(Ap, Pp, near_cat, camera, cfg, near_rows, near=near_front)   # the whole catalog's rows
            smear = (pstate is not None and exposure_s > 0 and len(pred.rows) > 0
                     and (cfg.smear_sigma_per_px > 0 or cfg.streak_psf_sigma_px > 0))
            if smear:
                # a streak fitted as a round PSF: its centroid error grows with the streak's length, which the
                # filter's rate predicts at each predicted star (nav/smear_weights.py): the detector's variance
                # along the streak by 1 + L^2 / (12 s^2) (streak_psf_sigma_px), plus smear_sigma_per_px along and
                # smear_cross_per_px across it per px, in the fit's 2 x 2 weights
                u_p, len_p = smear_axes(pred.G, filt.rate(pstate), exposure_s)
            else:                                     # still stars: the margin alone
                u_p = len_p = None
            inside = streak_inside(pred.xy, u_p, len_p, cfg.edge_margin_px, camera.width, camera.height)
            if not inside.all():                      # a streak cut by the image's edge: its centroid is biased
                pred = pred.take(inside)
                if smear:
                    u_p, len_p = u_p[inside], len_p[inside]
            if keep_predictions:
                predictions[k] = pred
            c1 = clock()
            res = track(pred, xy, sg, cat_unit, camera, cfg,
                        (u_p, (cfg.smear_sigma_per_px * len_p) ** 2,
                         (cfg.smear_cross_per_px * len_p) ** 2 if cfg.smear_cross_per_px > 0 else None,
                         along_gain(len_p, cfg.streak_psf_sigma_px)) if smear else None)
            c2 = clock()
            out["t_predict_ns"][k], out["t_track_ns"][k] = c1 - c0, c2 - c1
            out["reason"][k] = res.reason
            out["n_predicted"][k], out["n_matched"][k] = res.n_predicted, res.n_matched
            if res.locked:
                out["n_used"][k], out["two_star"][k] = res.n_used, res.two_star
                out["rms_sigma"][k], out["p_chance"][k] = res.rms_sigma, res.p_chance
                meas = (res.A, res.cov, TRACKING, res.det_row)
        if meas is None:                                                 # acquire, or fall back
            c0 = clock()
            fx_ = lis(xy, sg)
            out["t_lis_ns"][k] = clock() - c0
            out["T_lis"][k] = fx_.T
            if fx_.verified:
                out["n_used"][k], out["p_chance"][k] = fx_.n_used, fx_.p_chance
                meas = (fx_.A, fx_.cov, LOST_IN_SPACE, fx_.rows)
        if meas is not None:
            c0 = clock()
            A, P, mode, rows = meas
            out["frame_sigma_max"][k] = max_sigma(P)
            unconfirmed = False
            if use_filter:                # fuse the frame's solution; restart where it does not fit the track
                if pstate is None or filt.innovation(pstate, A, P) > cfg.filter_gate:
                    # a lost-in-space fix that contradicts an established track (two solutions or more fused, and
                    # tracking just lost lock on this frame): two answers disagree, so the filter restarts at the
                    # fix but does not output it before the next frame's tracking confirms it
                    unconfirmed = pstate is not None and mode == LOST_IN_SPACE and n_fused >= 2
                    om0 = C0 = None           # a restart keeps the rate between the last answer and this one, or
                    if pstate is not None and (unconfirmed or doubtful):    # the track's own rate when one of the
                        _, _, om0, C0 = filt.combined(pstate)                # two answers may be wrong
                    elif pstate is not None:
                        A_l, P_l, _, _ = filt.combined(state)
                        om0, C0 = rate_between(A_l, A, t[k] - state.t, P_l, P)
                    state = filt.start(A, P, t[k], cfg.rate_sigma_rad_s, 3, om0, C0, accel0)
                    n_fused, doubtful = 1, unconfirmed
                else:
                    state = filt.update(pstate, A, P)
                    n_fused, doubtful = n_fused + 1, False
                last_fused = k
                A, P, om_f, C_f = filt.combined(state)
                out["rate_filter"][k] = om_f
                out["rate_filter_cov"][k] = C_f + np.eye(3) * cfg.rate_jitter_rad_s ** 2    # the jitter it averages
                out["p_manoeuvre"][k] = 1.0 - state.mu[0]
            out["sigma_max"][k] = max_sigma(P)
            t_fuse = clock() - c0
            if out["sigma_max"][k] > cfg.max_sigma_rad:   # verified but too weak to output (nor a prior alone)
                out["degraded"][k] = True
                out["A_degraded"][k], out["cov_degraded"][k] = A, P
                if mode == TRACKING:
                    out["reason"][k] = DEGRADED
                A = None
            elif unconfirmed:
                out["reason"][k] = UNCONFIRMED
                A = None
            else:
                out["mode"][k] = mode
        else:
            A, t_fuse = None, 0
        if A is not None:
            det_row[s] = rows
            out["A"][k], out["cov"][k] = A, P
            c0 = clock()
            if fix is not None:
                dt = t[k] - t[fix[2]]
                om, C = rate_between(fix[0], A, dt, fix[1], P)
                out["rate_att"][k], out["rate_att_cov"][k] = om, C
                rate = (om, C)
                sp = slice(int(off[fix[2]]), int(off[fix[2] + 1]))
                ip, jn = pair_by_identity(det_row[sp], rows)
                if len(ip) >= 2:
                    b0 = camera.backproject(xy_all[sp][ip])
                    b1 = camera.backproject(xy[jn])
                    w0, w1 = (sig_all[sp][ip] / f) ** 2, (sg[jn] / f) ** 2
                    om_s, C_s, ok = rate_from_star_pairs(b0, b1, w0, w1, dt)
                    if ok:
                        out["rate_star"][k], out["rate_star_cov"][k] = om_s, C_s
                        out["rate_pairs"][k] = len(ip)
            out["t_rate_ns"][k] = clock() - c0
            fix = (A, P, k)
            if focal is not None:                 # the focal length refined from this fix (nav/focal_refine.py)
                camera = focal.update(k, xy, sg, rows, A, cat_unit, camera)
        if use_filter and (t_filt or t_fuse):
            out["t_filter_ns"][k] = t_filt + t_fuse
        out["t_total_ns"][k] = clock() - c_start
    for k, cam in shadow_cams.items():
        # lost-in-space on the same frames in a pass of its own: each mode is timed in its own loop, as a tracker
        # running one of them would run it (run between two tracked frames, it evicted tracking's arrays from
        # the caches and slowed the next tracked frame by ~20 %)
        s = slice(int(off[k]), int(off[k + 1]))
        c0 = clock()
        sh = lis(xy_all[s], sig_all[s], cam)
        t_shadow[k] = clock() - c0
        shadow_rows[s], shadow_ok[k] = sh.rows, sh.verified
    return SequenceResult(**out, det_row=det_row, shadow_rows=shadow_rows, shadow_verified=shadow_ok,
                          t_shadow_ns=t_shadow, predictions=predictions)
