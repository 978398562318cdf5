"""Per-star rows off above a case count (issue 24, point 5): ``[output] detections`` and ``star run --detections``.

One lake, two runs of the same 30 paper cases: ``auto`` (the bound lowered to 20 cases, so "auto" drops the
detections) and ``on`` (``--detections on``).  Truth is independent of the report code: numpy over the raw
``star_cases`` Parquet files, and the twin run's stored ``star_detections`` rows (pyarrow).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from dualsight.errors import ConfigError
from dualsight.jobs.cli.main import main
from dualsight.warehouse.lake import Lake

CASES, SEED, BOUND = 30, 5, 20
TIMING = ("t_",)


def _toml(folder: Path, text: str) -> Path:
    p = folder / "out.toml"
    p.write_text(text)
    return p


@pytest.fixture(scope="module")
def lake(tmp_path_factory, make_lake):
    cfg = _toml(tmp_path_factory.mktemp("cfg"), f"[output]\ndetections_max_cases = {BOUND}\n")
    base = ["star", "run", "--config", str(cfg), "--cases", str(CASES), "--seed", str(SEED), "--shard-size", "10"]
    root = make_lake("switch", [*base, "--run", "auto"], [*base, "--run", "on", "--detections", "on"])
    return root, cfg


def _table(root: Path, dataset: str, run: str) -> pa.Table:
    files = sorted((root / dataset / f"run={run}").glob("part-*.parquet"))
    return pa.concat_tables([pq.read_table(f) for f in files])


def _columns(t: pa.Table) -> dict:
    return {c: t.column(c).to_numpy(zero_copy_only=False) for c in t.column_names if not c.startswith(TIMING)}


def _rows(t: pa.Table) -> list:
    """Non-timing cells of every row, NaN as a string (so that equal rows compare equal)."""
    def norm(v):
        if isinstance(v, float) and v != v:
            return "nan"
        return [norm(x) for x in v] if isinstance(v, list) else v
    cols = [c for c in t.column_names if not c.startswith(TIMING)]
    return [tuple(norm(r[c]) for c in cols) for r in t.select(cols).to_pylist()]


def test_auto_above_the_bound_writes_no_detections(lake):
    root, _ = lake
    m_auto, m_on = Lake(root).read_manifest("auto"), Lake(root).read_manifest("on")
    assert not (root / "star_detections" / "run=auto").exists()
    assert "star_detections" not in m_auto["datasets"] and "star_detections" in m_on["datasets"]
    assert m_auto["spec"]["output"] == {"detections": "off"} and "output" not in m_on["spec"]
    assert m_auto["spec_hash"] != m_on["spec_hash"]
    assert _table(root, "star_detections", "on").num_rows == int(_table(root, "star_cases", "on")
                                                                   .column("n_observed").to_numpy().sum())
    # the cases themselves are the same rows with or without the per-star detail
    a, b = _table(root, "star_cases", "auto"), _table(root, "star_cases", "on")
    assert a.column_names == b.column_names and _rows(a) == _rows(b)


def test_auto_resolves_against_the_run_case_count():
    """At the bound the rows are kept (the canonical spec is the one a run had before the switch), one above
    they are not; "on"/"off" whatever the count; the TOML's own ``cases`` does not decide, the run's does."""
    from dualsight.jobs.kinds import star

    table = {"cases": 5, "output": {"detections_max_cases": BOUND}}
    spec_at, _ = star.resolve_spec(None, table, cases=BOUND)
    spec_above, _ = star.resolve_spec(None, table, cases=BOUND + 1)
    spec_plain, _ = star.resolve_spec(None, None, cases=BOUND)
    assert "output" not in spec_at and spec_at == spec_plain
    assert spec_above["output"] == {"detections": "off"}
    assert "output" not in star.resolve_spec(None, table, cases=10**6, detections="on")[0]
    assert star.resolve_spec(None, None, cases=1, detections="off")[0]["output"] == {"detections": "off"}
    # default bound: 100,000 cases
    assert "output" not in star.resolve_spec(None, None, cases=100_000)[0]
    assert star.resolve_spec(None, None, cases=100_001)[0]["output"] == {"detections": "off"}


def test_star_report_numbers_from_star_cases_alone(lake, capsys):
    root, _ = lake
    reports = {}
    for run in ("auto", "on"):
        assert main(["star", "report", "--lake", str(root), "--run", run, "--json"]) == 0
        reports[run] = json.loads(capsys.readouterr().out)
    js = reports["auto"]
    c = _columns(_table(root, "star_cases", "auto"))
    arcsec = 180 * 3600 / np.pi
    status = c["status"]
    succ = status == "success"
    assert js["cases"] == CASES == len(status)
    assert js["success_rate"] == pytest.approx(succ.mean(), abs=1e-12)
    assert js["confident_wrong_rate"] == pytest.approx((status == "confident_wrong").mean(), abs=1e-12)
    assert js["mean_T"] == pytest.approx(c["T"][succ].mean(), rel=1e-12)
    assert js["mean_stars_observed"] == pytest.approx(c["n_observed"][succ].mean(), rel=1e-12)
    assert js["mean_stars_generated"] == pytest.approx(c["n_generated"][succ].mean(), rel=1e-12)
    for axis in "xyz":
        e = np.abs(c[f"err_{axis}_rad"][succ].astype(np.float64)) * arcsec
        assert js["mean_error_arcsec"][axis] == pytest.approx(e.mean(), rel=1e-6)
    # every number but the blob breakdown is the run-with-detections report's
    on = reports["on"]
    assert "detections_per_successful_case" in on and "detections_per_successful_case" not in js
    assert "detections_note" in js and "detections_note" not in on
    strip = {"run", "detections_per_successful_case", "detections_note", "mean_ms_per_case"}
    assert {k: v for k, v in js.items() if k not in strip} == {k: v for k, v in on.items() if k not in strip}
    # the text report says it in one line, with how to get the rows
    assert main(["star", "report", "--lake", str(root), "--run", "auto"]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if "not kept" in ln]
    assert len(lines) == 1 and "--detections on" in lines[0] and "dualsight replay" in lines[0]
    assert "Traceback" not in out


def test_replay_of_a_run_without_detections_recomputes_them(lake, tmp_path):
    """The replay verifies the case against its star_cases row, and the detections it recomputes are the rows the
    twin run stored (every non-timing column)."""
    from dualsight.jobs.kinds import star
    from dualsight.jobs.replay.cases import recompute_case

    root, _ = lake
    case = 13
    out = tmp_path / "c.rrd"
    assert main(["replay", "--lake", str(root), "--run", "auto", "--case", str(case), "-o", str(out)]) == 0
    assert out.stat().st_size > 0
    *_, fresh_out, fresh = recompute_case(Lake(root), "auto", case, star, "star_cases", ("star",))
    stored = _table(root, "star_detections", "on")
    stored = stored.filter(pa.compute.equal(stored.column("case_id"), case))
    again = fresh_out["tables"]["star_detections"]
    assert again.num_rows == stored.num_rows == fresh["n_observed"] > 0
    assert again.column_names == stored.column_names and _rows(again) == _rows(stored)


def test_resume_refuses_to_mix_and_resumes_alike(lake, tmp_path, capsys):
    import shutil

    root, cfg = lake
    work = tmp_path / "lake"
    shutil.copytree(root, work)
    base = ["star", "run", "--config", str(cfg), "--cases", str(CASES), "--seed", str(SEED), "--lake", str(work),
            "--workers", "1", "--no-progress"]
    for run, flag in (("auto", "on"), ("on", "off"), ("on", "auto")):
        assert main([*base, "--run", run, "--detections", flag]) == 2
        err = [ln for ln in capsys.readouterr().err.strip().splitlines() if ln.startswith("dualsight:")]
        assert len(err) == 1 and "other settings" in err[0] and "spec keys output" in err[0], err
    assert not (work / "star_detections" / "run=auto").exists()
    # the same settings resume: every shard kept (none recomputed for a missing star_detections file)
    assert main([*base, "--run", "auto"]) == 0
    ex = Lake(work).read_manifest("auto")["executions"][-1]
    assert ex["resumed_shards"] == 3 and ex["recomputed_shards"] == 0
    # a shard's detections file removed from the run that keeps them: that shard is recomputed
    (work / "star_detections" / "run=on" / "part-000001.parquet").unlink()
    assert main([*base, "--run", "on", "--detections", "on"]) == 0
    ex = Lake(work).read_manifest("on")["executions"][-1]
    assert ex["resumed_shards"] == 2 and ex["recomputed_shards"] == 1


def test_nightly_metrics_without_detections(lake):
    """The nightly's centroid metric says "not kept" for a run without star_detections and tests nothing; the other
    metrics are read from star_cases; with no run of the lake keeping them the query still runs."""
    import shutil

    from dualsight.jobs.nightly.compare import MetricSource, metric_rows
    from dualsight.warehouse.query import connect

    root, _ = lake
    rows = {}
    for label, drop in (("mixed", False), ("none", True)):
        lk = root
        if drop:
            lk = root.parent / f"{root.name}-nodet"
            if not lk.exists():
                shutil.copytree(root, lk)
                shutil.rmtree(lk / "star_detections")
                for p in (lk / "_manifests").glob("*.json"):        # as if no run had kept them
                    m = json.loads(p.read_text())
                    m["datasets"] = [d for d in m["datasets"] if d != "star_detections"]
                    p.write_text(json.dumps(m))
        con = connect(lk, warn=lambda m: None)
        try:
            rows[label] = {r["metric"]: r for r in metric_rows(MetricSource(con, Lake(lk)), "j", "star", "fixed",
                                                               "on", "auto")}
        finally:
            con.close()
    for r in rows.values():
        for stat in ("mean", "p95"):
            c = r[f"centroid_err_px.{stat}"]
            assert c["verdict"] == "info" and c["test"] == "not kept" and "auto" in c["note"]
        succ = r["success_rate"]
        assert succ["n_now"] == succ["n_baseline"] == CASES and succ["test"] != "not kept"
    # both runs keep them: the centroid metric is measured
    con = connect(root, warn=lambda m: None)
    try:
        r = {x["metric"]: x for x in metric_rows(MetricSource(con, Lake(root)), "j", "star", "fixed", "on", "on")}
    finally:
        con.close()
    assert r["centroid_err_px.mean"]["test"] != "not kept" and r["centroid_err_px.mean"]["now"] < 0.5


def test_bad_values_one_line_exit_2(tmp_path, capsys):
    from dualsight.jobs.kinds import star

    assert main(["star", "run", "--cases", "5", "--detections", "maybe", "--lake", str(tmp_path / "l")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--detections" in err[0] and "'maybe'" in err[0]
    for text, key in (("[output]\ndetections = \"sometimes\"\n", "output.detections"),
                      ("[output]\ndetections_max_cases = -1\n", "output.detections_max_cases"),
                      ("[output]\ndetections_max_cases = 1.5\n", "output.detections_max_cases"),
                      ("[output]\nkeep = true\n", "output.keep")):
        cfg = _toml(tmp_path, text)
        assert main(["star", "run", "--config", str(cfg), "--cases", "5", "--lake", str(tmp_path / "l")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(cfg) in err[0] and key in err[0] and "Traceback" not in err[0], err
    assert not (tmp_path / "l").exists() or not any((tmp_path / "l").rglob("*.parquet"))
    with pytest.raises(ConfigError, match=r"output\.detections"):
        star.spec_from_dict({"camera": {"width": 64, "height": 64, "pixel_pitch_um": 5.0, "focal_length_mm": 10.0},
                             "output": {"detections": True}})


def test_runs_lists_the_runs_without_per_star_rows(lake, capsys):
    root, _ = lake
    assert main(["runs", "--lake", str(root)]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "not kept" in ln]
    assert len(lines) == 1 and lines[0].endswith(": auto")
