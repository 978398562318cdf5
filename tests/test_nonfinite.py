"""Pixels that are not numbers: NaN and infinite pixels of a float frame (FITS) in ``dualsight hil star``.

They are counted in the row (``nonfinite_pixels``), replaced by the frame's finite median before detection (so
they make no detection and the frame solves as without them), named in one stderr line per image; a frame with
fewer than ``MIN_FINITE_PIXELS`` finite pixels is an error row, not a silent ``no_solution``.  No numpy
RuntimeWarning reaches the terminal.  The runs are subprocesses: pytest's own warning capture would hide one.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import dualsight
from dualsight.errors import ImageError
from dualsight.jobs.kinds import hil_star as hs
from dualsight.scene.units import ARCSEC
from helpers import ROOT, lake_rows, shared_real

CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
ESA = shared_real() / "esa_tetra3"
ESA_NAME = "2019-07-29T204726_Alt60_Azi135_Try1"          # the frames' date is read from their file names
W, H = 1024, 768


def _write_fits(path: Path, data: np.ndarray) -> Path:
    from astropy.io import fits

    path.parent.mkdir(parents=True, exist_ok=True)
    fits.PrimaryHDU(data).writeto(path)
    return path


def _hil_star(tmp_path: Path, *images) -> tuple[subprocess.CompletedProcess, list[dict]]:
    """``dualsight hil star`` on ``images`` in a subprocess (its real stderr), and the run's ``hil_star`` rows."""
    lake = tmp_path / "lake"
    r = subprocess.run([sys.executable, "-m", "dualsight", "hil", "star", "--camera", str(CAMERA), "--no-compare",
                        "--no-progress", "--lake", str(lake), "--run", "nf", *map(str, images)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, PYTHONWARNINGS="default"))
    rows = lake_rows(lake, "nf", {"hil_star": "case_id"})["hil_star"] if (lake / "hil_star").exists() else []
    return r, rows


def _nan_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if "NaN or infinite" in ln]


def _esa_float32() -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    src = ESA / f"{ESA_NAME}.tiff"
    if not src.exists():
        pytest.skip(f"ESA tetra3 frames not found at {ESA}")
    raw = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
    return (raw >> 4).astype(np.float32)                       # the 12-bit ADC counts, as float32


def test_esa_frame_with_nan_and_inf_solves_as_clean(tmp_path):
    frame = _esa_float32()
    bad = frame.copy()
    bad[700:740, 20:60] = np.nan                               # a 40 x 40 block in a corner
    inf_at = [(10, 1000), (300, 512), (600, 100)]
    for k, (y, x) in enumerate(inf_at):
        bad[y, x] = np.inf if k % 2 == 0 else -np.inf
    planted = 40 * 40 + len(inf_at)
    clean = _write_fits(tmp_path / "clean" / f"{ESA_NAME}.fits", frame)
    dirty = _write_fits(tmp_path / "dirty" / f"{ESA_NAME}.fits", bad)

    r, rows = _hil_star(tmp_path, clean, dirty)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "RuntimeWarning" not in r.stderr, r.stderr[-3000:]
    assert _nan_lines(r.stderr) == [f"dualsight: {ESA_NAME}.fits: {planted:,} of {W * H:,} pixels are NaN or "
                                    "infinite; ignored"], r.stderr[-3000:]
    c, d = rows
    assert c["nonfinite_pixels"] == 0 and d["nonfinite_pixels"] == planted
    assert c["error"] is None and d["error"] is None
    assert c["identified"] and d["identified"], (c["status"], d["status"])
    A_c, A_d = np.reshape(c["A_est"], (3, 3)), np.reshape(d["A_est"], (3, 3))
    cos = np.clip((np.trace(A_c @ A_d.T) - 1) / 2, -1, 1)
    assert np.arccos(cos) < 1 * ARCSEC, np.arccos(cos) / ARCSEC


@pytest.mark.parametrize("finite, reason", [(0, f"all {W * H:,} pixels are NaN or infinite"),
                                            (hs.MIN_FINITE_PIXELS - 1, f"{W * H - hs.MIN_FINITE_PIXELS + 1:,} of "
                                             f"{W * H:,} pixels are NaN or infinite")])
def test_frame_without_enough_finite_pixels_is_an_error_row(tmp_path, finite, reason):
    data = np.full((H, W), np.nan, np.float32)
    data.flat[:finite] = 100.0
    path = _write_fits(tmp_path / "2019-07-29T204726_Alt40_Azi45_Try1.fits", data)
    r, rows = _hil_star(tmp_path, path)
    assert r.returncode == 1, r.stderr[-3000:]                 # as for any image that could not be processed
    assert "RuntimeWarning" not in r.stderr, r.stderr[-3000:]
    lines = _nan_lines(r.stderr)
    assert len(lines) == 1 and reason in lines[0] and lines[0].endswith("; skipped, the other images go on"), lines
    (row,) = rows
    assert reason in row["error"] and row["status"] == "error" and not row["identified"]
    assert row["nonfinite_pixels"] == W * H - finite
    assert "1 could not be processed" in r.stderr


def test_fill_nonfinite_leaves_clean_frames_alone():
    rng = np.random.default_rng(3)
    for frame in (rng.integers(0, 4096, (32, 32), dtype=np.uint16), rng.normal(100, 5, (32, 32)).astype(np.float32)):
        assert hs.nonfinite_pixels(frame) == 0
        assert hs.fill_nonfinite(frame, 0) is frame            # the same array: bit-identical detections
    f = rng.normal(100, 5, (32, 32))
    f[3, 4], f[5, 6], f[7, 8] = np.nan, np.inf, -np.inf
    assert hs.nonfinite_pixels(f) == 3
    out = hs.fill_nonfinite(f, 3)
    good = np.isfinite(f)
    assert np.isfinite(out).all() and np.array_equal(out[good], f[good])
    assert (out[~good] == np.median(f[good])).all()
    with pytest.raises(ImageError, match=f"all {32 * 32:,} pixels are NaN or infinite"):
        hs.fill_nonfinite(np.full((32, 32), np.nan), 32 * 32, source="x.fits")


def test_solve_still_refuses_nan_arrays():
    frame = np.zeros((H, W), np.float32)
    frame[5, 5] = np.nan
    with pytest.raises(ImageError, match="non-finite pixels"):
        dualsight.solve(frame, CAMERA)
