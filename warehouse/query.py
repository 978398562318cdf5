"""DuckDB over the lake: one view per dataset, report SQL files, ad-hoc queries.

Each dataset folder becomes a view of the same name over all its shards, with the hive partition
column ``run`` (from ``run=<id>``).  Report queries live in ``warehouse/sql/*.sql``, one file per table,
and take named parameters (``$run``).
"""

from __future__ import annotations

import contextlib
import os
import re
import resource
import sys
import threading
import time
from importlib import resources
from pathlib import Path

import duckdb

from dualsight.errors import InputError
from dualsight.scene.units import ARCSEC
from dualsight.warehouse.lake import Lake


def connect(lake: Lake | Path | str, threads: int | None = None, *, warn=None,
            locked: bool = True, memory_limit: int | None = None) -> duckdb.DuckDBPyConnection:
    """In-memory DuckDB connection with one view per dataset over the lake's *readable* shards.

    Only shard files recorded in a run's journal, with the recorded size, are read (:meth:`Lake.readable_files`):
    a damaged file or manifest is named through ``warn`` (default: one line each on stderr) and left out,
    every other run stays readable.  With ``locked`` (default) the connection is then made read-only in
    effect: external access (files, network, extensions) is switched off and the configuration locked, so
    no query can read or write anything but the views (see :func:`run_sql` for the statement check).
    With ``memory_limit`` (bytes) DuckDB's memory is capped there and spilling to disk is switched off (no
    temporary files, in the lake or elsewhere), before the configuration is locked.
    """
    lake = lake if isinstance(lake, Lake) else Lake(Path(lake))
    files, problems = lake.readable_files()
    report = warn if warn is not None else (lambda m: print(f"dualsight: warning: {m}", file=sys.stderr))
    for m in problems:
        report(m)
    con = duckdb.connect(":memory:")
    if threads:
        con.execute(f"SET threads = {int(threads)}")
    if memory_limit is not None:
        con.execute(f"SET memory_limit = '{int(memory_limit)}B'")
        con.execute("SET temp_directory = ''")          # no spilling: a big query fails, it fills no disk
    allowed = []
    for ds, paths in sorted(files.items()):
        if not _DATASET.fullmatch(ds):
            continue
        lst = ", ".join("'" + p.as_posix().replace("'", "''") + "'" for p in paths)
        con.execute(f"CREATE VIEW \"{ds}\" AS SELECT * FROM read_parquet([{lst}], hive_partitioning = true, "
                    f"union_by_name = true)")
        allowed.append((lake.root / ds).resolve().as_posix() + "/")
    # the one conversion of the report SQL to arcseconds, from the one units module
    con.execute(f"CREATE MACRO arcsec_per_rad() AS {1.0 / ARCSEC!r}")
    if locked:
        if allowed:
            con.execute("SET allowed_directories = " + "[" + ", ".join("'" + a.replace("'", "''") + "'"
                                                                     for a in allowed) + "]")
        con.execute("SET enable_external_access = false")
        con.execute("SET autoinstall_known_extensions = false")
        con.execute("SET autoload_known_extensions = false")
        con.execute("SET lock_configuration = true")
    return con


_DATASET = re.compile(r"[a-z][a-z0-9_]{0,63}")
READ_ONLY_STATEMENTS = {"SELECT", "EXPLAIN"}


def sql_text(name: str) -> str:
    """Text of the report query ``warehouse/sql/<name>.sql``."""
    try:
        return resources.files("dualsight.warehouse").joinpath("sql", f"{name}.sql").read_text()
    except FileNotFoundError:
        raise InputError(f"no report query named {name!r}") from None


_MISSING_COLUMN = re.compile(r'Referenced column "([^"]+)" not found')


def run_report(con: duckdb.DuckDBPyConnection, name: str, **params):
    """Run a report query; returns (column names, rows as tuples).

    A column the query needs that the lake's files lack (every run of that dataset was written by an older
    dualsight, before the column existed) is an :class:`InputError` naming the report, the column and the way
    out, not DuckDB's binder error."""
    sql = sql_text(name)
    used = {k: v for k, v in params.items() if f"${k}" in sql}
    try:
        cur = con.execute(sql, used) if used else con.execute(sql)
    except duckdb.BinderException as e:
        m = _MISSING_COLUMN.search(str(e))
        if not m:
            raise
        run = f" of run {params['run']!r}" if "run" in params else ""
        raise InputError(f"report {name}: the lake's rows{run} have no column {m.group(1)!r}: they were written by "
                         "an older dualsight; run the job again with this version (under a new --run id) or report "
                         "it with the version that wrote it", source="--run") from None
    cols = [d[0] for d in cur.description]
    return cols, cur.fetchall()


DEFAULT_TIMEOUT_S = 300.0
"""Default time limit of an ad-hoc query (``dualsight sql``, ``Lake.sql``): the report queries take under a
second at 10^6 cases, so a 10^7-row lake leaves them two orders of magnitude of room; a runaway query
(an endless recursive CTE, a huge cross join) ends within five minutes."""
DEFAULT_MEMORY_FRACTION = 0.5
"""Default DuckDB memory limit of an ad-hoc query, as a fraction of the machine's RAM (DuckDB's own default
is 80 %): the other half stays for the result in Python and for the runs that share the machine."""
DEFAULT_ROW_LIMIT = 1_000
"""Rows ``dualsight sql`` prints by default (``--limit``; ``--csv`` prints all)."""
MAX_CELL_CHARS = 10_000
"""Characters of one printed cell (``--csv`` prints whole cells)."""


class QueryTimeout(InputError):
    """An ad-hoc query ran past its time limit (and was interrupted)."""


def machine_memory() -> int:
    """Bytes of RAM of this machine (or of its cgroup, when that is lower)."""
    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    try:
        text = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if text.isdigit():
            total = min(total, int(text))
    except OSError:
        pass
    return total


_SIZE = re.compile(r"\s*(\d+(?:\.\d+)?)\s*(%|b|bytes|kb|mb|gb|tb|kib|mib|gib|tib)?\s*", re.IGNORECASE)
_UNITS = {"b": 1, "bytes": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12,
          "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40}


def memory_limit_bytes(value, *, name: str = "memory_limit") -> int:
    """``value`` as bytes: None (the default, :data:`DEFAULT_MEMORY_FRACTION` of :func:`machine_memory`), a
    number of bytes, or a string such as ``"4GB"``, ``"512MiB"``, ``"25%"`` (of the RAM); at least 64 MiB.
    InputError naming ``name`` otherwise."""
    if value is None:
        return int(DEFAULT_MEMORY_FRACTION * machine_memory())
    if isinstance(value, bool):
        value = str(value)
    if isinstance(value, (int, float)):
        n = float(value)
    else:
        m = _SIZE.fullmatch(str(value))
        if not m:
            raise InputError(f"{value!r} is not a size; give bytes, e.g. 4GB, 512MiB, or a share of the RAM, e.g. 25%",
                             source=name)
        unit = (m.group(2) or "b").lower()
        n = float(m.group(1)) * (machine_memory() / 100 if unit == "%" else _UNITS[unit])
    if not n >= 64 * 2**20 or n != n or n == float("inf"):
        raise InputError(f"{value!r} is below 64 MiB (or not a number); DuckDB needs at least that", source=name)
    return int(min(n, 2**62))


PROCESS_HEADROOM = 256 * 2**20
"""Bytes the ``dualsight sql`` process may map beyond DuckDB's memory limit (the printed rows, Python)."""


@contextlib.contextmanager
def process_memory_cap(memory_limit: int):
    """Within the block, this process's private writable memory (``RLIMIT_DATA``, Linux) is capped at what it
    maps on entry plus ``memory_limit`` plus :data:`PROCESS_HEADROOM` bytes; the previous limit is restored on
    exit.  Yields the cap, or None where it cannot be set (then nothing changes).

    DuckDB's ``memory_limit`` governs its buffer manager, not every allocation: ``repeat('x', 2000000000)``
    builds its string outside it and peaked near 8 GB under a 1 GB limit.  Under this cap the allocation
    fails inside DuckDB, which raises ``OutOfMemoryException`` (one line, :func:`_guarded`).  For the command
    line (``dualsight sql``), which may run in a caller's process (``main([...])``): hence the restore.
    ``Lake.sql`` keeps DuckDB's limit only.
    """
    try:
        status = Path("/proc/self/status").read_text()
        vm_data = next(int(line.split()[1]) * 1024 for line in status.splitlines() if line.startswith("VmData:"))
        old = resource.getrlimit(resource.RLIMIT_DATA)
        soft, hard = old
        cap = vm_data + int(memory_limit) + PROCESS_HEADROOM
        if hard != resource.RLIM_INFINITY:
            cap = min(cap, hard)
        if soft != resource.RLIM_INFINITY and soft <= cap:
            old = None                                    # already as tight: leave it
        else:
            resource.setrlimit(resource.RLIMIT_DATA, (cap, hard))
    except (OSError, ValueError, StopIteration):
        yield None
        return
    try:
        yield cap
    finally:
        if old is not None:
            resource.setrlimit(resource.RLIMIT_DATA, old)


def _timeout_seconds(value, name: str) -> float | None:
    if value is None or (not isinstance(value, bool) and isinstance(value, (int, float)) and value == 0):
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 10**9:
        raise InputError(f"{value!r} is not a time in seconds (> 0, or 0 for no limit)", source=name)
    return float(value)


def run_sql(lake: Lake | Path | str, sql: str, *, warn=None):
    """Ad-hoc read-only SQL over the lake's views: (column names, rows as tuples of Python values), every row.

    Only SELECT (and EXPLAIN) statements run; the connection has no file, network or extension access
    (:func:`connect`), so ``read_csv('/etc/passwd')``, ``COPY ... TO``, ``ATTACH``, ``INSTALL`` and writes
    into the lake are refused with one line (InputError).  No time or memory limit: the project's own short
    queries (replay predicates, tests); ``dualsight sql`` goes through :func:`sql_rows` / :func:`sql_csv`.
    """
    con, statements = _read_only_statements(lake, sql, warn)
    try:
        cur = None
        for st in statements:
            cur = con.execute(st)
    except duckdb.Error as e:
        raise InputError(f"{type(e).__name__}: {_first_line(e)}", source="sql") from None
    if cur is None or cur.description is None:
        return [], []
    return [d[0] for d in cur.description], cur.fetchall()


class SqlLimits:
    """The limits of one ad-hoc query: ``timeout`` seconds (None: none), ``memory_limit`` bytes of DuckDB
    memory, and the names the messages give them (``--timeout`` on the command line, ``timeout=`` in
    Python)."""

    def __init__(self, timeout=DEFAULT_TIMEOUT_S, memory_limit=None, *, timeout_name: str = "timeout",
                 memory_name: str = "memory_limit"):
        self.timeout = _timeout_seconds(timeout, timeout_name)
        self.memory_limit = memory_limit_bytes(memory_limit, name=memory_name)
        self.timeout_name, self.memory_name = timeout_name, memory_name


def sql_rows(lake: Lake | Path | str, sql: str, limits: SqlLimits, *, row_limit: int | None = DEFAULT_ROW_LIMIT,
             cell_chars: int | None = MAX_CELL_CHARS, warn=None):
    """What ``dualsight sql`` prints: (column names, at most ``row_limit`` rows, the result's row count,
    whether a cell was cut to ``cell_chars`` characters).  Only the rows shown are fetched (the LIMIT is part
    of the query, text cells are cut by DuckDB); the count runs the query again (without its columns) only when
    there are more rows.  Interruptible (KeyboardInterrupt, :class:`QueryTimeout`), within ``limits``."""
    con, statements = _read_only_statements(lake, sql, warn, limits.memory_limit)
    deadline = None if limits.timeout is None else time.monotonic() + limits.timeout

    def shown():
        rel = _last_relation(con, statements)
        if rel is None:
            return [], [], None, None
        cols = list(rel.columns)
        part = rel.limit(row_limit + 1) if row_limit is not None else rel
        if cell_chars is not None and any(str(t) == "VARCHAR" for t in rel.types):
            part = part.project(", ".join(f"left(#{i + 1}, {cell_chars + 1})" if str(t) == "VARCHAR" else f"#{i + 1}"
                                          for i, t in enumerate(rel.types)))
        return cols, part.fetchall(), rel, None

    try:
        cols, rows, rel, _ = _guarded(con, shown, deadline, limits)
        total = len(rows)
        if row_limit is not None and len(rows) > row_limit:
            rows = rows[:row_limit]
            total = _guarded(con, lambda: rel.aggregate("count(*)").fetchall()[0][0], deadline, limits)
        cut = False
        if cell_chars is not None:
            rows, cut = _cut_cells(rows, cell_chars)
        return cols, rows, total, cut
    finally:
        _close(con)


def sql_csv(lake: Lake | Path | str, sql: str, limits: SqlLimits, write_header, write_rows, *,
            row_limit: int | None = None, batch: int = 10_000, warn=None) -> int:
    """Stream the result to ``write_header(cols)`` and ``write_rows(rows)`` in batches of ``batch`` rows (never
    the whole result in memory), at most ``row_limit`` rows; returns the rows written (``row_limit`` + 1 when
    there were more).  Within ``limits``, interruptible as :func:`sql_rows`."""
    con, statements = _read_only_statements(lake, sql, warn, limits.memory_limit)
    deadline = None if limits.timeout is None else time.monotonic() + limits.timeout

    def stream():
        for st in statements[:-1]:
            _complete(con.execute(st))
        cur = con.execute(statements[-1])
        if cur.description is None:
            return 0
        write_header([d[0] for d in cur.description])
        n = 0
        while row_limit is None or n <= row_limit:
            want = batch if row_limit is None else min(batch, row_limit + 1 - n)
            rows = cur.fetchmany(want)
            if not rows:
                break
            n += len(rows)
            write_rows(rows if row_limit is None or n <= row_limit else rows[:len(rows) - (n - row_limit)])
        return n

    try:
        return _guarded(con, stream, deadline, limits)
    finally:
        _close(con)


def run_sql_arrow(lake: Lake | Path | str, sql: str, *, warn=None, limits: SqlLimits | None = None):
    """The last statement's result as a ``pyarrow.Table`` (DuckDB's column types kept), what
    ``dualsight.Lake.sql`` returns; the statement check, connection and errors of :func:`run_sql`, within
    ``limits`` (default :class:`SqlLimits`): the time limit, DuckDB's memory limit, and the same limit on
    the Arrow result, read in batches.  A KeyboardInterrupt interrupts the query."""
    import pyarrow as pa

    limits = limits if limits is not None else SqlLimits()
    con, statements = _read_only_statements(lake, sql, warn, limits.memory_limit)
    deadline = None if limits.timeout is None else time.monotonic() + limits.timeout

    def table():
        rel = _last_relation(con, statements)
        reader = rel.to_arrow_reader(65_536)
        batches, size = [], 0
        for b in reader:
            size += b.nbytes
            if size > limits.memory_limit:
                raise InputError(f"the result is larger than the memory limit ({limits.memory_limit / 2**30:.1f} "
                                 f"GiB); aggregate or filter in SQL, or raise {limits.memory_name}", source="sql")
            batches.append(b)
        return pa.Table.from_batches(batches, schema=reader.schema)

    try:
        return _guarded(con, table, deadline, limits)
    finally:
        _close(con)


def _complete(cur):
    done = getattr(cur, "complete", None)       # DuckDB 2 wants a pending result finished
    if done is not None:
        done()


def _last_relation(con, statements):
    """Run every statement but the last; the last one as a relation (run when read), None without a result."""
    for st in statements[:-1]:
        _complete(con.execute(st))
    return con.sql(statements[-1])


def _cut_cells(rows, n: int):
    cut = False
    out = []
    for r in rows:
        if any(isinstance(v, (str, bytes, list, dict, tuple)) and len(v) > n or
               not isinstance(v, (str, bytes, int, float, type(None))) and len(str(v)) > n for v in r):
            cut = True
            r = tuple(_cut(v, n) for v in r)
        out.append(r)
    return out, cut


def _cut(v, n: int):
    if isinstance(v, (int, float, type(None))):
        return v
    text = v if isinstance(v, str) else str(v)
    return text if len(text) <= n else text[:n] + "..."


def _guarded(con, work, deadline, limits: SqlLimits):
    """``work()`` in a worker thread while this thread waits: a KeyboardInterrupt (Ctrl-C, or SIGTERM turned
    into one) or the deadline interrupts DuckDB (``con.interrupt()``); the worker's DuckDB error becomes one
    InputError line.  The wait is on an Event, not ``Thread.join``: a join interrupted by a signal handler's
    exception marks a running thread as stopped (CPython 3.11)."""
    box = {}
    done = threading.Event()

    def target():
        try:
            box["value"] = work()
        except BaseException as e:          # noqa: BLE001 - handed to the waiting thread
            box["error"] = e
        finally:
            done.set()

    threading.Thread(target=target, name="dualsight-sql", daemon=True).start()
    try:
        while not done.is_set():
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                _stop(con, done)
                raise QueryTimeout(f"the query ran longer than {limits.timeout:g} s and was stopped; raise the limit "
                                   f"with {limits.timeout_name} (0 for none)", source="sql")
            done.wait(0.1 if left is None else min(0.1, max(left, 0.001)))
    except KeyboardInterrupt:
        _stop(con, done)
        raise
    if "error" in box:
        e = box["error"]
        if isinstance(e, (duckdb.OutOfMemoryException, MemoryError)):
            raise InputError(f"{type(e).__name__}: {_first_line(e)} (the memory limit is "
                             f"{limits.memory_limit / 2**30:.1f} GiB, {limits.memory_name} to change it)",
                             source="sql") from None
        if isinstance(e, duckdb.Error):
            raise InputError(f"{type(e).__name__}: {_first_line(e)}", source="sql") from None
        raise e
    return box["value"]


def _stop(con, done: threading.Event, grace: float = 3.0):
    """Interrupt the worker's query (again every 0.1 s: a statement may start after the first call) and wait
    up to ``grace`` seconds for it to end; a second Ctrl-C stops the waiting."""
    end = time.monotonic() + grace
    try:
        while not done.is_set() and time.monotonic() < end:
            con.interrupt()
            done.wait(0.1)
    except KeyboardInterrupt:
        pass


def _close(con):
    """Close the connection unless a worker that did not stop in time still uses it (the process ends soon)."""
    try:
        con.close()
    except duckdb.Error:
        pass


def _read_only_statements(lake, sql, warn, memory_limit: int | None = None):
    """(connection of :func:`connect`, the parsed statements of ``sql``), every one SELECT or EXPLAIN;
    otherwise InputError."""
    if not isinstance(sql, str) or not sql.strip():
        raise InputError("the query is empty", source="sql")
    if len(sql) > 1_000_000:
        raise InputError("the query is longer than 1 MB", source="sql")
    con = connect(lake, warn=warn, memory_limit=memory_limit)
    try:
        statements = con.extract_statements(sql)
    except duckdb.Error as e:
        con.close()
        raise InputError(f"{type(e).__name__}: {_first_line(e)}", source="sql") from None
    if not statements:
        con.close()
        raise InputError("the query is empty", source="sql")
    for st in statements:
        kind = st.type.name
        if kind not in READ_ONLY_STATEMENTS:
            con.close()
            name = statement_name(st)
            raise InputError(f"only read-only queries (SELECT, EXPLAIN) run here; refused {_article(name)} {name} "
                             "statement", source="sql")
    return con, statements


_LEADING = re.compile(r"\s*(?:(?:--[^\n]*(?:\n|$)|/\*.*?\*/)\s*)*(FORCE\s+)?([A-Za-z]+)", re.DOTALL)


def statement_name(st) -> str:
    """The keyword a statement starts with (``INSTALL``, ``FORCE INSTALL``, ``EXPORT``, ``RESET``), what a user
    typed; DuckDB's statement type (``LOAD`` for INSTALL) when the text starts otherwise (``WITH ... DELETE``)."""
    m = _LEADING.match(getattr(st, "query", "") or "")
    word = m.group(2).upper() if m else ""
    if not word or word in ("WITH", "FROM", "VALUES", "TABLE"):
        return st.type.name.replace("_", " ")
    return ("FORCE " if m.group(1) else "") + word


def _article(word: str) -> str:
    """'a' or 'an' before a keyword read as a word: an EXPORT, an INSTALL, an UPDATE, a USE, a LOAD."""
    if word.startswith(("USE", "UNIQUE")):
        return "a"
    return "an" if word[:1] in "AEIOU" else "a"


def _first_line(e: Exception) -> str:
    text = str(e).strip().splitlines()
    return text[0] if text else type(e).__name__


def format_table(cols, rows, floatfmt: str = "{:.4g}") -> str:
    """Plain-text table for the terminal."""
    def fmt(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return floatfmt.format(v)
        return str(v)

    cells = [[fmt(v) for v in r] for r in rows]
    widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(cols)]
    line = "  ".join(c.rjust(w) for c, w in zip(cols, widths))
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(v.rjust(w) for v, w in zip(r, widths)) for r in cells]
    return "\n".join(out)
