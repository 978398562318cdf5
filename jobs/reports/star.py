"""The star-tracker report: every number comes out of the SQL files in ``warehouse/sql``.

Two ways to the same numbers (issue 13):

* **summaries** (``warehouse/sql/star_summ_*.sql``): sums of the per-shard partial aggregates that every star shard
  writes beside its cases (dataset ``star_summaries``, :mod:`dualsight.jobs.kinds.star_summaries`, ~40 rows per shard of
  1,000 cases).  :func:`open_summaries` reads the run's summary files once (no view over the rest of the lake) and
  sums them per key as it reads, into an in-memory table of ~50 rows with one named column per sum and count; the
  six queries run on it.
* **scan** (``warehouse/sql/star_*.sql``): every row of ``star_cases`` of the run, over the lake's views.

The report takes the summaries when the run's journal has a readable ``star_summaries`` file for exactly the shards
that have a readable ``star_cases`` file, and the summaries' case counts add up to the journalled rows of those
``star_cases`` files; otherwise (runs made before the summaries, a damaged summaries file) it falls back to the full
scan, which gives the same numbers: counts and rates exactly, means to ~1e-16 relative (float sums in another
order).  Nothing in the report is an order statistic (median, percentile), so no query needs the rows themselves.
"""

from __future__ import annotations

import sys

import duckdb

from dualsight.errors import InputError
from dualsight.warehouse.cells import cell, percent, table_cells
from dualsight.jobs.kinds.star_summaries import DATASET as SUMMARIES
from dualsight.jobs.kinds.star_summaries import merge_sql
from dualsight.jobs.kinds.star_output import kept as detections_kept
from dualsight.jobs.kinds.star_output import not_kept_note
from dualsight.scene.units import ARCSEC
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.paths import is_run_id
from dualsight.warehouse.query import connect, format_table, run_report

REFERENCE = {"success_rate": 191 / 200, "confident_wrong_rate": 2 / 200, "mean_stars_generated": 11.4607,
             "mean_stars_observed": 10.1152, "mean_T": 8.6230,
             "mean_error_arcsec": {"x": 10.6237, "y": 7.7998, "z": 6.4789}}

#: The report's queries by their full-scan name; :func:`query_name` gives the file each path reads.
QUERIES = ("star_summary", "star_table5", "star_error_vs_observed", "star_status", "star_stage_times", "star_robust")
SOURCES = ("auto", "summaries", "scan")


def query_name(name: str, source: str) -> str:
    """SQL file of report query ``name`` (one of :data:`QUERIES`) for ``source`` "summaries" or "scan":
    ``star_summary`` -> ``star_summ_summary`` (summaries) or ``star_summary`` (scan)."""
    if name not in QUERIES:
        raise ValueError(f"unknown star report query {name!r}")
    return "star_summ_" + name[len("star_"):] if source == "summaries" else name


def _stderr(msg: str):
    print(f"dualsight: warning: {msg}", file=sys.stderr)


def open_summaries(lake: Lake, run_id: str, *, warn=None, locked: bool = True,
                   threads: int | None = None) -> duckdb.DuckDBPyConnection | None:
    """In-memory DuckDB connection with table ``star_summaries``: the run's summaries summed over its shards per key
    (status, status_robust, n_observed: ~40-60 rows), columns ``cases``, ``sum_<m>`` / ``n_<m>`` per measure and
    ``run``; or None when the summaries do not cover exactly the run's cases.

    Exact coverage: the run's journal (stat only, :meth:`Lake.scan`) lists a readable summaries file for exactly the
    shards with a readable ``star_cases`` file (at least one), and the summaries' ``cases`` add up to the rows the
    journal records for those ``star_cases`` files.  Only those files are read, once.  ``warn`` (default: one line
    on stderr) hears about a run whose summaries exist but do not match, and about this run's damaged files when
    the summaries are used.  ``locked``: as :func:`dualsight.warehouse.query.connect` (no file, network or
    extension access, configuration locked) once the table is loaded.
    """
    report = warn if warn is not None else _stderr
    if not is_run_id(run_id):
        return None                 # not a run id (no path from it); the scan path reports "no star cases"
    h = lake.scan(run_id)
    cases = {p.name for p in h.files.get("star_cases", [])}
    summ = sorted(h.files.get(SUMMARIES, []))
    if not cases or cases != {p.name for p in summ}:
        if summ:
            report(f"run {run_id}: its {SUMMARIES} files do not match its star_cases files; the report scans "
                   "star_cases")
        return None
    rows = sum(int((e.get("rows") or {}).get("star_cases", -1)) for e in lake.read_journal(run_id)
               if lake.shard_path("star_cases", run_id, int(e["shard"])).name in cases)
    con = duckdb.connect(":memory:")
    if threads:
        con.execute(f"SET threads = {int(threads)}")
    lst = ", ".join("'" + p.as_posix().replace("'", "''") + "'" for p in summ)
    try:
        # one pass over the files, summed per key as it reads (storing the packed lists in a table costs ~3x more)
        con.execute(f"CREATE TABLE {SUMMARIES} AS SELECT {merge_sql()}, $run::VARCHAR AS run "
                    f"FROM read_parquet([{lst}]) GROUP BY ALL", {"run": run_id})
        n = con.execute(f"SELECT coalesce(sum(cases), 0) FROM {SUMMARIES}").fetchone()[0]
    except duckdb.Error as e:
        report(f"run {run_id}: its {SUMMARIES} files do not read ({str(e).splitlines()[0][:120]}); the report "
               "scans star_cases")
        con.close()
        return None
    if int(n) != rows:
        report(f"run {run_id}: its {SUMMARIES} count {n} cases, its star_cases files {rows}; the report scans "
               "star_cases")
        con.close()
        return None
    for m in h.problems:
        report(m)
    con.execute(f"CREATE MACRO arcsec_per_rad() AS {1.0 / ARCSEC!r}")       # as warehouse.query.connect
    if locked:
        con.execute("SET enable_external_access = false")
        con.execute("SET autoinstall_known_extensions = false")
        con.execute("SET autoload_known_extensions = false")
        con.execute("SET lock_configuration = true")
    return con


def summaries_complete(lake: Lake, run_id: str) -> bool:
    """True when :func:`open_summaries` would give the summaries path for ``run_id`` (quietly)."""
    con = open_summaries(lake, run_id, warn=lambda m: None)
    if con is None:
        return False
    con.close()
    return True


def build(lake: Lake, run_id: str, source: str = "auto") -> dict:
    """Run the star report queries for ``run_id``; returns tables, the JSON summary and the path taken ("source").

    ``source``: "auto" (summaries when they cover the run exactly, else the full scan), "summaries" (InputError
    when they do not) or "scan" (see the module)."""
    if source not in SOURCES:
        raise InputError(f"report source must be one of {', '.join(SOURCES)}, got {source!r}")
    con, src = None, "scan"
    if source != "scan":
        con = open_summaries(lake, run_id)
        if con is not None:
            src = "summaries"
        elif source == "summaries":
            raise InputError(f"run {run_id!r} has no complete {SUMMARIES} (made before them, or a file is damaged); "
                             "the full scan gives the same numbers", source="--run")
    if con is None:
        if "star_cases" not in lake.datasets():
            raise InputError(f"no star_cases dataset in {lake.root}", source="--lake")
        con = connect(lake)
    cols, rows = run_report(con, query_name("star_summary", src), run=run_id)
    s = dict(zip(cols, rows[0]))
    if not s["cases"]:
        raise InputError(f"run {run_id!r} has no star cases in {lake.root}", source="--run")
    tables = {name: run_report(con, query_name(name, src), run=run_id) for name in QUERIES[1:]}
    breakdown = detection_breakdown(lake, run_id)
    js = {
        "run": run_id,
        "cases": int(s["cases"]),
        "success_rate": s["success_rate"],
        "confident_wrong_rate": s["confident_wrong_rate"],
        "no_solution_rate": s["no_solution_rate"],
        "identification_rate": s["identification_rate"],
        "robust": {"success_rate": s["robust_success_rate"],
                   "confident_wrong_rate": s["robust_confident_wrong_rate"],
                   "no_solution_rate": s["robust_no_solution_rate"],
                   "identification_rate": s["robust_identification_rate"]},
        "mean_stars_generated": s["mean_stars_generated"],
        "mean_stars_observed": s["mean_stars_observed"],
        "mean_T": s["mean_T"],
        "mean_error_arcsec": {"x": s["mean_err_x_arcsec"], "y": s["mean_err_y_arcsec"], "z": s["mean_err_z_arcsec"]},
        "mean_stars_generated_all_cases": s["mean_stars_generated_all"],
        "sky_share_ge3_stars": s["sky_share_ge3_stars"],
        "sky_share_ge4_stars": s["sky_share_ge4_stars"],
        "mean_ms_per_case": s["mean_ms_per_case"],
        "error_vs_stars_observed": [dict(zip(tables["star_error_vs_observed"][0], r))
                                    for r in tables["star_error_vs_observed"][1]],
        "reference": REFERENCE,
    }
    if breakdown is not None:
        js["detections_per_successful_case"] = breakdown
    note = detections_note(lake, run_id)
    if note:
        js["detections_note"] = note
    return {"summary": s, "tables": tables, "json": js, "source": src, "breakdown": breakdown, "note": note}


def detections_note(lake: Lake, run_id: str) -> str | None:
    """The one line the report prints in place of the blob breakdown when the run did not keep its per-star rows
    (``star_detections``: ``[output] detections``, issue 24.5), with how to get them; None when it kept them."""
    m = lake.read_manifest(run_id) if is_run_id(run_id) else None
    if m is None or detections_kept(m):
        return None
    return not_kept_note(m, "blob breakdown of Table 5 (per-star rows)")


BREAKDOWN_CASES = 100_000
"""The blob breakdown under Table 5 reads the detection rows of the cases with a smaller id only (a random sample:
cases are independent draws), so that a 10^7-case report does not scan 10^8 detection rows (~0.1 s per 20,000
cases on 2 loaded cores)."""


def detection_breakdown(lake: Lake, run_id: str) -> dict | None:
    """What "stars observed" counts, averaged over the successful cases (``warehouse/sql/star_detection_breakdown.sql``
    over ``star_cases`` and ``star_detections``): generated, observed (= blobs), matched, edge, split, false_blobs,
    missed (per case), cases and cases_observed_gt_generated (counts), sampled (True when only the successful
    cases among the first :data:`BREAKDOWN_CASES` were read).  None when the run has no detection rows (or did not
    keep them: ``[output] detections``) or no camera size in its manifest."""
    m = lake.read_manifest(run_id) or {}
    if not detections_kept(m) or "star_detections" not in lake.datasets():
        return None
    cam = (m.get("spec") or {}).get("camera") or {}
    if "width" not in cam or "height" not in cam:
        return None
    con = connect(lake, warn=lambda msg: None)
    try:
        cols, rows = run_report(con, "star_detection_breakdown", run=run_id, width=float(cam["width"]),
                                height=float(cam["height"]), max_case=BREAKDOWN_CASES)
    except duckdb.Error:
        return None
    finally:
        con.close()
    d = dict(zip(cols, rows[0]))
    d["sampled"] = int(m.get("n_cases") or 0) > BREAKDOWN_CASES
    return d if d["cases"] else None


#: Table 5's rows as the report prints them: what each counts (issue 25, point 10).
TABLE5_LABELS = {
    "Stars generated": "Stars generated (catalog stars centred in the image)",
    "Stars observed": "Stars observed (blobs detected, false and edge blobs included)",
    "T": "T (match threshold)",
}

STAGE_LABELS = {"render": "render + detect (fused: noise-free sparse path)"}


def table5_rows(rep: dict) -> tuple[list[str], list[list]]:
    """Table 5 with labelled rows and, under "stars observed", what the blobs are (:func:`detection_breakdown`):
    (columns, rows of printed cells)."""
    cols, rows = rep["tables"]["star_table5"]
    b = rep.get("breakdown")
    out = []
    for metric, ours, ref in rows:
        out.append([TABLE5_LABELS.get(metric, metric), "-" if ours is None else f"{ours:.2f}",
                    "-" if ref is None else f"{ref:.4f}".rstrip("0").rstrip(".")])
        if metric == "Stars observed" and b:
            for key, label in (("matched", "= matched blobs (a rendered star within 2 px)"),
                               ("edge", "incl. edge blobs (star centred outside the image)"),
                               ("split", "incl. split blobs (2nd blob of one star)"),
                               ("false_blobs", "+ false blobs (no rendered star within 2 px)"),
                               ("missed", "Generated stars not detected (missed)")):
                out.append([label + (f" [first {BREAKDOWN_CASES:,} cases]" if b.get("sampled") else ""),
                            f"{b[key]:.2f}", "-"])
    return ["metric", "dualsight", "reference"], out


def stage_rows(rep: dict) -> tuple[list[str], list[list]]:
    """The time-per-stage table without empty rows: a stage that never ran on its own (detection fused into the
    noise-free sparse render: ``t_detect_ns`` null) is left out and the render row says it holds both."""
    cols, rows = rep["tables"]["star_stage_times"]
    fused = any(r[0] == "detect" and r[1] is None for r in rows)
    out = []
    for stage, ms, share in rows:
        if ms is None:
            continue
        label = STAGE_LABELS.get(stage, stage) if fused else stage
        out.append([label, cell("ms_per_case", ms) if ms >= 1e-3 else f"{ms:.4f}", percent(share)])
    return ["stage", "ms per case", "share of total"], out


def text(rep: dict) -> str:
    j = rep["json"]
    ref = REFERENCE
    lines = [
        f"star-tracker run {j['run']}: {j['cases']} cases",
        "",
        "reliability                        dualsight      reference",
        f"  success (all axes <= 100 arcsec)  {percent(j['success_rate']):>10}   {percent(ref['success_rate']):>10}",
        f"  confident but wrong (T > 0)       {percent(j['confident_wrong_rate']):>10}   "
        f"{percent(ref['confident_wrong_rate']):>10}",
        f"  no confident solution (T <= 0)    {percent(j['no_solution_rate']):>10}",
        f"  identification right (ids)        {percent(j['identification_rate']):>10}",
        f"  sky limit: attitudes with >= 3 / >= 4 catalog stars in the field: "
        f"{percent(j['sky_share_ge3_stars'])} / {percent(j['sky_share_ge4_stars'])}",
        "",
        "Reference method beside dualsight's robust voting (unique maxima, consistent set, attitude check)",
        format_table(rep["tables"]["star_robust"][0], table_cells(*rep["tables"]["star_robust"])),
        "",
        "Table 5 (averages over the successful cases)",
        format_table(*table5_rows(rep)),
        *([rep["note"]] if rep.get("note") else []),
        "",
        "Error vs stars observed (Figures 9-10), successful cases",
        format_table(*rep["tables"]["star_error_vs_observed"], floatfmt="{:.2f}"),
        "",
        "Outcomes",
        format_table(*rep["tables"]["star_status"], floatfmt="{:.2f}"),
        "",
        "Time per case by stage",
        format_table(*stage_rows(rep)),
    ]
    return "\n".join(lines)
