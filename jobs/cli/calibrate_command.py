"""``dualsight calibrate``, the command itself (its options: jobs/cli/calibrate.py, which imports this module when
the command runs): the photos as the cases of a ``calibrate`` run (jobs/kinds/calibrate.py), the corners read back
from the lake, the camera fitted (scene/calibration.py) and written (scene/camera_file.py).
"""

from __future__ import annotations

import json
from pathlib import Path

from dualsight.errors import ImageError, InputError
from dualsight.jobs.cli.args import engine_lake, run_engine
from dualsight.jobs.kinds import calibrate as job
from dualsight.jobs.kinds.hil_common import n_cases
from dualsight.scene.imageio import list_images
from dualsight.scene import calibration as cal
from dualsight.scene.camera_file import write_camera_toml
from dualsight.warehouse.query import connect, run_report


def check_output(path: Path | None):
    """Refuse, before any work, an output whose folder does not exist or that is a folder."""
    if path is None:
        return
    if path.is_dir():
        raise InputError("is a folder; give the camera file's name, e.g. camera.toml", source=str(path))
    if not path.parent.is_dir():
        raise InputError(f"folder {path.parent} does not exist; create it first (calibrate writes into existing "
                         "folders only)", source=str(path))


def run(args) -> int:
    """``dualsight calibrate``: the photos as a ``calibrate`` run, the corners read back from the lake, the camera
    fitted (and with ``-o`` written), the summary or ``--json`` object printed."""
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
        manifest = run_engine("calibrate", spec_dict, n_cases(spec), lake, args, label="calibrate")
        con = connect(lake)
        cols, rows = run_report(con, "hil_calib_views", run=manifest["run_id"])
        con.close()
    rest_at = (f"every photo's reason: {job.rows_query(manifest['run_id'], lake.root)}" if kept else
               "run without --no-lake to keep every photo's reason in the lake")
    res = job.solve(spec, [dict(zip(cols, r)) for r in rows], rest_at=rest_at)
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
        print(cal.format_summary(res, rest_at) + (f"\nwrote {args.output}" if args.output is not None else "")
              + (f"\nrun {manifest['run_id']} in {lake.root} (dataset calib_views)" if kept else ""))
    return 0
