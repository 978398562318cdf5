"""Replay one star-tracking sequence (a ``star_track`` case) on rerun's ``frame`` time line (issue 22, point 5).

The sequence is recomputed from ``default_rng([seed, case_id])`` with the run's spec (``jobs/kinds/star_track.py``:
draw, render, detect, track); its ``star_sequences`` row and every one of its ``star_frames`` rows must equal the
stored ones (timings aside), and every delivered frame is re-rendered as a full image here, whose digest must equal
the frame's stored ``image_digest``, before anything is recorded.  Per frame the recording holds the image, the
detections (identified ones labelled with their HIP number), the catalog stars at the true attitude, the match
windows that tracking predicted (kept by the recomputed run, ``keep_predictions``; their count checked against the
row's ``n_predicted``), both attitudes as arrows, errors and rates as time series, and the mode as text.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from dualsight.errors import InputError
from dualsight.jobs.replay.cases import recording_path, refuse_frame_mismatch, refuse_mismatch, sequence_rows
from dualsight.kernels.digest import to_int64
from dualsight.kernels.sensor_config import flux_from_magnitude
from dualsight.nav.sequence import MODE_NAMES, NO_FIX
from dualsight.scene.attitude_trajectory import BLANK, DROPPED
from dualsight.scene.starfield_geometry import FieldStars, stars_in_field
from dualsight.warehouse.lake import Lake

__all__ = ["replay_track_case", "frame_images"]


def frame_images(spec, ctx, draw: dict) -> dict[int, tuple[np.ndarray, int]]:
    """{frame: (image (H, W) float32, digest int64)} of every delivered frame of a sequence, rendered one frame at
    a time with the camera and sensor of ``jobs/kinds/star_track.render_sequence`` (``truth_camera``,
    ``frame_sensor``: the frame's own true rate for the smear, the background at twice the full well on a blinded
    frame, the bright objects of a crossing frame; no star on a blank one).  The caller checks each
    digest against the row: the run rendered in groups, and the counter-based noise makes a frame the same alone."""
    from dualsight.jobs.kinds import star                     # Taichi
    from dualsight.jobs.kinds.star_track import frame_sensor, truth_camera      # pyarrow

    sp, seq = spec.star, spec.sequence
    ev = draw["events"]
    T = len(ev)
    rates = np.degrees(draw["omega"]) if seq.smear else np.zeros((T, 3))
    s_max = dataclasses.replace(sp.sensor, rate_deg_s=tuple(float(v) for v in rates[np.argmax(
        np.linalg.norm(rates, axis=1))])) if seq.smear else sp.sensor
    flux = flux_from_magnitude(ctx.catalog.vmag.astype(np.float64), sp.sensor)
    cam = truth_camera(spec)
    field = stars_in_field(draw["A_true"], ctx.catalog.unit, flux, cam, star.psf_margin_px(s_max, cam, ctx.psf))
    field = dataclasses.replace(field, valid=field.valid & (ev != BLANK)[:, None])
    out = {}
    for k in np.flatnonzero(ev != DROPPED):
        sensor = frame_sensor(spec, draw, int(k), rates)
        one = FieldStars(*(getattr(field, f.name)[k: k + 1] for f in dataclasses.fields(FieldStars)))
        r = star.render_and_detect(one, draw["noise_seeds"][k: k + 1], cam, sensor, sp.detect,
                                   keep_images=True, attitude=draw["A_true"][k: k + 1], detector=sp.detector,
                                   psf=ctx.psf)
        out[int(k)] = (r.images[0], int(to_int64(r.digest)[0]))
    return out


def replay_track_case(lake: Lake, run_id: str, case_id: int, output: Path | None = None, rec=None,
                      frame_offset: int = 0) -> Path:
    """Recompute sequence ``case_id`` of a ``star_track`` run, verify it against its rows (the sequence row, every
    frame row, every frame's image digest) and record its frames on the ``frame`` time line of ``rec`` (an open
    recording) or of a new recording at ``output``.  Frame k is recorded at ``frame_offset + k``: several sequences
    in one recording get disjoint stretches of the time line (``jobs/replay/run.py`` passes the frames recorded
    before), instead of overwriting each other at the same frame numbers."""
    from dualsight.jobs.kinds import star_track                # Taichi
    from dualsight.viz.recording import log_track_frame, open_recording

    if rec is None:
        output = recording_path(output or f"{run_id}-case{case_id}.rrd")
    manifest, seq_row, frames = sequence_rows(lake, run_id, case_id, "star_track", "star_sequences", "star_frames")
    spec = star_track.spec_from_dict(manifest["spec"], source=f"manifest of run {run_id}")
    ctx = star_track.make_context(spec)
    out = star_track.compute_sequence(spec, ctx, case_id, keep_predictions=True)
    refuse_mismatch(seq_row, out["sequence"], case_id, run_id, manifest)
    refuse_frame_mismatch(frames, out["frames"].to_pylist(), case_id, run_id, manifest)
    images = frame_images(spec, ctx, out["draw"])
    for k, (_, dig) in images.items():
        if dig != frames[k]["image_digest"]:
            raise InputError(f"replay of case {case_id}: frame {k}: column image_digest is {frames[k]['image_digest']} "
                             f"in the lake, {dig} for the frame re-rendered alone", source=f"run {run_id}")
    res, draw, rnd = out["result"], out["draw"], out["rendered"]
    windows = res.predictions
    for k, p in windows.items():
        if len(p.rows) != frames[k]["n_predicted"]:
            raise InputError(f"replay of case {case_id}: frame {k}: {len(p.rows)} predicted windows recomputed, "
                             f"n_predicted is {frames[k]['n_predicted']} in the lake", source=f"run {run_id}")
    hip, unit, cam = ctx.catalog.hip, ctx.catalog.unit, star_track.truth_camera(spec)
    output = Path(output or f"{run_id}-case{case_id}.rrd")
    own = rec is None
    rec = open_recording(output) if own else rec
    off = rnd["offsets"]
    for k, row in enumerate(frames):
        s = slice(int(off[k]), int(off[k + 1]))
        ids = res.det_row[s]
        px, front = cam.project(unit @ draw["A_true"][k].T)
        inside = front & cam.in_image(np.nan_to_num(px, nan=-1.0))
        p = windows.get(k)
        mode = MODE_NAMES[res.mode[k]]
        info = "\n".join([
            f"# star-tracking sequence {case_id} of run `{run_id}`, frame {k} (t = {row['t_s']:.3f} s)"
            + (f", at {int(frame_offset) + k} on the time line" if frame_offset else ""), "",
            f"- event: **{row['event']}**, mode: **{mode}**, lock reason: {row['lock_reason']}",
            f"- detections {row['n_detections']}, predicted {row['n_predicted']}, matched {row['n_matched']}, "
            f"used {row['n_used']}" + (" (two-star lock)" if row["two_star"] else ""),
            "- error (arcsec): " + ("no attitude" if row["err_x_arcsec"] is None else
                                    f"x {row['err_x_arcsec']:.2f}, y {row['err_y_arcsec']:.2f}, "
                                    f"z {row['err_z_arcsec']:.2f}") + (" **false lock**" if row["false_lock"] else ""),
            f"- image digest: {row['image_digest']} (re-rendered frame = stored)", "",
            f"Sequence: {seq_row['motion']}, peak rate {seq_row['rate_deg_s']:.3f} deg/s, availability "
            f"{100 * seq_row['availability']:.1f} %.", "",
            "Blue: catalog stars at the true attitude; yellow circles: tracking's predicted match windows; "
            "green: detections in the answer (HIP), grey: the others.", "",
            "Replay reproduced the lake's sequence and frame rows bit for bit."])
        scalars = {f"err_{a}_arcsec": row[f"err_{a}_arcsec"] for a in "xyz"} | {
            f"rate_{a}_deg_s": row[f"rate_att_{a}_deg_s"] for a in "xyz"} | {
            f"true_rate_{a}_deg_s": row[f"true_rate_{a}_deg_s"] for a in "xyz"} | {
            "n_matched": row["n_matched"], "n_used": row["n_used"], "valid": float(row["valid"])}
        log_track_frame(rec, frame=int(frame_offset) + k, image=images[k][0] if k in images else None,
                        det_xy=rnd["xy"][s], det_labels=[f"HIP {hip[i]}" if i >= 0 else "" for i in ids],
                        det_used=ids >= 0, windows_xy=None if p is None else p.xy,
                        windows_r=None if p is None else p.radius_px, truth_xy=px[inside],
                        mode_text=f"frame {k}: {mode} ({row['lock_reason']}, event {row['event']})", info_md=info,
                        attitudes={"true": draw["A_true"][k], "estimated": res.A[k] if res.mode[k] != NO_FIX else None},
                        scalars=scalars)
    if own:
        rec.flush()
    return output
