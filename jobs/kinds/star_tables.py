"""The star job's rows (:mod:`dualsight.jobs.kinds.star`): the explicit Arrow schemas of ``star_cases`` (one row
per case) and ``star_detections`` (one row per detection), and the functions that fill them from a batch's
stage outputs."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from dualsight.kernels.digest import to_int64
from dualsight.nav.errors import STATUS_NAMES
from dualsight.nav.observations import ragged_rank
from dualsight.scene.attitude import dcm_to_quat
from dualsight.scene.units import angle_between

__all__ = ["CASES_SCHEMA", "DETECTIONS_SCHEMA", "TARGET_CASE_FIELDS", "TARGET_DETECTION_FIELDS", "cases_table",
           "detections_table"]


# ------------------------------------------------------------------------------------------ tables
_QUAT = pa.list_(pa.float32(), 4)

TARGET_CASE_FIELDS = [
    ("target_present", pa.bool_()),            # the case has a target in its field (and it is lit)
    ("target_vmag", pa.float64()),             # apparent V magnitude (scene/target_photometry.py)
    ("target_electrons", pa.float64()),        # e- per exposure on the stars' zero point
    ("target_range_m", pa.float64()), ("target_phase_rad", pa.float64()),
    ("target_x_px", pa.float64()), ("target_y_px", pa.float64()),           # projection of the body origin
    ("target_cob_x_px", pa.float64()), ("target_cob_y_px", pa.float64()),   # of the photometric centre of brightness
    ("target_resolved", pa.bool_()), ("target_diameter_px", pa.float64()),  # bounding sphere's apparent diameter
    ("target_area_px", pa.float64()),          # projected area (px^2)
    ("target_pixels", pa.int32()),             # pixels it covers (resolved targets; null for a point)
    ("target_det_x_px", pa.float64()), ("target_det_y_px", pa.float64()),   # its detection (null: none)
    ("target_det_npix", pa.int32()),
    ("target_excluded", pa.bool_()),           # its blob was kept out of identification (nav/resolved_blobs.py)
    ("target_voted", pa.bool_()),              # its detection went to identification as an observation
    ("target_id_accepted", pa.bool_()),        # the reference's method accepted a catalog identity for it
    ("target_id_accepted_robust", pa.bool_()),  # the robust method did
    ("n_excluded", pa.int32()),                # blobs kept out of identification as larger than any star's
    ("sun_ra_rad", pa.float64()), ("sun_dec_rad", pa.float64()),
    ("sun_angle_rad", pa.float64()),           # Sun from the boresight
    ("sun_keepout", pa.bool_()),               # inside the [target] sun_keepout_deg cone
    # its inertial line of sight (nav/target_bearing.py) through the robust method's attitude (null: no attitude
    # or no detection of the target)
    ("target_ra_rad", pa.float64()), ("target_dec_rad", pa.float64()),
    ("target_bearing_err_rad", pa.float64()),      # against the true direction of the body origin
    ("target_bearing_cob_err_rad", pa.float64()),  # against the true direction of its centre of brightness
    ("target_bearing_sigma_rad", pa.float64()),    # stated 1-sigma per axis, sqrt(trace(cov) / 2)
    ("target_bearing_nees", pa.float64()),         # 2-dof NEES against the centre of brightness
    # with [target] phase_correction (null without): the bearing corrected for the phase angle by the target's mean
    # photocentre over random attitudes (pc: error against the body origin, stated 1-sigma with the photocentre's
    # spread over attitudes, 2-dof NEES against the body origin) and by its known attitude's (pck: error)
    ("target_bearing_pc_err_rad", pa.float64()), ("target_bearing_pc_sigma_rad", pa.float64()),
    ("target_bearing_pc_nees", pa.float64()), ("target_bearing_pck_err_rad", pa.float64()),
]
TARGET_DETECTION_FIELDS = [
    ("is_target", pa.bool_()),                 # the detection nearest the target's centre of brightness
    ("excluded", pa.bool_()),                  # kept out of identification (a blob larger than any star's)
]
ENVIRONMENT_CASE_FIELDS = [
    # with [target.environment] (scene/case_environment.py; null without): the case's epoch, and along its boresight
    # from its place in orbit (scene/keepout.py) the Earth's limb (negative: on the Earth's disk) and the Moon
    # (parallax included), the Earth and Moon keep-out cones, a sunlit part of the Earth in the Earth cone, the
    # Earth's shadow (eclipse: the umbra, no direct sunlight; penumbra: part of the Sun hidden).  sun_angle_rad and
    # sun_keepout above are then from the epoch's Sun.
    ("epoch_utc", pa.timestamp("us", tz="UTC")),
    ("earth_limb_angle_rad", pa.float64()), ("moon_angle_rad", pa.float64()),
    ("earth_keepout", pa.bool_()), ("moon_keepout", pa.bool_()), ("earth_lit_in_cone", pa.bool_()),
    ("eclipse", pa.bool_()), ("penumbra", pa.bool_()),
]

_F32 = pa.float32()

CASES_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("seed", pa.int64()), ("attitude_model", pa.string()),
    ("theta1_rad", _F32), ("theta2_rad", _F32), ("theta3_rad", _F32),
    ("q_est", _QUAT), ("boresight_err_rad", _F32),
    ("image_digest", pa.int64()), ("blobs_dropped", pa.int32()),
    ("n_generated", pa.int32()), ("n_observed", pa.int32()), ("n_used", pa.int32()),
    ("n_identified", pa.int32()), ("n_correct_ids", pa.int32()), ("n_wrong_ids", pa.int32()),
    ("id_correct", pa.bool_()), ("T", pa.int32()),
    ("err_x_rad", _F32), ("err_y_rad", _F32), ("err_z_rad", _F32),
    ("err_total_rad", _F32), ("status", pa.string()),
    ("T_robust", pa.int32()), ("n_identified_robust", pa.int32()), ("id_correct_robust", pa.bool_()),
    ("err_x_robust_rad", _F32), ("err_y_robust_rad", _F32), ("err_z_robust_rad", _F32),
    ("err_total_robust_rad", _F32), ("status_robust", pa.string()), ("p_chance", _F32),
    ("t_sample_ns", pa.int64()), ("t_render_ns", pa.int64()), ("t_detect_ns", pa.int64()),
    ("t_identify_ns", pa.int64()), ("t_attitude_ns", pa.int64()), ("t_robust_ns", pa.int64()),
    ("t_total_ns", pa.int64()),
    # issue 23: a target in the field (null in every row of a run without [target]); appended, so every column
    # above keeps its place and meaning
    *TARGET_CASE_FIELDS,
    *ENVIRONMENT_CASE_FIELDS,
])
"""One row per case, ~90 B per case on disk (issue 24 point 5; ``benchmarks/bench_lake_bytes.py``).  What a case
needs and nothing it can recompute: the truth attitude is the case's seed (``default_rng([seed, case_id])``: the
draw, the noise seed and the frame; replay redraws them and checks ``image_digest``), so neither ``A_true`` nor the
noise seed nor the boresight RA/Dec (the third rows of the attitudes) is stored.  Floats are float32 where their
precision is far beyond what they measure: angles and errors in rad to 6e-8 relative (an error of 10 arcsec to
6e-7 arcsec, a theta to 0.02 arcsec), ``p_chance`` to 6e-8 relative.

* ``theta1..3_rad``: the reference's 1-2-3 angles of the true attitude (NaN for ``attitude_model`` "uniform").
* ``q_est``: estimated attitude as a unit quaternion (x, y, z, w), w >= 0, with
  ``scene.attitude.quat_to_dcm(q_est) = A_est`` (inertial -> camera, to float32 rounding); NaN without attitude.
* ``boresight_err_rad``: angle between the estimated and the true camera +z axes (third rows of A_est, A_true),
  NaN without attitude.
* ``err_*_rad``: the reference's Eqs. 4-7 (:mod:`dualsight.nav.errors`); ``err_total_rad`` the rotation angle.
"""

DETECTIONS_SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("det_index", pa.int32()),
    ("x_px", pa.float64()), ("y_px", pa.float64()), ("flux", pa.float64()), ("npix", pa.int32()),
    ("used", pa.bool_()), ("votes", pa.int32()), ("verify_votes", pa.int32()), ("accepted", pa.bool_()),
    ("hip_assigned", pa.int32()), ("hip_true", pa.int32()), ("true_dist_px", pa.float64()),
    ("residual_rad", pa.float64()),
    *TARGET_DETECTION_FIELDS,
])




def cases_table(case_ids, spec, draw, field_, det, obs, ident, sol, truth, t, alt=None, det_digest=None,
                target: dict | None = None, environment: dict | None = None) -> pa.Table:
    """``star_cases`` rows of a batch; ``target``: the columns of :data:`TARGET_CASE_FIELDS` as (B,) arrays
    (None: a run without a target, all null); ``environment``: those of :data:`ENVIRONMENT_CASE_FIELDS` (None:
    all null)."""
    B = len(case_ids)
    total = sum(v for v in t.values() if v is not None)
    status = np.asarray(STATUS_NAMES, dtype=object)[sol.status]
    names = np.asarray(STATUS_NAMES, dtype=object)
    if alt is not None:
        ident_r, sol_r = alt
        robust = {"T_robust": ident_r.T, "n_identified_robust": ident_r.accepted.sum(1),
                  "id_correct_robust": truth.id_correct(ident_r),
                  "err_x_robust_rad": sol_r.axis_err[:, 0], "err_y_robust_rad": sol_r.axis_err[:, 1],
                  "err_z_robust_rad": sol_r.axis_err[:, 2], "err_total_robust_rad": sol_r.total_err,
                  "status_robust": names[sol_r.status],
                  # null (not NaN) without an answer, so that SQL aggregates over the column skip those cases
                  "p_chance": pa.array(ident_r.p_chance, pa.float32(), mask=~np.isfinite(ident_r.p_chance))}
    else:
        robust = {k: [None] * B for k in ("T_robust", "n_identified_robust", "id_correct_robust", "err_x_robust_rad",
                                          "err_y_robust_rad", "err_z_robust_rad", "err_total_robust_rad",
                                          "status_robust", "p_chance")}
    cols = {
        "case_id": np.asarray(case_ids, dtype=np.int64), "seed": np.full(B, spec.seed, dtype=np.int64),
        "attitude_model": np.full(B, spec.attitudes, dtype=object),
        "theta1_rad": draw["angles"][:, 0], "theta2_rad": draw["angles"][:, 1], "theta3_rad": draw["angles"][:, 2],
        "q_est": _quat(sol.A_est), "boresight_err_rad": angle_between(sol.A_est[:, 2], draw["A_true"][:, 2]),
        "image_digest": to_int64(det_digest),
        "blobs_dropped": (det.blobs_dropped.astype(np.int32) if det.blobs_dropped is not None else [None] * B),
        "n_generated": field_.n_generated.astype(np.int32), "n_observed": np.diff(det.offsets).astype(np.int32),
        "n_used": obs.valid.sum(1).astype(np.int32), "n_identified": ident.accepted.sum(1).astype(np.int32),
        "n_correct_ids": truth.n_correct(ident).astype(np.int32),
        "n_wrong_ids": truth.n_wrong(ident).astype(np.int32),
        "id_correct": truth.id_correct(ident), "T": ident.T.astype(np.int32),
        "err_x_rad": sol.axis_err[:, 0], "err_y_rad": sol.axis_err[:, 1], "err_z_rad": sol.axis_err[:, 2],
        "err_total_rad": sol.total_err, "status": status,
        **robust,
        "t_sample_ns": t["sample"], "t_render_ns": t["render"], "t_detect_ns": t["detect"] if t["detect"] is not None else [None] * B,
        "t_identify_ns": t["identify"], "t_attitude_ns": t["attitude"],
        "t_robust_ns": t["robust"] if t.get("robust") is not None else [None] * B, "t_total_ns": total,
        **{name: (target[name] if target is not None else pa.nulls(B, type=typ)) for name, typ in TARGET_CASE_FIELDS},
        **{name: (environment[name] if environment is not None else pa.nulls(B, type=typ))
           for name, typ in ENVIRONMENT_CASE_FIELDS},
    }
    return pa.table({k: pa.array(v, type=CASES_SCHEMA.field(k).type)
                     if not isinstance(v, pa.Array) else v
                     for k, v in cols.items()}, schema=CASES_SCHEMA)


def _quat(A: np.ndarray) -> pa.FixedSizeListArray:
    """(B, 3, 3) attitudes -> (B,) float32 quaternions (x, y, z, w), w >= 0 (:func:`dcm_to_quat`)."""
    flat = dcm_to_quat(A).astype(np.float32).ravel()
    return pa.FixedSizeListArray.from_arrays(pa.array(flat), 4)


def detections_table(case_ids, det, obs, ident, sol, truth, catalog, target: dict | None = None) -> pa.Table:
    """``star_detections`` rows of a batch; ``target``: the columns of :data:`TARGET_DETECTION_FIELDS` as (K,)
    arrays (None: a run without a target, all null)."""
    case_local, rank = ragged_rank(det.case, det.offsets)
    S = obs.valid.shape[1]
    used = rank < S
    r_ok = np.where(used, rank, 0)
    pick = lambda a, fill: np.where(used, a[case_local, r_ok], fill)  # noqa: E731
    ids = pick(ident.ids, -1)
    hip_assigned = np.where(ids >= 0, catalog.hip[np.maximum(ids, 0)], -1)
    cols = {
        "case_id": np.asarray(case_ids, dtype=np.int64)[case_local], "det_index": rank.astype(np.int32),
        "x_px": det.x, "y_px": det.y, "flux": det.flux, "npix": det.npix.astype(np.int32),
        "used": used & pick(obs.valid, False), "votes": pick(ident.votes, 0).astype(np.int32),
        "verify_votes": pick(ident.verify_votes, 0).astype(np.int32),
        "accepted": pick(ident.accepted, False), "hip_assigned": hip_assigned.astype(np.int32),
        "hip_true": truth.hip_true.astype(np.int32), "true_dist_px": truth.dist_px,
        "residual_rad": pick(sol.residual, np.nan),
        **{name: (target[name] if target is not None else pa.nulls(len(det.x), type=typ))
           for name, typ in TARGET_DETECTION_FIELDS},
    }
    t = pa.table({k: pa.array(v, type=DETECTIONS_SCHEMA.field(k).type) if not isinstance(v, pa.Array) else v
                  for k, v in cols.items()},
                 schema=DETECTIONS_SCHEMA)
    return t
