"""`dualsight replay` for every job kind, cases chosen by SQL; recordings read back with rerun's own reader
(``rerun.chunk.RrdReader``) and their entities and values checked against the lake's rows."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from dualsight.jobs.cli.main import main
from dualsight.jobs.engine.runner import run_job
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import run_sql
from helpers import esa_spec, shared_real

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
def star_lake(make_lake):
    return make_lake("lake", ["star", "run", "--preset", "paper", "--cases", "40", "--seed", "3", "--run", "s"])


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
    from dualsight.jobs.kinds import prox

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
    esa = shared_real() / "esa_tetra3"
    if not esa.is_dir():
        pytest.skip(f"real ESA frames not found in {esa}")
    spec = esa_spec()
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


# ------------------------------------------------------------------------------------------ issue 10, point 5
def _tamper(lake: Path, run: str, dataset: str, case_id: int, column_name: str, value) -> None:
    """Rewrite one stored value in a shard file, as a hostile edit would, and fix the journal's byte count
    so that the lake still serves the file (the replay, not the size check, must catch it)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    for f in sorted((lake / dataset / f"run={run}").glob("*.parquet")):
        t = pq.read_table(f)
        ids = t.column("case_id").to_numpy()
        if case_id not in ids:
            continue
        col = t.column(column_name).to_pylist()
        col[int(np.flatnonzero(ids == case_id)[0])] = value
        t = t.set_column(t.schema.get_field_index(column_name), t.schema.field(column_name),
                         pa.array(col, type=t.schema.field(column_name).type))
        pq.write_table(t, f)
        journal = lake / "_manifests" / f"{run}.shards.jsonl"
        lines = [json.loads(x) for x in journal.read_text().splitlines()]
        for e in lines:
            if e["case_start"] <= case_id < e["case_stop"]:
                e["bytes"][dataset] = f.stat().st_size
        journal.write_text("".join(json.dumps(e) + "\n" for e in lines))
        return
    raise AssertionError(f"case {case_id} not found")


@pytest.mark.parametrize("column_name,delta", [("image_digest", 1), ("err_x_rad", 1e-9)])
def test_a_tampered_stored_metric_fails_the_replay_naming_it(star_lake, tmp_path, capsys, column_name, delta):
    lake2 = tmp_path / "lake2"
    shutil.copytree(star_lake, lake2)
    _, rows = run_sql(lake2, f"SELECT {column_name} FROM star_cases WHERE run = 's' AND case_id = 7")
    old = rows[0][0]
    new = old + delta if isinstance(old, int) else float(np.float32(old + delta))   # errors are stored float32
    assert new != old
    _tamper(lake2, "s", "star_cases", 7, column_name, new)
    _, rows = run_sql(lake2, f"SELECT {column_name} FROM star_cases WHERE run = 's' AND case_id = 7")
    assert rows[0][0] == new                             # the lake serves the tampered value
    assert main(["replay", "--lake", str(lake2), "--run", "s", "--case", "7", "-o", str(tmp_path / "x.rrd")]) == 2
    err = capsys.readouterr().err
    assert f"column {column_name} is {new!r} in the lake, {old!r} recomputed" in err
    assert main(["replay", "--lake", str(lake2), "--run", "s", "--case", "6", "-o", str(tmp_path / "y.rrd")]) == 0


def test_star_recording_has_magnitudes_and_both_attitudes(star_lake, tmp_path):
    from dualsight.jobs.kinds import star

    from dualsight.scene.attitude import euler123_to_dcm, quat_to_dcm

    _, rows = run_sql(star_lake, "SELECT case_id, [theta1_rad, theta2_rad, theta3_rad], q_est FROM star_cases "
                                 "WHERE run = 's' AND status = 'success' ORDER BY case_id LIMIT 1")
    case_id, theta, q_est = rows[0]
    A_true, A_est = euler123_to_dcm(np.asarray([theta]))[0], quat_to_dcm(np.asarray(q_est))[0]   # float32 rows
    _, hips = run_sql(star_lake, f"SELECT hip_assigned FROM star_detections WHERE run = 's' AND case_id = {case_id} "
                                 "AND accepted ORDER BY det_index")
    out = tmp_path / "c.rrd"
    assert main(["replay", "--lake", str(star_lake), "--run", "s", "--case", str(case_id), "-o", str(out)]) == 0
    rec = read_rrd(out)
    np.testing.assert_allclose(np.asarray(column(rec["/attitude/true"], "Arrows3D:vectors")[0]),
                               np.reshape(A_true, (3, 3)), atol=1e-6)
    np.testing.assert_allclose(np.asarray(column(rec["/attitude/estimated"], "Arrows3D:vectors")[0]),
                               np.reshape(A_est, (3, 3)), atol=1e-6)
    labels = column(rec["/camera/image/detections"], "Points2D:labels")[0]
    spec, _ = star.resolve("paper", None)
    cat = star.make_context(spec).catalog
    vmag = dict(zip(cat.hip.tolist(), cat.vmag.tolist()))
    assert len(hips) >= 3
    for (hip,) in hips:
        assert any(lab.startswith(f"HIP {hip} V{vmag[hip]:.2f}") for lab in labels), hip
    assert column(rec["/metrics/err_x_arcsec"], "Scalars:scalars")


def test_a_trajectory_replays_as_one_recording_on_the_frame_time_line(tmp_path):
    from dualsight.jobs.kinds import prox

    spec = prox.resolve_spec("paper", None, job="trajectory", frames=8)
    run_job("prox_trajectory", spec, n_cases=8, lake=Lake(tmp_path / "l"), run_id="tr", workers=1, progress=False)
    _, rows = run_sql(tmp_path / "l", "SELECT case_id, true_x_m, true_y_m, true_z_m FROM prox_cases "
                                      "WHERE run = 'tr' AND case_id % 2 = 0 ORDER BY case_id")
    out = tmp_path / "traj.rrd"
    assert main(["replay", "--lake", str(tmp_path / "l"), "--run", "tr", "--where", "case_id % 2 = 0", "-o",
                 str(out)]) == 0
    rec = read_rrd(out)
    true_rows = rec["/scene/true"]
    assert [r["frame"] for r in true_rows] == [r[0] for r in rows]        # one point per frame, at its frame
    got = np.array([column([r], "Points3D:positions")[0][0] for r in true_rows])
    np.testing.assert_allclose(got, np.array([r[1:] for r in rows]), rtol=1e-6, atol=1e-6)
    assert len(rec["/camera/image"]) == len(rows)


def test_a_tampered_hil_image_digest_fails_the_replay(tmp_path, capsys):
    esa = shared_real() / "esa_tetra3"
    if not esa.is_dir():
        pytest.skip(f"real ESA frames not found in {esa}")
    spec = esa_spec()
    run_job("hil_star", spec, n_cases=2, lake=Lake(tmp_path / "l"), run_id="h", workers=1, progress=False)
    _, rows = run_sql(tmp_path / "l", "SELECT image_digest FROM hil_star WHERE run = 'h' AND case_id = 1")
    _tamper(tmp_path / "l", "h", "hil_star", 1, "image_digest", rows[0][0] ^ 1)
    assert main(["replay", "--lake", str(tmp_path / "l"), "--run", "h", "--case", "1", "-o",
                 str(tmp_path / "h.rrd")]) == 2
    assert f"column image_digest is {rows[0][0] ^ 1}" in capsys.readouterr().err
