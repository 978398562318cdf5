"""The ``dualsight calibrate`` command: chessboard photos -> camera file.

    dualsight calibrate FOLDER [--board 9x6] [--square 0.025] [-o camera.toml] [--pixel-pitch-um P] [--json]

Calibrates from every image in FOLDER (PNG, JPEG, TIFF, FITS; natural order) with
:func:`dualsight.scene.calibration.calibrate_main` (Zhang/Bouguet through OpenCV: inner corners, sub-pixel
refinement, ``calibrateCamera`` with the aspect ratio fixed), prints the summary (focal length in pixels,
principal point, distortion, RMS reprojection error, each board's distance) and writes the camera file
with ``-o``: the ``[camera]`` table every other command reads, plus ``[calibration]`` with the fit and the
per-image board poses (``[[calibration.views]]``: image, distance_m to the centre of the inner-corner
grid, rvec, tvec) -- the per-image range truth ``dualsight hil prox --range-truth camera.toml`` reads.

Without ``--pixel-pitch-um`` the pixel pitch is unknown: the file records a placeholder pitch and says so;
fx, fy (pixels) are the measured quantities, and everything downstream (projection, Eq. 1 of the blobber)
needs only them.

``--json`` prints one object instead of the summary: ``fx, fy, cx, cy`` (px, dualsight convention: from the
top-left pixel corner; OpenCV's principal point is 0.5 px less), ``distortion`` [k1, k2, p1, p2, k3],
``rms_px``, ``std`` (one-sigma of the intrinsics), ``focal_length_mm`` (null without the pitch),
``views`` [{image, distance_m, rms_px}], ``not_found``, ``unreadable``, ``output``.

Exit status 2 with one line naming the folder when it does not exist, holds no images, or the board is
found in fewer than 3 of them (the message lists where it was not found), and for a bad --board/--square.
"""

from __future__ import annotations

import json
from pathlib import Path


def register_calibrate(subparsers) -> None:
    """Add ``calibrate`` to the top-level sub-parsers of ``dualsight`` (jobs/cli.py)."""
    p = subparsers.add_parser("calibrate", help="camera calibration from chessboard photos -> camera file",
                              description="Calibrate a camera from photos of a flat chessboard (Zhang/Bouguet via "
                                          "OpenCV) and write a dualsight camera file.")
    p.add_argument("folder", type=Path, help="folder of chessboard photos")
    p.add_argument("--board", default="9x6", help="inner corners per row x per column (default 9x6: a 10x7-square board)")
    p.add_argument("--square", type=float, default=0.025, help="side of one square, m (default 0.025)")
    p.add_argument("-o", "--output", type=Path, default=None, help="camera file to write (TOML)")
    p.add_argument("--pixel-pitch-um", type=float, default=None,
                   help="physical pixel size, um, for the focal length in mm (default: unknown)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the summary")
    p.set_defaults(func=cmd_calibrate)


def cmd_calibrate(args) -> int:
    from dualsight.errors import InputError
    from dualsight.scene.calibration import calibrate_main

    try:
        res = calibrate_main(args.folder, board=args.board, square=args.square, output=args.output,
                             pixel_pitch_um=args.pixel_pitch_um, quiet=args.json)
    except OSError as e:          # the camera file could not be written
        raise InputError(f"cannot write the camera file ({e.strerror or e})",
                         source=str(args.output) if args.output else str(args.folder)) from None
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
            "output": str(args.output) if args.output else None}, indent=1))
    return 0
