"""Running a plan's shards on a Dask cluster.

Task keys are ``dualsight-<token>-<shard>`` with ``token`` a hash of (lake folder, run id, spec hash), so
two lakes, two runs or two specs never share a key on one scheduler.  Each task computes and writes its
own shard files (the lake must be on storage every worker can write); a worker that dies mid-shard is
replaced by Dask and the shard recomputed (``retries``), which rewrites the same files, never adding rows.
An unreachable scheduler is reported within :data:`CONNECT_TIMEOUT_S`; a scheduler lost mid-run ends the
run cleanly (status "interrupted") and the same command resumes it later.
"""

from __future__ import annotations

import hashlib

from dualsight.errors import InputError
from dualsight.jobs.engine.errors import EngineError

CONNECT_TIMEOUT_S = 8
RETRIES = 2


def task_token(lake_root: str, run_id: str, spec_hash: str) -> str:
    return hashlib.sha256(f"{lake_root}\0{run_id}\0{spec_hash}".encode()).hexdigest()[:16]


def connect(scheduler: str):
    """A Dask client of the scheduler at ``scheduler``; EngineError within :data:`CONNECT_TIMEOUT_S` when none
    answers.  The runner connects before it touches the lake, so an address without a scheduler leaves no
    manifest, lock or folder behind."""
    try:
        import dask.config
        from dask.distributed import Client
    except ImportError:
        raise InputError("--scheduler needs Dask: pip install 'dualsight[cluster]'", source="--scheduler") from None
    try:
        with dask.config.set({"distributed.comm.timeouts.connect": f"{CONNECT_TIMEOUT_S}s"}):
            return Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        raise EngineError(f"cannot reach the Dask scheduler within {CONNECT_TIMEOUT_S} s "
                          f"({type(e).__name__}: {str(e).splitlines()[0][:160] if str(e) else 'no answer'}); "
                          "nothing was written to the lake", source=scheduler) from None


def run_on_dask(tasks, plan, lake, scheduler: str, execute_shard, client=None):
    """Yield journal entries as shards complete on the cluster at ``scheduler`` (through ``client``, from
    :func:`connect`, or a new one); each task is ``execute_shard(task)`` (the runner's, which computes and
    writes one shard).  The client is closed at the end."""
    from dask.distributed import as_completed

    if client is None:
        client = connect(scheduler)
    token = task_token(str(lake.root.resolve()), plan.run_id, plan.spec_hash)
    try:
        window = max(4, 2 * sum(client.nthreads().values()))
        exhausted = False
        inflight = 0

        def top_up(sink):
            nonlocal exhausted, inflight
            while not exhausted and inflight < window:
                t = next(tasks, None)
                if t is None:
                    exhausted = True
                    return
                sink(client.submit(execute_shard, t, key=f"dualsight-{token}-{t.info.shard}", pure=False,
                                   retries=RETRIES))
                inflight += 1

        first: list = []
        top_up(first.append)
        if not first:
            return
        ac = as_completed(first, loop=client.loop)
        for fut in ac:
            inflight -= 1
            try:
                entry = fut.result()
            except OSError:
                raise
            except Exception as e:
                name = type(e).__name__
                if name in ("CancelledError", "CommClosedError", "TimeoutError", "FutureCancelledError"):
                    raise EngineError(f"lost the Dask scheduler ({name}); the completed shards are kept, run the "
                                      "same command again to resume", source=scheduler) from None
                raise EngineError(f"a shard failed on the cluster: {name}: {str(e).splitlines()[0][:200]}",
                                  source=scheduler) from None
            fut.release()
            yield entry
            top_up(ac.add)
    finally:
        try:
            client.close(timeout=5)
        except Exception:      # the scheduler may already be gone
            pass
