"""The Monte Carlo engine: atomic shards, manifests, Dask executor equivalence, Taichi laziness."""

from __future__ import annotations

import subprocess
import sys

import pyarrow as pa
import pytest

from dualsight.errors import InputError
from dualsight.jobs.runner import default_shard_size, run_job
from dualsight.warehouse.lake import Lake, check_run_id
from dualsight.warehouse.query import run_sql


def _tables(n):
    return {"a": pa.table({"case_id": list(range(n))}), "b": pa.table({"case_id": list(range(n)), "v": [1.0] * n})}


def test_shard_write_is_atomic_when_the_writer_fails(tmp_path, monkeypatch):
    lake = Lake(tmp_path)
    lake.write_shard("r1", 0, _tables(3), primary="a")
    import pyarrow.parquet as pq

    real = pq.write_table
    calls = []

    def failing(table, path, **kw):
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        return real(table, path, **kw)

    monkeypatch.setattr(pq, "write_table", failing)
    with pytest.raises(OSError):
        lake.write_shard("r1", 1, _tables(3), primary="a")
    # shard 1 left nothing behind (no final files, no temporaries); shard 0 intact
    assert lake.complete_shards("r1", ["a", "b"]) == {0}
    assert not list(tmp_path.rglob(".part-*"))
    assert not lake.shard_path("b", "r1", 1).exists() and not lake.shard_path("a", "r1", 1).exists()


def test_complete_shards_need_every_dataset(tmp_path):
    lake = Lake(tmp_path)
    lake.write_shard("r", 0, _tables(2), primary="a")
    lake.write_shard("r", 1, {"b": _tables(2)["b"]}, primary="b")     # as if killed before "a" was renamed
    assert lake.complete_shards("r", ["a", "b"]) == {0}


@pytest.mark.parametrize("bad", ["", "../x", "a/b", "x" * 200, "-lead"])
def test_run_ids_are_checked(bad):
    with pytest.raises(InputError):
        check_run_id(bad)


def test_default_shard_size_bounds():
    assert default_shard_size(200, 2) == 25
    assert default_shard_size(10_000, 2) == 1000
    assert default_shard_size(10**7, 2) == 1000


def test_dask_cluster_gives_the_same_cases(tmp_path):
    """The same shards on a Dask cluster (spawned worker processes) write the same rows."""
    distributed = pytest.importorskip("dask.distributed")
    from dualsight.jobs import star

    spec, _ = star.resolve_spec("paper", None, seed=9)
    local = Lake(tmp_path / "local")
    run_job("star", spec, n_cases=40, lake=local, run_id="r", workers=1, shard_size=20, progress=False)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                  silence_logs=40) as cluster:
        lake = Lake(tmp_path / "dask")
        m = run_job("star", spec, n_cases=40, lake=lake, run_id="r", scheduler=cluster.scheduler_address,
                    shard_size=20, progress=False)
    assert m["status"] == "complete" and m["executions"][-1]["scheduler"]
    sql = ("SELECT case_id, n_generated, n_observed, T, status, A_est::VARCHAR FROM star_cases "
           "WHERE run = 'r' ORDER BY case_id")
    assert run_sql(local.root, sql)[1] == run_sql(lake.root, sql)[1]


def test_taichi_is_not_initialised_at_import():
    code = ("import dualsight.jobs.star, dualsight.kernels.starfield, dualsight.kernels.detect, sys;"
            "from dualsight.kernels import _runtime; print(_runtime.is_initialised())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
