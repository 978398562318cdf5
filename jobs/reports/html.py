"""``dualsight report --run ID --html FILE``: one self-contained page per run, for any job kind.

Everything on the page comes from the lake (warehouse SQL over the read-only views) and the run's
manifest; figures are the ones the command-line reports draw (reference Figures 1, 6, 7, 8, 9-10) as inline
PNG; the worst cases are re-rendered (simulations) or re-read (real images) into thumbnails, each with the
``dualsight replay`` command that records it for rerun.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from dualsight.catalogs.areas import area_table
from dualsight.errors import InputError
from dualsight.jobs.reports import hil_prox as hil_prox_report
from dualsight.jobs.reports import star as star_report
from dualsight.jobs.reports.prox import build_report
from dualsight.scene.imageio import read_image
from dualsight.viz import html_page as H
from dualsight.viz import prox_figures
from dualsight.viz.figures import png_bytes, thumbnail_png
from dualsight.viz.star_figures import error_vs_observed_figure
from dualsight.viz.threshold_sweep import hil_prox_figure
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import connect, run_report

GALLERY = 6


def _rows(con, sql: str, run_id: str):
    cur = con.execute(sql, {"run": run_id})
    return [d[0] for d in cur.description], cur.fetchall()


def _report_table(con, name: str, run_id: str) -> str:
    cols, rows = run_report(con, name, run=run_id)
    return H.table(cols, rows)


def _gallery(items: list[tuple[bytes, str]], lake: Lake, run_id: str) -> str:
    figs = [H.figure(png, f"case-{i}", cap) for i, (png, cap) in enumerate(items)]
    note = (f"<p>Replay any of them into rerun: <code>dualsight replay --lake {H.esc(lake.root)} --run "
            f"{H.esc(run_id)} --case N -o caseN.rrd</code></p>")
    return note + '<div class="gallery">' + "".join(figs) + "</div>"


# ----------------------------------------------------------------------------------------------- per kind
def _star(lake, con, m, run_id):
    from dualsight.jobs.kinds import star                      # Taichi (re-renders the worst cases)

    rep = star_report.build(lake, run_id)      # per-shard summaries when the run has them, else a full scan
    t = rep["tables"]
    summ = rep["summary"]
    secs = [("Reliability (reference section 3.3)", H.table(list(summ), [list(summ.values())])),
            ("Table 5: stars and errors of the successful cases", H.table(*t["star_table5"])),
            ("Reference method beside dualsight's robust voting", H.table(*t["star_robust"])),
            ("Figures 9 and 10: error against stars observed",
             H.figure(png_bytes(lambda p: error_vs_observed_figure(rep["json"], p)), "fig9-10", "Mean error per axis and RSS error "
                      "against the number of stars observed"))]
    cols, rows = _rows(con, "SELECT case_id, status, T, n_observed, err_total_rad * 206264.806 AS err_arcsec "
                            "FROM star_cases WHERE run = $run ORDER BY (status = 'success'), "
                            f"err_total_rad DESC NULLS FIRST LIMIT {GALLERY}", run_id)
    spec = star.spec_from_dict(m["spec"])
    ctx = star.make_context(spec)
    ids = np.array([r[0] for r in rows], dtype=np.int64)
    items = []
    if len(ids):
        images = star.compute_batch(spec, ctx, ids, keep_images=True)["rendered"].images
        for img, r in zip(images, rows):
            items.append((thumbnail_png(img), f"case {r[0]}: {r[1]}, T={r[2]}, {r[3]} stars observed, "
                                       f"error {H.fmt(r[4])} arcsec"))
    secs.append(("Worst cases (failures first, then largest attitude error)", _gallery(items, lake, run_id)))
    secs.append(("Time per case by stage", H.table(*t["star_stage_times"])))
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
            items.append((thumb, f"case {r[0]}: true {H.fmt(r[1])} m, found {r[2]}, "
                                 f"subpixel estimate {H.fmt(r[3])} m" + (" (crop around the blob)" if ok else "")))
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
    secs = [("Images", _report_table(con, "hil_star_images", run_id)),
            ("Table 6: identified stars", _report_table(con, "hil_star_table6", run_id))]
    cols, rows = _rows(con, "SELECT case_id, image, status, boresight_error_rad * 206264.806 FROM hil_star "
                            "WHERE run = $run ORDER BY (status = 'success'), boresight_error_rad DESC NULLS FIRST "
                            f"LIMIT {GALLERY}", run_id)
    secs.append(("Worst frames", _hil_images(lake, m, run_id, [
        (r[0], f"case {r[0]} {r[1]}: {r[2]}, boresight error {H.fmt(r[3])} arcsec") for r in rows])))
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
    return [(f"First rows of {ds}", H.table(cols, rows))]


KINDS = {"star": _star, "prox_sweep": _prox, "prox_trajectory": _prox, "hil_star": _hil_star,
         "hil_prox": _hil_prox}


def build_html(lake: Lake, run_id: str) -> str:
    """The page of run ``run_id`` (any job kind)."""
    m = lake.read_manifest(run_id)
    if m is None:
        raise InputError(f"no run {run_id!r} in {lake.root}", source="--run")
    problems: list[str] = []
    con = connect(lake, warn=problems.append)
    head = [("Run", H.table(["key", "value"], [
        ("run", run_id), ("kind", m["kind"]), ("status", lake.live_status(m)), ("cases", m["n_cases"]),
        ("shards", f"{m.get('shards_done')}/{m['n_shards']}"), ("seed", m.get("seed")),
        ("spec hash", m["spec_hash"]), ("code version", m.get("code_version"))], left=2))]
    if problems:
        head.append(("Damaged files (left out)", H.pre("\n".join(problems))))
    body = KINDS.get(m["kind"], _generic)(lake, con, m, run_id)
    ex = m.get("executions") or []
    tail = [("Executions (timings)", H.table(["started (unix)", "workers", "scheduler", "elapsed s", "cases run",
                                              "resumed shards"],
                                             [(e.get("started_unix"), e.get("workers"), e.get("scheduler"),
                                               e.get("elapsed_s"), e.get("cases_run"), e.get("resumed_shards"))
                                              for e in ex])),
            ("Spec", H.pre(json.dumps(m["spec"], indent=1, sort_keys=True))),
            ("Versions", H.pre(json.dumps(m.get("versions"), indent=1, sort_keys=True)))]
    return H.page(f"dualsight run {run_id}", head + body + tail,
                  subtitle=f"{m['kind']} run, {m['n_cases']} cases, from the lake {lake.root}")


def write_html(lake: Lake, run_id: str, path: Path) -> Path:
    """Write the page; the folder must exist (no folder is created that was not named)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("folder does not exist", source=str(path.parent))
    text = build_html(lake, run_id)
    path.write_text(text, encoding="utf-8")
    return path
