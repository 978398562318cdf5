"""The nightly's star-tracking job (issue 22, point 5): its metrics (jobs/nightly/compare.py METRICS["star_track"],
warehouse/sql/nightly_star_track.sql) recomputed with numpy from the raw ``star_frames`` Parquet rows (pyarrow, not
the nightly's SQL): availability per sequence (share of frames within the limit), the share of sequences with a
false lock, the RMS total error per sequence; a second night on the same build is identical."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from dualsight.jobs.nightly import run as nightly
from dualsight.jobs.nightly import suite as ns
from dualsight.warehouse.lake import Lake

JOB = {"name": "track", "kind": "star_track", "cases": 6, "seed": 2,
       "spec": {"preset": "paper", "sequence": {"frames": 20, "motion": "mixed", "rate_max_deg_s": 1.0,
                                                "error_limit_arcsec": 4.0}}}
"""A 4 arcsec limit, so that some valid attitudes are false locks and availability differs from validity."""


def by(rows, comparison, metric) -> dict:
    hit = [r for r in rows if (r["job"], r["comparison"], r["metric"]) == ("track", comparison, metric)]
    assert len(hit) == 1, (comparison, metric)
    return hit[0]


def test_tracking_metrics_against_the_frame_rows(tmp_path):
    lake = Lake(tmp_path / "lake")
    suite = ns.build_suite({"name": "t", "job": [JOB]}, source="test suite", base=ns.REPO)
    first = nightly.run_nightly(suite, lake, workers=1, log=lambda m: None, accept=True, fresh_seed=5)
    assert first["exit"] == 0 and first["accepted"], first["message"]
    s = nightly.run_nightly(suite, lake, workers=1, log=lambda m: None, fresh_seed=6)
    assert s["exit"] == 0, s["message"]
    rows = s["verdicts"]
    r = by(rows, "fixed", "availability.mean")
    assert r["verdict"] == "identical"
    t = pq.read_table(lake.root / "star_frames" / f"run={r['now_run']}")
    case = t.column("case_id").to_numpy()
    within = t.column("within_limit").to_numpy(zero_copy_only=False).astype(bool)
    false = t.column("false_lock").to_numpy(zero_copy_only=False).astype(bool)
    err = np.array([np.nan if v is None else v for v in t.column("err_total_arcsec").to_pylist()])
    ids = np.unique(case)
    assert len(ids) == 6
    avail = np.array([within[case == i].mean() for i in ids])
    fl = np.array([false[case == i].any() for i in ids])
    rms = np.array([np.sqrt(np.nanmean(err[case == i] ** 2)) for i in ids])
    assert 0 < fl.sum() and avail.mean() < 1
    assert r["now"] == pytest.approx(avail.mean(), rel=1e-12)
    assert by(rows, "fixed", "false_lock_rate")["now"] == pytest.approx(fl.mean())
    assert by(rows, "fixed", "err_total_arcsec.mean")["now"] == pytest.approx(rms.mean(), rel=1e-9)
    assert by(rows, "fixed", "rows")["verdict"] == "identical"
