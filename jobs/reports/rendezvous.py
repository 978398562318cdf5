"""The rendezvous report (``dualsight rendezvous report``): every number comes out of the SQL files
``warehouse/sql/rendezvous_*.sql`` over the run's ``rendezvous_frames`` and ``rendezvous_cases`` (issue 23, point 5),
set against the issue's targets (point 6 c, d, e):

* ``rendezvous_summary``: availability, bearing error and its stated sigma, the filtered range error against the
  single-frame blobber error and the velocity error from frame :data:`AFTER_FRAMES` on, the position error as % of
  range one orbit after the first manoeuvre;
* ``rendezvous_nees``: per frame, the mean NEES over the approaches (held against the two-sided 95 % chi-square
  bounds of a mean of M approaches, ``nav/relative_filter.chi2_mean_bounds``, from the spec's
  ``converged_after_frames`` on), the RMS position error and the filter's RMS sqrt(trace P_rr), against range;
* ``rendezvous_nees_cases``: each of the first 100 approaches' NEES per frame after convergence, whose persistence
  from frame to frame sets a simultaneous 95 % band beside those bounds (:func:`simultaneous_band`,
  ``nav/nees_band.py``): the one-frame bounds, held at every frame, fail a consistent filter in about half of the
  campaigns.
"""

from __future__ import annotations

import shlex

import numpy as np

from dualsight.errors import InputError
from dualsight.nav.nees_band import inside_probability, lag1_correlation, simultaneous_mean_bounds
from dualsight.nav.relative_filter import chi2_mean_bounds
from dualsight.viz import html_page as H
from dualsight.warehouse.cells import formatted, percent, verdict
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import connect, format_table, run_report

QUERIES = ("rendezvous_summary", "rendezvous_nees", "rendezvous_nees_cases")
NEES_APPROACHES = 100
"""Point 6 (c) holds the mean NEES of 100 approaches to its bounds: the report checks the approaches with case_id <
100 (all of them in a smaller run) and, beside, all of the run's against their own (tighter) bounds."""
AFTER_FRAMES = 20
"""Point 6 (d): errors 'after 20 frames' are taken over the frames with index >= 20."""
TARGETS = {"nees_inside_share": 1.0, "range_err_ratio": 0.5, "vel_err_m_s": 0.01, "orbit_pos_err_pct": 1.0}
"""Issue 23, point 6: (c) the mean NEES inside its 95 % bounds at every frame after convergence; (d) filtered range
error <= half the single-frame blobber error and velocity error <= 1 cm/s after 20 frames; (e) position error <= 1 %
of range (1 sigma: RMS over approaches) one orbit after the manoeuvre."""


def build(lake: Lake, run_id: str) -> dict:
    """Run the queries for ``run_id``; returns {"tables": {name: (cols, rows)}, "summary": dict, "json": dict}."""
    if "rendezvous_frames" not in lake.datasets():
        raise InputError(f"no rendezvous_frames dataset in {lake.root}", source="--lake")
    m = lake.read_manifest(run_id) or {}
    rdv = (m.get("spec") or {}).get("rendezvous") or {}
    conv = int(rdv.get("converged_after_frames", 10))
    con = connect(lake)
    try:
        tables = {q: run_report(con, q, run=run_id, after=AFTER_FRAMES, first=NEES_APPROACHES, conv=conv)
                  for q in QUERIES}
    finally:
        con.close()
    cols, rows = tables["rendezvous_summary"]
    s = dict(zip(cols, rows[0]))
    if not s["frames"]:
        raise InputError(f"run {run_id!r} has no rendezvous frames in {lake.root}", source="--run")
    per_frame = [dict(zip(tables["rendezvous_nees"][0], r)) for r in tables["rendezvous_nees"][1]]
    M = int(s["approaches"])
    lo, hi = chi2_mean_bounds(6, M, 0.95)
    after = [r for r in per_frame if r["frame"] >= conv]
    inside = [lo <= r["mean_nees"] <= hi for r in after]
    m100 = min(M, NEES_APPROACHES)
    lo1, hi1 = chi2_mean_bounds(6, m100, 0.95)
    inside1 = [lo1 <= r["mean_nees_first"] <= hi1 for r in after if r["mean_nees_first"] is not None]
    band = simultaneous_band(tables["rendezvous_nees_cases"][1], [r["mean_nees_first"] for r in after])
    ratio = (s["filtered_range_err_rms_m"] / s["blobber_range_err_rms_m"]
             if s["filtered_range_err_rms_m"] is not None and s["blobber_range_err_rms_m"] else None)
    js = {"run": run_id, **{k: (float(v) if isinstance(v, float) else v) for k, v in s.items()},
          "after_frames": AFTER_FRAMES, "converged_after_frames": conv, "nees_bounds_95": [lo, hi],
          "bearing_point": rdv.get("bearing_point", "brightness"),
          "nees_frames_checked": len(after), "nees_frames_inside": int(sum(inside)),
          "nees_inside_share": (sum(inside) / len(after)) if after else None,
          "nees_frames_outside": [r["frame"] for r, ok in zip(after, inside) if not ok],
          "nees_first_approaches": m100, "nees_first_bounds_95": [lo1, hi1],
          "nees_first_frames_inside": int(sum(inside1)),
          "nees_first_inside_share": (sum(inside1) / len(inside1)) if inside1 else None,
          "nees_first_frames_outside": [r["frame"] for r, ok in zip(after, inside1) if not ok],
          **band,
          "nees_mean_after_convergence": (sum(r["mean_nees"] for r in after) / len(after)) if after else None,
          "z2_after_convergence": ([sum(r[k] for r in after) / len(after)
                                    for k in ("z2_radial", "z2_along", "z2_cross")] if after else None),
          "range_err_ratio": ratio, "per_frame": per_frame, "targets": TARGETS}
    return {"tables": tables, "summary": s, "json": js}


def simultaneous_band(rows: list, means: list) -> dict:
    """The simultaneous 95 % band of the first approaches' mean NEES (those in ``rows``) over the frames after
    convergence (``nav/nees_band.py``: wide enough that a consistent filter with this run's frame-to-frame NEES
    correlation, from ``rows`` (case_id, frame, nees) of ``rendezvous_nees_cases``, stays inside at every frame with
    95 %), how many of ``means`` (their mean NEES per frame after convergence) it holds, and how often a consistent
    filter stays inside the one-frame 95 % bounds at every one of those frames: the ``nees_band_*`` and
    ``nees_bounds_inside_probability`` fields of the report's json (None where there are under 3 approaches or 2
    frames)."""
    out = {"nees_band_95": None, "nees_band_level": None, "nees_band_lag1": None, "nees_band_frames_inside": None,
           "nees_bounds_inside_probability": None}
    if not rows:
        return out
    t = np.array(rows, np.float64)                                  # None (no NEES) -> NaN
    ci, fi = (np.unique(t[:, c], return_inverse=True)[1] for c in (0, 1))
    nees = np.full((ci.max() + 1, fi.max() + 1), np.nan)
    nees[ci, fi] = t[:, 2]
    if nees.shape[0] < 3 or nees.shape[1] < 2:
        return out
    lag1 = lag1_correlation(nees)
    lo, hi, level = simultaneous_mean_bounds(6, nees.shape[0], len(means), lag1)
    return {"nees_band_95": [lo, hi], "nees_band_level": level, "nees_band_lag1": lag1,
            "nees_band_frames_inside": int(sum(m is not None and lo <= m <= hi for m in means)),
            "nees_bounds_inside_probability": inside_probability(len(means), lag1)}


def target_rows(rep: dict) -> list[list[str]]:
    """The targets table (metric, run, target, verdict) of :func:`text`, as printed cells (the HTML report's too)."""
    j = rep["json"]
    lo, hi = j["nees_bounds_95"]
    lo1, hi1 = j["nees_first_bounds_95"]
    share, share1 = j["nees_inside_share"], j["nees_first_inside_share"]
    rows = [[f"(c) mean NEES of the first {j['nees_first_approaches']} approaches inside its 95 % bounds, frames >= "
             f"{j['converged_after_frames']}",
             "-" if share1 is None else f"inside at {j['nees_first_frames_inside']} of {j['nees_frames_checked']} "
             "frames "
             f"(bounds {lo1:.2f}-{hi1:.2f})", "every frame",
             verdict(None if share1 is None else share1 >= TARGETS["nees_inside_share"])],
            ["    the same against a simultaneous 95 % band over the frames (information)",
             "-" if j["nees_band_95"] is None else f"inside at {j['nees_band_frames_inside']} of "
             f"{j['nees_frames_checked']} frames (band {j['nees_band_95'][0]:.2f}-{j['nees_band_95'][1]:.2f})", "", ""],
            [f"    the same over all {j['approaches']} approaches",
             "-" if share is None else f"inside at {j['nees_frames_inside']} of {j['nees_frames_checked']} "
             "frames "
             f"(bounds {lo:.2f}-{hi:.2f}, mean {formatted(j['nees_mean_after_convergence'], '{:.2f}')})", "", ""]]
    if j["late_range_frames"]:
        r = j["range_err_ratio"]
        rows.append([f"(d) filtered / single-frame blobber range error (RMS, frames >= {j['after_frames']} with a "
                     "range)", "-" if r is None else f"{r:.3f} ({formatted(j['filtered_range_err_rms_m'], '{:.4f}')} m vs "
                     f"{formatted(j['blobber_range_err_rms_m'], '{:.4f}')} m)", "<= 0.5",
                     verdict(None if r is None else r <= TARGETS["range_err_ratio"])])
        v = j["late_vel_err_rms_m_s"]
        rows.append([f"(d) velocity error RMS, frames >= {j['after_frames']}",
                     "-" if v is None else f"{100 * v:.3f} cm/s (p95 {100 * j['late_vel_err_p95_m_s']:.3f}, max "
                     f"{100 * j['late_vel_err_max_m_s']:.3f})", "<= 1 cm/s",
                     verdict(None if v is None else v <= TARGETS["vel_err_m_s"])])
    if j["orbit_frames"] and not j["range_share"]:              # point 6 (e) is about bearings alone
        p = j["orbit_pos_err_rms_pct"]
        rows.append(["(e) position error / range one orbit after the burn, RMS over approaches",
                     f"{p:.3f} % at {j['orbit_range_mean_m']:.0f} m (p95 {j['orbit_pos_err_p95_pct']:.3f} %, filter "
                     f"{j['orbit_sigma_mean_pct']:.3f} %)", "<= 1 %", verdict(p <= TARGETS["orbit_pos_err_pct"])])
    return rows


def text(rep: dict) -> str:
    j = rep["json"]
    lines = [
        f"rendezvous run {j['run']}: {j['approaches']} approaches x {j['frames_per_approach']} frames "
        f"({j['frames']:,} frames), {j['camera']} camera",
        "",
        "Targets (issue 23, point 6)",
        format_table(["metric", "run", "target", "verdict"], target_rows(rep)),
        *([] if j["nees_band_95"] is None else [
            f"(c)'s one-frame bounds, held at every one of {j['nees_frames_checked']} frames whose NEES correlates at "
            f"{j['nees_band_lag1']:.2f} from frame to frame, hold a consistent filter in "
            f"{100 * j['nees_bounds_inside_probability']:.0f} % of campaigns; the simultaneous band (per-frame level "
            f"{100 * j['nees_band_level']:.2f} %) in 95 % (nav/nees_band.py, docs/rendezvous.md)"]),
        "",
        f"availability (a bearing entered the filter): {percent(j['availability'])} of frames; target in the "
        f"field {percent(j['in_field_share'])}, attitude {percent(j['attitude_share'])}, blobber range "
        f"{percent(j['range_share'])}",
        f"target found without the truth (its motion against the stars, the filter's gate): "
        f"{'-' if j['target_found_rate'] is None else percent(j['target_found_rate'])} of the frames with a "
        f"detection of it ({'-' if j['target_detected_share'] is None else percent(j['target_detected_share'])} of "
        f"frames); {j['target_false_picks']} picks not the target, {j['target_gated_out']} frames gated out",
        ("bearing error (used: through the target's silhouette centre): RMS " if j["bearing_point"] == "silhouette"
         else "bearing error (used, after the centre-of-brightness correction): RMS ") +
        f"{formatted(j['bearing_err_rms_arcsec'], '{:.2f}')} arcsec, median {formatted(j['bearing_err_p50_arcsec'], '{:.2f}')}, "
        f"p95 {formatted(j['bearing_err_p95_arcsec'], '{:.2f}')}"
        f"; as measured {formatted(j['bearing_raw_err_rms_arcsec'], '{:.2f}')}; stated 1-sigma per axis RMS "
        f"{formatted(j['bearing_sigma_rms_arcsec'], '{:.2f}')}; within 3 sigma (2-D: 3 sqrt 2 sigma) "
        f"{'-' if j['bearing_within_3sigma'] is None else percent(j['bearing_within_3sigma'])}",
        f"final: range {formatted(j['final_range_mean_m'], '{:.1f}')} m mean, position error RMS "
        f"{formatted(j['final_pos_err_rms_m'], '{:.3f}')} m, velocity error RMS "
        f"{formatted(j['final_vel_err_rms_m_s'], '{:.5f}')} m/s",
        f"time: {formatted(j['ms_per_approach'], '{:.0f}')} ms per approach (render {formatted(j['render_ms_per_frame'], '{:.1f}')} "
        "ms per frame)",
        "",
        "position error over its stated sigma, squared, mean over the frames after convergence (1 where the sigma is "
        "right): radial / along-track / cross-track "
        + ("-" if j["z2_after_convergence"] is None else " / ".join(f"{v:.2f}" for v in j["z2_after_convergence"])),
        "",
        "mean NEES per frame (every 5th; * outside the 95 % bounds after convergence; z2: the position error over its "
        "stated sigma, squared, per Hill axis)",
    ]
    lo, hi = j["nees_bounds_95"]
    lo1, hi1 = j["nees_first_bounds_95"]
    rows = [[str(r["frame"]), f"{r['t_s']:.0f}", f"{r['range_mean_m']:.1f}", f"{r['pos_err_rms_m']:.3f}",
             f"{r['sigma_pos_rms_m']:.3f}", f"{r['mean_nees']:.2f}" + (
                 "*" if r["frame"] >= j["converged_after_frames"] and not lo <= r["mean_nees"] <= hi else ""),
             f"{r['mean_nees_first']:.2f}" + (
                 "*" if r["frame"] >= j["converged_after_frames"] and not lo1 <= r["mean_nees_first"] <= hi1 else ""),
             percent(r["availability"]), f"{r['z2_radial']:.2f} / {r['z2_along']:.2f} / {r['z2_cross']:.2f}"]
            for r in j["per_frame"] if r["frame"] % 5 == 0 or r["frame"] == len(j["per_frame"]) - 1]
    lines.append(format_table(["frame", "t s", "range m", "pos err RMS m", "sigma RMS m", "mean NEES",
                               f"NEES first {j['nees_first_approaches']}", "bearings", "z2 R / A / C"],
                              rows))
    return "\n".join(lines)


DRAWN = 4
"""Approaches drawn one by one in the HTML error figure (the largest final position error / range first)."""


def html_sections(lake: Lake, con, m: dict, run_id: str) -> list[tuple[str, str]]:
    """The rendezvous run's sections of ``dualsight report --html`` (``jobs/reports/html.py``): the targets table,
    the campaign summary and the figures of ``viz/rendezvous_figures.py`` (error against range and time with the
    3-sigma envelope; mean NEES against its bounds)."""
    from dualsight.viz import rendezvous_figures as figs      # matplotlib
    from dualsight.viz.figures import png_bytes

    rep = build(lake, run_id)
    j = rep["json"]
    pf = j["per_frame"]
    cols = ("t_s", "range_mean_m", "pos_err_rms_m", "sigma_pos_rms_m", "mean_nees", "mean_nees_first")
    per_frame = {c: np.array([np.nan if r[c] is None else r[c] for r in pf], np.float64) for c in cols}
    worst = con.execute("SELECT case_id FROM rendezvous_cases WHERE run = $run ORDER BY final_pos_err_pct DESC, "
                        f"case_id LIMIT {DRAWN}", {"run": run_id}).fetchall()
    ids = [int(r[0]) for r in worst]
    cur = con.execute("SELECT case_id, t_s, range_m, pos_err_m, sigma_pos_m FROM rendezvous_frames WHERE run = $run "
                      f"AND case_id IN ({','.join(map(str, ids)) or '-1'}) ORDER BY case_id, frame", {"run": run_id})
    rows = np.array(cur.fetchall(), np.float64).reshape(-1, 5)
    approaches = [{"case_id": i, **{k: rows[rows[:, 0] == i, c] for c, k in
                                    enumerate(("case_id", "t_s", "range_m", "pos_err_m", "sigma_pos_m")) if c}}
                  for i in ids]
    lo, hi = j["nees_bounds_95"]
    lo1, hi1 = j["nees_first_bounds_95"]
    bounds = [("mean_nees", lo, hi, f"all {j['approaches']} approaches")]
    if j["nees_first_approaches"] < j["approaches"]:
        bounds.append(("mean_nees_first", lo1, hi1, f"first {j['nees_first_approaches']} approaches"))
    band = None if j["nees_band_95"] is None else (bounds[-1][0], *j["nees_band_95"])
    summary = [("approaches x frames", f"{j['approaches']} x {j['frames_per_approach']}"), ("camera", j["camera"]),
               ("availability (bearing used)", percent(j["availability"])),
               ("target in the field / attitude / blobber range", f"{percent(j['in_field_share'])} / "
                f"{percent(j['attitude_share'])} / {percent(j['range_share'])}"),
               ("bearing error RMS / median / p95 (arcsec)", f"{formatted(j['bearing_err_rms_arcsec'], '{:.2f}')} / "
                f"{formatted(j['bearing_err_p50_arcsec'], '{:.2f}')} / {formatted(j['bearing_err_p95_arcsec'], '{:.2f}')}"),
               ("bearing as measured, RMS (arcsec)", formatted(j["bearing_raw_err_rms_arcsec"], "{:.2f}")),
               ("bearing within 3 stated sigma", percent(j["bearing_within_3sigma"])),
               ("target found (of frames with its detection) / false picks / gated out",
                f"{'-' if j['target_found_rate'] is None else percent(j['target_found_rate'])} / "
                f"{j['target_false_picks']} / {j['target_gated_out']}"),
               ("final range mean (m) / position error RMS (m) / velocity error RMS (m/s)",
                f"{formatted(j['final_range_mean_m'], '{:.1f}')} / {formatted(j['final_pos_err_rms_m'], '{:.3f}')} / "
                f"{formatted(j['final_vel_err_rms_m_s'], '{:.5f}')}"),
               ("ms per approach", formatted(j["ms_per_approach"], "{:.0f}"))]
    replay = (f"<p>Replay an approach into rerun (image and 3-D trajectory on the <code>frame</code> time line): "
              f"<code>dualsight rendezvous replay --lake {H.esc(shlex.quote(str(lake.root)))} --run "
              f"{H.esc(shlex.quote(run_id))} --case N -o approachN.rrd</code></p>")
    return [("Rendezvous: targets (issue 23, point 6)",
             H.table(["metric", "run", "target", "verdict"], target_rows(rep))),
            ("Rendezvous: campaign", H.table(["measure", "value"], summary)),
            ("Rendezvous: error against range and time",
             replay + H.figure(png_bytes(lambda p: figs.error_vs_range_figure(per_frame, approaches, p)),
                               "rdv-error", "Relative-position error: RMS over all approaches (black) with 3 x the "
                               "filter's RMS sigma (thick grey); the approaches with the largest final error / "
                               "range, each with its own 3-sigma envelope (dashed)")),
            ("Rendezvous: filter consistency",
             H.figure(png_bytes(lambda p: figs.nees_figure(per_frame, bounds, j["converged_after_frames"], p,
                                                            band=band)),
                      "rdv-nees", "Mean NEES per frame against the two-sided 95 % chi-square bounds of its mean "
                      "(dashed) and, dotted, the simultaneous 95 % band of the first approaches' mean over the frames "
                      "after convergence; grey: before convergence"))]
