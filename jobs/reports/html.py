"""``dualsight report --run ID --html FILE``: one self-contained page per run, for any job kind.

Everything on the page comes from the lake (warehouse SQL over the read-only views) and the run's
manifest; figures are the ones the command-line reports draw (reference Figures 1, 6, 7, 8, 9-10) as inline
PNG; the worst cases are re-rendered (simulations) or re-read (real images) into thumbnails, each with the
``dualsight replay`` command that records it for rerun.
"""

from __future__ import annotations

import shlex
import time
from pathlib import Path

import numpy as np

from dualsight.catalogs.areas import area_table
from dualsight.errors import InputError
from dualsight.jobs.reports import hil_prox as hil_prox_report
from dualsight.jobs.reports import rendezvous as rendezvous_report
from dualsight.jobs.reports import star as star_report
from dualsight.jobs.reports import star_track as track_report
from dualsight.jobs.reports.prox import build_report
from dualsight.scene.imageio import read_image
from dualsight.viz import html_page as H
from dualsight.viz import prox_figures, track_figures
from dualsight.viz.case_crop import case_crop_png
from dualsight.viz.figures import png_bytes, thumbnail_png
from dualsight.viz.star_figures import error_vs_observed_figure
from dualsight.viz.threshold_sweep import hil_prox_figure
from dualsight.warehouse.cells import cell, iso_utc, percent, table_cells
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import connect, run_report

GALLERY = 6
"""Cases drawn as crops (the first failures, then the largest errors)."""
LISTED = 500
"""Failures listed with their replay command; beyond it the page gives the count and the SQL for the rest."""


def _rows(con, sql: str, run_id: str):
    cur = con.execute(sql, {"run": run_id})
    return [d[0] for d in cur.description], cur.fetchall()


def _report_table(con, name: str, run_id: str) -> str:
    cols, rows = run_report(con, name, run=run_id)
    return H.table(cols, table_cells(cols, rows))


def _lake_arg(lake: Lake) -> str:
    return shlex.quote(str(Path(lake.root).resolve()))


def _gallery(items: list[tuple[bytes, str]], lake: Lake, run_id: str, marks: list[dict] | None = None,
             command: str = "dualsight replay") -> str:
    figs = [H.figure(png, f"case-{i}", cap, data={"marks": marks[i]} if marks else None)
            for i, (png, cap) in enumerate(items)]
    note = (f"<p>Replay any of them into rerun: <code>{H.esc(command)} --lake {H.esc(_lake_arg(lake))} --run "
            f"{H.esc(shlex.quote(run_id))} --case N -o caseN.rrd</code></p>")
    return note + '<div class="gallery">' + "".join(figs) + "</div>"


def _star_crops(star, spec, ctx, ids: np.ndarray) -> list[tuple[bytes, dict]]:
    """Each case of ``ids`` re-rendered (bit-identical to its row) as a stretched crop with its detections
    (circles, HIP labels of the identified ones), the catalog predicted by the solved attitude (x) and the
    catalog stars at the true attitude (+): viz/case_crop.py."""
    out = star.compute_batch(spec, ctx, ids, keep_images=True)
    det, ident, sol, field_, truth = (out["rendered"].detections, out["ident"], out["sol"], out["field"],
                                      out["truth"])
    hip = ctx.catalog.hip
    items = []
    for b in range(len(ids)):
        lo, hi = int(det.offsets[b]), int(det.offsets[b + 1])
        xy = np.stack([det.x[lo:hi], det.y[lo:hi]], -1)
        K, S = hi - lo, ident.ids.shape[1]
        rows = np.full(K, -1)
        acc = np.zeros(K, bool)
        rows[:min(K, S)] = ident.ids[b, :min(K, S)]
        acc[:min(K, S)] = ident.accepted[b, :min(K, S)]
        acc &= rows >= 0
        right = acc & (rows == truth.true_row[lo:hi])
        state = np.where(acc, np.where(right, 1, 2), 0)
        labels = [f"HIP {hip[r]}" if a else "" for r, a in zip(rows, acc)]
        pred = None
        if np.isfinite(sol.A_est[b]).all():
            px, front = spec.camera.project(ctx.catalog.unit @ sol.A_est[b].T)
            pred = px[front]
        ref = np.stack([field_.x[b][field_.inside[b]], field_.y[b][field_.inside[b]]], -1)
        items.append(case_crop_png(out["rendered"].images[b], detections=xy, det_state=state, det_labels=labels,
                                   predicted=pred, reference=ref))
    return items


def _failures_table(con, lake: Lake, run_id: str) -> tuple[int, str]:
    """(number of failures, the HTML listing every one of them, up to :data:`LISTED`, with its replay command)."""
    where = "run = $run AND status <> 'success'"
    n = con.execute(f"SELECT count(*) FROM star_cases WHERE {where}", {"run": run_id}).fetchone()[0]
    if not n:
        return 0, "<p>No failure: every case succeeded.</p>"
    cols, rows = _rows(con, "SELECT case_id, status, status_robust, n_generated, n_observed, n_identified, T, "
                            "err_total_rad * arcsec_per_rad() AS err_total_arcsec FROM star_cases "
                            f"WHERE {where} ORDER BY case_id LIMIT {LISTED}", run_id)
    lk, rid = _lake_arg(lake), shlex.quote(run_id)
    body = [[*table_cells(cols, [r])[0], f"dualsight star replay --lake {lk} --run {rid} --case {r[0]} "
                                         f"-o case{r[0]}.rrd"] for r in rows]
    head = ["case", "status", "robust method", "stars generated", "stars observed", "identified", "T",
            "total error (arcsec)", "replay into rerun"]
    more = ""
    if n > LISTED:
        sql = f"SELECT * FROM star_cases WHERE run = '{run_id}' AND status <> 'success' ORDER BY case_id"
        more = (f'<p class="note">The first {LISTED} of {n} failures; all of them: <code>dualsight sql '
                f"{H.esc(shlex.quote(sql))} --lake {H.esc(lk)}</code></p>")
    return n, (f'<p>{n} failure(s): every case whose status is not success, by case id.</p>'
               + H.table(head, body, left=3, mono=(8,)) + more)


# ----------------------------------------------------------------------------------------------- per kind
def _reliability(rep: dict) -> str:
    """The reliability numbers as rows (measure, dualsight, reference), rates in percent."""
    j, ref = rep["json"], star_report.REFERENCE
    rows = [("cases", j["cases"], "200"),
            ("success (every axis <= 100 arcsec)", percent(j["success_rate"]), percent(ref["success_rate"])),
            ("confident but wrong (T > 0)", percent(j["confident_wrong_rate"]), percent(ref["confident_wrong_rate"])),
            ("no confident solution (T <= 0)", percent(j["no_solution_rate"]), "-"),
            ("identification right", percent(j["identification_rate"]), "-"),
            ("robust method: success", percent(j["robust"]["success_rate"]), "-"),
            ("robust method: confident but wrong", percent(j["robust"]["confident_wrong_rate"]), "-"),
            ("attitudes with >= 3 catalog stars in the field", percent(j["sky_share_ge3_stars"]), "-"),
            ("attitudes with >= 4 catalog stars in the field", percent(j["sky_share_ge4_stars"]), "-"),
            ("stars generated, mean over every case", cell("mean", j["mean_stars_generated_all_cases"]), "-"),
            ("time per case (ms, sum of the stages)", cell("ms", j["mean_ms_per_case"]), "-")]
    return H.table(["measure", "dualsight", "reference"], rows)


def _star(lake, con, m, run_id):
    from dualsight.jobs.kinds import star                      # Taichi (re-renders the worst cases)

    rep = star_report.build(lake, run_id)      # per-shard summaries when the run has them, else a full scan
    t = rep["tables"]
    secs = [("Reliability (reference section 3.3)", _reliability(rep)),
            ("Table 5: stars and errors of the successful cases", H.table(*star_report.table5_rows(rep))
             + (f'<p class="note">{H.esc(rep["note"])}</p>' if rep.get("note") else "")),
            ("Reference method beside dualsight's robust voting",
             H.table(t["star_robust"][0], table_cells(*t["star_robust"]))),
            ("Figures 9 and 10: error against stars observed",
             H.figure(png_bytes(lambda p: error_vs_observed_figure(rep["json"], p)), "fig9-10", "Mean error per axis "
                      "and RSS error against the number of stars observed; under Fig. 10 the cases behind each bar"))]
    cols, rows = _rows(con, "SELECT case_id, status, T, n_observed, err_total_rad * arcsec_per_rad() AS err_arcsec "
                            "FROM star_cases WHERE run = $run ORDER BY (status = 'success'), "
                            f"err_total_rad DESC NULLS FIRST, case_id LIMIT {GALLERY}", run_id)
    spec = star.spec_from_dict(m["spec"])
    ctx = star.make_context(spec)
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    crops = _star_crops(star, spec, ctx, ids) if len(ids) else []
    items = [(png, f"case {r[0]}: {r[1]}, T = {r[2]}, {r[3]} stars observed, "
                   + (f"total error {cell('arcsec', r[4])} arcsec" if r[4] is not None and r[4] == r[4] else "no attitude"))
             for (png, _), r in zip(crops, rows)]
    n_fail, listing = _failures_table(con, lake, run_id)
    title = (f"Worst cases: {min(n_fail, GALLERY)} of {n_fail} failures drawn" if n_fail else
             "Worst cases: largest attitude errors (no failure)")
    secs.append((title, _gallery(items, lake, run_id, [mk for _, mk in crops], "dualsight star replay")))
    secs.append(("Every failure, with its replay command", listing))
    secs.append(("Time per case by stage", H.table(*star_report.stage_rows(rep))))
    return secs


def _prox(lake, con, m, run_id):
    from dualsight.jobs.kinds import prox                      # Taichi (re-renders the worst cases)

    rep = build_report(lake, run_id)
    spec = prox.spec_from_dict(m["spec"])
    secs = []
    if rep["job"] == "sweep":
        secs.append(("Table 3: range estimates per true range", _report_table(con, "prox_table3", run_id)))
        secs.append(("Figure 7: estimated against true range",
                     H.figure(png_bytes(lambda p: prox_figures.plot_sweep(rep, p)), "fig7", "Mean range estimate "
                              "per true range, both estimators, with the reference's")))
        order = "abs(subpixel_range_est_m - true_range_m) / true_range_m DESC NULLS FIRST"
    else:
        secs.append(("Trajectory errors", _report_table(con, "prox_trajectory", run_id)))
        secs.append(("Figure 6: true and estimated position per axis",
                     H.figure(png_bytes(lambda p: prox_figures.plot_trajectory(rep, p)), "fig6", "Position per axis "
                              "over the frames")))
        order = "subpixel_pos_err_m DESC NULLS FIRST"
    try:
        table = area_table(spec.satellite, n=spec.areas["samples"], bin_width=spec.areas["bin_width"])
        secs.append(("Figure 1: projected-area curves of the target",
                     H.figure(png_bytes(lambda p: prox_figures.areas_figure(table, p)), "fig1", "A/A0 against axis ratio")))
    except (AttributeError, TypeError, ValueError) as e:
        secs.append(("Figure 1: projected-area curves of the target", H.pre(f"not available: {e}")))
    cols, rows = _rows(con, f"SELECT case_id, true_range_m, found, subpixel_range_est_m, cob_x_px, cob_y_px, "
                            f"major_px FROM prox_cases "
                            f"WHERE run = $run ORDER BY {order} LIMIT {GALLERY}", run_id)
    ctx = prox.make_context(spec)
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    items = []
    if len(ids):
        images = prox.compute_batch(spec, ctx, ids, keep_images=True)["images"]
        for img, r in zip(images, rows):
            ok = r[2] and r[4] is not None and r[6] is not None
            thumb = thumbnail_png(img, centre=(r[4], r[5]), half=1.5 * r[6] + 8) if ok else thumbnail_png(img)
            items.append((thumb, f"case {r[0]}: true {cell('m', r[1])} m, found {r[2]}, "
                                 f"subpixel estimate {cell('m', r[3])} m" + (" (crop around the blob)" if ok else "")))
    secs.append(("Worst cases (largest range error)", _gallery(items, lake, run_id)))
    secs.append(("Time per case by stage", _report_table(con, "prox_stage_times", run_id)))
    return secs


def _hil_images(lake, m, run_id, cases: list[tuple[int, str]]):
    items = []
    for case_id, cap in cases:
        try:
            path = m["spec"]["images"][case_id]["path"]
            items.append((thumbnail_png(read_image(Path(path), as_gray=True).adc_counts()), cap))
        except (InputError, KeyError, IndexError, TypeError):
            continue
    return _gallery(items, lake, run_id)


def _hil_star(lake, con, m, run_id):
    cols, rows = run_report(con, "hil_star_images", run=run_id)
    halves = (["image", "status", "stars_detected", "stars_identified", "T", "ra_deg", "dec_deg", "roll_deg", "ms"],
              ["image", "truth_source", "boresight_error_arcsec", "attitude_error_arcsec", "residual_median_arcsec",
               "truth_residual_median_arcsec", "truth_ids_agree", "truth_ids_disagree", "alt_method",
               "alt_boresight_error_arcsec"])
    secs = []
    for title, keep in zip(("Images: attitude found", "Images: errors against the truth"), halves):
        k = [cols.index(c) for c in keep if c in cols]
        sub = [[r[i] for i in k] for r in rows]
        secs.append((title, H.table([cols[i] for i in k], table_cells([cols[i] for i in k], sub))))
    cols, rows = run_report(con, "hil_star_table6", run=run_id)
    keep = [i for i, c in enumerate(cols) if c not in ("case_id", "image")]
    per: dict = {}
    for r in rows:
        per.setdefault((r[0], r[1]), []).append([r[i] for i in keep])
    heads = [cols[i] for i in keep]
    secs.append(("Table 6: identified stars (brightest first; open an image)", "".join(
        f"<details><summary>case {cid}: {H.esc(img)}, {len(rs)} stars identified</summary>"
        f"{H.table(heads, table_cells(heads, rs))}</details>" for (cid, img), rs in per.items())))
    cols, rows = _rows(con, "SELECT case_id, image, status, boresight_error_rad * arcsec_per_rad() FROM hil_star "
                            "WHERE run = $run ORDER BY (status = 'success'), boresight_error_rad DESC NULLS FIRST "
                            f"LIMIT {GALLERY}", run_id)
    items, marks = [], []
    for r in rows:
        try:
            path = m["spec"]["images"][r[0]]["path"]
            img = read_image(Path(path), as_gray=True).adc_counts()
        except (InputError, KeyError, IndexError, TypeError):
            continue
        _, st = _rows(con, "SELECT x_px, y_px, pred_x_px, pred_y_px, hip, truth_id_agrees FROM hil_star_stars "
                           f"WHERE run = $run AND case_id = {int(r[0])} ORDER BY det_index", run_id)
        obs = np.array([s[:2] for s in st], float).reshape(-1, 2)
        pred = np.array([s[2:4] for s in st], float).reshape(-1, 2)
        state = np.array([2 if s[5] is False else 1 for s in st], int)
        png, mk = case_crop_png(img, detections=obs, det_state=state, det_labels=[f"HIP {s[4]}" for s in st],
                                predicted=pred, reference=None)
        items.append((png, f"case {r[0]} {r[1]}: {r[2]}, {len(st)} stars identified, boresight error "
                           f"{cell('arcsec', r[3])} arcsec (circles: identified stars' centroids)"))
        marks.append(mk)
    secs.append(("Worst frames", _gallery(items, lake, run_id, marks)))
    return secs


def _hil_prox(lake, con, m, run_id):
    data = hil_prox_report.fetch(con, run_id)
    secs = [("Threshold sweep", _report_table(con, "hil_prox_sweep", run_id))]
    if data["rows"]:
        secs.append(("Figure 8: range against binary threshold",
                     H.figure(png_bytes(lambda p: hil_prox_figure(data, p, title=run_id)), "fig8",
                              "Estimated range per threshold")))
    secs.append(("Images", _hil_images(lake, m, run_id, [(c["case_id"], f"case {c['case_id']} {c.get('image')}")
                                                          for c in data["cases"][:GALLERY]])))
    return secs


def _generic(lake, con, m, run_id):
    ds = m["primary"]
    cols, rows = _rows(con, f"SELECT * EXCLUDE (run) FROM {ds} WHERE run = $run ORDER BY case_id LIMIT 20",
                       run_id)
    return [(f"First rows of {ds}", H.table(cols, table_cells(cols, rows)))]

TRACKED = 4
"""Sequences of a star-tracking run drawn as error against time (the least available first)."""


def _star_track(lake, con, m, run_id):
    """Star tracking (issue 22, point 5): the text report's targets, summary, per-mode and lock-reason tables
    (``jobs/reports/star_track.py`` over ``warehouse/sql/star_track_*.sql``) and the figures of
    ``viz/track_figures.py``: error per axis against time of the least available sequences with the mode shaded,
    availability at each frame and latency per frame by mode."""
    rep = track_report.build(lake, run_id)
    j = rep["json"]
    summary = [("sequences", j["sequences"]), ("frames (normal: no blank, blinded or dropped)",
                                                 f"{j['frames']:,} ({j['frames_normal']:,})"),
               ("availability, all frames", percent(j["availability"])),
               ("availability, normal frames", percent(j["availability_normal_frames"])),
               ("valid attitude (within the limit or not)", percent(j["valid_share"])),
               ("tracking share", percent(j["tracking_share"])), ("two-star locks", j["two_star_frames"]),
               ("time to first fix, mean / max (s)", f"{cell('s', j['mean_time_to_first_fix_s'])} / "
                                                     f"{cell('s', j['max_time_to_first_fix_s'])}"),
               ("sequences never fixed", j["sequences_never_fixed"]),
               ("re-acquisitions after a loss (mean / max frames)",
                f"{j['reacquisitions']} ({cell('mean', j['mean_reacquisition_frames'])} / "
                f"{cell('frames', j['max_reacquisition_frames'])})"),
               ("losses not recovered before the sequence ended", j["unrecovered_losses"]),
               ("false locks", j["false_locks"]),
               ("rate error RMS from attitudes / from stars (deg/s)",
                f"{cell('rate_deg_s', j['rate_att_err_rms_deg_s'])} / {cell('rate_deg_s', j['rate_star_err_rms_deg_s'])}"),
               ("rate from stars within 3 stated sigmas", percent(j["rate_star_within_3sigma"])),
               ("identities of tracking vs lost-in-space on the same frames (equal / different)",
                "-" if j["ids_equal_to_lost_in_space"] is None else
                f"{j['ids_equal_to_lost_in_space']} / {j['ids_different_from_lost_in_space']}")]
    secs = [("Star tracking: targets (issue 22, point 6)",
             H.table(["metric", "run", "target", "verdict"], track_report.target_rows(rep))),
            ("Star tracking: campaign", H.table(["measure", "value"], summary)),
            ("Star tracking: error and latency per mode",
             H.table(*_cells(rep["tables"]["star_track_modes"]))),
            ("Star tracking: lock reasons by frame event",
             H.table(*_cells(rep["tables"]["star_track_reasons"]), left=3))]
    cols, seqs = _rows(con, "SELECT case_id, motion, rate_deg_s, availability, losses, false_locks "
                            "FROM star_sequences WHERE run = $run ORDER BY availability, losses DESC, case_id "
                            f"LIMIT {TRACKED}", run_id)
    ids = ",".join(str(int(r[0])) for r in seqs) or "-1"
    fcols, frames = _rows(con, "SELECT case_id, t_s, mode, err_x_arcsec, err_y_arcsec, err_z_arcsec FROM star_frames "
                               f"WHERE run = $run AND case_id IN ({ids}) ORDER BY case_id, frame", run_id)
    fr = {c: np.array([r[i] for r in frames], dtype=object) for i, c in enumerate(fcols)}
    drawn = []
    for cid, motion, rate, avail, losses, fl in seqs:
        k = fr["case_id"] == cid
        drawn.append({"case_id": cid, "t_s": fr["t_s"][k].astype(float), "mode": fr["mode"][k],
                      "title": f"sequence {cid}: {motion}, peak rate {cell('rate_deg_s', rate)} deg/s, available "
                               f"{percent(avail)}, {losses} loss(es), {fl} false lock(s)",
                      **{f"err_{a}_arcsec": np.array([np.nan if v is None else v for v in fr[f"err_{a}_arcsec"][k]],
                                                     dtype=float) for a in "xyz"}})
    limit = (m["spec"].get("sequence") or {}).get("error_limit_arcsec")
    replay = (f"<p>Replay a sequence into rerun (its frames on the <code>frame</code> time line): <code>dualsight "
              f"replay --lake {H.esc(_lake_arg(lake))} --run {H.esc(shlex.quote(run_id))} --case N -o seqN.rrd</code>"
              "</p>")
    secs.append(("Star tracking: error per axis against time",
                 replay + H.figure(png_bytes(lambda p: track_figures.error_vs_time_figure(drawn, p, limit)),
                                   "track-error-vs-time", f"Error per axis (arcsec, symmetric log) of the "
                                   f"{len(drawn)} least available sequences; background: tracking (green), "
                                   "lost in space (orange), no fix (red); dashed: the error limit")))
    ev = j["error_vs_time"]
    per_frame = {"t_s": [r["t_s"] for r in ev], "availability": [r["availability"] for r in ev]}
    secs.append(("Star tracking: availability and latency by mode",
                 H.figure(png_bytes(lambda p: track_figures.availability_latency_figure(per_frame, j["modes"], p)),
                          "track-availability-latency", "Left: share of the sequences with a valid attitude within "
                          "the limit at each frame.  Right: latency per frame by mode and stage (ms, log scale)")))
    return secs


def _cells(table: tuple) -> tuple:
    cols, rows = table
    return cols, table_cells(cols, rows)


KINDS = {"star": _star, "prox_sweep": _prox, "prox_trajectory": _prox, "hil_star": _hil_star,
         "hil_prox": _hil_prox, "star_track": _star_track, "rendezvous": rendezvous_report.html_sections}


def build_html(lake: Lake, run_id: str) -> str:
    """The page of run ``run_id`` (any job kind)."""
    m = lake.read_manifest(run_id)
    if m is None:
        raise InputError(f"no run {run_id!r} in {lake.root}", source="--run")
    problems: list[str] = []
    con = connect(lake, warn=problems.append)
    root = Path(lake.root).resolve()
    head = [("Run", H.table(["key", "value"], [
        ("run", run_id), ("kind", m["kind"]), ("status", lake.live_status(m)), ("cases", m["n_cases"]),
        ("shards", f"{m.get('shards_done')}/{m['n_shards']}"), ("seed", m.get("seed")),
        ("spec hash", m["spec_hash"]), ("code version", m.get("code_version")), ("lake folder", str(root)),
        ("page made", iso_utc(time.time()))], left=2))]
    if problems:
        head.append(("Damaged files (left out)", H.pre("\n".join(problems))))
    body = KINDS.get(m["kind"], _generic)(lake, con, m, run_id)
    ex = m.get("executions") or []
    tail = [("Executions (timings)", H.table(["started (UTC)", "workers", "scheduler", "elapsed (s)", "cases run",
                                              "resumed shards"],
                                             [(iso_utc(e.get("started_unix")), e.get("workers"), e.get("scheduler"),
                                               cell("s", e.get("elapsed_s")), e.get("cases_run"),
                                               e.get("resumed_shards")) for e in ex])),
            ("Spec", H.definitions(m["spec"])),
            ("Versions", H.definitions(m.get("versions") or {}))]
    return H.page(f"dualsight run {run_id}", head + body + tail,
                  subtitle=f"{m['kind']} run of {m['n_cases']} cases, read from the lake folder {root}")


def write_html(lake: Lake, run_id: str, path: Path) -> Path:
    """Write the page; the folder must exist (no folder is created that was not named)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("folder does not exist", source=str(path.parent))
    text = build_html(lake, run_id)
    path.write_text(text, encoding="utf-8")
    return path
