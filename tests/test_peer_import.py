"""A peer solver's answers in the lake (``jobs/kinds/peer_star.py``, dataset ``peer_star``).

Independent truths: the answers files written here by hand (every stored value must equal the value written,
angles through one degrees <-> radians conversion; the attitude matrices are built here from RA/Dec/roll by an
explicit construction, not by dualsight's code), and ``dualsight hil star`` run on two ESA frames into the
same lake, which ``peer_star`` must join frame by frame (skipped when ../shared/data/real is absent).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from dualsight.errors import InputError
from dualsight.jobs.kinds import peer_star as pi
from dualsight.jobs.engine.lakecheck import check_run
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import run_sql
from helpers import ROOT, run_cli, shared_real

CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
ESA = shared_real() / "esa_tetra3"
TRUTH = ESA / "truth.json"
needs_esa = pytest.mark.skipif(not TRUTH.exists(), reason=f"ESA tetra3 frames not found at {ESA}")


def attitude(ra_deg: float, dec_deg: float, roll_deg: float) -> list[float]:
    """ICRS -> camera (+x column, +y row, +z boresight) for a boresight and a roll = position angle of the
    image's up (-y) from north through east: built from the local east/north basis, row-major."""
    a, d, p = (math.radians(v) for v in (ra_deg, dec_deg, roll_deg))
    z = np.array([math.cos(d) * math.cos(a), math.cos(d) * math.sin(a), math.sin(d)])
    east = np.array([-math.sin(a), math.cos(a), 0.0])
    north = np.array([-math.sin(d) * math.cos(a), -math.sin(d) * math.sin(a), math.cos(d)])
    up = math.cos(p) * north + math.sin(p) * east
    y = -up
    x = np.cross(y, z)
    return [float(v) for v in np.stack([x, y, z]).ravel()]


FRAMES = [
    {"path": "/data/night/f0.tiff", "solved": True, "status": "MATCH_FOUND", "ra_deg": 230.6652617,
     "dec_deg": 11.0351960, "roll_deg": 27.716, "A": attitude(230.6652617, 11.0351960, 27.716), "stars_detected": 23,
     "stars_matched": 22, "prob_false_match": 2.24e-38, "time_ms": 47.77, "detect_ms": 44.45, "solve_ms": 3.32,
     "fov_deg": 11.4238, "residual_rms_arcsec": 6.13},
    {"path": "f1.png", "solved": True, "A": attitude(12.5, -63.25, 300.0), "stars_matched": 9, "time_ms": 80.5},
    {"path": "/data/night/f2.tiff", "solved": False, "status": "NO_MATCH", "stars_detected": 3, "time_ms": 5120.0,
     "error": None},
]


def write(path: Path, doc) -> Path:
    path.write_text(json.dumps(doc, indent=1) if not isinstance(doc, str) else doc)
    return path


def rows(lake: Path, run: str) -> list[dict]:
    cols, rs = run_sql(lake, f"SELECT * FROM peer_star WHERE run = '{run}' ORDER BY case_id")
    return [dict(zip(cols, r)) for r in rs]


# ============================================================================================ values
def test_imported_rows_equal_the_answers_file(tmp_path):
    f = write(tmp_path / "answers.json", {"method": "cedar-solve", "method_version": "0.5.1",
                                          "settings": {"database": "default_database"}, "frames": FRAMES})
    lake = tmp_path / "lake"
    m = pi.import_answers(Lake(lake), f, run_id="peer1")
    assert m["kind"] == "peer_star" and m["status"] == "complete" and m["n_cases"] == 3
    assert m["spec"]["method"] == "cedar-solve" and m["peer_version"] == "0.5.1"
    got = rows(lake, "peer1")
    assert len(got) == len(FRAMES)
    for k, (r, w) in enumerate(zip(got, FRAMES)):
        assert r["case_id"] == k and r["method"] == "cedar-solve" and r["method_version"] == "0.5.1"
        want_path = w["path"] if w["path"].startswith("/") else str(tmp_path / w["path"])
        assert r["path"] == want_path and r["image"] == Path(w["path"]).name
        assert r["solved"] is w["solved"]
        for key in ("status", "error", "stars_detected", "stars_matched", "prob_false_match", "time_ms",
                    "detect_ms", "solve_ms", "fov_deg"):
            assert r[key] == w.get(key), (k, key)
        assert r["A_est"] == w.get("A"), k
    # angles: one conversion each way
    r0, r1, r2 = got
    assert math.degrees(r0["ra_rad"]) == pytest.approx(FRAMES[0]["ra_deg"], abs=1e-12)
    assert math.degrees(r0["dec_rad"]) == pytest.approx(FRAMES[0]["dec_deg"], abs=1e-12)
    assert r0["roll_deg"] == FRAMES[0]["roll_deg"]
    assert r0["residual_rms_rad"] * 180 * 3600 / math.pi == pytest.approx(6.13, abs=1e-12)
    # A only: the boresight and roll come from A, which was built from these numbers
    assert math.degrees(r1["ra_rad"]) == pytest.approx(12.5, abs=1e-9)
    assert math.degrees(r1["dec_rad"]) == pytest.approx(-63.25, abs=1e-9)
    assert r1["roll_deg"] == pytest.approx(300.0, abs=1e-9)
    assert r2["ra_rad"] is None and r2["dec_rad"] is None and r2["roll_deg"] is None and r2["A_est"] is None


def test_the_import_is_a_run_listed_checked_and_refused_under_another_spec(tmp_path):
    f = write(tmp_path / "a.json", {"method": "cedar-solve", "frames": FRAMES})
    lake = Lake(tmp_path / "lake")
    m = pi.import_answers(lake, f)
    rid = m["run_id"]
    assert rid.startswith("peer-star-") and [x["run_id"] for x in lake.list_manifests()] == [rid]
    assert check_run(lake, rid)["verdict"] == "ok"
    assert len(lake.read_journal(rid)) == m["n_shards"]
    assert lake.spec_copy_path(rid).exists()
    again = pi.import_answers(lake, f)                       # same file: the same run, nothing rewritten
    assert again["run_id"] == rid and again["spec_hash"] == m["spec_hash"]
    assert len(rows(lake.root, rid)) == 3
    other = write(tmp_path / "b.json", {"method": "cedar-solve", "frames": FRAMES[:2]})
    with pytest.raises(InputError, match="--run.*other settings.*answers_sha256"):
        pi.import_answers(lake, other, run_id=rid)
    # the command `dualsight peer import`: one line, exit 0, and the --method check
    rc, _, err1 = run_cli(["peer", "import", other, "--lake", lake.root, "--run", "cli-run"])
    assert rc == 0 and "run cli-run" in err1
    rc, _, err2 = run_cli(["peer", "import", other, "--lake", lake.root, "--method", "tetra3"])
    assert rc == 2 and "contradicts" in err2 and len(err2.strip().splitlines()) == 1
    assert len(rows(lake.root, "cli-run")) == 2


# ============================================================================================ bad input
BAD = [
    ("frames.1.solved", lambda d: d["frames"][1].pop("solved")),
    ("frames.0.ra_deg", lambda d: d["frames"][0].update(ra_deg="230.6")),
    ("frames.0.dec_deg", lambda d: d["frames"][0].update(dec_deg=95.0)),
    ("frames.0", lambda d: d["frames"][0].update(ra_deg=FRAMES[0]["dec_deg"], dec_deg=FRAMES[0]["ra_deg"] - 180)),
    ("frames.0", lambda d: d["frames"][0].update(roll_deg=-27.716)),
    ("frames.1.A", lambda d: d["frames"][1].update(A=[1.0, 0, 0, 0, 1, 0, 0, 0])),
    ("frames.2", lambda d: d["frames"][2].update(ra_deg=10.0, dec_deg=0.0)),
    ("frames.0.colour", lambda d: d["frames"][0].update(colour="red")),
    ("frames", lambda d: d.update(frames=[])),
    ("method", lambda d: d.pop("method")),
]


@pytest.mark.parametrize("field,damage", BAD, ids=[b[0] + f"-{i}" for i, b in enumerate(BAD)])
def test_a_malformed_answers_file_is_one_line_naming_file_and_field(tmp_path, field, damage):
    doc = {"method": "cedar-solve", "frames": json.loads(json.dumps(FRAMES))}
    damage(doc)
    f = write(tmp_path / "bad answers.json", doc)
    lake = tmp_path / "lake"
    with pytest.raises(InputError) as e:
        pi.import_answers(Lake(lake), f)
    msg = str(e.value)
    assert "\n" not in msg and str(f) in msg and f"[{field}]" in msg, msg
    assert not lake.exists()                                   # nothing touched


@pytest.mark.parametrize("text,what", [("{not json", "not valid JSON"), ("[1, 2]", "JSON object"), ("", "empty")])
def test_an_unreadable_answers_file_is_one_line_naming_the_file(tmp_path, text, what):
    f = write(tmp_path / "a.json", text)
    with pytest.raises(InputError, match=what) as e:
        pi.import_answers(Lake(tmp_path / "lake"), f)
    assert str(f) in str(e.value) and "\n" not in str(e.value)


# ============================================================================================ join with hil_star
@needs_esa
def test_peer_rows_join_hil_star_frame_by_frame(tmp_path):
    """hil star on two ESA frames and a peer's answers for the same two frames (given in the other order, the
    truth file's plate solutions as the peer's numbers) in one lake: the join on the image path pairs every
    frame with its own row, and the two boresights agree within the hil_star result's error."""
    truth = json.loads(TRUTH.read_text())
    names = sorted(truth)[:2]
    lake = tmp_path / "lake"
    rc, _, err = run_cli(["hil", "star", *[ESA / n for n in names], "--camera", CAMERA, "--truth", TRUTH,
                          "--lake", lake, "--run", "ds", "--no-compare", "--no-progress", "--workers", "1"])
    assert rc == 0, err
    frames = [{"path": str(ESA / n), "solved": True, "ra_deg": truth[n]["ra_deg"], "dec_deg": truth[n]["dec_deg"],
               "roll_deg": (-truth[n]["roll_deg_tetra3"]) % 360, "stars_matched": truth[n]["matches"],
               "time_ms": 50.0 + k} for k, n in enumerate(names)][::-1]
    f = write(tmp_path / "cedar.json", {"method": "cedar-solve", "frames": frames})
    pi.import_answers(Lake(lake), f, run_id="cedar")
    cols, rs = run_sql(lake, """
        SELECT h.image, h.case_id AS h_case, p.case_id AS p_case, h.identified, p.solved, p.stars_matched,
               p.time_ms, degrees(h.ra_rad) AS h_ra, degrees(p.ra_rad) AS p_ra,
               degrees(h.dec_rad) AS h_dec, degrees(p.dec_rad) AS p_dec
        FROM hil_star h JOIN peer_star p USING (path)
        WHERE h.run = 'ds' AND p.run = 'cedar' ORDER BY h.case_id""")
    got = [dict(zip(cols, r)) for r in rs]
    assert [g["image"] for g in got] == names
    assert [(g["h_case"], g["p_case"]) for g in got] == [(0, 1), (1, 0)]
    for g in got:
        n = g["image"]
        assert g["identified"] and g["solved"] and g["stars_matched"] == truth[n]["matches"]
        assert g["p_ra"] == pytest.approx(truth[n]["ra_deg"], abs=1e-12)
        assert g["p_dec"] == pytest.approx(truth[n]["dec_deg"], abs=1e-12)
        # hil star's boresight is within 30 arcsec of the plate solution (tests/test_hil_star.py)
        cos_dec = math.cos(math.radians(g["h_dec"]))
        assert abs(g["h_ra"] - g["p_ra"]) * cos_dec * 3600 < 30 and abs(g["h_dec"] - g["p_dec"]) * 3600 < 30
    assert {g["time_ms"] for g in got} == {50.0, 51.0}
