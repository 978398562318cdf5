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

import json
from pathlib import Path


def register_calibrate(subparsers) -> None:
    """Add ``calibrate`` to the top-level sub-parsers of ``dualsight`` (jobs/cli/main.py)."""
    from dualsight.jobs.cli.args import add_engine_args

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


def check_output(path: Path | None):
    """Refuse, before any work, an output whose folder does not exist or that is a folder."""
    from dualsight.errors import InputError

    if path is None:
        return
    if path.is_dir():
        raise InputError("is a folder; give the camera file's name, e.g. camera.toml", source=str(path))
    if not path.parent.is_dir():
        raise InputError(f"folder {path.parent} does not exist; create it first (calibrate writes into existing "
                         "folders only)", source=str(path))


def cmd_calibrate(args) -> int:
    from dualsight.errors import ImageError, InputError
    from dualsight.jobs.kinds import calibrate as job
    from dualsight.jobs.cli.args import engine_lake, run_engine
    from dualsight.scene import calibration as cal
    from dualsight.scene.camera_file import write_camera_toml
    from dualsight.kernels.imageio import list_images
    from dualsight.warehouse.query import connect, run_report

    board = cal.parse_board(args.board)
    pitch_m = None if args.pixel_pitch_um is None else float(args.pixel_pitch_um) * 1e-6
    cal.check_settings(board, args.square, pitch_m)
    check_output(args.output)
    paths = list_images(args.folder)
    if not paths:
        raise ImageError("no images (.png .jpg .jpeg .tif .tiff .fits .fit .fts) in this folder", source=str(args.folder))
    spec_dict = job.build_spec(paths, board=board, square_m=args.square, pixel_pitch_um=args.pixel_pitch_um)
    spec = job.spec_from_dict(spec_dict, source="calibrate")
    with engine_lake(args) as (lake, kept):
        manifest = run_engine("calibrate", spec_dict, job.n_cases(spec), lake, args, label="calibrate")
        con = connect(lake)
        cols, rows = run_report(con, "hil_calib_views", run=manifest["run_id"])
        con.close()
    res = job.solve(spec, [dict(zip(cols, r)) for r in rows])
    if args.output is not None:
        try:
            write_camera_toml(res, args.output, name=Path(args.folder).name)
        except OSError as e:          # the camera file could not be written
            raise InputError(f"cannot write the camera file ({e.strerror or e})", source=str(args.output)) from None
    if args.json:
        c = res.camera
        print(json.dumps({
            "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height,
            "distortion": list(c.distortion), "rms_px": res.rms_px, "std": res.std,
            "focal_length_mm": res.focal_length_mm,
            "pixel_pitch_um": c.pixel_pitch_m * 1e6 if res.pixel_pitch_known else None,
            "board": list(res.board), "square_m": res.square_m,
            "views": [{"image": v.path.name, "distance_m": v.distance_m, "rms_px": v.rms_px} for v in res.views],
            "not_found": [p.name for p in res.not_found],
            "unreadable": [{"image": p.name, "reason": why} for p, why in res.unreadable],
            "output": str(args.output) if args.output else None,
            "run": manifest["run_id"] if kept else None}, indent=1))
    else:
        print(cal.format_summary(res) + (f"\nwrote {args.output}" if args.output is not None else "")
              + (f"\nrun {manifest['run_id']} in {lake.root} (dataset calib_views)" if kept else ""))
    return 0
