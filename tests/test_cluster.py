"""The engine on a real loopback Dask cluster: ``dask scheduler`` and two ``dask worker`` processes on
127.0.0.1, started by the test.  The cluster's rows must equal the in-process rows for the same seed."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dualsight.errors import InputError
from dualsight.jobs.engine.errors import EngineError
from dualsight.jobs.engine.runner import run_job
from dualsight.warehouse.lake import Lake
from dualsight.warehouse.query import run_sql
from helpers import esa_spec, hil_star_rows, shared_real

pytest.importorskip("dask.distributed")
ENV = dict(os.environ, TI_SKIP_VERSION_CHECK="ON", DUALSIGHT_TI_THREADS="1", OMP_NUM_THREADS="1")
DASK = str(Path(sys.executable).with_name("dask"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    def __init__(self, tmp: Path, workers: int = 2):
        self.port = _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.log = open(tmp / "dask.log", "w")
        self.scheduler = subprocess.Popen([DASK, "scheduler", "--host", "127.0.0.1", "--port", str(self.port),
                                           "--no-dashboard"], env=ENV, stdout=self.log, stderr=self.log)
        self.workers = [subprocess.Popen([DASK, "worker", self.address, "--nthreads", "1", "--nworkers", "1",
                                          "--no-dashboard", "--host", "127.0.0.1", "--local-directory", str(tmp)],
                                         env=ENV, stdout=self.log, stderr=self.log) for _ in range(workers)]
        from dask.distributed import Client

        deadline = time.time() + 60
        while True:
            try:
                with Client(self.address, timeout="5s") as c:
                    c.wait_for_workers(workers, timeout=60)
                break
            except (OSError, TimeoutError):
                if time.time() > deadline:
                    raise

    def close(self):
        for p in self.workers + [self.scheduler]:
            p.terminate()
        for p in self.workers + [self.scheduler]:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        self.log.close()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = Cluster(tmp_path_factory.mktemp("dask"))
    yield c
    c.close()


def rows(lake: Path, dataset: str, run: str, cols: str):
    return run_sql(lake, f"SELECT {cols} FROM {dataset} WHERE run = '{run}' ORDER BY ALL", warn=lambda m: None)[1]


def test_selftest_cluster_equals_in_process_and_two_lakes_do_not_collide(tmp_path, cluster):
    local, a, b = tmp_path / "local", tmp_path / "a", tmp_path / "b"
    run_job("selftest", {"seed": 7}, n_cases=500, lake=Lake(local), run_id="r", workers=1, progress=False)
    for lake in (a, b):       # same command, same run id, same spec, two lakes, one cluster
        m = run_job("selftest", {"seed": 7}, n_cases=500, lake=Lake(lake), run_id="r", scheduler=cluster.address,
                    shard_size=50, progress=False)
        assert m["status"] == "complete"
    want = rows(local, "selftest_cases", "r", "case_id, x, k")
    assert len(want) == 500
    for lake in (a, b):
        assert rows(lake, "selftest_cases", "r", "case_id, x, k") == want
        assert rows(lake, "selftest_items", "r", "case_id, item, y") == rows(local, "selftest_items", "r",
                                                                              "case_id, item, y")


def test_star_and_prox_on_the_cluster_equal_in_process(tmp_path, cluster):
    from dualsight.jobs.kinds import prox, star

    spec, _ = star.resolve_spec("paper", None, seed=9)
    cols = "case_id, n_generated, n_observed, T, status, q_est::VARCHAR, err_total_rad::VARCHAR"
    for where, kw in (("local", {"workers": 1}), ("dask", {"scheduler": cluster.address})):
        run_job("star", spec, n_cases=40, lake=Lake(tmp_path / where), run_id="s", shard_size=20, progress=False,
                **kw)
    assert rows(tmp_path / "local", "star_cases", "s", cols) == rows(tmp_path / "dask", "star_cases", "s", cols)
    pspec = prox.resolve_spec("paper", None, orientations=2)
    pcols = ("case_id, true_range_m, found, n_pixels, paper_range_est_m::VARCHAR, "
             "subpixel_range_est_m::VARCHAR")   # as text: NaN (not found) equals NaN
    for where, kw in (("local", {"workers": 1}), ("dask", {"scheduler": cluster.address})):
        run_job("prox_sweep", pspec, n_cases=22, lake=Lake(tmp_path / where), run_id="p", shard_size=6,
                progress=False, **kw)
    got = rows(tmp_path / "dask", "prox_cases", "p", pcols)
    assert len(got) == 22 and got == rows(tmp_path / "local", "prox_cases", "p", pcols)


def test_unreachable_scheduler_is_one_error_within_10_s(tmp_path):
    t0 = time.time()
    with pytest.raises(EngineError, match="cannot reach the Dask scheduler"):
        run_job("selftest", {"seed": 1}, n_cases=50, lake=Lake(tmp_path), run_id="r",
                scheduler=f"tcp://127.0.0.1:{_free_port()}", progress=False)
    assert time.time() - t0 < 10
    assert Lake(tmp_path).read_manifest("r") is None
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == []   # nothing written


def test_scheduler_dying_mid_run_then_resume(tmp_path):
    c = Cluster(tmp_path / "c", workers=1) if (tmp_path / "c").mkdir() is None else None
    import threading

    def kill_later():
        time.sleep(3)
        c.scheduler.kill()

    threading.Thread(target=kill_later, daemon=True).start()
    t0 = time.time()
    with pytest.raises((EngineError, InputError)):
        run_job("selftest", {"seed": 3, "sleep_ms": 20}, n_cases=1000, lake=Lake(tmp_path / "l"), run_id="r",
                scheduler=c.address, shard_size=25, progress=False)
    assert time.time() - t0 < 90
    c.close()
    m = run_job("selftest", {"seed": 3, "sleep_ms": 20}, n_cases=1000, lake=Lake(tmp_path / "l"), run_id="r",
                workers=2, progress=False)
    assert m["status"] == "complete"
    got = np.array(rows(tmp_path / "l", "selftest_cases", "r", "case_id"))[:, 0]
    np.testing.assert_array_equal(got, np.arange(1000))


def test_hil_star_on_the_cluster_equals_in_process(tmp_path, cluster):
    """The 8 real ESA frames (shards of 3 images) on the loopback cluster: every image and star row equal the
    in-process run's, timing columns excepted."""
    esa = shared_real() / "esa_tetra3"
    if not esa.is_dir():
        pytest.skip(f"real ESA frames not found in {esa}")
    spec = esa_spec()
    run_job("hil_star", spec, n_cases=8, lake=Lake(tmp_path / "local"), run_id="h", workers=1, progress=False)
    m = run_job("hil_star", spec, n_cases=8, lake=Lake(tmp_path / "dask"), run_id="h", shard_size=3,
                scheduler=cluster.address, progress=False)
    assert m["status"] == "complete" and m["n_shards"] == 3
    a, b = hil_star_rows(tmp_path / "local", "h"), hil_star_rows(tmp_path / "dask", "h")
    assert len(a["hil_star"]) == 8 and sum(r["identified"] for r in a["hil_star"]) == 8
    assert a == b


def test_dask_worker_killed_mid_shard_is_recomputed_never_duplicated(tmp_path):
    (tmp_path / "c").mkdir()
    c = Cluster(tmp_path / "c", workers=2)
    import threading

    def kill_one():
        time.sleep(2.5)
        os.kill(c.workers[0].pid, 9)          # the nanny process and its worker die with it
        subprocess.run(["pkill", "-9", "-P", str(c.workers[0].pid)], capture_output=True)

    threading.Thread(target=kill_one, daemon=True).start()
    try:
        m = run_job("selftest", {"seed": 5, "sleep_ms": 20}, n_cases=600, lake=Lake(tmp_path / "l"), run_id="r",
                    scheduler=c.address, shard_size=25, progress=False)
    finally:
        c.close()
    assert m["status"] == "complete"
    got = rows(tmp_path / "l", "selftest_cases", "r", "case_id, x, k")
    local = tmp_path / "local"
    run_job("selftest", {"seed": 5, "sleep_ms": 20}, n_cases=600, lake=Lake(local), run_id="r", workers=2,
            progress=False)
    assert len(got) == 600 and got == rows(local, "selftest_cases", "r", "case_id, x, k")
