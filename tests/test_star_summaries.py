"""Per-shard star summaries (issue 13): the star report from them equals numpy over the raw ``star_cases`` rows.

Every number of ``star report`` (star_summary, Table 5, error vs observed, outcomes, stage times, robust) is
recomputed here with numpy from the Parquet files (pyarrow, no SQL, no dualsight code), and compared: counts and
rates exactly, means to 1e-12 relative.  Both report paths are checked: the summaries (runs made now) and the full
scan (runs made before the summaries existed, simulated by running the job with the dataset switched off, and runs
whose summaries file is damaged).
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from dualsight.errors import InputError
from dualsight.jobs.kinds import star
from dualsight.jobs.reports import star as star_report
from dualsight.jobs.kinds import star_summaries as ss
from dualsight.jobs.cli.main import main
from dualsight.warehouse.lake import Lake

ARCSEC_PER_RAD = 180 * 3600 / np.pi
RUN_ARGS = ["--preset", "paper", "--cases", "300", "--seed", "5", "--workers", "1", "--no-progress",
            "--shard-size", "50"]


def _run(lake: Path, run: str, *extra) -> None:
    assert main(["star", "run", *RUN_ARGS, "--lake", str(lake), "--run", run, *extra]) == 0


def _run_without_summaries(lake: Path, run: str) -> None:
    """A run as the code made it before the summaries: the job kind without the dataset (in-process worker)."""
    real = star.compute_shard
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(star, "SCHEMAS", {k: v for k, v in star.SCHEMAS.items() if k != ss.DATASET})
        mp.setattr(star, "compute_shard",
                   lambda spec, ids, ctx: {k: v for k, v in real(spec, ids, ctx).items() if k != ss.DATASET})
        _run(lake, run)


@pytest.fixture(scope="module")
def lakes(tmp_path_factory):
    """old: a lake with one run made without summaries (no star_summaries view at all);
    mixed: a copy of it plus a run with summaries, and one without the robust method on noisy frames (nulls in
    status_robust, the robust columns and t_robust_ns; t_detect_ns not null)."""
    old = tmp_path_factory.mktemp("old")
    _run_without_summaries(old, "old")
    mixed = tmp_path_factory.mktemp("mixed") / "lake"
    shutil.copytree(old, mixed)
    _run(mixed, "new")
    cfg = tmp_path_factory.mktemp("cfg") / "norobust.toml"
    cfg.write_text('preset = "noisy"\ncompare_robust = false\nbatch_size = 8\n')
    assert main(["star", "run", "--config", str(cfg), "--cases", "40", "--seed", "2", "--workers", "1",
                 "--no-progress", "--shard-size", "10", "--lake", str(mixed), "--run", "norobust"]) == 0
    return {"old": old, "mixed": mixed}


# ------------------------------------------------------------------------ the independent computation
def _raw(lake: Path, run: str, dataset: str = "star_cases") -> pa.Table:
    files = sorted((lake / dataset / f"run={run}").glob("part-*.parquet"))
    return pa.concat_tables([pq.read_table(f) for f in files])


def _cols(t: pa.Table) -> dict:
    """name -> (values, valid): numpy arrays, nulls filled with a placeholder and marked in ``valid``."""
    out = {}
    for name in t.column_names:
        col = t.column(name)
        if pa.types.is_fixed_size_list(col.type):
            continue
        valid = ~pc.is_null(col).to_numpy(zero_copy_only=False).astype(bool)
        fill = "" if pa.types.is_string(col.type) else (False if pa.types.is_boolean(col.type) else 0)
        v = col.fill_null(fill).to_numpy(zero_copy_only=False)
        out[name] = (v.astype(np.float64) if v.dtype.kind == "f" else v, valid)   # float32 rows: sums in double
    return out


def _mean(c, name, sel=None, f=lambda v: v):
    v, ok = c[name]
    keep = ok if sel is None else ok & sel
    if not keep.any():
        return None
    x = f(v[keep])
    if x.dtype.kind in "iub":
        return int(x.astype(np.int64).sum()) / int(keep.sum())
    return float(x.mean())


def _rate(c, name, value, sel=None):
    v, ok = c[name]
    keep = ok if sel is None else ok & sel
    return None if not keep.any() else int((v[keep] == value).sum()) / int(keep.sum())


def _distinct(*cols) -> list[tuple]:
    """Distinct combinations of the values of equal-length string arrays (numpy, no loop over rows)."""
    u = np.unique(np.stack([np.asarray(c, dtype=str) for c in cols], 1), axis=0)
    return [tuple(str(v) for v in r) for r in u]


def expected(t: pa.Table) -> dict:
    """The whole star report from the rows, with numpy: {"summary": {column: value}, table name: [row tuples]}."""
    c = _cols(t)
    n = t.num_rows
    st, _ = c["status"]
    succ = st == "success"
    rob, rob_ok = c["status_robust"]
    arc = lambda v: None if v is None else v * ARCSEC_PER_RAD  # noqa: E731
    err = lambda name, sel: arc(_mean(c, name, sel, np.abs))  # noqa: E731
    x, y, z = (c[f"err_{a}_rad"][0] for a in "xyz")
    rss = np.sqrt(x * x + y * y + z * z)
    s = {
        "cases": n, "success_rate": _rate(c, "status", "success"),
        "confident_wrong_rate": _rate(c, "status", "confident_wrong"),
        "no_solution_rate": _rate(c, "status", "no_solution"),
        "identification_rate": _mean(c, "id_correct"),
        "robust_success_rate": _rate(c, "status_robust", "success"),
        "robust_confident_wrong_rate": _rate(c, "status_robust", "confident_wrong"),
        "robust_no_solution_rate": _rate(c, "status_robust", "no_solution"),
        "robust_identification_rate": _mean(c, "id_correct_robust"),
        "mean_stars_generated": _mean(c, "n_generated", succ), "mean_stars_observed": _mean(c, "n_observed", succ),
        "mean_T": _mean(c, "T", succ),
        "mean_err_x_arcsec": err("err_x_rad", succ), "mean_err_y_arcsec": err("err_y_rad", succ),
        "mean_err_z_arcsec": err("err_z_rad", succ),
        "mean_stars_generated_all": _mean(c, "n_generated"),
        "sky_share_ge3_stars": _mean(c, "n_generated", f=lambda v: v >= 3),
        "sky_share_ge4_stars": _mean(c, "n_generated", f=lambda v: v >= 4),
        "mean_ms_per_case": _mean(c, "t_total_ns") / 1e6,
    }
    out = {"summary": s}
    out["star_table5"] = [("Stars generated", s["mean_stars_generated"]), ("Stars observed", s["mean_stars_observed"]),
                          ("T", s["mean_T"]), ("eps_x (arcsec)", s["mean_err_x_arcsec"]),
                          ("eps_y (arcsec)", s["mean_err_y_arcsec"]), ("eps_z (arcsec)", s["mean_err_z_arcsec"])]
    nobs, _ = c["n_observed"]
    rows = []
    for k in np.unique(nobs[succ]):
        sel = succ & (nobs == k)
        rows.append((int(k), int(sel.sum()), err("err_x_rad", sel), err("err_y_rad", sel), err("err_z_rad", sel),
                     float(rss[sel].mean()) * ARCSEC_PER_RAD))
    out["star_error_vs_observed"] = rows
    keys = sorted(((a, b or None) for a, b in _distinct(st, np.where(rob_ok, rob, ""))),
                  key=lambda k: (k[0], k[1] is None, k[1] or ""))   # status_robust "" never occurs: null
    rows = []
    for a, b in keys:
        sel = (st == a) & ((rob == b) & rob_ok if b is not None else ~rob_ok)
        rows.append((a, b, int(sel.sum()), _mean(c, "T", sel), _mean(c, "n_generated", sel),
                     _mean(c, "n_observed", sel)))
    out["star_status"] = sorted(rows, key=lambda r: -r[2])        # stable: ties keep (status, status_robust) order
    total = _mean(c, "t_total_ns")
    rows = []
    for stage, col in (("sample", "t_sample_ns"), ("render", "t_render_ns"), ("detect", "t_detect_ns"),
                       ("identify", "t_identify_ns"), ("attitude", "t_attitude_ns"), ("robust method", "t_robust_ns")):
        m = _mean(c, col)
        rows.append((stage, None if m is None else m / 1e6, None if m is None else (m / 1e6) / (total / 1e6)))
    out["star_stage_times"] = sorted(rows, key=lambda r: (r[1] is None, -(r[1] or 0), r[0]))
    rsel = rob_ok
    rsucc = rob_ok & (rob == "success")
    out["star_robust"] = [
        ("reference (paper)", s["success_rate"], s["confident_wrong_rate"], s["no_solution_rate"],
         s["identification_rate"], s["mean_err_x_arcsec"], s["mean_err_y_arcsec"], s["mean_err_z_arcsec"]),
        ("robust (dualsight)", _rate(c, "status_robust", "success", rsel),
         _rate(c, "status_robust", "confident_wrong", rsel), _rate(c, "status_robust", "no_solution", rsel),
         _mean(c, "id_correct_robust", rsel), err("err_x_robust_rad", rsucc), err("err_y_robust_rad", rsucc),
         err("err_z_robust_rad", rsucc))]
    return out


# ------------------------------------------------------------------------ comparison
def _same(got, want, what: str):
    col = what.rsplit(".", 1)[-1]
    exact = col.endswith("_rate") or col.startswith("sky_share")      # k / n: the same double both ways
    if want is None or got is None:
        assert got is None and want is None, (what, got, want)
    elif isinstance(want, str) or isinstance(want, (int, np.integer)) and not isinstance(want, bool):
        assert got == want, (what, got, want)
    elif math.isnan(want):
        assert math.isnan(got), (what, got, want)
    elif exact:
        assert got == want, (what, got, want)
    else:
        assert got == pytest.approx(want, rel=1e-12, abs=0), (what, got, want)


def assert_report_equals(rep: dict, exp: dict):
    """Every number of ``rep`` (star_report.build) equals the numpy value in ``exp``."""
    assert set(rep["summary"]) == set(exp["summary"])
    for k, v in exp["summary"].items():
        _same(rep["summary"][k], v, k)
    for name in ("star_table5", "star_error_vs_observed", "star_status", "star_stage_times", "star_robust"):
        cols, rows = rep["tables"][name]
        want = exp[name]
        assert len(rows) == len(want), (name, rows, want)
        for r, w in zip(rows, want):
            for col, g, e in zip(cols, r, w):         # Table 5's reference column is not compared (zip stops)
                _same(g, e, f"{name}.{col}")


# ------------------------------------------------------------------------ tests
def test_summaries_report_equals_numpy_over_the_rows(lakes):
    lake = Lake(lakes["mixed"])
    exp = expected(_raw(lakes["mixed"], "new"))
    rep = star_report.build(lake, "new")
    assert rep["source"] == "summaries"
    assert_report_equals(rep, exp)
    assert exp["summary"]["success_rate"] > 0.9 and len(exp["star_error_vs_observed"]) > 5


def test_full_scan_equals_numpy_and_the_summaries(lakes):
    lake = Lake(lakes["mixed"])
    exp = expected(_raw(lakes["mixed"], "new"))
    scan = star_report.build(lake, "new", source="scan")
    assert scan["source"] == "scan"
    assert_report_equals(scan, exp)
    summ = star_report.build(lake, "new", source="summaries")
    assert summ["json"]["cases"] == scan["json"]["cases"] == 300
    assert [r[:3] for r in summ["tables"]["star_status"][1]] == [r[:3] for r in scan["tables"]["star_status"][1]]


def test_nulls_robust_off_and_detect_timed(lakes):
    """compare_robust = false (status_robust and robust columns null), noisy frames (t_detect_ns timed): the
    summaries keep SQL's null rules (avg over non-null values; all-null -> NULL)."""
    t = _raw(lakes["mixed"], "norobust")
    assert t.column("status_robust").null_count == t.num_rows and t.column("t_detect_ns").null_count == 0
    exp = expected(t)
    assert exp["summary"]["robust_success_rate"] is None
    for source in ("auto", "scan"):
        rep = star_report.build(Lake(lakes["mixed"]), "norobust", source=source)
        assert rep["source"] == ("summaries" if source == "auto" else "scan")
        assert_report_equals(rep, exp)


def test_run_made_before_the_summaries_falls_back_to_the_scan(lakes):
    for root in (lakes["old"], lakes["mixed"]):     # alone (no star_summaries view) and beside runs that have them
        lake = Lake(root)
        assert not (root / ss.DATASET / "run=old").exists()
        assert ss.DATASET not in lake.read_manifest("old")["datasets"]
        assert not star_report.summaries_complete(lake, "old")
        rep = star_report.build(lake, "old")
        assert rep["source"] == "scan"
        assert_report_equals(rep, expected(_raw(root, "old")))
        with pytest.raises(InputError, match="no complete star_summaries"):
            star_report.build(lake, "old", source="summaries")
    # the same cases (same seed and plan) as the run with summaries: every non-timing number is the same
    old = star_report.build(Lake(lakes["mixed"]), "old")["json"]
    new = star_report.build(Lake(lakes["mixed"]), "new")["json"]
    for k in ("cases", "success_rate", "confident_wrong_rate", "identification_rate", "sky_share_ge4_stars"):
        assert old[k] == new[k]
    for k in ("mean_T", "mean_stars_observed"):
        assert old[k] == pytest.approx(new[k], rel=1e-12)


def test_damaged_summaries_file_falls_back_to_the_scan(lakes, tmp_path):
    root = tmp_path / "lake"
    shutil.copytree(lakes["mixed"], root)
    victim = root / ss.DATASET / "run=new" / "part-000003.parquet"
    victim.write_bytes(b"not parquet")
    lake = Lake(root)
    assert not star_report.summaries_complete(lake, "new")
    rep = star_report.build(lake, "new")
    assert rep["source"] == "scan"
    assert_report_equals(rep, expected(_raw(root, "new")))


def test_summaries_rows_are_exact_partial_aggregates(lakes):
    """Each shard's summary (as written) against numpy over that shard's rows; shards add up to the run."""
    root = lakes["mixed"]
    files = sorted((root / "star_cases" / "run=new").glob("part-*.parquet"))
    assert len(files) == 6
    total = 0
    for f in files:
        cases = pq.read_table(f)
        packed = pq.read_table(root / ss.DATASET / "run=new" / f.name)
        assert packed.schema.remove_metadata().equals(ss.SCHEMA)
        summ = ss.unpack(packed)
        c = _cols(cases)
        st, _ = c["status"]
        rob, rob_ok = c["status_robust"]
        nobs, _ = c["n_observed"]
        assert summ.num_rows == len(_distinct(st, np.where(rob_ok, rob, ""), nobs.astype(str)))
        assert sum(summ.column("cases").to_pylist()) == cases.num_rows
        for row in summ.to_pylist():
            sel = (st == row["status"]) & (nobs == row["n_observed"]) & (
                (rob == row["status_robust"]) & rob_ok if row["status_robust"] is not None else ~rob_ok)
            assert row["cases"] == int(sel.sum())
            assert row["sum_T"] == int(c["T"][0][sel].sum()) and row["n_T"] == int(sel.sum())
            assert row["sum_ge4_stars"] == int((c["n_generated"][0][sel] >= 4).sum())
            assert row["t_total_sum_ns"] == int(c["t_total_ns"][0][sel].sum())
            assert row["sum_abs_err_z_rad"] == pytest.approx(float(np.abs(c["err_z_rad"][0][sel]).sum()),
                                                      rel=1e-12, nan_ok=True)
        total += cases.num_rows
    assert total == 300
    # merging the shards' rows in Python gives the summary of the concatenated rows
    whole = ss.unpack(ss.summarize(_raw(root, "new")))
    merged = ss.merge(ss.unpack(_raw(root, "new", ss.DATASET).select(ss.SCHEMA.names)))
    assert merged.num_rows == whole.num_rows
    for name in ss.WIDE_SCHEMA.names:
        a, b = merged.column(name).to_pylist(), whole.column(name).to_pylist()
        if pa.types.is_floating(ss.WIDE_SCHEMA.field(name).type):
            assert a == pytest.approx(b, rel=1e-12, nan_ok=True)
        else:
            assert a == b, name


def test_summarize_null_and_nan_semantics():
    """Synthetic rows: nulls are left out of sums and counts, an all-null group sums to null, NaN propagates."""
    t = pa.table({
        "status": ["success", "success", "no_solution", "success"],
        "status_robust": [None, None, "success", None],
        "n_observed": pa.array([5, 5, 2, 6], pa.int32()),
        "id_correct": [True, False, None, True], "id_correct_robust": pa.array([None] * 4, pa.bool_()),
        "n_generated": pa.array([5, 6, 2, 3], pa.int32()), "T": pa.array([3, 4, 0, 1], pa.int32()),
        "err_x_rad": [1e-6, -2e-6, float("nan"), 0.0], "err_y_rad": [0.0, 1e-6, 1.0, None],
        "err_z_rad": [2e-6, 0.0, 1.0, 0.0],
        **{f"err_{a}_robust_rad": pa.array([None] * 4, pa.float64()) for a in "xyz"},
        **{f"t_{s}_ns": pa.array([10, 20, 30, 40], pa.int64()) for s in ("sample", "render", "identify",
                                                                          "attitude", "total")},
        "t_detect_ns": pa.array([None] * 4, pa.int64()), "t_robust_ns": pa.array([None, 5, None, None], pa.int64()),
    })
    s = {(r["status"], r["status_robust"], r["n_observed"]): r for r in ss.unpack(ss.summarize(t)).to_pylist()}
    assert set(s) == {("success", None, 5), ("no_solution", "success", 2), ("success", None, 6)}
    a, b, c = s[("success", None, 5)], s[("no_solution", "success", 2)], s[("success", None, 6)]
    assert (a["cases"], a["sum_id_correct"], a["n_id_correct"]) == (2, 1, 2)
    assert (b["sum_id_correct"], b["n_id_correct"]) == (None, 0)
    assert a["sum_abs_err_x_rad"] == pytest.approx(3e-6) and math.isnan(b["sum_abs_err_x_rad"])
    assert (c["sum_abs_err_y_rad"], c["n_abs_err_y_rad"]) == (None, 0)
    assert (c["sum_rss_err_rad"], c["n_rss_err_rad"]) == (None, 0)
    assert (a["t_detect_sum_ns"], a["n_t_detect_ns"]) == (None, 0)
    assert (a["t_robust_sum_ns"], a["n_t_robust_ns"]) == (5, 1)
    assert (a["sum_ge3_stars"], a["sum_ge4_stars"], c["sum_ge4_stars"]) == (2, 2, 0)
