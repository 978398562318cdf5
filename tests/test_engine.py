"""The engine and the lake under faults: identity, verification, locks, kills, damaged files, safe SQL.

Every count here is checked against an independent truth: the self-test job's rows are recomputed with
numpy (``default_rng([seed, i])``) in the test, and case counts are read back with DuckDB.
"""

from __future__ import annotations

import errno
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import duckdb
import pytest

from dualsight.errors import InputError
from dualsight.jobs.kinds import selftest
from dualsight.jobs.engine.runner import default_shard_size, run_job
from dualsight.warehouse.lake import Lake, LakeError
from dualsight.warehouse.paths import check_run_id
from dualsight.warehouse.shards import ShardInfo, verify_shard
from dualsight.warehouse.query import run_sql
from helpers import snapshot

ENV = dict(os.environ, TI_SKIP_VERSION_CHECK="ON", PYTHONUNBUFFERED="1")


def truth(seed: int, n: int, lam: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """x and k of cases 0..n-1, drawn here independently of the job's code."""
    xs, ks = np.empty(n), np.empty(n, dtype=np.int64)
    for i in range(n):
        rng = np.random.default_rng([seed, i])
        xs[i], ks[i] = rng.uniform(), rng.poisson(lam)
    return xs, ks


def counts(lake: Path, run: str) -> tuple[int, int, int]:
    """(rows, distinct case ids, item rows) of a run, read back through DuckDB."""
    _, r = run_sql(lake, f"SELECT count(*), count(DISTINCT case_id) FROM selftest_cases WHERE run = '{run}'",
                   warn=lambda m: None)
    _, r2 = run_sql(lake, f"SELECT count(*) FROM selftest_items WHERE run = '{run}'", warn=lambda m: None)
    return r[0][0], r[0][1], r2[0][0]


def assert_exact(lake: Path, run: str, seed: int, n: int):
    xs, ks = truth(seed, n)
    _, rows = run_sql(lake, f"SELECT case_id, x, k FROM selftest_cases WHERE run = '{run}' ORDER BY case_id",
                      warn=lambda m: None)
    got = np.array(rows, dtype=float).reshape(-1, 3)
    assert len(got) == n, f"{len(got)} rows for {n} cases"
    np.testing.assert_array_equal(got[:, 0], np.arange(n))
    np.testing.assert_array_equal(got[:, 1], xs)
    np.testing.assert_array_equal(got[:, 2], ks)
    assert counts(lake, run) == (n, n, int(ks.sum()))


def cli(*args, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dualsight", *args], capture_output=True, text=True, env=ENV,
                          timeout=timeout)


# ============================================================================================ lake
def test_shard_write_is_atomic_when_the_writer_fails(tmp_path, monkeypatch):
    lake = Lake(tmp_path)
    spec = selftest.spec_from_dict({})
    t0 = selftest.compute_shard(spec, np.arange(0, 5), None)
    lake.write_shard(ShardInfo("r1", "h", 0, 0, 5), t0, "selftest_cases", selftest.SCHEMAS)
    real = pq.write_table
    calls = []

    def failing(table, path, **kw):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(table, path, **kw)

    monkeypatch.setattr(pq, "write_table", failing)
    with pytest.raises(OSError):
        lake.write_shard(ShardInfo("r1", "h", 1, 5, 10), selftest.compute_shard(spec, np.arange(5, 10), None),
                         "selftest_cases", selftest.SCHEMAS)
    assert not list(tmp_path.rglob(".part-*"))
    assert lake.shard_indices_on_disk("r1", list(selftest.SCHEMAS)) == {0}
    assert lake.verify_shard(ShardInfo("r1", "h", 0, 0, 5), list(selftest.SCHEMAS), "selftest_cases") is None


def test_verify_shard_names_every_kind_of_damage(tmp_path):
    lake = Lake(tmp_path)
    spec = selftest.spec_from_dict({"seed": 4})
    info = ShardInfo("r", "abc", 2, 50, 75)
    lake.write_shard(info, selftest.compute_shard(spec, np.arange(50, 75), None), "selftest_cases",
                     selftest.SCHEMAS)
    p = lake.shard_path("selftest_cases", "r", 2)
    assert verify_shard(p, info, "selftest_cases", primary=True) is None
    assert "spec_hash" in verify_shard(p, ShardInfo("r", "xyz", 2, 50, 75), "selftest_cases", primary=True)
    assert "case_start" in verify_shard(p, ShardInfo("r", "abc", 2, 40, 75), "selftest_cases", primary=True)
    assert "run_id" in verify_shard(p, ShardInfo("q", "abc", 2, 50, 75), "selftest_cases", primary=True)
    # a file with the right metadata but a dropped row
    t = pq.read_table(p)
    pq.write_table(t.slice(1), p)
    assert "rows" in verify_shard(p, info, "selftest_cases", primary=True)
    # right metadata and row count, wrong case ids
    ids = t.column("case_id").to_numpy().copy()
    ids[3] = 9999
    pq.write_table(t.set_column(0, "case_id", pa.array(ids)), p)
    assert "case ids" in verify_shard(p, info, "selftest_cases", primary=True)
    p.write_bytes(p.read_bytes()[:200])
    assert "unreadable" in verify_shard(p, info, "selftest_cases", primary=True)


@pytest.mark.parametrize("bad", ["", "x\n", "../x", "a/b", "x" * 65, "a b", "é", ".", ".."])
def test_run_ids_are_checked_in_full(bad):
    with pytest.raises(InputError):
        check_run_id(bad)


def test_default_shard_size_depends_on_the_case_count_only():
    assert default_shard_size(200) == 25
    assert default_shard_size(8000) == 1000
    assert default_shard_size(10**7) == 1000
    assert default_shard_size(10**9) == 10**5          # at most ~10^4 shards
    assert -(-10**9 // default_shard_size(10**9)) == 10**4


def test_a_kind_with_slow_cases_caps_its_shards(tmp_path, monkeypatch):
    assert default_shard_size(2000, 25) == 25               # 80 shards instead of 8 of 250
    assert default_shard_size(100, 25) == 25
    assert default_shard_size(2000, 7) == 7
    assert default_shard_size(10**9, 25) == 10**5           # the cap never makes more than ~10^4 shards
    from dualsight.jobs.kinds import selftest
    monkeypatch.setattr(selftest, "MAX_SHARD_CASES", 10, raising=False)
    m = run_job("selftest", {"seed": 1}, n_cases=100, lake=Lake(tmp_path), run_id="r", workers=1, progress=False)
    assert (m["shard_size"], m["n_shards"]) == (10, 10)     # the runner plans with the kind's cap
    ids = duckdb.sql(f"SELECT case_id FROM read_parquet('{tmp_path}/{selftest.PRIMARY}/**/*.parquet') ORDER BY 1")
    assert [r[0] for r in ids.fetchall()] == list(range(100))


# ============================================================================================ identity
def test_same_id_with_another_spec_is_refused_and_nothing_is_written(tmp_path):
    lake = Lake(tmp_path)
    run_job("selftest", {"seed": 1}, n_cases=100, lake=lake, run_id="r", workers=1, progress=False)
    before = snapshot(tmp_path)
    for spec, n in (({"seed": 2}, 100), ({"seed": 1}, 120), ({"seed": 1, "lam": 4.0}, 100)):
        with pytest.raises(InputError, match="other settings"):
            run_job("selftest", spec, n_cases=n, lake=lake, run_id="r", workers=1, progress=False)
    with pytest.raises(InputError, match="shard"):
        run_job("selftest", {"seed": 1}, n_cases=100, lake=lake, run_id="r", shard_size=7, workers=1,
                progress=False)
    after = snapshot(tmp_path)
    after.pop("_locks/r.lock", None), before.pop("_locks/r.lock", None)
    assert after == before
    assert_exact(tmp_path, "r", 1, 100)


def test_lost_manifest_then_another_seed_is_refused_same_spec_resumes(tmp_path):
    lake = Lake(tmp_path)
    run_job("selftest", {"seed": 1}, n_cases=300, lake=lake, run_id="r", workers=1, progress=False)
    lake.manifest_path("r").unlink()
    with pytest.raises(InputError, match="another spec"):
        run_job("selftest", {"seed": 2}, n_cases=300, lake=lake, run_id="r", workers=1, progress=False)
    with pytest.raises(InputError, match="another spec"):
        run_job("selftest", {"seed": 1}, n_cases=299, lake=lake, run_id="r", workers=1, progress=False)
    m = run_job("selftest", {"seed": 1}, n_cases=300, lake=lake, run_id="r", workers=2, progress=False)
    assert m["status"] == "complete" and m["executions"][-1]["resumed_shards"] == m["n_shards"]
    assert_exact(tmp_path, "r", 1, 300)


def test_default_run_ids_differ_per_spec(tmp_path):
    lake = Lake(tmp_path)
    a = run_job("selftest", {"seed": 1}, n_cases=50, lake=lake, workers=1, progress=False)
    b = run_job("selftest", {"seed": 2}, n_cases=50, lake=lake, workers=1, progress=False)
    assert a["run_id"] != b["run_id"] and a["spec_hash"] in a["run_id"]
    assert_exact(tmp_path, a["run_id"], 1, 50)
    assert_exact(tmp_path, b["run_id"], 2, 50)


def test_every_shard_carries_run_hash_and_case_range(tmp_path):
    lake = Lake(tmp_path)
    m = run_job("selftest", {"seed": 5}, n_cases=130, lake=lake, run_id="r", shard_size=50, workers=1,
                progress=False)
    for s, (a, b) in enumerate([(0, 50), (50, 100), (100, 130)]):
        for d in selftest.SCHEMAS:
            meta = json.loads(pq.read_metadata(lake.shard_path(d, "r", s)).metadata[b"dualsight"])
            assert (meta["run_id"], meta["spec_hash"], meta["case_start"], meta["case_stop"]) == ("r", m["spec_hash"],
                                                                                                   a, b)


# ============================================================================================ damage
def test_damaged_shard_is_named_left_out_and_repaired(tmp_path):
    lake = Lake(tmp_path)
    run_job("selftest", {"seed": 1}, n_cases=200, lake=lake, run_id="bad", shard_size=25, workers=1, progress=False)
    run_job("selftest", {"seed": 2}, n_cases=80, lake=lake, run_id="good", workers=1, progress=False)
    p = lake.shard_path("selftest_items", "bad", 3)
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])               # truncated
    warnings = []
    _, rows = run_sql(tmp_path, "SELECT count(*) FROM selftest_items WHERE run = 'good'", warn=warnings.append)
    xs, ks = truth(2, 80)
    assert rows[0][0] == ks.sum()                                        # the other run is unaffected
    assert any("part-000003" in w and "bad" in w for w in warnings)
    from dualsight.jobs.engine.lakecheck import check_lake

    rep = {r["run"]: r for r in check_lake(lake)}
    assert rep["bad"]["damaged_shards"] == [3] and rep["bad"]["found"] == 175 and rep["good"]["verdict"] == "ok"
    rep = {r["run"]: r for r in check_lake(lake, repair=True, workers=1)}
    assert rep["bad"]["verdict"] == "repaired" and rep["bad"]["found_after"] == 200
    assert_exact(tmp_path, "bad", 1, 200)


def test_garbage_manifest_is_named_and_repaired(tmp_path):
    lake = Lake(tmp_path)
    run_job("selftest", {"seed": 3}, n_cases=60, lake=lake, run_id="m", workers=1, progress=False)
    run_job("selftest", {"seed": 4}, n_cases=60, lake=lake, run_id="other", workers=1, progress=False)
    for garbage in (b"\x00\xff garbage", b"[1, 2]", b'{"run_id": "m"}', b"{" * 10000):
        lake.manifest_path("m").write_bytes(garbage)
        r = cli("runs", "--lake", str(tmp_path))
        assert r.returncode == 0 and "DAMAGED" in r.stdout and "Traceback" not in r.stderr
        r = cli("sql", "SELECT count(*) FROM selftest_cases WHERE run = 'other'", "--lake", str(tmp_path), "--csv")
        assert r.returncode == 0 and r.stdout.splitlines()[1] == "60" and "Traceback" not in r.stderr
        with pytest.raises(LakeError, match="damaged"):
            run_job("selftest", {"seed": 3}, n_cases=60, lake=lake, run_id="m", workers=1, progress=False)
    r = cli("lake", "check", "--repair", "--lake", str(tmp_path))
    assert r.returncode == 0, r.stdout + r.stderr
    assert_exact(tmp_path, "m", 3, 60)


def test_files_copied_into_the_lake_are_not_counted(tmp_path):
    lake = Lake(tmp_path)
    run_job("selftest", {"seed": 1}, n_cases=50, lake=lake, run_id="r", workers=1, progress=False)
    src = lake.shard_path("selftest_cases", "r", 0)
    (src.parent / "part-000999.parquet").write_bytes(src.read_bytes())      # a duplicate planted by hand
    pq.write_table(pa.table({"case_id": [7]}), src.parent / "part-000998.parquet")
    assert_exact(tmp_path, "r", 1, 50)


SQL_ESCAPES = [
    "SELECT * FROM read_csv('/etc/passwd')",
    "SELECT * FROM read_text('/etc/hostname')",
    "SELECT * FROM glob('/*')",
    "COPY (SELECT 1) TO '/tmp/dualsight-escape.csv'",
    "COPY (SELECT 0::BIGINT AS case_id) TO '{lake}/selftest_cases/run=r/part-000050.parquet'",
    "ATTACH '/tmp/dualsight-escape.db' AS x",
    "INSTALL httpfs",
    "LOAD httpfs",
    "SET enable_external_access = true",
    "CREATE TABLE t AS SELECT 1",
    "SELECT 1; COPY (SELECT 1) TO '/tmp/dualsight-escape2.csv'",
    "EXPORT DATABASE '/tmp/dualsight-escape-db'",
    "SELECT * FROM read_parquet('/etc/*.parquet')",
    "PRAGMA enable_profiling",
]


@pytest.mark.parametrize("query", SQL_ESCAPES)
def test_sql_cannot_escape_the_views(tmp_path, query):
    lake = Lake(tmp_path)
    run_job("selftest", {"seed": 1}, n_cases=30, lake=lake, run_id="r", workers=1, progress=False)
    before = snapshot(tmp_path)
    with pytest.raises(InputError):
        run_sql(tmp_path, query.format(lake=tmp_path))
    assert snapshot(tmp_path) == before
    assert not Path("/tmp/dualsight-escape.csv").exists() and not Path("/tmp/dualsight-escape2.csv").exists()
    assert_exact(tmp_path, "r", 1, 30)


# ============================================================================================ concurrency
def test_one_writer_per_run(tmp_path):
    lake = Lake(tmp_path)
    with lake.lock("r"):
        with pytest.raises(LakeError, match="being written"):
            run_job("selftest", {"seed": 1}, n_cases=20, lake=lake, run_id="r", workers=1, progress=False)
    run_job("selftest", {"seed": 1}, n_cases=20, lake=lake, run_id="r", workers=1, progress=False)
    assert_exact(tmp_path, "r", 1, 20)


def test_concurrent_runs_into_one_lake_and_same_id_refused(tmp_path):
    procs = [subprocess.Popen([sys.executable, "-m", "dualsight", "selftest", "run", "--cases", "400", "--seed",
                               str(s), "--run", f"c{s}", "--lake", str(tmp_path), "--workers", "1",
                               "--shard-size", "20", "--sleep-ms", "1", "--no-progress"], env=ENV,
                              stderr=subprocess.PIPE, text=True) for s in (1, 2)]
    time.sleep(1.0)
    dup = cli("selftest", "run", "--cases", "400", "--seed", "9", "--run", "c1", "--lake", str(tmp_path),
              "--workers", "1", "--no-progress")
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    assert dup.returncode == 2 and ("being written" in dup.stderr or "other settings" in dup.stderr)
    assert_exact(tmp_path, "c1", 1, 400)
    assert_exact(tmp_path, "c2", 2, 400)


# ============================================================================================ kills
def _start(tmp_path, run="k", n=600, workers=1, sleep_ms=2, shard=20, seed=1):
    return subprocess.Popen([sys.executable, "-m", "dualsight", "selftest", "run", "--cases", str(n), "--seed",
                             str(seed), "--run", run, "--lake", str(tmp_path), "--workers", str(workers),
                             "--shard-size", str(shard), "--sleep-ms", str(sleep_ms), "--no-progress"], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


@pytest.mark.slow
def test_sigkill_at_random_moments_20_resumes(tmp_path):
    """SIGKILL the whole run (parent and workers) at random moments; each rerun resumes. The final lake
    has every case exactly once, equal to the independent draw."""
    rnd = random.Random(12345)
    kills = 0
    for attempt in range(60):
        p = _start(tmp_path, workers=2 if attempt % 3 == 0 else 1)
        try:
            p.wait(timeout=rnd.uniform(0.4, 1.6))
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            kills += 1
            if kills >= 20:
                break
            continue
        assert p.returncode == 0, p.stderr.read()
        if kills >= 20:
            break
        # finished before the kill: start over in a fresh run folder to reach 20 kills
        run_sql(tmp_path, "SELECT 1", warn=lambda m: None)
        assert_exact(tmp_path, "k", 1, 600)
        import shutil

        shutil.rmtree(tmp_path)
        tmp_path.mkdir()
    assert kills >= 20
    p = _start(tmp_path)
    assert p.wait(timeout=120) == 0, p.stderr.read()
    assert_exact(tmp_path, "k", 1, 600)
    from dualsight.jobs.engine.lakecheck import check_lake

    (row,) = check_lake(Lake(tmp_path))
    assert (row["requested"], row["found"], row["duplicated"], row["verdict"]) == (600, 600, 0, "ok")


def _workers_of(pid: int) -> list[int]:
    """Spawned worker processes of ``pid`` (not its multiprocessing resource tracker)."""
    out = subprocess.run(["pgrep", "-P", str(pid)], capture_output=True, text=True).stdout.split()
    return [int(x) for x in out if "spawn_main" in Path(f"/proc/{x}/cmdline").read_bytes().decode(errors="replace")]


def test_sigterm_stops_workers_within_5_s_and_marks_interrupted(tmp_path):
    p = _start(tmp_path, n=2000, workers=2, sleep_ms=5)
    deadline = time.time() + 30
    while time.time() < deadline and not Lake(tmp_path).read_journal("k"):
        time.sleep(0.1)
    workers = _workers_of(p.pid)
    assert workers
    p.send_signal(signal.SIGTERM)
    p.wait(timeout=10)
    t0 = time.time()
    while time.time() - t0 < 5 and any(Path(f"/proc/{w}").exists() for w in workers):
        time.sleep(0.05)
    assert not any(Path(f"/proc/{w}").exists() and "zombie" not in Path(f"/proc/{w}/status").read_text().lower()
                   for w in workers)
    assert p.returncode == 130 and "interrupted" in p.stderr.read()
    assert Lake(tmp_path).read_manifest("k")["status"] == "interrupted"
    p = _start(tmp_path, n=2000, workers=2, sleep_ms=5)
    assert p.wait(timeout=120) == 0
    assert_exact(tmp_path, "k", 1, 2000)


def test_killed_worker_is_recomputed_never_duplicated(tmp_path):
    p = _start(tmp_path, n=400, workers=2, sleep_ms=10)
    deadline = time.time() + 30
    while time.time() < deadline and not _workers_of(p.pid):
        time.sleep(0.1)
    time.sleep(1.5)
    victims = [w for w in _workers_of(p.pid)]
    os.kill(victims[0], signal.SIGKILL)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert "worker process died" in err
    assert Lake(tmp_path).read_manifest("k")["status"] == "complete"
    assert_exact(tmp_path, "k", 1, 400)


def test_full_disk_is_a_clean_error_and_earlier_shards_stay(tmp_path, monkeypatch):
    lake = Lake(tmp_path)
    real = Lake.write_shard
    calls = []

    def full(self, info, *a, **k):
        calls.append(info.shard)
        if len(calls) > 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.root))
        return real(self, info, *a, **k)

    monkeypatch.setattr(Lake, "write_shard", full)
    with pytest.raises(LakeError, match="No space left"):
        run_job("selftest", {"seed": 1}, n_cases=200, lake=lake, run_id="r", shard_size=25, workers=1,
                progress=False)
    assert lake.read_manifest("r")["status"] == "interrupted"
    monkeypatch.setattr(Lake, "write_shard", real)
    _, rows = run_sql(tmp_path, "SELECT count(*), count(DISTINCT case_id) FROM selftest_cases")
    assert rows[0] == (75, 75)
    m = run_job("selftest", {"seed": 1}, n_cases=200, lake=lake, run_id="r", workers=1, progress=False)
    assert m["executions"][-1]["resumed_shards"] == 3
    assert_exact(tmp_path, "r", 1, 200)


def test_unwritable_lake_is_one_line(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    r = cli("selftest", "run", "--cases", "10", "--lake", str(blocker / "lake"), "--no-progress")
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "cannot write to the lake" in r.stderr


def test_taichi_is_not_initialised_at_import():
    code = ("import dualsight.jobs.kinds.star, dualsight.kernels.starfield, dualsight.kernels.detect, sys;"
            "from dualsight.kernels import taichi_runtime; print(taichi_runtime.is_initialised())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=ENV)
    assert out.stdout.strip() == "False"


def _rss_when_running(tmp_path, n: int, run: str) -> int:
    """Resident memory (kB) of a run's coordinating process once its first shards are done."""
    p = subprocess.Popen([sys.executable, "-m", "dualsight", "selftest", "run", "--cases", str(n), "--run", run,
                          "--lake", str(tmp_path), "--workers", "1", "--shard-size", "20", "--sleep-ms", "1",
                          "--no-progress"], env=ENV, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.time() + 60
        while time.time() < deadline and len(Lake(tmp_path).read_journal(run)) < 5:
            time.sleep(0.1)
        status = Path(f"/proc/{p.pid}/status").read_text()
        return int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmRSS")))
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()


def test_planning_a_billion_cases_takes_the_memory_of_a_thousand(tmp_path):
    small = _rss_when_running(tmp_path, 1000, "small")
    huge = _rss_when_running(tmp_path, 10**9, "huge")
    assert huge < 1.15 * small + 5000, (small, huge)
    m = Lake(tmp_path).read_manifest("huge")
    assert m["n_cases"] == 10**9 and m["n_shards"] == 5 * 10**7


@pytest.fixture
def ro_mount(tmp_path):
    """``(source, mountpoint, set_ro)``: a bind mount of a folder that the test can switch to read-only."""
    src, mnt = tmp_path / "src", tmp_path / "mnt"
    src.mkdir(), mnt.mkdir()
    if subprocess.run(["mount", "--bind", str(src), str(mnt)], capture_output=True).returncode != 0:
        pytest.skip("cannot bind-mount here (needs root); the full-disk test covers the write-failure path")

    def set_ro(ro: bool):
        opt = "remount,bind,ro" if ro else "remount,bind,rw"
        assert subprocess.run(["mount", "-o", opt, str(mnt)], capture_output=True).returncode == 0

    yield src, mnt, set_ro
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_read_only_lake_is_a_clean_error_stays_readable_and_resumes(ro_mount):
    """A lake remounted read-only after a run was SIGKILLed mid-way: queries still work, writing (a new run,
    the resume) is one line, the run reads "stopped"; remounted read-write, the same command completes it."""
    src, mnt, set_ro = ro_mount
    run_job("selftest", {"seed": 2}, n_cases=100, lake=Lake(mnt), run_id="done", workers=1, progress=False)
    p = _start(mnt, run="r", n=1000, sleep_ms=5)
    deadline = time.time() + 30
    while time.time() < deadline and len(Lake(mnt).read_journal("r")) < 3:
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    set_ro(True)
    assert_exact(mnt, "done", 2, 100)
    for run, n in (("new", 10), ("r", 1000)):
        r = cli("selftest", "run", "--cases", str(n), "--lake", str(mnt), "--run", run, "--shard-size", "20",
                "--sleep-ms", "5", "--workers", "1", "--no-progress")
        assert r.returncode == 2 and "Read-only file system" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
    r = cli("runs", "--lake", str(mnt))
    assert r.returncode == 0 and "stopped" in r.stdout
    set_ro(False)
    p = _start(mnt, run="r", n=1000, sleep_ms=5)
    assert p.wait(timeout=120) == 0
    assert_exact(mnt, "r", 1, 1000)


@pytest.mark.parametrize("kind", ["star", "star_track", "rendezvous"])
@pytest.mark.parametrize("text, cases", [("1", 1), ("1000000000", 10**9), ("0", None), ("1000000001", None),
                                         ("-3", None), ("true", None), ("2.0", None), ('"many"', None)])
def test_the_case_count_of_a_config_is_an_integer_in_1_to_1e9(kind, text, cases, tmp_path):
    """A config file's ``cases`` (the documented range [1, 1e9]; a bool or a float is not a count) is checked the
    same way by every Monte Carlo kind (jobs/engine/specs.seed_and_case_count), and the error names the file, not
    ``--cases``; a ``--seed`` flag replaces the file's seed."""
    import importlib

    module = {"star": "dualsight.jobs.kinds.star", "star_track": "dualsight.jobs.kinds.star_track",
              "rendezvous": "dualsight.jobs.kinds.rendezvous_spec"}[kind]
    resolve_spec = importlib.import_module(module).resolve_spec
    f = tmp_path / "c.toml"
    f.write_text(f"seed = 3\ncases = {text}\n")
    if cases is not None:
        spec, n = resolve_spec(None, f, seed=11)
        assert n == cases and (spec if isinstance(spec, dict) else spec.to_dict())["seed"] == 11
    else:
        with pytest.raises(InputError) as e:
            resolve_spec(None, f, seed=11)
        assert str(f) in str(e.value) and "[1, 1e9]" in str(e.value) and "--cases" not in str(e.value)
