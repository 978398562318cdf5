"""DuckDB over the lake: one view per dataset, report SQL files, ad-hoc queries.

Each dataset folder becomes a view of the same name over all its shards, with the hive partition
column ``run`` (from ``run=<id>``).  Report queries live in ``warehouse/sql/*.sql``, one file per table,
and take named parameters (``$run``).
"""

from __future__ import annotations

import re
import sys
from importlib import resources
from pathlib import Path

import duckdb

from dualsight.errors import InputError
from dualsight.scene.units import ARCSEC
from dualsight.warehouse.lake import Lake


def connect(lake: Lake | Path | str, threads: int | None = None, *, warn=None,
            locked: bool = True) -> duckdb.DuckDBPyConnection:
    """In-memory DuckDB connection with one view per dataset over the lake's *readable* shards.

    Only shard files recorded in a run's journal, with the recorded size, are read (:meth:`Lake.readable_files`):
    a damaged file or manifest is named through ``warn`` (default: one line each on stderr) and left out,
    every other run stays readable.  With ``locked`` (default) the connection is then made read-only in
    effect: external access (files, network, extensions) is switched off and the configuration locked, so
    no query can read or write anything but the views (see :func:`run_sql` for the statement check).
    """
    lake = lake if isinstance(lake, Lake) else Lake(Path(lake))
    files, problems = lake.readable_files()
    report = warn if warn is not None else (lambda m: print(f"dualsight: warning: {m}", file=sys.stderr))
    for m in problems:
        report(m)
    con = duckdb.connect(":memory:")
    if threads:
        con.execute(f"SET threads = {int(threads)}")
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


def run_report(con: duckdb.DuckDBPyConnection, name: str, **params):
    """Run a report query; returns (column names, rows as tuples)."""
    sql = sql_text(name)
    used = {k: v for k, v in params.items() if f"${k}" in sql}
    cur = con.execute(sql, used) if used else con.execute(sql)
    cols = [d[0] for d in cur.description]
    return cols, cur.fetchall()


def run_sql(lake: Lake | Path | str, sql: str, *, warn=None):
    """Ad-hoc read-only SQL over the lake's views: (column names, rows as tuples of Python values), what
    ``dualsight sql`` prints.

    Only SELECT (and EXPLAIN) statements run; the connection has no file, network or extension access
    (:func:`connect`), so ``read_csv('/etc/passwd')``, ``COPY ... TO``, ``ATTACH``, ``INSTALL`` and writes
    into the lake are refused with one line (InputError).
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


def run_sql_arrow(lake: Lake | Path | str, sql: str, *, warn=None):
    """:func:`run_sql` with the last statement's result as a ``pyarrow.Table`` (DuckDB's column types kept),
    what ``dualsight.Lake.sql`` returns; the same statement check, connection and errors."""
    con, statements = _read_only_statements(lake, sql, warn)
    try:
        for st in statements[:-1]:
            done = getattr(con.execute(st), "complete", None)   # DuckDB 2 wants a pending result finished
            if done is not None:
                done()
        return con.sql(statements[-1]).to_arrow_table()
    except duckdb.Error as e:
        raise InputError(f"{type(e).__name__}: {_first_line(e)}", source="sql") from None
    finally:
        con.close()


def _read_only_statements(lake, sql, warn):
    """(connection of :func:`connect`, the parsed statements of ``sql``), every one SELECT or EXPLAIN;
    otherwise InputError."""
    if not isinstance(sql, str) or not sql.strip():
        raise InputError("the query is empty", source="sql")
    if len(sql) > 1_000_000:
        raise InputError("the query is longer than 1 MB", source="sql")
    con = connect(lake, warn=warn)
    try:
        statements = con.extract_statements(sql)
    except duckdb.Error as e:
        raise InputError(f"{type(e).__name__}: {_first_line(e)}", source="sql") from None
    if not statements:
        raise InputError("the query is empty", source="sql")
    for st in statements:
        kind = st.type.name
        if kind not in READ_ONLY_STATEMENTS:
            raise InputError(f"only read-only queries (SELECT, EXPLAIN) run here; refused a {kind} statement",
                             source="sql")
    return con, statements


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
