"""The README, top to bottom (issue 25 point 9): every command of its ``bash`` blocks runs, in the README's
order, in a fresh folder with a fresh ``./lake``, as a newcomer would paste it, and gives what the README says
it gives. The truth each command is held to is the README's own sentence next to it, checked against the lake
by SQL, against the files written (PNG and rerun signatures, video frame counts read by OpenCV) or against
OpenCV's reference intrinsics of the chessboard photos; never against another dualsight printout.

Skipped, by name: the set-up and test commands themselves (this suite *is* ``scripts/test.sh``; the
environment is the one ``scripts/quickstart.sh`` made) and the two commands whose inputs are the reader's own
(``my_frames/``, ``night/``). A README command that is neither run nor named here fails the test, so the README
cannot grow a command this test does not run. The Python block's calls are those of ``docs/api.md``, whose
examples ``tests/test_api.py`` runs.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import cv2
import duckdb
import pytest

from helpers import ROOT, shared_real

SETUP = ["bash scripts/quickstart.sh", "bash scripts/test.sh", "source .venv/bin/activate"]
READERS_OWN = ["my_frames/", "night/ "]          # commands on the reader's own images: named, not run


def readme_commands(text: str) -> list[str]:
    """The logical command lines of the README's ``bash`` blocks, in order (backslash continuations joined;
    trailing comments kept: bash drops them)."""
    cmds = []
    for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S):
        line = ""
        for raw in block.splitlines():
            line += raw
            if line.endswith("\\"):
                line = line[:-1]
                continue
            if line.strip():
                cmds.append(" ".join(line.split()))
            line = ""
    return cmds


def rows(lake: Path, sql: str):
    """Rows of ``sql`` over the lake's Parquet files (``{ds}`` stands for a dataset's glob), by DuckDB directly."""
    con = duckdb.connect()
    try:
        return con.execute(sql.replace("{", f"read_parquet('{lake}/").replace("}", "/run=*/*.parquet', "
                                                                                 "hive_partitioning=true)")).fetchall()
    finally:
        con.close()


@pytest.fixture(scope="module")
def readme_run(tmp_path_factory):
    if not shared_real().is_dir():
        pytest.skip(f"the README's HIL commands read ../shared/data/real ({shared_real()} is absent)")
    base = tmp_path_factory.mktemp("readme")
    work = base / "newcomer"
    work.mkdir()
    (work / "examples").symlink_to(ROOT / "examples")               # the clone's examples/
    (base / "shared").symlink_to(shared_real().parents[1])          # ../shared beside it
    env = {k: v for k, v in os.environ.items() if k not in ("DUALSIGHT_LAKE",)}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["COLUMNS"] = "200"
    results, skipped = {}, []
    for cmd in readme_commands((ROOT / "README.md").read_text()):
        if cmd in SETUP or any(w in cmd for w in READERS_OWN):
            skipped.append(cmd)
            continue
        t0 = time.monotonic()
        p = subprocess.run(["bash", "-c", cmd], cwd=work, env=env, capture_output=True, text=True, timeout=900)
        results[cmd] = (p.returncode, p.stdout, p.stderr, time.monotonic() - t0)
    return work, results, skipped


def result(readme_run, start: str):
    """(exit status, stdout, stderr, seconds) of the one README command that starts with ``start``."""
    _, results, _ = readme_run
    hits = [k for k in results if k.startswith(start)]
    assert len(hits) == 1, (start, hits)
    return results[hits[0]]


def test_every_command_runs_cleanly(readme_run):
    work, results, skipped = readme_run
    assert len(results) >= 25
    bad = {c: (rc, err[-600:]) for c, (rc, out, err, _) in results.items() if rc != 0 or "Traceback" in err}
    assert not bad, bad
    # what is not run is exactly the set-up and the reader's own images
    assert len(skipped) == len(SETUP) + len(READERS_OWN), skipped
    assert set(SETUP) <= set(skipped)


def test_star_runs_give_their_cases_with_progress(readme_run):
    work, _, _ = readme_run
    rc, out, err, _ = result(readme_run, "dualsight star run --preset paper --cases 10000")
    assert re.search(r"\d+case/s", err) and re.search(r"\[\d\d:\d\d<\d\d:\d\d", err)   # progress, rate, ETA
    lake = work / "lake"
    assert rows(lake, "SELECT count(*), count(DISTINCT case_id) FROM {star_cases} WHERE run = 'big'") == [(10000, 10000)]
    assert rows(lake, "SELECT count(*) FROM {star_cases} WHERE run = 'real'") == [(1000,)]


def test_star_report_sql_and_json_agree_with_the_lake(readme_run):
    work, _, _ = readme_run
    lake = work / "lake"
    (n_ok, n), = rows(lake, "SELECT count(*) FILTER (status = 'success'), count(*) FROM {star_cases} "
                            "WHERE run = 'big'")
    rc, out, err, _ = result(readme_run, "dualsight star report --run big --json")
    doc = json.loads(out)
    assert doc["success_rate"] == pytest.approx(n_ok / n, abs=1e-12)
    rc, out, err, _ = result(readme_run, "dualsight star report --run big #")
    assert f"{100 * n_ok / n:.1f}" in out
    rc, out, err, _ = result(readme_run, "dualsight sql \"SELECT status")
    printed = {m.group(1): int(m.group(2)) for m in re.finditer(r"^\s*(\w+)\s+(\d+)\s*$", out, flags=re.M)}
    assert printed.get("success") == n_ok and sum(printed.values()) == n == 10000


def test_figures_recordings_pages_and_video(readme_run):
    work, _, _ = readme_run
    for png in ("fig9_10.png", "fig6.png", "fig8.png"):
        img = cv2.imread(str(work / png))
        assert img is not None and min(img.shape[:2]) >= 300, png
    assert (work / "case42.rrd").read_bytes()[:4] == b"RRF2"
    lake = work / "lake"
    (fails,), = rows(lake, "SELECT count(*) FROM {star_cases} WHERE run = 'big' AND status <> 'success'")
    files = sorted((work / "failures").glob("big-case*.rrd"))
    assert len(files) == min(20, fails) and all(f.read_bytes()[:4] == b"RRF2" for f in files)
    page = (work / "big.html").read_text()
    assert "<table" in page and "big" in page and "https://" not in page
    assert (work / "night.html").is_file() and (work / "trends.html").is_file()
    cap = cv2.VideoCapture(str(work / "traj.mp4"))
    (frames,), = rows(lake, "SELECT count(*) FROM {prox_cases} WHERE run = 'prox-trajectory-paper-1-50'")
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == frames == 50
    rc, out, err, _ = result(readme_run, "dualsight replay --run prox-trajectory-paper-1-50")
    assert "50 cases verified and recorded in 1 file" in err
    assert (work / "traj.rrd").read_bytes()[:4] == b"RRF2"


def test_rendezvous_and_unknown_objects(readme_run):
    work, _, _ = readme_run
    lake = work / "lake"
    # 4 approaches of the far preset, 64 frames each, every frame with a relative-state estimate
    assert rows(lake, "SELECT count(*) FROM {rendezvous_cases} WHERE run = 'rdv-far'") == [(4,)]
    assert rows(lake, "SELECT count(*), count(DISTINCT case_id) FROM {rendezvous_frames} WHERE run = 'rdv-far'") \
        == [(4 * 64, 4)]
    assert (work / "approach0.rrd").read_bytes()[:4] == b"RRF2"
    rc, out, err, _ = result(readme_run, "dualsight rendezvous report --run rdv-far")
    assert "NEES" in out and "(e)" in out
    # the unknown objects the SQL prints are the lake's rows (the README: 0-3 per ESA frame)
    (n,), = rows(lake, "SELECT count(*) FROM {hil_star_objects}")
    rc, out, err, _ = result(readme_run, "dualsight sql \"SELECT image, round(mag, 2)")
    assert rc == 0 and sum(1 for line in out.splitlines() if ".tif" in line) == n


def test_runs_lake_check_and_nightly(readme_run):
    rc, out, err, _ = result(readme_run, "dualsight runs")
    assert re.search(r"^\s*big\s+star\s+10000\b", out, flags=re.M) and re.search(r"^\s*real\s+star\s+1000\b", out,
                                                                                   flags=re.M)
    rc, out, err, _ = result(readme_run, "dualsight lake check --repair")
    verdicts = [line.split()[-1] for line in out.splitlines()[2:] if line.strip()]
    assert verdicts and set(verdicts) == {"ok"}, out
    rc, out, err, _ = result(readme_run, "dualsight nightly --suite quick --accept")
    assert rc == 0 and "accepted night" in out + err
    rc, out, err, _ = result(readme_run, "dualsight nightly --suite quick --html")       # the next night: green
    assert rc == 0 and "GREEN" in out + err


def test_proximity_commands(readme_run):
    work, _, _ = readme_run
    lake = work / "lake"
    assert rows(lake, "SELECT count(*) FROM {prox_cases} WHERE run = 'prox-sweep-paper-1-99'") == [(99,)]   # 11 x 9
    assert rows(lake, "SELECT count(*) FROM {prox_cases} WHERE run = 'prox-sweep-accurate-1-3300'") == [(3300,)]
    rc, out, err, _ = result(readme_run, "dualsight prox report --run prox-sweep-accurate-1-3300")
    assert len(re.findall(r"^\s*(1\.000|1\.585|2\.512|3\.981|6\.310|10\.000|15\.849|25\.119|39\.811|63\.096|"
                          r"100\.000)\s+300\b", out, flags=re.M)) == 11
    rc, out, err, _ = result(readme_run, "dualsight prox resolvable --size 0.1")
    assert "0.1680 m" in out and "64.52 m" in out                # the README's comment on this command


def test_hil_commands(readme_run):
    work, _, _ = readme_run
    # calibrate: OpenCV's reference intrinsics of these photos (the data folder's README): fx = fy = 535.9 px
    text = (work / "chessboard.toml").read_text()
    fx = float(re.search(r"^fx\s*=\s*([\d.]+)", text, flags=re.M).group(1))
    assert fx == pytest.approx(535.916, rel=0.005)
    rc, out, err, _ = result(readme_run, "dualsight hil star ../shared/data/real/esa_tetra3/*.tiff --camera "
                                         "examples/cameras/esa_tetra3.toml --truth")
    assert "8 images: 8 identified" in out + err
    assert len(list((work / "overlays").glob("*.png"))) == 8
    rc, out, err, _ = result(readme_run, "dualsight hil star ../shared/data/real/esa_tetra3/*.tiff --camera "
                                         "examples/cameras/esa_tetra3.toml --sweep")
    lake = work / "lake"
    runs = rows(lake, "SELECT DISTINCT run FROM {hil_star}")
    assert len(runs) >= 2
    rc, out, err, _ = result(readme_run, "dualsight hil prox ")
    assert (work / "fig8.png").is_file()
