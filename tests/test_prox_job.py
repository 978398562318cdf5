"""Proximity jobs end to end: sweep and trajectory into the lake, Table 3 SQL, replay, video, bad input."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from dualsight.jobs.cli import main
from dualsight.warehouse.query import run_sql

RANGES = ["1.585", "6.31", "25.12"]


def _snapshot(root):
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def lake(tmp_path_factory):
    root = tmp_path_factory.mktemp("prox")
    assert main(["prox", "sweep", "--preset", "accurate", "--ranges", *RANGES, "--orientations", "40",
                 "--lake", str(root), "--run", "acc", "--workers", "1", "--no-progress"]) == 0
    assert main(["prox", "trajectory", "--preset", "paper", "--frames", "12", "--lake", str(root), "--run", "traj",
                 "--workers", "1", "--no-progress", "--video", str(root / "traj.avi")]) == 0
    return root


def test_sweep_rows_and_truth(lake):
    _, rows = run_sql(lake, "SELECT count(*), count(DISTINCT case_id), avg(found::INT) FROM prox_cases "
                            "WHERE run = 'acc'")
    assert rows[0] == (120, 120, 1.0)
    # the true position is on the boresight at the requested range (independent of the pipeline)
    _, rows = run_sql(lake, "SELECT range_index, min(true_range_m), max(true_range_m), max(abs(true_x_m)) "
                            "FROM prox_cases WHERE run = 'acc' GROUP BY ALL ORDER BY 1")
    for (i, lo, hi, x), r in zip(rows, RANGES):
        assert lo == pytest.approx(float(r)) and hi == pytest.approx(float(r)) and x == 0


def test_report_json_and_accuracy(lake, capsys):
    assert main(["prox", "report", "--lake", str(lake), "--run", "acc", "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["estimator"] == "subpixel"
    for r in js["ranges"]:
        for k in ("true_range_m", "avg_est_range_m", "avg_abs_error_m", "avg_rel_error_pct", "within_min_max_pct"):
            assert k in r
        # accurate rendering + subpixel estimator: orientation ambiguity alone leaves ~4 % (DESIGN.md);
        # the reference had 7.8-20 % at these ranges
        assert r["avg_rel_error_pct"] < 8.0
        assert r["avg_rel_error_pct"] < r["reference"]["avg_rel_err_pct"]
        assert r["within_min_max_pct"] >= 85.0


def test_trajectory_follows_table2_motion(lake, capsys):
    # frame k of Table 2: p = (0, 0, 1) + k (0.02, 0.02, 0.4) m
    _, rows = run_sql(lake, "SELECT frame, true_x_m, true_y_m, true_z_m FROM prox_cases WHERE run = 'traj' "
                            "ORDER BY frame")
    for k, x, y, z in rows:
        assert (x, y, z) == pytest.approx((0.02 * k, 0.02 * k, 1 + 0.4 * k))
    assert main(["prox", "report", "--lake", str(lake), "--run", "traj", "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["summary"]["frames"] == 12 and js["summary"]["frames_found"] == 12
    assert js["summary"]["paper_mean_rel_range_err_pct"] < 25
    cap = cv2.VideoCapture(str(lake / "traj.avi"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 12


def test_replay_prox_case(lake, tmp_path):
    out = tmp_path / "c.rrd"
    assert main(["prox", "replay", "--lake", str(lake), "--run", "acc", "--case", "41", "-o", str(out)]) == 0
    assert out.stat().st_size > 1000


@pytest.mark.parametrize("toml, needle", [
    ("satellite = 'nosuch.toml'", "file not found"),
    ("orientations = 0", "orientations"),
    ("ranges_m = [0.05]", "inside the body"),
    ("mode = 'fancy'", "mode"),
    ("[sensor]\npsf_sigma_px = -1", "sensor.psf_sigma_px"),
])
def test_bad_input_leaves_lake_untouched(lake, tmp_path, capsys, toml, needle):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(toml + "\n")
    before = _snapshot(lake)
    assert main(["prox", "sweep", "--config", str(cfg), "--lake", str(lake), "--run", "bad", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert needle in err
    assert _snapshot(lake) == before


def test_bad_satellite_file_names_key(lake, tmp_path, capsys):
    sat = tmp_path / "sat.toml"
    sat.write_text("[camera]\nwidth = 1024\nheight = 768\npixel_pitch_um = 4.65\nfocal_length_mm = 6\n"
                   "light_direction = [0, 0, -1]\n[body]\nposition = [0, 0, 2]\n"
                   "[[component]]\nshape = 'pyramid'\nsize = [0.1, 0.1, 0.1]\n")
    before = _snapshot(lake)
    assert main(["prox", "sweep", "--satellite", str(sat), "--lake", str(lake), "--run", "bad2",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "component" in err and "shape" in err and str(sat) in err
    assert _snapshot(lake) == before
