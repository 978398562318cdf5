"""The rendezvous job's rows (:mod:`dualsight.jobs.kinds.rendezvous`): the explicit Arrow schemas of
``rendezvous_frames`` (one row per frame of an approach) and ``rendezvous_cases`` (one row per approach), and the
functions that fill them.

Units: Hill-frame positions in m, velocities in m/s (x radial, y along-track, z cross-track; the chaser relative to
the target, ``scene/relative_orbit.py``), angles in arcsec, times in s and ns.  Null where a value does not exist
(no bearing, no range, no attitude), never NaN, so that SQL aggregates skip it.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa

from dualsight.nav.target_finding import FOUND_BY
from dualsight.scene.units import ARCSEC

__all__ = ["FRAMES_SCHEMA", "CASES_SCHEMA", "ATTITUDE_NAMES", "frames_table", "case_row", "view_columns"]

_F, _I, _L, _B = pa.float64(), pa.int32(), pa.int64(), pa.bool_()
_STATE = ("x", "y", "z", "vx", "vy", "vz")

ATTITUDE_NAMES = ("none", "stars", "external")
"""Per-frame attitude status codes: no attitude (the stars were not identified), the stars of this frame, the
chaser's own star tracker (a proximity camera: no stars rendered)."""

FRAMES_SCHEMA = pa.schema(
    [("case_id", _L), ("frame", _I), ("t_s", _F), ("t_since_burn_s", _F), ("orbit_after_burn", _B)]
    + [(f"true_{c}", _F) for c in _STATE] + [(f"est_{c}", _F) for c in _STATE]
    + [(f"sigma_{c}", _F) for c in _STATE]
    + [("range_m", _F), ("range_est_m", _F), ("pos_err_m", _F), ("vel_err_m_s", _F), ("range_err_m", _F),
       ("sigma_pos_m", _F), ("nees", _F), ("nees_pos", _F),
       ("attitude", pa.string()), ("n_stars", _I), ("target_in_field", _B), ("target_detected", _B),
       ("target_resolved", _B), ("target_pixels", _I), ("target_vmag", _F), ("phase_deg", _F),
       ("target_found_by", pa.string()), ("target_found_true", _B), ("bearing_used", _B), ("bearing_raw_err_arcsec", _F), ("bearing_err_arcsec", _F),
       ("bearing_sigma_arcsec", _F),
       ("range_meas_m", _F), ("range_min_m", _F), ("range_max_m", _F), ("range_used", _B),
       ("image_digest", _L), ("t_render_ns", _L), ("t_nav_ns", _L)]
    # with [rendezvous.environment] (jobs/kinds/rendezvous_truth.frame_view, scene/keepout.py; null without): along the
    # boresight from the chaser, the Sun and Moon (parallax included) and the Earth's limb (negative: on its disk),
    # the keep-out cones, a sunlit part of the Earth in the Earth cone, the Earth's shadow (eclipse: the umbra)
    + [("sun_angle_deg", _F), ("earth_limb_angle_deg", _F), ("moon_angle_deg", _F), ("sun_keepout", _B),
       ("earth_keepout", _B), ("moon_keepout", _B), ("earth_lit_in_cone", _B), ("eclipse", _B), ("penumbra", _B)])
"""One row per frame.  ``true_*``/``est_*``: the chaser's Hill state (truth, filter after this frame's updates);
``sigma_*``: the square roots of the covariance diagonal; ``range_m``: true |rho|; ``range_est_m``: |rho_est|;
``pos_err_m``/``vel_err_m_s``: norms of the estimate's errors; ``range_err_m``: range_est - range;
``sigma_pos_m``: sqrt(trace P_rr); ``nees``: 6-dof e^T P^-1 e (``nees_pos``: position block, 3 dof);
``t_since_burn_s``: time since the first manoeuvre (null before it or without one); ``orbit_after_burn``: the frame
nearest one orbital period after the first manoeuvre; ``attitude``: :data:`ATTITUDE_NAMES`; ``bearing_err_arcsec``:
the line of sight the filter used (after its centre-of-brightness correction) against the true direction to the
target's body origin (``bearing_raw_err_arcsec``: the measured one, before it); ``bearing_sigma_arcsec``: its stated
1-sigma per axis (sqrt(trace C / 2)); ``range_meas_m`` with ``range_min_m``/``range_max_m``: the blobber's
single-frame range where the target was resolved; ``*_used``: the measurement entered the filter;
``target_detected``: a detection of the true target exists (scored by the truth); ``target_found_by``: how the
filter found it (``nav/target_finding.FOUND_BY``: none, gate, gated_out, resolved_blob) and
``target_found_true``: the detection it picked is the true target's (scored after the pick)."""

CASES_SCHEMA = pa.schema([
    ("case_id", _L), ("seed", _L), ("camera", pa.string()), ("frames", _I), ("frames_bearing", _I),
    ("frames_range", _I), ("frames_attitude", _I), ("frames_in_field", _I), ("availability", _F),
    ("initial_range_m", _F), ("final_range_m", _F), ("final_pos_err_m", _F), ("final_pos_err_pct", _F),
    ("final_vel_err_m_s", _F), ("final_sigma_pos_m", _F), ("final_nees", _F), ("mean_nees_converged", _F),
    ("burn_orbit_pos_err_pct", _F), ("burn_orbit_sigma_pct", _F), ("bearing_err_rms_arcsec", _F),
    ("dv_exec_err_m_s", _F), ("t_render_ns", _L), ("t_nav_ns", _L), ("t_total_ns", _L),
])
"""One row per approach.  ``availability``: frames_bearing / frames; ``final_*``: at the last frame;
``final_pos_err_pct``: 100 pos_err / range; ``mean_nees_converged``: mean NEES over the frames from
``converged_after_frames`` on; ``burn_orbit_*``: position error and the filter's sqrt(trace P_rr) as % of range at
the frame one orbit after the first manoeuvre (null without one); ``dv_exec_err_m_s``: |executed - nominal| of all
manoeuvres (norm)."""


def _nullable(a, typ=_F) -> pa.Array:
    a = np.asarray(a, np.float64)
    return pa.array(np.where(np.isfinite(a), a, 0.0), typ, mask=~np.isfinite(a))


def frames_table(case_id: int, out: dict) -> pa.Table:
    """Rows of one approach from :func:`dualsight.jobs.kinds.rendezvous.compute_case`'s dict."""
    t, truth, xs, Ps = out["times"], out["truth"], out["est"], out["cov"]
    T = len(t)
    m = out["meas"]
    sig = np.sqrt(np.diagonal(Ps, axis1=1, axis2=2))
    rng = np.linalg.norm(truth[:, :3], axis=1)
    rng_e = np.linalg.norm(xs[:, :3], axis=1)
    cols = {"case_id": np.full(T, case_id, np.int64), "frame": np.arange(T, dtype=np.int32), "t_s": t,
            "t_since_burn_s": _nullable(np.where(out["t_since_burn"] >= 0, out["t_since_burn"], np.nan)),
            "orbit_after_burn": np.arange(T) == out["orbit_frame"]}
    for i, c in enumerate(_STATE):
        cols[f"true_{c}"] = truth[:, i]
    for i, c in enumerate(_STATE):
        cols[f"est_{c}"] = xs[:, i]
    for i, c in enumerate(_STATE):
        cols[f"sigma_{c}"] = sig[:, i]
    bear = m["bearing_used"]
    cols.update({
        "range_m": rng, "range_est_m": rng_e, "pos_err_m": np.linalg.norm(xs[:, :3] - truth[:, :3], axis=1),
        "vel_err_m_s": np.linalg.norm(xs[:, 3:] - truth[:, 3:], axis=1), "range_err_m": rng_e - rng,
        "sigma_pos_m": np.sqrt(np.trace(Ps[:, :3, :3], axis1=1, axis2=2)), "nees": out["nees"],
        "nees_pos": out["nees_pos"],
        "attitude": np.asarray(ATTITUDE_NAMES, object)[m["attitude"]], "n_stars": m["n_stars"].astype(np.int32),
        "target_in_field": m["in_field"], "target_detected": m["detected"], "target_resolved": m["resolved"],
        "target_pixels": pa.array(m["pixels"].astype(np.int32), _I, mask=m["pixels"] < 0),
        "target_vmag": _nullable(m["vmag"]), "phase_deg": np.degrees(m["phase"]),
        "target_found_by": np.asarray(FOUND_BY, object)[m["found_by"]], "target_found_true": m["found_true"],
        "bearing_used": bear,
        "bearing_raw_err_arcsec": _nullable(np.where(bear, m["bearing_raw_err"], np.nan) / ARCSEC),
        "bearing_err_arcsec": _nullable(np.where(bear, m["bearing_err"], np.nan) / ARCSEC),
        "bearing_sigma_arcsec": _nullable(np.where(bear, m["bearing_sigma"], np.nan) / ARCSEC),
        "range_meas_m": _nullable(m["range"]), "range_min_m": _nullable(m["range_min"]),
        "range_max_m": _nullable(m["range_max"]), "range_used": m["range_used"],
        "image_digest": m["digest"].astype(np.int64), "t_render_ns": m["t_render_ns"].astype(np.int64),
        "t_nav_ns": np.full(T, out["t_nav_ns"] // max(T, 1), np.int64)})
    cols.update(view_columns(out.get("view"), T))
    return pa.table({k: v if isinstance(v, pa.Array) else pa.array(v, FRAMES_SCHEMA.field(k).type)
                     for k, v in cols.items()}, schema=FRAMES_SCHEMA)


def view_columns(view, T: int) -> dict:
    """The Sun / Earth / Moon columns of :data:`FRAMES_SCHEMA` from a ``scene/keepout.KeepOut`` over the T frames
    (None: all null)."""
    names = ("sun_angle_deg", "earth_limb_angle_deg", "moon_angle_deg", "sun_keepout", "earth_keepout",
             "moon_keepout", "earth_lit_in_cone", "eclipse", "penumbra")
    if view is None:
        return {k: pa.nulls(T, FRAMES_SCHEMA.field(k).type) for k in names}
    return dict(zip(names, (np.degrees(view.sun_angle_rad), np.degrees(view.earth_limb_angle_rad),
                            np.degrees(view.moon_angle_rad), view.sun_keepout, view.earth_keepout, view.moon_keepout,
                            view.earth_lit_in_cone, view.umbra, view.penumbra)))


def case_row(case_id: int, seed: int, camera: str, conv: int, out: dict) -> dict:
    """The ``rendezvous_cases`` row of one approach (see :data:`CASES_SCHEMA`)."""
    truth, xs, Ps, m = out["truth"], out["est"], out["cov"], out["meas"]
    T = len(out["times"])
    rng = np.linalg.norm(truth[:, :3], axis=1)
    err = np.linalg.norm(xs[:, :3] - truth[:, :3], axis=1)
    sd = np.sqrt(np.trace(Ps[:, :3, :3], axis1=1, axis2=2))
    k = out["orbit_frame"]
    be = m["bearing_err"][m["bearing_used"]]
    fin = lambda v: float(v) if np.isfinite(v) else None  # noqa: E731
    return {
        "case_id": int(case_id), "seed": int(seed), "camera": camera, "frames": T,
        "frames_bearing": int(m["bearing_used"].sum()), "frames_range": int(m["range_used"].sum()),
        "frames_attitude": int(np.sum(m["attitude"] > 0)), "frames_in_field": int(m["in_field"].sum()),
        "availability": float(m["bearing_used"].sum() / T), "initial_range_m": float(rng[0]),
        "final_range_m": float(rng[-1]), "final_pos_err_m": float(err[-1]),
        "final_pos_err_pct": float(100.0 * err[-1] / rng[-1]),
        "final_vel_err_m_s": float(np.linalg.norm(xs[-1, 3:] - truth[-1, 3:])), "final_sigma_pos_m": float(sd[-1]),
        "final_nees": fin(out["nees"][-1]),
        "mean_nees_converged": fin(np.mean(out["nees"][conv:])) if conv < T else None,
        "burn_orbit_pos_err_pct": float(100.0 * err[k] / rng[k]) if k >= 0 else None,
        "burn_orbit_sigma_pct": float(100.0 * sd[k] / rng[k]) if k >= 0 else None,
        "bearing_err_rms_arcsec": float(math.sqrt(np.mean(be ** 2)) / ARCSEC) if be.size else None,
        "dv_exec_err_m_s": float(np.linalg.norm(out["dv_exec"] - out["dv_nominal"])),
        "t_render_ns": int(np.sum(m["t_render_ns"])), "t_nav_ns": int(out["t_nav_ns"]),
        "t_total_ns": int(out["t_total_ns"]),
    }
