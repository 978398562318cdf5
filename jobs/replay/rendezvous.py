"""Replay one approach (a ``rendezvous`` case) on rerun's ``frame`` time line (issue 23, point 5).

The approach is recomputed from ``default_rng([seed, case_id])`` with the run's spec (``jobs/kinds/rendezvous.py``:
draw, truth, render, measure, filter); its ``rendezvous_cases`` row and every one of its ``rendezvous_frames`` rows
must equal the stored ones (timings aside), and every frame is re-rendered here as a full image (the star camera's
run may have rendered only the windows around its stars) whose digest must equal the frame's stored
``image_digest``, before anything is recorded.  Per frame the recording holds the image with the target's measured
and true positions, the chaser's true and estimated Hill trajectory up to that frame in 3-D with the filter's 3-sigma
ellipsoid, and the errors, range, NEES and bearing error as time series.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualsight.errors import InputError
from dualsight.jobs.replay.cases import recording_path, refuse_frame_mismatch, refuse_mismatch, sequence_rows
from dualsight.warehouse.lake import Lake

__all__ = ["replay_rendezvous_case", "verified_approach"]


def verified_approach(lake: Lake, run_id: str, case_id: int) -> tuple[dict, list[dict], dict]:
    """Recompute approach ``case_id`` of a ``rendezvous`` run and verify it against the lake: its case row, every
    frame row (timings aside) and every frame's digest re-rendered as a full image.  Returns (the kind's
    ``compute_case`` dict with ``images`` (T, H, W), the stored frame rows, the stored case row); InputError naming
    the first column that differs."""
    from dualsight.jobs.kinds import rendezvous as rz         # Taichi
    from dualsight.jobs.kinds import rendezvous_measure

    manifest, case_row, frames = sequence_rows(lake, run_id, case_id, "rendezvous", "rendezvous_cases",
                                               "rendezvous_frames")
    spec = rz.spec_from_dict(manifest["spec"], source=f"manifest of run {run_id}")
    ctx = rz.make_context(spec)
    out = rz.compute_case(spec, ctx, case_id)
    refuse_mismatch(case_row, out["case"], case_id, run_id, manifest)
    refuse_frame_mismatch(frames, out["frames"].to_pylist(), case_id, run_id, manifest)
    measure = rendezvous_measure.measure_star if spec.is_star else rendezvous_measure.measure_prox
    m2, images = measure(spec, ctx, out["draw"], out["geo"], keep_images=True)
    for k, row in enumerate(frames):
        if int(m2["digest"][k]) != row["image_digest"]:
            raise InputError(f"replay of case {case_id}: frame {k}: column image_digest is {row['image_digest']} in "
                             f"the lake, {int(m2['digest'][k])} for the frame re-rendered whole",
                             source=f"run {run_id}")
    out["images"] = images
    return out, frames, case_row


def replay_rendezvous_case(lake: Lake, run_id: str, case_id: int, output: Path | None = None, rec=None) -> Path:
    """Verify approach ``case_id`` (:func:`verified_approach`) and record its frames on the ``frame`` time line of
    ``rec`` (an open recording) or of a new recording at ``output``."""
    from dualsight.viz.recording import open_recording       # rerun
    from dualsight.viz.rendezvous_figures import log_rendezvous_frame

    if rec is None:
        output = recording_path(output or f"{run_id}-case{case_id}.rrd")
    out, frames, case_row = verified_approach(lake, run_id, case_id)
    own = rec is None
    output = Path(output or f"{run_id}-case{case_id}.rrd")
    rec = open_recording(output) if own else rec
    geo, m, truth, est, P = out["geo"], out["meas"], out["truth"], out["est"], out["cov"]
    cam_xy, _ = _project(out, geo)
    for k, row in enumerate(frames):
        info = "\n".join([
            f"# approach {case_id} of run `{run_id}`, frame {k} (t = {row['t_s']:.1f} s)", "",
            f"- range {row['range_m']:.2f} m (estimate {row['range_est_m']:.2f} m), position error "
            f"{row['pos_err_m']:.3f} m (3 sigma {3 * row['sigma_pos_m']:.3f} m), NEES {row['nees']:.2f}",
            f"- attitude: {row['attitude']} ({row['n_stars']} stars); target "
            + ("detected" if row["target_detected"] else "not detected")
            + (f", resolved ({row['target_pixels']} px)" if row["target_resolved"] else "")
            + ("" if row["bearing_err_arcsec"] is None else
               f"; bearing error {row['bearing_err_arcsec']:.2f} arcsec (sigma {row['bearing_sigma_arcsec']:.2f})")
            + ("" if row["range_meas_m"] is None else
               f"; blobber range {row['range_meas_m']:.3f} m [{row['range_min_m']:.3f}, {row['range_max_m']:.3f}]"),
            f"- image digest: {row['image_digest']} (re-rendered frame = stored)", "",
            f"Approach: {case_row['initial_range_m']:.1f} m -> {case_row['final_range_m']:.1f} m, availability "
            f"{100 * case_row['availability']:.1f} %.", "",
            "Image: green the target's measured centre, blue its true position.  hill: the target at the origin "
            "(x radial, y along-track, z cross-track, m), blue the chaser's true path, orange the estimate with its "
            "3-sigma ellipsoid (covariance diagonal).", "",
            "Replay reproduced the lake's case and frame rows bit for bit."])
        log_rendezvous_frame(rec, frame=k, image=out["images"][k], target_xy=m["target_xy"][k],
                             truth_xy=cam_xy[k], truth_path=truth[: k + 1, :3], est_path=est[: k + 1, :3],
                             sigma3=3 * np.sqrt(np.diagonal(P[k])[:3]), info_md=info,
                             scalars={"pos_err_m": row["pos_err_m"], "sigma_pos_m": row["sigma_pos_m"],
                                      "range_m": row["range_m"], "range_meas_m": row["range_meas_m"],
                                      "nees": row["nees"], "bearing_err_arcsec": row["bearing_err_arcsec"]})
    if own:
        rec.flush()
    return output


def _project(out: dict, geo: dict):
    """(T, 2) the target's true projection (NaN outside the image or behind the camera), (T,) bool inside."""
    tc = geo["targets"]
    xy = np.full((len(tc.range_m), 2), np.nan)
    cam = out["camera"]
    p, _ = cam.project(tc.pos_cam)
    xy[tc.present] = p[tc.present]
    return xy, tc.present
