"""DuckDB over the lake: one view per dataset, report SQL files, ad-hoc queries.

Each dataset folder becomes a view of the same name over all its shards, with the hive partition
column ``run`` (from ``run=<id>``).  Report queries live in ``warehouse/sql/*.sql``, one file per table,
and take named parameters (``$run``).
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import duckdb

from dualsight.errors import InputError
from dualsight.warehouse.lake import Lake


def connect(lake: Lake | Path | str, threads: int | None = None) -> duckdb.DuckDBPyConnection:
    """In-memory DuckDB connection with a view per dataset of the lake."""
    lake = lake if isinstance(lake, Lake) else Lake(Path(lake))
    con = duckdb.connect(":memory:")
    if threads:
        con.execute(f"SET threads = {int(threads)}")
    for ds in lake.datasets():
        glob = (lake.root / ds / "run=*" / "part-*.parquet").as_posix().replace("'", "''")
        con.execute(f"CREATE VIEW \"{ds}\" AS SELECT * FROM read_parquet('{glob}', hive_partitioning = true, "
                    f"union_by_name = true)")
    return con


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


def run_sql(lake: Lake | Path | str, sql: str):
    """Ad-hoc SQL over the lake's views; errors are reported as InputError with DuckDB's message."""
    con = connect(lake)
    try:
        cur = con.execute(sql)
    except duckdb.Error as e:
        raise InputError(f"{type(e).__name__}: {e}", source="sql") from None
    if cur.description is None:
        return [], []
    return [d[0] for d in cur.description], cur.fetchall()


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
