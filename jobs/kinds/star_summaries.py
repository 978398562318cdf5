"""Per-shard partial aggregates of ``star_cases``: the star report without scanning every case.

Each star shard writes, beside its ``star_cases`` rows, the dataset ``star_summaries``: the shard's cases grouped by
:data:`KEYS` = (``status``, ``status_robust``, ``n_observed``), and per group the number of cases and, for every
measure of :data:`MEASURES`, the sum of its non-null values and how many there were.  These are exact partial
aggregates: the report's every number is a ratio of sums over groups and shards (``warehouse/sql/star_summ_*.sql``),

    mean of m over the cases in a set S of groups = sum over shards and S of ``sum_m`` / sum of ``n_m``
    rate of an outcome                            = sum of ``cases`` of its groups / sum of ``cases`` (or of ``n_m``)

so it equals the full scan of ``star_cases`` (``warehouse/sql/star_*.sql``): counts and rates exactly (integer
sums and counts, one division), integer means (stars, T, nanoseconds) from exact integer sums to the rounding of the
final division (DuckDB's ``avg`` of integers may divide in long double: within 1 ulp), float means (errors) to the
rounding of a differently ordered sum (~1e-16 relative).  NULL follows SQL: a null value is left out of ``sum_m``
and ``n_m`` (as ``avg`` leaves it out), a group whose values are all null has ``sum_m`` null; NaN propagates as in
``avg``.  The grouping keys keep null as its own key (``status_robust`` is null when the robust method is off).

Nothing in today's report is an order statistic (no median, no percentile), so nothing is left to a full scan.  A
future percentile would get a mergeable exact form: an integer histogram per group over fixed bins (e.g. the error
in whole 0.01 arcsec bins up to a stated limit plus an overflow count), summed over shards like the counts here.

Layout: the sums and counts are packed into four fixed-size list columns (:data:`SCHEMA`: 8 Parquet columns, not
46), because a reader's cost per file grows with its columns and a 10^7-case run has 10^4 files (measured on 10^4
summary files, 2 loaded cores: DuckDB reads the 46-column layout in ~20 s, this one in ~2-4 s when it sums the lists
as it reads, :func:`merge_sql`).  :func:`unpack` (Arrow) and :func:`unpack_sql` / :func:`merge_sql` (DuckDB) give
the named columns (``sum_<m>``, ``n_<m>``, ``t_<stage>_sum_ns``) the report SQL reads.  Size: a shard of 1,000
paper-preset cases has ~40 groups (rows), ~8 kB of Parquet, so a 10^7-case run (10^4 shards) has ~4x10^5 summary
rows (~80 MiB) for 10^7 case rows (~3.3 GiB).

Units: errors in rad (the SQL converts to arcsec with ``arcsec_per_rad()``), times in ns, counts in cases.
Pure functions over Arrow tables; no Python loop over rows.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

DATASET = "star_summaries"

#: Grouping keys (columns of ``star_cases``): outcome by the reference's method, by the robust method (null when
#: it did not run), and the number of stars detected (the error-vs-observed table's exact "bin").
KEYS = (("status", pa.string()), ("status_robust", pa.string()), ("n_observed", pa.int32()))


def _col(t: pa.Table, name: str) -> pa.ChunkedArray:
    return t.column(name)


def _abs(name):
    return lambda t: pc.abs(_col(t, name))


def _as_int(name):
    return lambda t: pc.cast(_col(t, name), pa.int64())


def _rss(t: pa.Table) -> pa.ChunkedArray:
    """sqrt(err_x^2 + err_y^2 + err_z^2) (rad), null when any axis is null (as the SQL expression)."""
    x, y, z = (pc.cast(_col(t, f"err_{a}_rad"), pa.float64()) for a in "xyz")   # stored float32: square in double
    return pc.sqrt(pc.add(pc.add(pc.multiply(x, x), pc.multiply(y, y)), pc.multiply(z, z)))


def _at_least(k: int):
    return lambda t: pc.cast(pc.greater_equal(_col(t, "n_generated"), k), pa.int64())


_TIMES = ("sample", "render", "detect", "identify", "attitude", "robust", "total")

#: name -> (value per case from a ``star_cases`` table (B rows) -> (B,) array, kind of its sum): "int" (exact int64
#: sums), "float" (float64 sums) or "time" (int64 sums of wall time in ns, kept apart: see :data:`SCHEMA`).
MEASURES: dict[str, tuple] = {
    "id_correct": (_as_int("id_correct"), "int"),                   # cases identified right (0/1)
    "id_correct_robust": (_as_int("id_correct_robust"), "int"),
    "stars_generated": (_as_int("n_generated"), "int"),             # catalog stars in the field
    "stars_observed": (_as_int("n_observed"), "int"),               # stars detected
    "T": (_as_int("T"), "int"),                                     # match threshold T
    "ge3_stars": (_at_least(3), "int"),                             # n_generated >= 3 (0/1)
    "ge4_stars": (_at_least(4), "int"),
    "abs_err_x_rad": (_abs("err_x_rad"), "float"),                 # |axis error| (rad), Eqs. 4-7
    "abs_err_y_rad": (_abs("err_y_rad"), "float"),
    "abs_err_z_rad": (_abs("err_z_rad"), "float"),
    "rss_err_rad": (_rss, "float"),                                 # sqrt(x^2 + y^2 + z^2) (rad)
    "abs_err_x_robust_rad": (_abs("err_x_robust_rad"), "float"),
    "abs_err_y_robust_rad": (_abs("err_y_robust_rad"), "float"),
    "abs_err_z_robust_rad": (_abs("err_z_robust_rad"), "float"),
    **{f"t_{s}_ns": (_as_int(f"t_{s}_ns"), "time") for s in _TIMES},   # stage wall time per case (ns)
}
_TYPES = {"int": pa.int64(), "float": pa.float64(), "time": pa.int64()}

#: The packed sum columns, by kind: (column, kind).  The timing sums are in ``t_sums_ns`` (a name matching
#: ``t_*_ns``, the columns the nightly "identical" check leaves out, as wall times differ between identical runs).
PACKS = (("sums_int", "int"), ("sums_float", "float"), ("t_sums_ns", "time"))


def _names(kind: str) -> list[str]:
    return [m for m, (_, k) in MEASURES.items() if k == kind]


#: The Parquet layout, narrow on purpose (8 columns; a reader's cost per file grows with the columns, and a
#: 10^7-case run has 10^4 files): keys, ``cases``, and fixed-size lists, row-major per group:
#: ``sums_int`` / ``sums_float`` / ``t_sums_ns`` the sums of the "int" / "float" / "time" measures in
#: :data:`MEASURES` order (null when every value of the group is null), ``counts`` the non-null counts of every
#: measure in :data:`MEASURES` order.  :func:`unpack` (Arrow) and :func:`unpack_sql` (DuckDB) name them.
SCHEMA = pa.schema([*KEYS, ("cases", pa.int64())]
                   + [(col, pa.list_(_TYPES[kind], len(_names(kind)))) for col, kind in PACKS]
                   + [("counts", pa.list_(pa.int64(), len(MEASURES)))])


def sum_column(name: str) -> str:
    """Name of the sum of measure ``name`` once unpacked: ``sum_<name>``, or ``t_<stage>_sum_ns`` for a time."""
    return f"{name[:-3]}_sum_ns" if MEASURES[name][1] == "time" else f"sum_{name}"


def count_column(name: str) -> str:
    """Name of the number of non-null values of measure ``name`` once unpacked."""
    return f"n_{name}"


#: The unpacked (wide) layout the report SQL reads (``warehouse/sql/star_summ_*.sql``): keys, ``cases``, then per
#: measure its sum (type of its kind) and its non-null count.
WIDE_SCHEMA = pa.schema([*KEYS, ("cases", pa.int64())]
                        + [f for m, (_, kind) in MEASURES.items()
                           for f in ((sum_column(m), _TYPES[kind]), (count_column(m), pa.int64()))])


def _slots() -> list[tuple[str, int, str]]:
    """(packed column, 0-based index, unpacked name) of every value in the lists."""
    out = [(col, i, sum_column(m)) for col, kind in PACKS for i, m in enumerate(_names(kind))]
    return out + [("counts", i, count_column(m)) for i, m in enumerate(MEASURES)]


def measures(cases: pa.Table) -> pa.Table:
    """Per-case measure values: ``cases`` (B rows of ``star_cases``) -> table of B rows, the keys and one column
    per measure (:data:`MEASURES`; units as there)."""
    cols = {k: pc.cast(cases.column(k), typ) for k, typ in KEYS}
    cols.update({m: pc.cast(f(cases), _TYPES[kind]) for m, (f, kind) in MEASURES.items()})
    return pa.table(cols)


def _pack(cols: list, typ: pa.DataType) -> pa.FixedSizeListArray:
    """K arrays of G values (nulls allowed) -> G fixed-size lists of K, row-major (no loop over rows)."""
    cols = [c.combine_chunks() if isinstance(c, pa.ChunkedArray) else c for c in cols]
    dtype = typ.to_pandas_dtype()
    vals = np.stack([np.asarray(pc.fill_null(c, 0).to_numpy(zero_copy_only=False), dtype=dtype) for c in cols], 1)
    mask = np.stack([pc.is_null(c).to_numpy(zero_copy_only=False) for c in cols], 1)
    return pa.FixedSizeListArray.from_arrays(pa.array(vals.ravel(), type=typ, mask=mask.ravel()), len(cols))


def summarize(cases: pa.Table) -> pa.Table:
    """The shard's partial aggregates: ``cases`` (B rows of ``star_cases``) -> G rows of :data:`SCHEMA`, one per
    distinct (status, status_robust, n_observed), G <= B; ``cases`` sums to B.

    Single-threaded aggregation, so a recomputed shard has bit-identical float sums (the nightly check compares
    every non-timing column)."""
    m = measures(cases)
    names = [k for k, _ in KEYS]
    aggs = [(names[0], "count", pc.CountOptions(mode="all"))]
    for name in MEASURES:
        aggs += [(name, "sum", pc.ScalarAggregateOptions(skip_nulls=True, min_count=1)),
                 (name, "count", pc.CountOptions(mode="only_valid"))]
    g = m.group_by(names, use_threads=False).aggregate(aggs)
    # one order (keys ascending, nulls last: the default) so a shard's file does not depend on hash-table order
    g = g.sort_by([(k, "ascending") for k in names])
    cols = {k: pc.cast(g.column(k), typ) for k, typ in KEYS}
    cols["cases"] = pc.cast(g.column(f"{names[0]}_count"), pa.int64())
    for col, kind in PACKS:
        cols[col] = _pack([g.column(f"{m}_sum") for m in _names(kind)], _TYPES[kind])
    cols["counts"] = _pack([g.column(f"{m}_count") for m in MEASURES], pa.int64())
    return pa.table(cols, schema=SCHEMA)


def unpack(packed: pa.Table) -> pa.Table:
    """:data:`SCHEMA` rows (R) -> the same R rows in :data:`WIDE_SCHEMA` (one named column per sum and count).

    Each packed column's values are viewed as an (R, K) matrix (numpy, one copy per slot); nulls are kept."""
    n = packed.num_rows
    out = {k: packed.column(k) for k in [k for k, _ in KEYS] + ["cases"]}
    mats = {}
    for f in SCHEMA:
        if pa.types.is_fixed_size_list(f.type):
            col = packed.column(f.name).combine_chunks()
            flat = pc.list_flatten(col) if n else pa.array([], f.type.value_type)
            k = f.type.list_size
            vals = np.asarray(pc.fill_null(flat, 0).to_numpy(zero_copy_only=False)).reshape(n, k)
            null = np.asarray(pc.is_null(flat).to_numpy(zero_copy_only=False)).reshape(n, k)
            mats[f.name] = (vals, null)
    for col, i, name in _slots():
        vals, null = mats[col]
        out[name] = pa.array(vals[:, i], mask=null[:, i] if null[:, i].any() else None)
    return pa.table({f.name: pc.cast(out[f.name], f.type) for f in WIDE_SCHEMA}, schema=WIDE_SCHEMA)


def unpack_sql() -> str:
    """DuckDB select list turning :data:`SCHEMA` columns into :data:`WIDE_SCHEMA` ones (lists are 1-based)."""
    return ", ".join([k for k, _ in KEYS] + ["cases"] + [f"{col}[{i + 1}] AS {name}" for col, i, name in _slots()])


def merge_sql() -> str:
    """DuckDB select list that sums :data:`SCHEMA` rows per key into the :data:`WIDE_SCHEMA` columns, in one pass
    over the files (use with ``GROUP BY ALL``; sums of integers come out as HUGEINT, null when all null)."""
    return ", ".join([k for k, _ in KEYS] + ["sum(cases) AS cases"]
                     + [f"sum({col}[{i + 1}]) AS {name}" for col, i, name in _slots()])


def merge(wide: pa.Table) -> pa.Table:
    """Sum partial aggregates (rows of :data:`WIDE_SCHEMA` from any shards) per key: -> one row per distinct key,
    same schema.  The in-Python twin of what the report SQL does (for tests and tools)."""
    names = [k for k, _ in KEYS]
    value_cols = [f.name for f in WIDE_SCHEMA if f.name not in names]
    aggs = [(c, "sum", pc.ScalarAggregateOptions(skip_nulls=True, min_count=1)) for c in value_cols]
    g = wide.group_by(names, use_threads=False).aggregate(aggs).sort_by([(k, "ascending") for k in names])
    out = {k: g.column(k) for k in names}
    out.update({c: g.column(f"{c}_sum") for c in value_cols})
    return pa.table({f.name: pc.cast(out[f.name], f.type) for f in WIDE_SCHEMA}, schema=WIDE_SCHEMA)
