"""A report over rows written before one of its columns existed (an older dualsight's run) ends with one line
naming the report, the column and the way out, not DuckDB's binder error (warehouse/query.run_report)."""

from __future__ import annotations

import duckdb
import pytest

from dualsight.errors import InputError
from dualsight.warehouse.query import run_report, sql_text


def test_a_column_the_rows_lack_is_named_with_the_way_out():
    con = duckdb.connect()
    # every column star_track_summary reads but 'degraded' (the column a run of 2026-11-26 lacks)
    con.execute("CREATE MACRO arcsec_per_rad() AS 206264.80624709636")
    sql = sql_text("star_track_summary")
    assert "degraded" in sql
    con.execute("CREATE TABLE star_frames AS SELECT 'old' AS run, 0 AS case_id")
    con.execute("CREATE TABLE star_sequences AS SELECT 'old' AS run, 0 AS case_id")
    with pytest.raises(InputError) as e:
        run_report(con, "star_track_summary", run="old", limit=100.0)
    msg = str(e.value)
    assert "star_track_summary" in msg and "'old'" in msg and "older dualsight" in msg and "\n" not in msg


def test_other_binder_errors_stay_errors():
    con = duckdb.connect()
    with pytest.raises(duckdb.Error):
        run_report(con, "star_track_summary", run="old", limit=100.0)        # no star_frames at all
