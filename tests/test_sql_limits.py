"""`dualsight sql` and `Lake.sql` under their limits: Ctrl-C / SIGTERM interrupt a runaway query, --timeout
stops it, the printout is capped (rows and cell characters) and fetched within bounded memory, --limit and
--csv, and the refusal messages of INSTALL / EXPORT.  Each command runs in a subprocess with a hard timeout
and an address-space cap (RLIMIT_AS), so a broken guard fails the test instead of hanging the suite."""

from __future__ import annotations

import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ENDLESS = "WITH RECURSIVE t(n) AS (SELECT 1 UNION ALL SELECT n+1 FROM t) SELECT count(*) FROM t"
AS_CAP = 3 * 2**30            # address space: DuckDB reserves more than it touches
# the child writes its own peak resident memory (KiB, VmHWM) to $PEAK_FILE at exit (RUSAGE_CHILDREN would be the
# largest child of the whole test session, and the child's own ru_maxrss carries the forking test process's
# size across exec)
# The child caps its own address space ($AS_CAP_BYTES) before it imports anything (a preexec_fn would run Python
# between fork and exec of this multi-threaded test process), and takes Ctrl-C as a command in a terminal's
# foreground does: a suite started in the background by a non-interactive shell (`bash .ci/run &`) passes SIGINT
# down ignored, and an ignored signal stays ignored across exec.
DUALSIGHT = [sys.executable, "-c", "import atexit, os, resource, signal, sys\n"
             "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
             "cap = int(os.environ['AS_CAP_BYTES']); resource.setrlimit(resource.RLIMIT_AS, (cap, cap))\n"
             "atexit.register(lambda: open(os.environ['PEAK_FILE'], 'w').write(next(x.split()[1] for x in "
             "open('/proc/self/status') if x.startswith('VmHWM:'))))\n"
             "from dualsight.jobs.cli.main import main; sys.exit(main())"]


def start(args, lake, as_cap: int = AS_CAP):
    env = dict(os.environ, PEAK_FILE=str(Path(lake).parent / "peak_kib"), AS_CAP_BYTES=str(int(as_cap)))
    return subprocess.Popen(DUALSIGHT + ["sql", *args, "--lake", str(lake)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)


def finish(p, timeout: float):
    """(exit status, stdout, stderr, seconds) of ``p``; killed after ``timeout`` s."""
    t0 = time.monotonic()
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        p.kill()
        p.communicate()
        pytest.fail(f"still running after {timeout} s")
    return p.returncode, out.decode(), err.decode(), time.monotonic() - t0


def run(args, lake, timeout: float = 60, as_cap: int = AS_CAP):
    """``finish`` and the command's own peak resident memory in bytes."""
    rc, out, err, dt = finish(start(args, lake, as_cap), timeout)
    return rc, out, err, dt, int((Path(lake).parent / "peak_kib").read_text()) * 1024


@pytest.fixture(scope="module")
def lake(tmp_path_factory):
    d = tmp_path_factory.mktemp("sqllake")          # an empty lake: range() and CTEs need no dataset
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.mark.parametrize("sig, status", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_interrupts_endless_query(lake, sig, status):
    p = start([ENDLESS], lake)
    time.sleep(1.0)
    assert p.poll() is None, "the query ended by itself"
    p.send_signal(sig)
    rc, out, err, dt = finish(p, 5)
    assert rc == status and dt < 2.5      # interrupted, not given up on (the grace is 3 s)
    assert out == "" and err == "dualsight: interrupted\n"


def test_timeout_stops_endless_query(lake):
    rc, out, err, dt, _ = run([ENDLESS, "--timeout", "1"], lake, timeout=15)
    assert rc == 2 and dt < 8 and out == ""
    assert err.count("\n") == 1 and "--timeout" in err and "longer than 1 s" in err


def test_big_result_printed_capped_bounded(lake):
    rc, out, err, dt, rss = run(["SELECT * FROM range(10000000)"], lake, timeout=30)
    assert rc == 0, err
    lines = out.splitlines()
    assert lines[0].strip() == "range" and len(lines) == 2 + 1000 and lines[-1].strip() == "999"
    assert err == "(showing 1,000 of 10,000,000 rows; --limit / --csv for all)\n"
    assert dt < 15
    assert rss < 2**30


def test_huge_cell_capped(lake):
    rc, out, err, dt, rss = run(["SELECT repeat('x', 200000000) AS s, 7 AS n"], lake, timeout=60)
    assert rc == 0, err
    lines = out.splitlines()
    assert len(lines) == 3 and len(lines[2]) < 10_100 and lines[2].rstrip().endswith("...  7")
    assert "x" * 10_000 + "..." in lines[2] and "x" * 10_001 not in lines[2]
    assert err == "(cells longer than 10,000 characters are cut; --csv for whole cells)\n"


@pytest.mark.parametrize("args, limit", [([], "1.0 GiB"), (["--memory-limit", "512MiB"], "0.5 GiB")])
def test_memory_limit_holds_for_the_whole_process(lake, args, limit):
    # repeat() builds its 2 GB string outside DuckDB's buffer manager (it peaked near 8 GB under a 1 GB
    # memory_limit); the process cap turns that allocation into DuckDB's own out-of-memory error
    # the address-space cap of the other tests would end it alone: give room to fail without the guard
    rc, out, err, dt, rss = run(["SELECT repeat('x', 2000000000)", *args], lake, timeout=60, as_cap=12 * 2**30)
    assert rc == 2 and out == "" and err.count("\n") == 1, err
    assert "OutOfMemoryException" in err and f"the memory limit is {limit}, --memory-limit to change it" in err
    assert dt < 10 and rss < 2**30


def test_limit_and_csv(lake):
    rc, out, err, _, _ = run(["SELECT * FROM range(10)", "--limit", "5"], lake)
    assert rc == 0 and out.split() == ["range", "-----", "0", "1", "2", "3", "4"]
    assert err == "(showing 5 of 10 rows; --limit / --csv for all)\n"
    rc, out, err, _, _ = run(["SELECT * FROM range(2500)", "--csv"], lake)
    assert rc == 0 and err == "" and out.splitlines() == ["range"] + [str(i) for i in range(2500)]
    rc, out, err, _, _ = run(["SELECT * FROM range(2500)", "--csv", "--limit", "3"], lake)
    assert rc == 0 and out.splitlines() == ["range", "0", "1", "2"]
    assert err == "(showing the first 3 rows; without --limit all)\n"
    rc, out, err, _, _ = run(["SELECT * FROM range(2500)", "--limit", "0", "--json"], lake)
    assert rc == 0 and err == "" and out.count('"range"') == 2500


@pytest.mark.parametrize("stmt, name", [("INSTALL httpfs", "an INSTALL"), ("LOAD httpfs", "a LOAD"),
                                        ("EXPORT DATABASE 'x'", "an EXPORT"), ("UPDATE t SET a = 1", "an UPDATE"),
                                        ("DELETE FROM t", "a DELETE")])
def test_refusal_names_statement(lake, stmt, name):
    rc, out, err, _, _ = run([stmt], lake)
    assert rc == 2 and out == ""
    assert err == ("dualsight: error: sql: only read-only queries (SELECT, EXPLAIN) run here; refused "
                   f"{name} statement\n")


API_CHECK = """
import os, resource
resource.setrlimit(resource.RLIMIT_AS, (int(os.environ['AS_CAP_BYTES']),) * 2)      # before any import
import sys, time, dualsight, pytest
from dualsight.warehouse.query import QueryTimeout
L = dualsight.Lake(sys.argv[1])
t0 = time.monotonic()
with pytest.raises(QueryTimeout, match="timeout=SECONDS"):
    L.sql(sys.argv[2], timeout=1)
assert time.monotonic() - t0 < 3.5, time.monotonic() - t0      # interrupted (the grace is 3 s)
assert L.sql("SELECT * FROM range(5000)", timeout=10).num_rows == 5000          # no row cap
with pytest.raises(dualsight.errors.InputError, match="memory limit"):
    L.sql("SELECT * FROM range(20000000)", memory_limit="64MiB")                # a 160 MB result
print("ok")
"""


def test_lake_sql_timeout_and_memory_limit(lake):
    p = subprocess.Popen([sys.executable, "-c", API_CHECK, str(lake), ENDLESS], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env=dict(os.environ, AS_CAP_BYTES=str(AS_CAP)))
    rc, out, err, _ = finish(p, 30)
    assert rc == 0 and out == "ok\n", err


def test_in_process_sql_restores_the_process_memory_limit(lake):
    # `main(["sql", ...])` in a caller's process (tests, notebooks): the cap holds during the query only; a cap
    # left behind made every later test of the suite run out of memory
    from helpers import run_cli

    before = resource.getrlimit(resource.RLIMIT_DATA)
    rc, out, err = run_cli(["sql", "SELECT 42 AS x", "--lake", lake])
    assert rc == 0 and "42" in out, err
    rc, out, err = run_cli(["sql", "SELECT repeat('x', 2000000000)", "--lake", lake, "--memory-limit", "256MiB"])
    assert rc == 2 and "OutOfMemoryException" in err
    assert resource.getrlimit(resource.RLIMIT_DATA) == before
