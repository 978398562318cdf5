"""The star-tracking job's rows (:mod:`dualsight.jobs.kinds.star_track`): the explicit Arrow schemas of
``star_frames`` (one row per frame) and ``star_sequences`` (one row per sequence), and the functions that fill them.

Units: errors per axis in arcsec (``nav/errors.py``'s Eqs. 4-7 in the spec's ``error_frame``), rates and their 1-sigma
in deg/s in the camera frame, times in s and ns.  Null where a value does not exist (no attitude, no rate, a stage
that did not run), never NaN, so that SQL aggregates skip it.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa

from dualsight.kernels.digest import to_int64
from dualsight.nav.angular_rate import rate_from_attitudes
from dualsight.nav.errors import axis_errors
from dualsight.nav.sequence import LOST_IN_SPACE, MODE_NAMES, NO_FIX, REASON_NAMES, TRACKING
from dualsight.scene.attitude import boresight_radec
from dualsight.scene.attitude_trajectory import DROPPED, EVENT_NAMES
from dualsight.scene.units import ARCSEC

__all__ = ["FRAMES_SCHEMA", "SEQUENCES_SCHEMA", "frames_table", "sequence_row", "reacquisitions"]

_MAT9 = pa.list_(pa.float64(), 9)
_F, _I, _L = pa.float64(), pa.int32(), pa.int64()
_XYZ = ("x", "y", "z")

FRAMES_SCHEMA = pa.schema(
    [("case_id", _L), ("frame", _I), ("t_s", _F), ("event", pa.string()), ("A_true", _MAT9), ("A_est", _MAT9),
     ("ra_true_rad", _F), ("dec_true_rad", _F), ("ra_est_rad", _F), ("dec_est_rad", _F),
     ("mode", pa.string()), ("lock_reason", pa.string()), ("valid", pa.bool_()), ("within_limit", pa.bool_()),
     ("false_lock", pa.bool_()), ("n_generated", _I), ("n_detections", _I), ("n_predicted", _I), ("n_matched", _I),
     ("n_used", _I), ("two_star", pa.bool_()), ("residual_rms_sigma", _F), ("p_chance", _F), ("T_lis", _I),
     ("err_x_arcsec", _F), ("err_y_arcsec", _F), ("err_z_arcsec", _F), ("err_total_arcsec", _F),
     ("sigma_x_arcsec", _F), ("sigma_y_arcsec", _F), ("sigma_z_arcsec", _F),
     ("degraded", pa.bool_()), ("sigma_max_arcsec", _F), ("degraded_err_max_arcsec", _F),
     ("frame_sigma_max_arcsec", _F), ("p_manoeuvre", _F)]
    + [(f"rate_att_{a}_deg_s", _F) for a in _XYZ] + [(f"rate_att_sigma_{a}_deg_s", _F) for a in _XYZ]
    + [(f"rate_star_{a}_deg_s", _F) for a in _XYZ] + [(f"rate_star_sigma_{a}_deg_s", _F) for a in _XYZ]
    + [("rate_star_pairs", _I)]
    + [(f"rate_filter_{a}_deg_s", _F) for a in _XYZ] + [(f"rate_filter_sigma_{a}_deg_s", _F) for a in _XYZ]
    + [(f"true_rate_{a}_deg_s", _F) for a in _XYZ] + [(f"true_rate_mean_{a}_deg_s", _F) for a in _XYZ]
    + [(f"gyro_{a}_deg_s", _F) for a in _XYZ]
    + [("image_digest", _L), ("t_render_ns", _L), ("t_detect_ns", _L), ("t_predict_ns", _L), ("t_track_ns", _L),
       ("t_lis_ns", _L), ("t_rate_ns", _L), ("t_filter_ns", _L), ("t_nav_ns", _L), ("shadow_verified", pa.bool_()),
       ("t_shadow_lis_ns", _L), ("n_id_agree", _I), ("n_id_disagree", _I), ("focal_px", _F), ("focal_sigma_px", _F)])
"""One row per frame.  ``A_true``/``A_est``: row-major inertial -> camera matrices (``A_est`` null without a fix);
``mode``: ``nav.sequence.MODE_NAMES``; ``lock_reason``: ``nav.sequence.REASON_NAMES`` (``locked``: tracking held,
``no_prior``: tracking did not run); ``valid``: an attitude was output; ``within_limit``: valid and every axis error
(and the total angle / sqrt 3) within ``error_limit_arcsec``; ``false_lock``: valid and not within the limit;
``sigma_*``: the attitude's stated 1-sigma per camera axis (the withheld one's on a degraded frame);
``degraded``: the tracker verified an attitude but withheld it, its largest principal 1-sigma ``sigma_max_arcsec``
(stated on every verified answer) above ``tracking.max_sigma_rad`` (not valid, so no false lock: it costs
availability); ``degraded_err_max_arcsec``: the withheld attitude's largest axis error (what it would have cost);
``frame_sigma_max_arcsec``: the frame's own solution's largest principal 1-sigma (before the attitude filter;
``sigma_max_arcsec`` is the filtered one's with ``tracking.attitude_filter``); ``p_manoeuvre``: the filter's
manoeuvre-model probability; ``rate_filter_*``: the filter's rate at the frame and its 1-sigma (compare with
``true_rate_*``); ``rate_att_*``: the rate from this fix and the previous
one (``rate_star_*``: from the stars seen in both), ``true_rate_*``: the true body rate at the frame,
``true_rate_mean_*``: the true mean rate over the same interval as ``rate_att``; ``t_nav_ns``: the tracker's whole
time on the frame (tracking, fallback, rates and the attitude filter, ``t_filter_ns``); ``shadow_*``, ``n_id_*``: lost-in-space run beside tracking
(``shadow_lost_in_space``), identities equal / different where both identified a detection; ``focal_px``,
``focal_sigma_px``: the focal length (fx) refined while tracking up to this frame and its 1-sigma
(``refine_focal``, ``nav/focal_refine.py``; null without it or before the first estimate)."""

SEQUENCES_SCHEMA = pa.schema([
    ("case_id", _L), ("seed", _L), ("motion", pa.string()), ("rate_deg_s", _F), ("gyro", pa.bool_()),
    ("frames", _I), ("frames_with_image", _I), ("frames_valid", _I), ("frames_within_limit", _I),
    ("availability", _F), ("frames_tracking", _I), ("frames_lost_in_space", _I), ("frames_none", _I),
    ("first_fix_frame", _I), ("time_to_first_fix_s", _F), ("losses", _I), ("reacquisition_frames", pa.list_(_I)),
    ("max_reacquisition_frames", _I), ("unrecovered_losses", _I), ("false_locks", _I),
    ("rate_att_err_rms_deg_s", _F), ("rate_star_err_rms_deg_s", _F), ("rate_att_within_3sigma", _F),
    ("t_sample_ns", _L), ("t_total_ns", _L),
])
"""One row per sequence.  ``availability`` = frames_within_limit / frames; ``first_fix_frame`` / ``time_to_first_fix_s``
from the first frame (null: never); a *loss* is a frame without a valid attitude after one with it, its
re-acquisition the frames from the loss to the next valid attitude (1 = the next frame; a loss never recovered
counts in ``unrecovered_losses``); ``rate_att_err_rms_deg_s``: RMS of |rate_att - true_rate_mean|;
``rate_att_within_3sigma``: share of the rate components within 3 stated sigmas."""


def _nullable(a: np.ndarray) -> pa.Array:
    a = np.asarray(a, np.float64)
    return pa.array(a, _F, mask=~np.isfinite(a))


def _int_or_null(a: np.ndarray, typ=_L) -> pa.Array:
    a = np.asarray(a, np.int64)
    return pa.array(a, typ, mask=a < 0)


def _mat9(A: np.ndarray, mask: np.ndarray | None = None) -> pa.Array:
    flat = pa.array(np.ascontiguousarray(A.reshape(-1, 9), np.float64).ravel())
    arr = pa.FixedSizeListArray.from_arrays(flat, 9)
    if mask is None:
        return arr
    return pa.FixedSizeListArray.from_arrays(flat, 9, mask=pa.array(mask))


def reacquisitions(valid: np.ndarray) -> tuple[list[int], int]:
    """(frames from each loss to the next valid frame, losses never recovered) of a (T,) bool series: a loss is a
    frame without a valid attitude that follows one with it."""
    v = np.asarray(valid, bool)
    loss = np.flatnonzero(~v[1:] & v[:-1]) + 1
    nxt = np.flatnonzero(v)
    out, unrec = [], 0
    for k in loss:
        j = np.searchsorted(nxt, k)
        if j < len(nxt):
            out.append(int(nxt[j] - k))
        else:
            unrec += 1
    return out, unrec


def _true_mean_rate(A_true: np.ndarray, t: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """(T, 3) rad/s mean true rate between frame ``prev[k]`` and ``k`` (NaN where prev < 0)."""
    ok = prev >= 0
    out = np.full((len(t), 3), np.nan)
    if ok.any():
        k = np.flatnonzero(ok)
        om, _ = rate_from_attitudes(A_true[prev[k]], A_true[k], t[k] - t[prev[k]])
        out[k] = om
    return out


def previous_fix(valid: np.ndarray) -> np.ndarray:
    """(T,) int64 the last frame before k with a valid attitude (-1 none): the other end of ``rate_att``."""
    v = np.asarray(valid, bool)
    last = np.where(v, np.arange(len(v)), -1)
    prior = np.maximum.accumulate(np.concatenate([[-1], last[:-1]]))
    return prior


def frames_table(case_id: int, spec, out: dict) -> pa.Table:
    d, r, res = out["draw"], out["rendered"], out["result"]
    T = len(d["t"])
    valid, within = out["valid"], out["within"]
    ra_t, dec_t = boresight_radec(d["A_true"])
    ra_e, dec_e = boresight_radec(res.A)
    deg = 180.0 / math.pi
    off = r["offsets"]
    cols = {
        "case_id": np.full(T, case_id, np.int64), "frame": np.arange(T, dtype=np.int32), "t_s": d["t"],
        "event": np.asarray(EVENT_NAMES, object)[d["events"]], "A_true": _mat9(d["A_true"]),
        "A_est": _mat9(np.nan_to_num(res.A), ~valid), "ra_true_rad": ra_t, "dec_true_rad": dec_t,
        "ra_est_rad": _nullable(ra_e), "dec_est_rad": _nullable(dec_e),
        "mode": np.asarray(MODE_NAMES, object)[res.mode], "lock_reason": np.asarray(REASON_NAMES, object)[res.reason],
        "valid": valid, "within_limit": within, "false_lock": valid & ~within,
        "n_generated": r["n_generated"], "n_detections": np.diff(off).astype(np.int32),
        "n_predicted": res.n_predicted, "n_matched": res.n_matched, "n_used": res.n_used, "two_star": res.two_star,
        "residual_rms_sigma": _nullable(res.rms_sigma), "p_chance": _nullable(res.p_chance), "T_lis": res.T_lis,
        **{f"err_{a}_arcsec": _nullable(out["err"][:, i] / ARCSEC) for i, a in enumerate(_XYZ)},
        "err_total_arcsec": _nullable(out["total_err"] / ARCSEC),
        **{f"sigma_{a}_arcsec": _nullable(np.sqrt(np.where(res.degraded, res.cov_degraded[:, i, i], res.cov[:, i, i]))
                                          / ARCSEC) for i, a in enumerate(_XYZ)},
        "degraded": res.degraded, "sigma_max_arcsec": _nullable(res.sigma_max / ARCSEC),
        "degraded_err_max_arcsec": _nullable(np.max(np.abs(axis_errors(res.A_degraded, d["A_true"],
                                                                       frame=spec.star.error_frame)), axis=1) / ARCSEC),
        "frame_sigma_max_arcsec": _nullable(res.frame_sigma_max / ARCSEC), "p_manoeuvre": _nullable(res.p_manoeuvre),
    }
    prev = previous_fix(valid)
    true_mean = _true_mean_rate(d["A_true"], d["t"], np.where(valid, prev, -1))
    gyro = d["gyro"] if d["gyro"] is not None else np.full((T, 3), np.nan)
    for i, a in enumerate(_XYZ):
        cols[f"rate_att_{a}_deg_s"] = _nullable(res.rate_att[:, i] * deg)
        cols[f"rate_att_sigma_{a}_deg_s"] = _nullable(np.sqrt(res.rate_att_cov[:, i, i]) * deg)
        cols[f"rate_star_{a}_deg_s"] = _nullable(res.rate_star[:, i] * deg)
        cols[f"rate_star_sigma_{a}_deg_s"] = _nullable(np.sqrt(res.rate_star_cov[:, i, i]) * deg)
    cols["rate_star_pairs"] = res.rate_pairs
    for i, a in enumerate(_XYZ):
        cols[f"rate_filter_{a}_deg_s"] = _nullable(res.rate_filter[:, i] * deg)
    for i, a in enumerate(_XYZ):
        cols[f"rate_filter_sigma_{a}_deg_s"] = _nullable(np.sqrt(res.rate_filter_cov[:, i, i]) * deg)
    for i, a in enumerate(_XYZ):
        cols[f"true_rate_{a}_deg_s"] = d["omega"][:, i] * deg
    for i, a in enumerate(_XYZ):
        cols[f"true_rate_mean_{a}_deg_s"] = _nullable(np.where(np.isfinite(res.rate_att[:, i]), true_mean[:, i],
                                                               np.nan) * deg)
    for i, a in enumerate(_XYZ):
        cols[f"gyro_{a}_deg_s"] = _nullable(gyro[:, i] * deg)
    frame_of = np.repeat(np.arange(T), np.diff(off))
    if res.shadow_rows is not None:
        both = (res.det_row >= 0) & (res.shadow_rows >= 0) & (res.mode[frame_of] == TRACKING) & res.shadow_verified[frame_of]
        agree = np.bincount(frame_of[both & (res.det_row == res.shadow_rows)], minlength=T).astype(np.int32)
        disagree = np.bincount(frame_of[both & (res.det_row != res.shadow_rows)], minlength=T).astype(np.int32)
        shadow = {"shadow_verified": res.shadow_verified, "t_shadow_lis_ns": _int_or_null(res.t_shadow_ns),
                  "n_id_agree": agree, "n_id_disagree": disagree}
    else:
        shadow = {k: pa.nulls(T, FRAMES_SCHEMA.field(k).type)
                  for k in ("shadow_verified", "t_shadow_lis_ns", "n_id_agree", "n_id_disagree")}
    cols.update({"image_digest": pa.array(to_int64(r["digest"].view(np.uint64)), _L,
                                          mask=d["events"] == DROPPED),
                 "t_render_ns": _int_or_null(r["t_render_ns"]), "t_detect_ns": _int_or_null(r["t_detect_ns"]),
                 "t_predict_ns": _int_or_null(res.t_predict_ns), "t_track_ns": _int_or_null(res.t_track_ns),
                 "t_lis_ns": _int_or_null(res.t_lis_ns), "t_rate_ns": _int_or_null(res.t_rate_ns),
                 "t_filter_ns": _int_or_null(res.t_filter_ns),
                 "t_nav_ns": _int_or_null(res.t_total_ns), **shadow})
    fz = out.get("focal")
    cols["focal_px"] = _nullable(fz.f_fused if fz is not None else np.full(T, np.nan))
    cols["focal_sigma_px"] = _nullable(fz.sigma_fused if fz is not None else np.full(T, np.nan))
    return pa.table({k: v if isinstance(v, pa.Array) else pa.array(v, FRAMES_SCHEMA.field(k).type)
                     for k, v in cols.items()}, schema=FRAMES_SCHEMA)


def sequence_row(case_id: int, spec, out: dict) -> dict:
    d, res = out["draw"], out["result"]
    seq = spec.sequence
    T = len(d["t"])
    valid, within = out["valid"], out["within"]
    first = np.flatnonzero(valid)
    reacq, unrec = reacquisitions(valid)
    deg = 180.0 / math.pi
    prev = previous_fix(valid)
    true_mean = _true_mean_rate(d["A_true"], d["t"], np.where(valid, prev, -1))

    def rms(est):
        e = np.linalg.norm(est - true_mean, axis=1)
        e = e[np.isfinite(e)]
        return float(np.sqrt(np.mean(e ** 2)) * deg) if e.size else None

    z = (res.rate_att - true_mean) / np.sqrt(np.diagonal(res.rate_att_cov, axis1=1, axis2=2))
    z = z[np.all(np.isfinite(z), axis=1)]
    return {
        "case_id": int(case_id), "seed": int(spec.seed), "motion": d["motion"], "rate_deg_s": d["rate_deg_s"],
        "gyro": bool(seq.gyro), "frames": T, "frames_with_image": int(np.sum(d["events"] != DROPPED)),
        "frames_valid": int(valid.sum()), "frames_within_limit": int(within.sum()),
        "availability": float(within.sum() / T),
        "frames_tracking": int(np.sum(res.mode == TRACKING)),
        "frames_lost_in_space": int(np.sum(res.mode == LOST_IN_SPACE)),
        "frames_none": int(np.sum(res.mode == NO_FIX)),
        "first_fix_frame": int(first[0]) if first.size else None,
        "time_to_first_fix_s": float(d["t"][first[0]] - d["t"][0]) if first.size else None,
        "losses": len(reacq) + unrec, "reacquisition_frames": reacq,
        "max_reacquisition_frames": max(reacq) if reacq else None, "unrecovered_losses": unrec,
        "false_locks": int(np.sum(valid & ~within)),
        "rate_att_err_rms_deg_s": rms(res.rate_att), "rate_star_err_rms_deg_s": rms(res.rate_star),
        "rate_att_within_3sigma": float(np.mean(np.abs(z) <= 3.0)) if z.size else None,
        "t_sample_ns": int(out["t_sample_ns"]), "t_total_ns": int(out["t_sample_ns"] + np.sum(np.maximum(
            out["rendered"]["t_render_ns"], 0)) + np.sum(np.maximum(out["rendered"]["t_detect_ns"], 0))
            + np.sum(np.maximum(res.t_total_ns, 0))),
    }
