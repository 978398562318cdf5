"""A lake that scales (issue 24 point 5): ``star_cases`` <= 100 bytes per case on disk, with what a report or a
replay needs still in the row.

Truth is independent of the code under test: the attitudes from the stored float32 angles and quaternion are
rebuilt here with numpy (the reference's 1-2-3 sequence written out, the quaternion-to-matrix formula), the error
angles from them by the trace formula; the encodings are read back from the Parquet footers (pyarrow), the values
through DuckDB and pyarrow both.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from dualsight.jobs.cli.main import main
from dualsight.scene.attitude import dcm_to_quat
from dualsight.warehouse.lake import parquet_options
from dualsight.warehouse.query import run_sql

CASES, SHARD = 2000, 1000


def _R(axis: int, a: np.ndarray) -> np.ndarray:
    """Passive rotation about x/y/z (1/2/3) by angles a (Markley & Crassidis 2014, Eq. 2.165), written out here."""
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    m = {1: [[o, z, z], [z, c, s], [z, -s, c]], 2: [[c, z, -s], [z, o, z], [s, z, c]],
         3: [[c, s, z], [-s, c, z], [z, z, o]]}[axis]
    return np.moveaxis(np.array(m), (0, 1), (-2, -1))


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """(B, 3, 3) active rotation of (B, 4) quaternions (x, y, z, w) (Shuster 1993, Eq. 161, transposed)."""
    x, y, z, w = np.asarray(q, np.float64).T
    return np.moveaxis(np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - z * w), 2 * (x * z + y * w)],
                                 [2 * (x * y + z * w), w * w - x * x + y * y - z * z, 2 * (y * z - x * w)],
                                 [2 * (x * z - y * w), 2 * (y * z + x * w), w * w - x * x - y * y + z * z]]),
                       (0, 1), (-2, -1))


def test_dcm_to_quat_inverts_the_quaternion_matrix_everywhere():
    rng = np.random.default_rng([24, 5])
    q = rng.normal(size=(20000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[:4] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]          # 180 deg about x, y, z; identity
    q[4:7] = [[1, 1e-9, 0, 1e-12], [0, 1, 1e-9, -1e-12], [1e-9, 0, 1, 0]]       # next to 180 deg
    q[4:7] /= np.linalg.norm(q[4:7], axis=1, keepdims=True)
    canon = q * np.where(q[:, 3:] < 0, -1, 1)
    got = dcm_to_quat(_quat_matrix(q))
    assert np.all(got[:, 3] >= 0)
    # q and -q are one rotation: compare up to sign where w = 0 (the 180-degree rotations)
    err = np.minimum(np.abs(got - canon).max(1), np.abs(got + canon).max(1))
    assert err.max() < 1e-12
    assert np.isnan(dcm_to_quat(np.full((2, 3, 3), np.nan))).all()


@pytest.fixture(scope="module")
def lake(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bytes")
    assert main(["star", "run", "--preset", "paper", "--cases", str(CASES), "--seed", "3", "--workers", "1",
                 "--no-progress", "--shard-size", str(SHARD), "--lake", str(root), "--run", "b"]) == 0
    return root


def _files(lake: Path, dataset: str) -> list[Path]:
    return sorted((lake / dataset / "run=b").glob("part-*.parquet"))


def test_star_cases_fit_in_100_bytes_per_case(lake):
    size = sum(p.stat().st_size for p in _files(lake, "star_cases"))
    assert size / CASES <= 100, size / CASES           # whole files: pages, footers, metadata (measured ~89)
    assert size / CASES >= 50                           # a sanity floor: the rows are really there


def test_encodings_and_types_in_the_footer(lake):
    md = pq.ParquetFile(_files(lake, "star_cases")[0]).metadata
    assert md.num_row_groups == 1 and md.num_rows == SHARD
    rg = md.row_group(0)
    enc = {rg.column(i).path_in_schema: rg.column(i).encodings for i in range(rg.num_columns)}
    assert "DELTA_BINARY_PACKED" in enc["case_id"]
    for c in ("err_x_rad", "theta1_rad", "q_est.list.element", "p_chance", "boresight_err_rad"):
        assert "BYTE_STREAM_SPLIT" in enc[c], c
    assert "RLE_DICTIONARY" in enc["status"] and "RLE_DICTIONARY" in enc["n_observed"]
    names = md.schema.to_arrow_schema().names
    for gone in ("A_true", "A_est", "noise_seed", "ra_true_rad", "dec_true_rad", "ra_est_rad", "dec_est_rad"):
        assert gone not in names
    st = rg.column(names.index("case_id")).statistics
    assert st.has_min_max and (st.min, st.max) == (0, SHARD - 1)


def test_stored_attitudes_give_the_stored_errors(lake):
    """theta (float32) -> A_true by the 1-2-3 sequence, q_est (float32) -> A_est; the rotation angle of
    A_est^T A_true and the angle between their third rows equal err_total_rad and boresight_err_rad to the
    float32 rounding of the stored angles (~1e-7 rad each: 1e-6 rad = 0.2 arcsec allowed)."""
    cols, rows = run_sql(lake, "SELECT theta1_rad, theta2_rad, theta3_rad, q_est, err_total_rad, boresight_err_rad, "
                               "status FROM star_cases WHERE run = 'b' ORDER BY case_id")
    th = np.array([r[:3] for r in rows], np.float64)
    q = np.array([r[3] for r in rows], np.float64)
    tot, bore = (np.array([r[k] for r in rows], np.float64) for k in (4, 5))
    assert len(rows) == CASES
    A_true = _R(3, th[:, 2]) @ _R(2, th[:, 1]) @ _R(1, th[:, 0])
    A_est = _quat_matrix(q)
    ok = np.isfinite(q).all(1)
    assert ok.mean() > 0.9 and np.array_equal(ok, np.isfinite(tot)) and np.array_equal(ok, np.isfinite(bore))
    np.testing.assert_allclose(np.linalg.norm(q[ok], axis=1), 1, atol=1e-6)
    assert np.all(q[ok, 3] >= 0)
    M = np.swapaxes(A_est[ok], 1, 2) @ A_true[ok]
    sin = np.linalg.norm(np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]], 1),
                         axis=1) / 2                     # atan2(sin, cos): no loss near 0, unlike arccos
    np.testing.assert_allclose(np.arctan2(sin, (np.trace(M, axis1=1, axis2=2) - 1) / 2), tot[ok], atol=1e-6)
    a, b = A_est[ok, 2], A_true[ok, 2]
    np.testing.assert_allclose(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("bi,bi->b", a, b)),
                               bore[ok], atol=1e-6)
    assert np.median(tot[ok]) > 1e-6                     # the check is not vacuous: errors are ~arcseconds


def test_writer_options_keep_nested_columns_and_values(tmp_path):
    """Lists, structs and maps get their encodings by leaf path and read back equal (pyarrow and DuckDB)."""
    import duckdb

    t = pa.table({"case_id": pa.array([5, 6, 7], pa.int64()),
                  "l": pa.array([[1, 2], [3], []], pa.list_(pa.int32())),
                  "s": pa.array([{"a": 1.5, "b": "x"}, {"a": -2.0, "b": "x"}, {"a": 0.25, "b": "y"}]),
                  "q": pa.FixedSizeListArray.from_arrays(pa.array(np.arange(6) / 7, pa.float32()), 2),
                  "m": pa.array([[("k", 1)], [("k", 2)], []], pa.map_(pa.string(), pa.int32())),
                  "f": pa.array([0.1, float("nan"), None], pa.float64())})
    opts = parquet_options(t.schema)
    assert opts["column_encoding"] == {"case_id": "DELTA_BINARY_PACKED", "s.a": "BYTE_STREAM_SPLIT",
                                       "q.list.element": "BYTE_STREAM_SPLIT", "f": "BYTE_STREAM_SPLIT"}
    path = tmp_path / "x.parquet"
    pq.write_table(t, path, **opts)
    back = pq.read_table(path).cast(t.schema)                   # list child named "element" on disk
    assert back.drop_columns("f").equals(t.drop_columns("f"))
    f = back.column("f").to_pylist()
    assert f[0] == 0.1 and np.isnan(f[1]) and f[2] is None
    got = duckdb.sql(f"SELECT case_id, s.a, q[2], f FROM '{path}' ORDER BY case_id").fetchall()
    assert got[0][:3] == (5, 1.5, float(np.float32(1 / 7))) and got[2][3] is None
