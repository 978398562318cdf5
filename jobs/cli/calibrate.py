"""The ``dualsight calibrate`` command: chessboard photos -> camera file (job kind ``calibrate``).

    dualsight calibrate FOLDER [--board 9x6] [--square 0.025] [-o camera.toml] [--pixel-pitch-um P] [--json]
                       [--lake DIR] [--run ID] [--no-lake] [--workers N] [--scheduler ADDR] [--shard-size N]

The photos of FOLDER (PNG, JPEG, TIFF, FITS; natural order) are the cases of the engine: each shard of photos
finds the board's inner corners (OpenCV ``findChessboardCorners`` + ``cornerSubPix``) and writes them to the
lake (dataset ``calib_views``, resumable, default run id ``calibrate-<spec hash>``); then the corners are read
back (``warehouse/sql/hil_calib_views.sql``) and ``cv2.calibrateCameraExtended`` fits the camera (Zhang/
Bouguet, aspect ratio fixed: jobs/kinds/calibrate.py, scene/calibration.py).  The command prints the summary (focal
length in pixels, principal point, distortion, RMS reprojection error, each board's distance) and with ``-o``
writes the camera file: the ``[camera]`` table every other command reads, plus ``[calibration]`` with the fit
and the per-image board poses (``[[calibration.views]]``: image, distance_m to the centre of the inner-corner
grid, rvec, tvec) -- the per-image range truth ``dualsight hil prox --range-truth camera.toml`` reads.
``-o`` writes into an existing folder only (a missing folder is an error, nothing is created).

Without ``--pixel-pitch-um`` the pixel pitch is unknown: the file records a placeholder pitch and says so;
fx, fy (pixels) are the measured quantities, and everything downstream (projection, Eq. 1 of the blobber)
needs only them.

``--json`` prints one object instead of the summary: ``fx, fy, cx, cy`` (px, dualsight convention: from the
top-left pixel corner; OpenCV's principal point is 0.5 px less), ``distortion`` [k1, k2, p1, p2, k3],
``rms_px``, ``std`` (one-sigma of the intrinsics), ``focal_length_mm`` (null without the pitch),
``views`` [{image, distance_m, rms_px}], ``not_found``, ``unreadable``, ``output``, ``run`` (null with
``--no-lake``).

Exit status 2 with one line naming the folder or file when the folder does not exist or holds no images,
the board is found in fewer than 3 of them (the message lists where it was not found), for a bad
--board/--square, or when the output's folder does not exist.
"""

from __future__ import annotations

from pathlib import Path

from dualsight.jobs.cli.args import add_engine_args


def register_calibrate(subparsers) -> None:
    """Add ``calibrate`` to the top-level sub-parsers of ``dualsight`` (jobs/cli/main.py)."""
    p = subparsers.add_parser("calibrate", help="camera calibration from chessboard photos -> camera file",
                              description="Calibrate a camera from photos of a flat chessboard (Zhang/Bouguet via "
                                          "OpenCV) and write a dualsight camera file.")
    p.add_argument("folder", type=Path, help="folder of chessboard photos")
    p.add_argument("--board", default="9x6", help="inner corners per row x per column (default 9x6: a 10x7-square board)")
    p.add_argument("--square", type=float, default=0.025, help="side of one square, m (default 0.025)")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="camera file to write (TOML), in an existing folder")
    p.add_argument("--pixel-pitch-um", type=float, default=None,
                   help="physical pixel size, um, for the focal length in mm (default: unknown)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the summary")
    add_engine_args(p, prefix="calibrate")
    p.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args) -> int:
    """``dualsight calibrate`` (the module docstring): run by jobs/cli/calibrate_command.py, imported when the
    command runs (the calibrate kind: pyarrow, OpenCV)."""
    from dualsight.jobs.cli import calibrate_command

    return calibrate_command.run(args)
