"""The star job's columns for a spacecraft in the field (issue 23; ``jobs/kinds/star.py`` ``compute_batch``): the
detection that is the target, its ICRS bearing through the star attitude with its covariance and phase correction,
the target's own row fields and its detections' flags, and the Sun, Earth and Moon columns of
``[target.environment]``."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from dualsight.nav.attitude import solve_identified
from dualsight.nav.observations import ragged_rank
from dualsight.nav.relative_filter import isotropic_bearing_cov
from dualsight.nav.target_bearing import (BLOB_SIGMA_FRAC_BY_DETECTOR, attitude_covariance, bearing_error, bearing_nees,
                                          blob_centroid_sigma, inertial_bearing, offset_correction,
                                          sphere_phase_correction)
from dualsight.scene.attitude import unit_to_radec
from dualsight.scene.case_environment import CaseEnvironment
from dualsight.scene.target_in_field import TargetFrame
from dualsight.scene.target_photometry import photocentre_offset


def environment_columns(env: CaseEnvironment | None) -> dict | None:
    """The columns of ``star_cases`` of ``jobs/kinds/star_tables.ENVIRONMENT_CASE_FIELDS`` as (B,) arrays (None
    without an environment: all null)."""
    if env is None:
        return None
    v = env.view
    return {"epoch_utc": np.round(env.epoch_unix_s * 1e6).astype(np.int64),       # microseconds, UTC
            "earth_limb_angle_rad": v.earth_limb_angle_rad, "moon_angle_rad": v.moon_angle_rad,
            "earth_keepout": v.earth_keepout, "moon_keepout": v.moon_keepout, "earth_lit_in_cone": v.earth_lit_in_cone,
            "eclipse": v.umbra, "penumbra": v.penumbra}


def target_detection(det, tf: TargetFrame) -> np.ndarray:
    """(B,) int64 index (into the batch's detections) of the detection nearest each case's target centre of
    brightness within ``max(3, diameter / 2 + 3)`` px, -1 where none (or no target)."""
    B = len(tf.present)
    case = np.asarray(det.case, np.int64)
    d2 = (det.x - tf.cob_x_px[case]) ** 2 + (det.y - tf.cob_y_px[case]) ** 2
    rad = np.maximum(3.0, 0.5 * tf.diameter_px + 3.0)
    k = np.flatnonzero(tf.present[case] & (d2 <= rad[case] ** 2))
    k = k[np.lexsort((d2[k], case[k]))]
    out = np.full(B, -1, np.int64)
    first = np.unique(case[k], return_index=True)[1]
    out[case[k[first]]] = k[first]
    return out


CENTROID_FLOOR_PX = 0.02
"""Smallest 1-sigma centroid error (px) assumed for the stars and the target in the bearing's covariance (the PSF
model's own error; the same floor as the attitude weights of ``jobs/kinds/star.compute_batch``)."""


PHASE_CORRECTED_COLUMNS = ("target_bearing_pc_err_rad", "target_bearing_pc_sigma_rad", "target_bearing_pc_nees",
                           "target_bearing_pck_err_rad")
"""The columns of :func:`target_bearing_columns` written with ``[target] phase_correction`` (null without)."""


def target_bearing_columns(spec, tf: TargetFrame, tcases, det, obs, ident, sol, alt, cat_unit, A_true,
                           ctx=None) -> dict:
    """The target's inertial bearing (``nav/target_bearing.py``) from its detection and the attitude of the robust
    method (the reference's without ``compare_robust``; ``spec``, ``ctx``: the star job's ``StarSpec`` and
    ``StarContext``, ``jobs/kinds/star.py``), per case: estimate (RA, Dec), errors against the true
    direction of the body origin and of the centre of brightness, 1-sigma (rad, per axis: sqrt(trace / 2)) and
    NEES (2 dof, against the centre of brightness: what the covariance describes).  Null where there is no
    attitude or no detection of the target.

    The centroid's sigma is the blob's (``nav/target_bearing.blob_centroid_sigma``: the point-source sigma plus
    a fraction of the blob's RMS radius, larger for a blob larger than any star, ``ctx.star_blob_limit``, the
    fractions of the spec's detector).  With
    ``[target] phase_correction`` (``ctx.target_photocentre``) the bearing is also corrected for the phase angle
    between the known Sun and the measured line of sight, at the case's range (what a filter's prediction gives;
    here the truth): ``target_bearing_pc_*`` by the target's mean photocentre over random attitudes (its spread
    over attitudes joins the covariance, so the NEES is against the body origin), ``target_bearing_pck_err_rad``
    by the exact photocentre of its known attitude (``scene/target_photometry.photocentre_offset``)."""
    B = len(tf.present)
    idn, sl = (alt if alt is not None else (ident, sol))
    kt = target_detection(det, tf)
    n_used = (idn.accepted & (idn.ids >= 0) & obs.valid).sum(1)
    _, ok, cov_unit = solve_identified(obs.vec, idn.ids, idn.accepted & obs.valid, cat_unit, return_cov=True)
    f = max(spec.camera.fx, spec.camera.fy)
    # the stars' a-posteriori variance per axis (rad^2): the attitude's scale and the target centroid's variance
    s2 = attitude_covariance(np.ones((B, 1, 1)), sl.residual, n_used, floor_rad=CENTROID_FLOOR_PX / f)[:, 0, 0]
    P = np.where(ok[:, None, None], cov_unit, 0.0) * s2[:, None, None]
    sigma_px = np.sqrt(s2) * f
    kk = np.maximum(kt, 0)
    if det.sigma_px is not None:
        sigma_px = np.where(kt >= 0, np.hypot(np.asarray(det.sigma_px)[kk], CENTROID_FLOOR_PX), sigma_px)
    npix = np.asarray(det.npix)[kk] if len(det.x) else np.zeros(B)
    limit = ctx.star_blob_limit if ctx is not None and ctx.star_blob_limit is not None else np.inf
    sigma_px = blob_centroid_sigma(npix, sigma_px, npix > limit, *BLOB_SIGMA_FRAC_BY_DETECTOR[spec.detector])
    use = (kt >= 0) & ok & sl.ok
    A = np.where(use[:, None, None], sl.A_est, np.eye(3))
    xy = np.stack([det.x[kk], det.y[kk]], -1) if len(det.x) else np.zeros((B, 2))
    u, C = inertial_bearing(A, np.where(use[:, None, None], P, 0.0), xy, sigma_px, spec.camera)
    At = np.swapaxes(np.asarray(A_true, np.float64), 1, 2)
    u_body = np.einsum("bij,bj->bi", At, tcases.pos_cam / tcases.range_m[:, None])
    cob = spec.camera.backproject(np.stack([tf.cob_x_px, tf.cob_y_px], -1))
    u_cob = np.einsum("bij,bj->bi", At, cob)
    ra, dec = unit_to_radec(u)
    nees = np.full(B, np.nan)
    if use.any():
        nees[use] = bearing_nees(u[use], u_cob[use], C[use])
    m = lambda v: pa.array(np.where(use, v, 0.0), pa.float64(), mask=~use)  # noqa: E731
    out = {"target_ra_rad": m(ra), "target_dec_rad": m(dec), "target_bearing_err_rad": m(bearing_error(u, u_body)),
           "target_bearing_cob_err_rad": m(bearing_error(u, u_cob)),
           "target_bearing_sigma_rad": m(np.sqrt(np.trace(C, axis1=1, axis2=2) / 2)), "target_bearing_nees": m(nees)}
    if ctx is None or not ctx.target_photocentre:
        return {**out, **{k: pa.nulls(B, pa.float64()) for k in PHASE_CORRECTED_COLUMNS}}
    grid, mean, spread = ctx.target_photocentre
    s = tcases.sun_icrs
    alpha = np.arccos(np.clip(-np.einsum("bk,bk->b", u, s), -1.0, 1.0))      # Sun - target - camera, measured
    r = tcases.range_m
    u_pc = sphere_phase_correction(u, s, np.interp(alpha, grid, mean), r)
    C_pc = C + isotropic_bearing_cov(u_pc, np.interp(alpha, grid, spread) / r)
    nees_pc = np.full(B, np.nan)
    if use.any():
        nees_pc[use] = bearing_nees(u_pc[use], u_body[use], C_pc[use])
    # the known attitude: the exact photocentre of the lit, visible facets, camera frame -> ICRS by the estimate
    off_cam = photocentre_offset(ctx.target_shape, tcases.R_body, tcases.sun_cam, -tcases.pos_cam / r[:, None])
    u_pck = offset_correction(u, np.einsum("bji,bj->bi", A, off_cam), r)
    return {**out, "target_bearing_pc_err_rad": m(bearing_error(u_pc, u_body)),
            "target_bearing_pc_sigma_rad": m(np.sqrt(np.trace(C_pc, axis1=1, axis2=2) / 2)),
            "target_bearing_pc_nees": m(nees_pc), "target_bearing_pck_err_rad": m(bearing_error(u_pck, u_body))}


def target_columns(tcases, tf: TargetFrame, det, obs, ident, alt, excluded, bearing: dict | None = None
                   ) -> tuple[dict, dict]:
    """The target columns of ``star_cases`` and ``star_detections`` (jobs/kinds/star_tables.py
    TARGET_CASE_FIELDS, TARGET_DETECTION_FIELDS) of a batch; ``bearing``: :func:`target_bearing_columns`."""
    B, K = len(tf.present), len(det.x)
    kt = target_detection(det, tf)
    has = kt >= 0
    kk = np.maximum(kt, 0)
    _, rank = ragged_rank(det.case, det.offsets)
    S = obs.valid.shape[1]
    b = np.arange(B)
    rk = rank[kk] if K else np.zeros(B, np.int64)
    in_obs = has & (rk < S)
    slot = np.where(in_obs, rk, 0)
    voted = in_obs & obs.valid[b, slot]
    acc = lambda idn: voted & idn.accepted[b, slot] & (idn.ids[b, slot] >= 0)  # noqa: E731
    exc = np.zeros(K, bool) if excluded is None else np.asarray(excluded, bool)
    masked = lambda v: pa.array(v, mask=~has)  # noqa: E731
    ra, dec = unit_to_radec(tcases.sun_icrs)
    pres = tf.present
    cases = {
        "target_present": pres, "target_vmag": tf.vmag, "target_electrons": tf.electrons,
        "target_range_m": tcases.range_m, "target_phase_rad": tcases.phase_rad,
        "target_x_px": tf.x_px, "target_y_px": tf.y_px, "target_cob_x_px": tf.cob_x_px, "target_cob_y_px": tf.cob_y_px,
        "target_resolved": tf.resolved, "target_diameter_px": tf.diameter_px, "target_area_px": tf.area_px,
        "target_pixels": pa.array(tf.pixels.astype(np.int32), mask=tf.pixels < 0),
        "target_det_x_px": masked(det.x[kk] if K else np.zeros(B)),
        "target_det_y_px": masked(det.y[kk] if K else np.zeros(B)),
        "target_det_npix": masked((det.npix[kk] if K else np.zeros(B)).astype(np.int32)),
        "target_excluded": masked(exc[kk] if K else np.zeros(B, bool)),
        "target_voted": voted, "target_id_accepted": acc(ident),
        "target_id_accepted_robust": acc(alt[0]) if alt is not None else pa.nulls(B, pa.bool_()),
        "n_excluded": np.bincount(np.asarray(det.case, np.int64)[exc], minlength=B).astype(np.int32),
        "sun_ra_rad": ra, "sun_dec_rad": dec, "sun_angle_rad": tf.sun_angle_rad, "sun_keepout": tf.sun_keepout,
        **(bearing or {}),
    }
    is_t = np.zeros(K, bool)
    is_t[kt[has]] = True
    return cases, {"is_target": is_t, "excluded": exc}
