"""The nightly's comparisons: every metric of every job against the accepted baseline, by SQL over the lake.

Per job, up to four comparisons (column ``comparison`` of the verdicts):

``fixed``       tonight's fixed-seed run against the baseline's.  Same canonical spec and case count (else
                "not comparable") -> the per-case rows of every dataset are compared by SQL
                (warehouse/sql/nightly_identical.sql, timing columns excluded): equal -> every metric
                "identical"; otherwise every metric is tested (below).
``fresh``       tonight's fresh-seed sample against the baseline's fresh sample: the specs must agree except
                for the seed (else "not comparable"); always tested, never "identical".
``seeds``       tonight's fixed run against tonight's fresh sample: red when the fixed seeds do significantly
                *better* than fresh ones (a method tuned to the fixed seeds).
``throughput``  cases/s of the fixed run (manifest executions) as a ratio to the baseline's.

Metrics come from per-kind SQL (warehouse/sql/nightly_<kind>.sql, one row per case: rates as booleans,
distributions as doubles); the tests are in jobs/nightly/stats.py.  Each tested row gets its p-value; the
verdicts are decided afterwards with alpha = (the suite's family-wise alpha) / (number of tests tonight).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from dualsight.jobs.engine.runner import job_module
from dualsight.jobs.kinds.star_tables import DETECTIONS_SCHEMA
from dualsight.jobs.nightly import stats as st
from dualsight.warehouse.query import run_report, sql_text


@dataclass(frozen=True)
class Metric:
    name: str
    query: str            # warehouse/sql/<query>.sql, parameter $run
    column: str
    kind: str             # "rate" | "dist"
    direction: str        # "higher" | "lower" | "zero" (closer to zero is better)
    needs: str | None = None   # a dataset a run may not keep (star_detections: [output] detections, issue 24.5)


def _rate(name, col, q, direction="higher"):
    return Metric(name, q, col, "rate", direction)


def _dist(name, col, q, direction="lower", needs=None):
    return Metric(name, q, col, "dist", direction, needs)


_STAR = [
    _rate("success_rate", "success", "nightly_star"),
    _rate("confident_wrong_rate", "confident_wrong", "nightly_star", "lower"),
    _rate("identification_rate", "identification", "nightly_star"),
    _rate("success_robust_rate", "success_robust", "nightly_star"),
    _rate("confident_wrong_robust_rate", "confident_wrong_robust", "nightly_star", "lower"),
    _dist("err_x_arcsec", "err_x_arcsec", "nightly_star"),
    _dist("err_y_arcsec", "err_y_arcsec", "nightly_star"),
    _dist("err_z_arcsec", "err_z_arcsec", "nightly_star"),
    _dist("centroid_err_px", "centroid_err_px", "nightly_star", needs="star_detections"),
]
_PROX = [
    _rate("found_rate", "found", "nightly_prox"),
    _rate("within_paper_rate", "within_paper", "nightly_prox"),
    _rate("within_subpixel_rate", "within_subpixel", "nightly_prox"),
    _dist("range_rel_err_paper", "range_rel_err_paper", "nightly_prox"),
    _dist("range_rel_err_subpixel", "range_rel_err_subpixel", "nightly_prox"),
    _dist("range_bias_paper", "range_bias_paper", "nightly_prox", "zero"),
    _dist("range_bias_subpixel", "range_bias_subpixel", "nightly_prox", "zero"),
    _dist("dir_err_arcsec", "dir_err_arcsec", "nightly_prox"),
]
METRICS = {
    "star": _STAR,
    "prox_sweep": _PROX,
    "prox_trajectory": _PROX + [_dist(f"pos_err_{a}_m", f"pos_err_{a}_m", "nightly_prox") for a in "xyz"],
    "hil_star": [
        _rate("identified_rate", "identified", "nightly_hil_star"),
        _rate("success_rate", "success", "nightly_hil_star"),
        _dist("boresight_err_arcsec", "boresight_err_arcsec", "nightly_hil_star"),
        _dist("attitude_err_arcsec", "attitude_err_arcsec", "nightly_hil_star"),
        _dist("residual_arcsec", "residual_arcsec", "nightly_hil_star_stars"),
    ],
    "star_track": [
        _dist("availability", "availability", "nightly_star_track", "higher"),
        _rate("false_lock_rate", "false_lock", "nightly_star_track", "lower"),
        _dist("rate_err_deg_s", "rate_err_deg_s", "nightly_star_track"),
        _dist("err_total_arcsec", "err_total_arcsec", "nightly_star_track"),
    ],
    "hil_prox": [
        _rate("found_rate", "found", "nightly_hil_prox"),
        _rate("within_rate", "within", "nightly_hil_prox"),
        _dist("range_rel_err", "range_rel_err", "nightly_hil_prox"),
        _dist("range_bias", "range_bias", "nightly_hil_prox", "zero"),
    ],
}


class MetricSource:
    """Per-run metric values from the lake (one SQL query per (query, run), cached).

    ``lake`` (optional): where the runs' manifests say which datasets each run kept (:meth:`kept`); a dataset
    that no run of the lake kept is an empty view of its schema, so a query joining it still runs."""

    def __init__(self, con, lake=None):
        self.con = con
        self.lake = lake
        self._cache = {}
        views = {r[0] for r in con.execute("SELECT view_name FROM duckdb_views() WHERE NOT internal").fetchall()}
        if "star_detections" not in views:
            con.register("star_detections", DETECTIONS_SCHEMA.append(pa.field("run", pa.string())).empty_table())

    def kept(self, run: str | None, dataset: str | None) -> bool:
        """False when run ``run``'s manifest leaves ``dataset`` out of its datasets (True without a lake)."""
        if run is None or dataset is None or self.lake is None:
            return True
        m = self.lake.read_manifest(run) or {}
        return dataset in (m.get("datasets") or [dataset])

    def column(self, query: str, run: str, column: str) -> list:
        key = (query, run)
        if key not in self._cache:
            cols, rows = run_report(self.con, query, run=run)
            self._cache[key] = {c: [r[i] for r in rows] for i, c in enumerate(cols)}
        return self._cache[key][column]

    def values(self, m: Metric, run: str):
        """Rates: (successes, cases); distributions: finite values as a float array."""
        v = self.column(m.query, run, m.column)
        if m.kind == "rate":
            vals = [x for x in v if x is not None]
            return int(sum(bool(x) for x in vals)), len(vals)
        a = np.array([x for x in v if x is not None], dtype=np.float64)
        return a[np.isfinite(a)]

    def identical(self, run_a: str, run_b: str, datasets: list[str]) -> tuple[int, int, int]:
        """(rows of a, rows of b, rows in one but not the other) over ``datasets`` (non-timing columns)."""
        ra = rb = diff = 0
        for ds in datasets:
            if not ds.replace("_", "").isalnum():
                raise ValueError(f"bad dataset name {ds!r}")
            sql = sql_text("nightly_identical").replace("{dataset}", ds)
            a, b, only_a, only_b = self.con.execute(sql, {"a": run_a, "b": run_b}).fetchone()
            ra, rb, diff = ra + a, rb + b, diff + only_a + only_b
        return ra, rb, diff


def spec_differences(now: dict, base: dict, *, ignore_seed: bool, ignore_cases: bool) -> list[str]:
    """What makes two runs' manifests not comparable: kind, case count, top-level spec keys."""
    out = []
    if now.get("kind") != base.get("kind"):
        out.append(f"kind {base.get('kind')} -> {now.get('kind')}")
    if not ignore_cases and now.get("n_cases") != base.get("n_cases"):
        out.append(f"cases {base.get('n_cases')} -> {now.get('n_cases')}")
    a, b = dict(now.get("spec") or {}), dict(base.get("spec") or {})
    if ignore_seed:
        a.pop("seed", None)
        b.pop("seed", None)
    keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    if keys:
        out.append("spec keys " + ", ".join(keys[:6]))
    return out


def _row(job, kind, comparison, metric, base, now, test, *, p=None, verdict=None, direction="",
         n_base=None, n_now=None, base_run=None, now_run=None, note="", threshold=None):
    return {"job": job, "kind": kind, "comparison": comparison, "metric": metric, "baseline": base, "now": now,
            "test": test, "p": p, "threshold": threshold, "verdict": verdict, "direction": direction,
            "n_baseline": n_base, "n_now": n_now, "baseline_run": base_run, "now_run": now_run, "note": note}


def metric_rows(src: MetricSource, job: str, kind: str, comparison: str, base_run: str, now_run: str, *,
                verdict: str | None = None, test: str | None = None, note: str = "") -> list[dict]:
    """One row per metric (two per distribution: mean and p95) comparing ``now_run`` with ``base_run``.
    With ``verdict`` given (identical, not comparable) the values are filled in but nothing is tested."""
    out = []
    for m in METRICS[kind]:
        tag = f"{job}/{comparison}/{m.name}"
        common = dict(direction=m.direction, base_run=base_run, now_run=now_run, note=note)
        lost = [r for r in (base_run, now_run) if not src.kept(r, m.needs)]
        if lost:            # the per-star rows were not kept: said in one line, nothing tested
            why = f"{m.needs} not kept in run {', '.join(lost)} ([output] detections; rerun with --detections on)"
            for stat in ((m.name,) if m.kind == "rate" else (f"{m.name}.mean", f"{m.name}.p95")):
                out.append(_row(job, kind, comparison, stat, None, None, "not kept", verdict="info",
                                **dict(common, note=why)))
            continue
        if m.kind == "rate":
            kb, nb = src.values(m, base_run) if base_run else (0, 0)
            kn, nn = src.values(m, now_run)
            rb, rn, p, t = st.rate_test(kb, nb, kn, nn)
            if verdict is not None:
                p, t, rb, nb = None, test, (rb if base_run else None), (nb if base_run else None)
            out.append(_row(job, kind, comparison, m.name, rb, rn, t, p=p, n_base=nb, n_now=nn,
                            verdict=verdict if verdict else (None if p is not None else "info"), **common))
            continue
        xb, xn = (src.values(m, base_run) if base_run else None), src.values(m, now_run)
        if verdict is not None:
            res = {"mean": (_mean(xb), _mean(xn), None, test), "p95": (_q95(xb), _q95(xn), None, test)}
        else:
            res = st.distribution_tests(xb, xn, tag)
        for stat in ("mean", "p95"):
            b, n, p, t = res[stat]
            out.append(_row(job, kind, comparison, f"{m.name}.{stat}", b, n, t, p=p,
                            n_base=None if xb is None else len(xb), n_now=len(xn),
                            verdict=verdict if verdict else (None if p is not None else "info"), **common))
    return out


def _mean(x):
    return None if x is None else (float(np.mean(x)) if len(x) else float("nan"))


def _q95(x):
    return None if x is None else (float(np.quantile(x, 0.95)) if len(x) else float("nan"))


def throughput(manifest: dict) -> tuple[float | None, float | None, int | None]:
    """(cases/s, elapsed s, workers) of a run's last execution that computed cases."""
    for ex in reversed(manifest.get("executions") or []):
        el, n = ex.get("elapsed_s"), ex.get("cases_run")
        if el and n:
            return n / el, el, ex.get("workers")
    return None, None, None


def compare_job(src: MetricSource, lake, job, runs: dict, base: dict | None, tp_history: list[float],
                min_s: float) -> list[dict]:
    """Every verdict row of one job (``runs``: {"fixed": run id, "fresh": run id | None, "fresh_seed"})."""
    name, kind = job.name, job.kind
    now_fixed, now_fresh = runs["fixed"], runs.get("fresh")
    m_now = lake.read_manifest(now_fixed)
    rows = []
    fresh_note = f"fresh seed {runs.get('fresh_seed')}" if now_fresh else ""
    if now_fresh:
        rows += metric_rows(src, name, kind, "seeds", now_fresh, now_fixed, note=fresh_note)
        for r in rows:
            r["seeds"] = True
    base_fixed = (base or {}).get("fixed")
    m_base = lake.read_manifest(base_fixed) if base_fixed else None
    if m_base is None:
        why = "no baseline for this job" if not base_fixed else f"baseline run {base_fixed} is not in the lake"
        rows += metric_rows(src, name, kind, "fixed", None, now_fixed, verdict="no baseline", test=why)
        if now_fresh:
            rows += metric_rows(src, name, kind, "fresh", None, now_fresh, verdict="no baseline", test=why)
        return rows
    diffs = spec_differences(m_now, m_base, ignore_seed=False, ignore_cases=False)
    if diffs:
        rows += metric_rows(src, name, kind, "fixed", base_fixed, now_fixed, verdict="not comparable",
                            test="spec differs: " + "; ".join(diffs))
    else:
        datasets = [d for d in job_module(kind).SCHEMAS if src.kept(now_fixed, d) and src.kept(base_fixed, d)]
        ra, rb, diff = src.identical(now_fixed, base_fixed, datasets)
        same = diff == 0 and ra == rb
        rows.append(_row(name, kind, "fixed", "rows", float(rb), float(ra),
                         "EXCEPT ALL both ways, non-timing columns of " + ", ".join(datasets),
                         threshold=float(diff), verdict="identical" if same else "changed", n_base=rb, n_now=ra,
                         base_run=base_fixed, now_run=now_fixed,
                         note="" if same else f"{diff} rows differ: the metrics are tested"))
        rows += metric_rows(src, name, kind, "fixed", base_fixed, now_fixed,
                            verdict="identical" if same else None, test="identical rows" if same else None)
    base_fresh = (base or {}).get("fresh")
    if now_fresh and base_fresh and lake.read_manifest(base_fresh) is not None:
        d = spec_differences(lake.read_manifest(now_fresh), lake.read_manifest(base_fresh), ignore_seed=True,
                             ignore_cases=True)
        rows += metric_rows(src, name, kind, "fresh", base_fresh, now_fresh, note=fresh_note,
                            **({"verdict": "not comparable", "test": "spec differs: " + "; ".join(d)} if d else {}))
    elif now_fresh:
        rows += metric_rows(src, name, kind, "fresh", None, now_fresh, verdict="no baseline",
                            test="the baseline night has no fresh sample of this job")
    rows.append(_throughput_row(name, kind, m_base, m_now, tp_history, min_s))
    return rows


def _throughput_row(name, kind, m_base, m_now, history, min_s) -> dict:
    tb, eb, wb = throughput(m_base)
    tn, en, wn = throughput(m_now)
    r = _row(name, kind, "throughput", "cases_per_s", tb, tn, "ratio now / baseline", direction="higher",
             base_run=m_base["run_id"], now_run=m_now["run_id"], n_base=m_base.get("n_cases"),
             n_now=m_now.get("n_cases"))
    if tb is None or tn is None:
        r.update(verdict="info", note="no timed execution")
    elif min(eb, en) < min_s:
        r.update(verdict="info", note=f"run shorter than {min_s:g} s: start-up dominates, not tested")
    elif wb != wn:
        r.update(verdict="info", note=f"workers differ ({wb} -> {wn}): not tested")
    else:
        tol, how = st.throughput_tolerance(history)
        r.update(threshold=tol, verdict=st.throughput_verdict(tb, tn, tol),
                 test=f"ratio now / baseline = {tn / tb:.3f}, tolerance +-{tol:.0%} ({how})")
    return r


def decide_all(rows: list[dict], family_alpha: float) -> tuple[float, int]:
    """Verdicts of the tested rows with alpha = family_alpha / m (Bonferroni over the m tests of the night);
    returns (per-test alpha, m)."""
    tested = [r for r in rows if r["verdict"] is None and r["p"] is not None]
    m = len(tested)
    alpha = family_alpha / max(m, 1)
    for r in tested:
        v = st.decide(r["p"], alpha, r["baseline"], r["now"], r["direction"])
        if r.get("seeds"):                # baseline = fresh sample, now = fixed seeds (same night)
            if v == "improved":
                v = "REGRESSION"
                r["note"] = (r["note"] + "; " if r["note"] else "") + "fixed seeds significantly better than a " \
                    "fresh sample: tuned to the fixed seeds?"
            elif v == "REGRESSION":
                v = "ok"
                r["note"] = (r["note"] + "; " if r["note"] else "") + \
                    "fixed seeds significantly worse than a fresh sample"
        r["verdict"], r["alpha"], r["threshold"] = v, alpha, r["p"]
    return alpha, m
