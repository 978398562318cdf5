"""Job kind ``calibrate``: chessboard photos -> inner corners per photo (the engine's cases) -> the camera.

Case i = photo i of the spec's image list.  ``compute_shard`` reads each photo and finds the board's
sub-pixel inner corners (:func:`dualsight.scene.chessboard.find_view`: OpenCV ``findChessboardCorners`` +
``cornerSubPix``), one ``calib_views`` row per photo (an unreadable photo or one changed since the run was
planned gives a row with ``error`` set).  The calibration itself (one ``cv2.calibrateCameraExtended`` over
every view) needs all photos at once: :func:`solve` runs it on the rows read back from the lake
(``warehouse/sql/hil_calib_views.sql``), with exactly the numbers of an in-process
:func:`~dualsight.scene.calibration.calibrate_chessboard` (the corners are stored as float64, which holds
OpenCV's float32 corners exactly).

Spec (pydantic strict)::

    board = [9, 6]               inner corners per row, per column (integers >= 2)
    square_m = 0.025             side of one square (m, > 0)
    pixel_pitch_um = null        physical pixel size (um, > 0) or unknown
    flags = 2                    cv2.calibrateCamera flags (CALIB_FIX_ASPECT_RATIO, as OpenCV's reference)
    aspect_ratio = 1.0           fx / fy when fixed
    find_flags = 11              cv2.findChessboardCorners flags (OpenCV's calibration sample)
    min_views = 3                fewest photos with a board
    images = [{path, bytes, mtime_ns}, ...]
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pyarrow as pa
from pydantic import Field

from dualsight.errors import ConfigError, ImageError
from dualsight.config import validate
from dualsight.jobs.kinds.hil_common import Frozen, ImageEntry, check_unchanged, image_entries, rows_table
from dualsight.scene import calibration as cal
from dualsight.scene.chessboard import FIND_FLAGS_DEFAULT, ViewCorners, find_view

NAME = "calibrate"
PRIMARY = "calib_views"


class CalibSpec(Frozen):
    """A validated calibration run (module docstring)."""

    board: tuple[int, int] = (9, 6)
    square_m: float = Field(default=0.025, gt=0)
    pixel_pitch_um: float | None = Field(default=None, gt=0)
    flags: int = Field(default=cal.CALIB_FLAGS_DEFAULT, ge=0, lt=2**31)
    aspect_ratio: float = Field(default=1.0, gt=0)
    find_flags: int = Field(default=FIND_FLAGS_DEFAULT, ge=0, lt=2**31)
    min_views: int = Field(default=3, ge=1, le=100_000)
    images: tuple[ImageEntry, ...] = Field(min_length=1, max_length=1_000_000)


def spec_from_dict(d: dict, source: str = "spec") -> CalibSpec:
    if not isinstance(d, dict):
        raise ConfigError("must be a table", source=source)
    m = validate(CalibSpec, d, source=source)
    try:
        cal.check_settings(m.board, m.square_m)
    except ConfigError as e:
        raise ConfigError(e.detail, source=source, field="board" if "board" in str(e.field) else "square_m") from None
    return m


def build_spec(paths, *, board=(9, 6), square_m: float = 0.025, pixel_pitch_um: float | None = None) -> dict:
    """A spec dict for ``run_job("calibrate", ...)`` (photos stat'ed now)."""
    return {"board": list(board), "square_m": float(square_m), "pixel_pitch_um": pixel_pitch_um,
            "images": image_entries(paths)}


def make_context(spec: CalibSpec):
    return None


SCHEMA = pa.schema([
    ("case_id", pa.int64()), ("image", pa.string()), ("path", pa.string()), ("error", pa.string()),
    ("width", pa.int32()), ("height", pa.int32()), ("bit_depth", pa.int32()), ("image_digest", pa.int64()),
    ("found", pa.bool_()),
    ("n_corners", pa.int32()), ("corners_px", pa.list_(pa.float64())), ("t_find_ns", pa.int64()),
])
SCHEMAS = {PRIMARY: SCHEMA}
TIMING_COLUMNS = ("t_find_ns",)


def compute_shard(spec: CalibSpec, case_ids: np.ndarray, ctx=None) -> dict[str, pa.Table]:
    """One ``calib_views`` row per photo: size, found, corners (col, row pairs, OpenCV's convention)."""
    rows = []
    for k in np.asarray(case_ids, np.int64):
        entry = spec.images[int(k)]
        t0 = time.perf_counter_ns()
        try:
            check_unchanged(entry)
            v = find_view(entry.path, spec.board, spec.find_flags)
        except ImageError as e:
            v = ViewCorners(Path(entry.path), error=e.detail)
        c = None if v.corners is None else np.asarray(v.corners, np.float64).ravel().tolist()
        rows.append({"case_id": int(k), "image": entry.name, "path": entry.path, "error": v.error,
                     "width": v.width, "height": v.height, "bit_depth": v.bit_depth, "image_digest": v.digest,
                     "found": c is not None,
                     "n_corners": None if c is None else len(c) // 2, "corners_px": c,
                     "t_find_ns": time.perf_counter_ns() - t0})
    return {PRIMARY: rows_table(rows, SCHEMA)}


def shard_summary(tables: dict[str, pa.Table]) -> dict[str, int]:
    t = tables[PRIMARY]
    return {"images": t.num_rows, "found": sum(bool(x) for x in t.column("found").to_pylist()),
            "errors": sum(e is not None for e in t.column("error").to_pylist())}


def progress_postfix(stats: dict) -> str:
    return f"board found in {stats.get('found', 0)}"


def views_from_rows(rows: list[dict]) -> list[ViewCorners]:
    """``calib_views`` rows (case order) -> the corners of each photo."""
    out = []
    for r in rows:
        c = None if r["corners_px"] is None else np.asarray(r["corners_px"], np.float64).reshape(-1, 2).astype(np.float32)
        out.append(ViewCorners(Path(r["path"]), r["width"], r["height"], r["bit_depth"], c, r["error"]))
    return out


def solve(spec: CalibSpec, rows: list[dict], rest_at: str | None = None) -> cal.CalibrationResult:
    """The calibration of a run from its ``calib_views`` rows (InputError when too few boards were found, naming
    the first few photos it could not use; ``rest_at`` says where every one is listed)."""
    return cal.solve_calibration(views_from_rows(rows), board=spec.board, square_m=spec.square_m,
                                 pixel_pitch_m=None if spec.pixel_pitch_um is None else spec.pixel_pitch_um * 1e-6,
                                 flags=spec.flags, aspect_ratio=spec.aspect_ratio, min_views=spec.min_views,
                                 rest_at=rest_at)


def rows_query(run_id: str, lake_root) -> str:
    """The ``dualsight sql`` command that lists every photo of a run with its reason (board found, error)."""
    return (f"dualsight sql \"SELECT image, found, error FROM {PRIMARY} WHERE run = '{run_id}' ORDER BY case_id\" "
            f"--lake {lake_root}")


__all__ = ["NAME", "PRIMARY", "SCHEMAS", "CalibSpec", "spec_from_dict", "build_spec", "make_context",
           "compute_shard", "shard_summary", "progress_postfix", "views_from_rows", "solve", "rows_query"]
