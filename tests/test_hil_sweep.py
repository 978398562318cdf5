"""`dualsight hil star --sweep`: a grid of settings over real images as one engine job (issue 11.6)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dualsight.jobs.kinds import hil_star_sweep as sw
from dualsight.warehouse.query import run_sql

from helpers import ROOT, run_cli, shared_real

CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
ESA = shared_real() / "esa_tetra3"


def _A(ra_deg: float, dec_deg: float) -> list[float]:
    """An attitude whose boresight (third row) points at (ra, dec)."""
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    z = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z]).ravel().tolist()


def test_agreement_and_ranking_by_hand():
    # image 0: variants 0 and 1 agree (10 arcsec apart), variant 2 is 1 deg off; image 1: only variant 2 solved
    rows = [
        {"variant": 0, "image_index": 0, "identified": True, "A_est": _A(10, 20), "status": "identified"},
        {"variant": 1, "image_index": 0, "identified": True, "A_est": _A(10, 20 + 10 / 3600), "status": "identified"},
        {"variant": 2, "image_index": 0, "identified": True, "A_est": _A(10, 21), "status": "identified"},
        {"variant": 0, "image_index": 1, "identified": False, "A_est": None, "status": "no_solution"},
        {"variant": 1, "image_index": 1, "identified": False, "A_est": None, "status": "no_solution"},
        {"variant": 2, "image_index": 1, "identified": True, "A_est": _A(50, -5), "status": "identified"},
    ]
    for r in rows:
        r.update(error=None, truth_source="none", t_total_ns=10**6 * (1 + r["variant"]))
    s = {d["variant"]: d for d in sw.summarize(rows, 3, ["a", "b", "c"])}
    assert s[0]["solved_rate"] == s[1]["solved_rate"] == 0.5 and s[2]["solved_rate"] == 1.0
    # variant 2's image-0 answer disagrees with the majority, its image-1 answer is the only one (agrees)
    assert s[0]["agreement"] == s[1]["agreement"] == 1.0 and s[2]["agreement"] == 0.5
    # score = solved x agreement: 0.5, 0.5, 0.5 -> ties broken by time: a (1 ms), b (2 ms), c (3 ms)
    assert [d["label"] for d in sw.summarize(rows, 3, ["a", "b", "c"])] == ["a", "b", "c"]
    assert s[0]["success_rate"] is None and s[0]["ms_per_image"] == 1.0


def test_sweep_keys_are_checked():
    assert sw.parse_sweeps(["k-sigma=3,4", "max-stars=10"]) == [("k-sigma", [3.0, 4.0]), ("max-stars", [10])]
    assert len(sw.grid(sw.parse_sweeps(["k-sigma=3,4", "max-stars=10,20,30"]))) == 6
    assert sw.parse_sweeps(["detector=local,global"]) == [("detector", ["local", "global"])]
    for bad, msg in [("foo=1", "unknown key"), ("k-sigma=", "KEY=V1"), ("k-sigma=a", "floats"),
                     ("k-sigma=3,3", "repeated"), ("k-sigma=nan", "finite")]:
        with pytest.raises(Exception, match=msg):
            sw.parse_sweeps([bad])


def test_sweep_over_the_esa_frames_matches_single_runs_and_truth(tmp_path):
    if not ESA.is_dir():
        pytest.skip(f"real ESA frames not found in {ESA}")
    frames = sorted(ESA.glob("*.tiff"))[:4]
    truth = ESA / "truth.json"
    lake = tmp_path / "lake"
    common = ["--camera", CAMERA, "--truth", truth, "--no-compare", "--lake", lake, "--workers", "1"]
    rc, out, err = run_cli(["hil", "star", *frames, *common, "--sweep", "k-sigma=5,100", "--run", "sw", "--json"])
    assert rc == 0, err
    summary = json.loads(out)
    assert [d["label"] for d in summary][0] == "k-sigma=5"           # k 100 leaves 2 of the 4 unsolved
    _, rows = run_sql(lake, "SELECT variant, image_index, identified, ra_rad, dec_rad, stars_identified, status "
                            "FROM hil_sweep WHERE run = 'sw' ORDER BY variant, image_index")
    assert len(rows) == 2 * len(frames)
    # each variant's rows are exactly what a plain `hil star` run with those settings gives
    for v, ks in enumerate((5, 100)):
        rc, _, err = run_cli(["hil", "star", *frames, *common, "--k-sigma", ks, "--run", f"one{v}"])
        assert rc == 0, err
        _, single = run_sql(lake, f"SELECT {v}, case_id, identified, ra_rad, dec_rad, stars_identified, status "
                                  f"FROM hil_star WHERE run = 'one{v}' ORDER BY case_id")
        assert [tuple(r) for r in rows if r[0] == v] == [tuple(r) for r in single]
    # the success rate against the truth file, computed here from the rows and truth.json
    tj = json.loads(truth.read_text())
    for d in summary:
        v = d["variant"]
        ok = 0
        for r in rows:
            if r[0] != v or not r[2]:
                continue
            t = tj[frames[r[1]].name]
            z = np.array([math.cos(r[4]) * math.cos(r[3]), math.cos(r[4]) * math.sin(r[3]), math.sin(r[4])])
            ra, dec = math.radians(t["ra_deg"]), math.radians(t["dec_deg"])
            zt = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
            ok += math.degrees(math.acos(min(1.0, float(z @ zt)))) * 3600 < 100
        assert d["success_rate"] == pytest.approx(ok / len(frames))
    # the same sweep again is the same run, resumed with nothing to do
    rc, out2, _ = run_cli(["hil", "star", *frames, *common, "--sweep", "k-sigma=5,100", "--run", "sw", "--json"])
    assert rc == 0 and json.loads(out2) == summary


def test_sweep_over_the_detectors_matches_single_runs(tmp_path):
    """``--sweep detector=local,global``: each variant's row is the plain run's with ``--detector``."""
    if not ESA.is_dir():
        pytest.skip(f"real ESA frames not found in {ESA}")
    frames = sorted(ESA.glob("*.tiff"))[:1]
    lake = tmp_path / "lake"
    common = ["--camera", CAMERA, "--no-compare", "--lake", lake, "--workers", "1"]
    rc, _, err = run_cli(["hil", "star", *frames, *common, "--sweep", "detector=local,global", "--run", "sd"])
    assert rc == 0, err
    _, rows = run_sql(lake, "SELECT variant, stars_detected, ra_rad, dec_rad FROM hil_sweep WHERE run = 'sd' "
                            "ORDER BY variant")
    assert len(rows) == 2 and rows[0][1] > 2 * rows[1][1]               # the local detector finds far more
    for v, det in enumerate(("local", "global")):
        rc, _, err = run_cli(["hil", "star", *frames, *common, "--detector", det, "--run", f"d{v}"])
        assert rc == 0, err
        _, single = run_sql(lake, f"SELECT {v}, stars_detected, ra_rad, dec_rad FROM hil_star WHERE run = 'd{v}'")
        assert [tuple(r) for r in single] == [tuple(rows[v])]
