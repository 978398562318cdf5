"""`dualsight replay` for every job kind, cases chosen by SQL; recordings read back with rerun's own reader
(``rerun.chunk.RrdReader``) and their entities and values checked against the lake's rows."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dualsight.jobs.cli import main
from dualsight.jobs.runner import run_job
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import run_sql

rerun_chunk = pytest.importorskip("rerun.chunk")


def read_rrd(path: Path) -> dict[str, list[dict]]:
    """{entity path: [rows as dicts]} of a recording, via rerun's RrdReader (timestamps left out)."""
    out: dict[str, list[dict]] = {}
    for ch in rerun_chunk.RrdReader(str(path)).stream().to_chunks():
        rb = ch.to_record_batch()
        keep = [n for n in rb.schema.names if n not in ("log_time", "rerun.controls.RowId")]
        out.setdefault(ch.entity_path, []).extend(rb.select(keep).to_pylist())
    return out


def column(rows: list[dict], suffix: str):
    return [v for r in rows for k, v in r.items() if k.endswith(suffix)]


@pytest.fixture(scope="module")
def star_lake(tmp_path_factory):
    lake = tmp_path_factory.mktemp("lake")
    assert main(["star", "run", "--preset", "paper", "--cases", "40", "--seed", "3", "--lake", str(lake), "--run", "s",
                 "--workers", "1", "--no-progress"]) == 0
    return lake


def test_star_cases_chosen_by_sql_are_recorded_with_their_numbers(star_lake, tmp_path):
    _, rows = run_sql(star_lake, "SELECT case_id, n_observed, status FROM star_cases WHERE run = 's' "
                                 "AND n_observed >= 12 ORDER BY case_id LIMIT 3")
    assert len(rows) == 3
    out = tmp_path / "rec"
    assert main(["replay", "--lake", str(star_lake), "--run", "s", "--where", "n_observed >= 12", "--limit", "3",
                 "-o", str(out)]) == 0
    for case_id, n_obs, status in rows:
        rec = read_rrd(out / f"s-case{case_id}.rrd")
        assert "/camera/image" in rec
        pts = column(rec["/camera/image/detections"], "Points2D:positions")
        assert len(pts[0]) == n_obs                       # every detection of the row is drawn
        text = column(rec["/case"], "TextDocument:text")[0][0]
        assert f"star case {case_id}" in text and status in text


def test_a_tampered_row_or_seed_fails_the_replay(star_lake, tmp_path, capsys):
    lake2 = tmp_path / "lake2"
    shutil.copytree(star_lake, lake2)
    m = json.loads((lake2 / "_manifests" / "s.json").read_text())
    m["spec"]["seed"] = 4
    (lake2 / "_manifests" / "s.json").write_text(json.dumps(m))
    assert main(["replay", "--lake", str(lake2), "--run", "s", "--case", "5", "-o", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err
    assert "does not reproduce" in err and "in the lake" in err and "recomputed" in err


def test_prox_case_recording_has_the_blob_and_its_numbers(tmp_path):
    from dualsight.jobs import prox

    spec = prox.resolve_spec("paper", None, orientations=1)
    run_job("prox_sweep", spec, n_cases=11, lake=Lake(tmp_path / "l"), run_id="p", workers=1, progress=False)
    _, rows = run_sql(tmp_path / "l", "SELECT case_id, cob_x_px, cob_y_px, paper_range_est_m FROM prox_cases "
                                      "WHERE run = 'p' AND found ORDER BY true_range_m LIMIT 1")
    case_id, cx, cy, rng = rows[0]
    out = tmp_path / "p.rrd"
    assert main(["replay", "--lake", str(tmp_path / "l"), "--run", "p", "--case", str(case_id), "-o", str(out)]) == 0
    rec = read_rrd(out)
    cob = column(rec["/camera/image/cob"], "Points2D:positions")[0][0]
    np.testing.assert_allclose(cob, [cx, cy], rtol=0, atol=1e-3)       # stored as float32 by rerun
    assert "/camera/image/axes" in rec and "/camera/image/blob" in rec
    val = column(rec["/metrics/paper_range_m"], "Scalars:scalars")[0]
    assert val[0] == pytest.approx(rng, rel=1e-12)


def test_selftest_and_predicate_errors(tmp_path, capsys):
    run_job("selftest", {"seed": 1}, n_cases=50, lake=Lake(tmp_path / "l"), run_id="t", workers=1, progress=False)
    _, rows = run_sql(tmp_path / "l", "SELECT count(*) FROM selftest_cases WHERE run = 't' AND k >= 5")
    out = tmp_path / "many"
    assert main(["replay", "--lake", str(tmp_path / "l"), "--run", "t", "--where", "k >= 5", "--limit", "1000",
                 "-o", str(out)]) == 0
    assert len(list(out.glob("*.rrd"))) == rows[0][0] > 0
    for bad in ("nosuchcolumn > 1", "1=1; COPY (SELECT 1) TO '/tmp/x.csv'"):
        assert main(["replay", "--lake", str(tmp_path / "l"), "--run", "t", "--where", bad, "-o",
                     str(tmp_path / "z")]) == 2
    assert main(["replay", "--lake", str(tmp_path / "l"), "--run", "t", "--case", "3", "-o",
                 str(tmp_path / "no" / "such" / "x.rrd")]) == 2
    assert not (tmp_path / "no").exists()


def test_hil_star_frame_is_reread_verified_and_recorded(tmp_path):
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    import test_hil_star as th

    if not th.ESA.is_dir():
        pytest.skip(f"real ESA frames not found in {th.ESA}")
    spec = th._esa_spec()
    run_job("hil_star", spec, n_cases=8, lake=Lake(tmp_path / "l"), run_id="h", workers=1, progress=False)
    _, rows = run_sql(tmp_path / "l", "SELECT s.case_id, count(*) FROM hil_star_stars s WHERE s.run = 'h' "
                                      "AND s.x_px IS NOT NULL GROUP BY ALL ORDER BY 1 LIMIT 1")
    case_id, n_stars = rows[0]
    out = tmp_path / "h.rrd"
    assert main(["replay", "--lake", str(tmp_path / "l"), "--run", "h", "--case", str(case_id), "-o", str(out)]) == 0
    rec = read_rrd(out)
    assert "/camera/image" in rec
    assert len(column(rec["/camera/image/detections"], "Points2D:positions")[0]) == n_stars
    assert "HIP" in str(column(rec["/camera/image/detections"], "Points2D:labels")[0])
