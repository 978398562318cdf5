"""``dualsight hil prox``: the proximity blobber on real photos of a target (job kind ``hil_prox``).

    dualsight hil prox IMAGES... --camera FILE --target FILE [--invert] [--threshold T | --sweep A:B:STEP]
                       [--open K] [--close K] [--border PX] [--undistort] [--estimator paper|subpixel]
                       [--blob largest|all] [--range-truth M|FILE] [--json] [--plot FILE.png]
                       [--lake DIR] [--run ID] [--no-lake] [--workers N] [--scheduler ADDR] [--shard-size N]

The processing (threshold on any channel, inversion, border, opening and closing, the blobber, Eq. 1) is
described in jobs/kinds/hil_prox.py; the truth (``--range-truth``: metres, a JSON file, or a camera file from
``dualsight calibrate``) in jobs/kinds/hil_truth.py.  The images run as the cases of the engine (shards of images,
local workers or Dask, resumable; default run id ``hil-prox-<spec hash>``) into the lake datasets
``hil_prox_cases`` (one row per image) and ``hil_prox`` (one row per image x threshold); everything printed
comes back through the warehouse SQL (``warehouse/sql/hil_prox_*.sql``).

``--json`` prints ONE object::

    {"run": id | null (--no-lake), "camera": {...}, "target": {...}, "settings": {...},
     "images": [{"image", "path", "error", "truth_range_m", "truth_source",
                 "results": [{"threshold", "found", "n_blobs", "n_foreground", "n_pixels", "axis_ratio",
                              "cob_px": [col, row], "unit": [x, y, z], "range_min_m", "range_m",
                              "range_max_m", "error_m", "abs_error_m", "rel_error_pct",
                              "within_min_max", "touches_edge"}, ...]}, ...],
     "sweep": [{"threshold", "images", "found", "with_truth", "avg_range_m", "avg_range_min_m",
                "avg_range_max_m", "avg_truth_m", "avg_abs_error_m", "avg_rel_error_pct",
                "median_rel_error_pct", "within_min_max_pct", ...}, ...],
     "best": the sweep row of the threshold chosen without truth (where the range estimates change least
             with the threshold; null with fewer than 3 thresholds),
     "oracle": the sweep row with the smallest avg_rel_error_pct (chosen with the truth: optimistic; null
               without truth),
     "cross_validated_rel_error_pct": leave-one-image-out error of choosing by truth (null without truth)}

Exit status: 0 when every image was processed (a blob found or not), 1 when an image could not be read
(it is reported on stderr, gets an error entry/row, and the others run), 2 for bad options (nothing
is written).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from dualsight.viz.threshold_sweep import hil_prox_figure

_FLAGS = {"thresholds": "--threshold", "open_px": "--open", "close_px": "--close", "border_px": "--border",
          "roi_px": "--roi",
          "estimator": "--estimator", "blob": "--blob", "area_curve": "--area-curve", "min_pixels": "--min-pixels",
          "table_samples": "--table-samples", "bin_width": "--bin-width"}


def add_parser(hsub) -> argparse.ArgumentParser:
    """Add ``hil prox`` to the ``hil`` group's sub-parsers (jobs/cli/hil_star.py)."""
    from dualsight.jobs.cli.args import add_engine_args, add_image_args
    from dualsight.jobs.kinds.hil_defaults import DEFAULT_THRESHOLD
    from dualsight.nav.blobber_names import ESTIMATORS, TARGETS

    p = hsub.add_parser("prox", help="the proximity blobber on real photos of a target (range vs threshold)",
                        description="Threshold real photos of a target (any channel >= T, optionally inverted, "
                                    "opened and closed) and run the simulations' blobber on them: direction and "
                                    "range by Eq. 1 with the target's projected-area table; a threshold sweep "
                                    "gives the reference's Figure 8.")
    add_image_args(p)
    p.add_argument("--target", type=Path, required=True,
                   help="target model: a satellite TOML (examples/targets/), for its projected-area table")
    g = p.add_argument_group("image processing (reference Sec. 2.4)")
    g.add_argument("--invert", action="store_true", help="dark object on a light background: v -> full scale - v")
    th = g.add_mutually_exclusive_group()
    th.add_argument("--threshold", type=float, default=None,
                    help=f"binary threshold in image units: foreground if ANY channel >= T (default {DEFAULT_THRESHOLD:g})")
    th.add_argument("--sweep", default=None, help="threshold sweep A:B:STEP (B included), e.g. 200:250:5")
    g.add_argument("--open", type=int, default=0, dest="open_px", help="opening with a K x K square, px (0: off)")
    g.add_argument("--close", type=int, default=0, dest="close_px",
                   help="closing with a K x K square, px (0: off); applied after the opening")
    g.add_argument("--border", type=int, default=0, dest="border_px",
                   help="force the outer PX pixels of the frame to background (default 0)")
    g.add_argument("--roi", default=None, metavar="X0,Y0,X1,Y1", dest="roi_px",
                   help="region of interest, pixels (columns X0..X1-1, rows Y0..Y1-1): everything outside is "
                        "background, so the target is not lost to a larger blob elsewhere (the Earth beside the Moon)")
    g.add_argument("--undistort", action="store_true",
                   help="remap each image to the ideal pinhole (same fx, fy, cx, cy) before thresholding")
    b = p.add_argument_group("blobber")
    b.add_argument("--estimator", choices=list(ESTIMATORS), default="paper",
                   help="paper: Eq. 1 as printed (default); subpixel: the blobber's refined estimator")
    b.add_argument("--blob", choices=list(TARGETS), default="largest",
                   help="largest blob (default) or all foreground pixels as one blob")
    b.add_argument("--area-curve", choices=["min", "mean", "max", "median", "relopt"], default=None,
                   help="area curve for the estimate (default: mean for paper, relopt for subpixel)")
    b.add_argument("--min-pixels", type=int, default=1, help="smallest target blob, px (default 1)")
    b.add_argument("--table-samples", type=int, default=20000,
                   help="random orientations of the projected-area table (default 20000)")
    t = p.add_argument_group("truth")
    t.add_argument("--range-truth", default=None, metavar="M|FILE",
                   help="true range: metres for every image, a JSON {image: metres}, or a camera file from "
                        "`dualsight calibrate` (its [[calibration.views]] distance_m per image)")
    o = p.add_argument_group("output")
    o.add_argument("--json", action="store_true", help="print one JSON object (images, sweep, best)")
    o.add_argument("--plot", type=Path, default=None,
                   help="write the reference's Figure 8 (range with min/max bars against threshold) as PNG")
    add_engine_args(p, prefix="hil-prox")
    p.set_defaults(func=cmd_hil_prox)
    return p


def _roi(text):
    """``"X0,Y0,X1,Y1"`` -> four ints (None stays None); a malformed value is a one-line error."""
    if text is None:
        return None
    from dualsight.errors import InputError

    try:
        v = [int(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 4:
        raise InputError(f"must be four integers X0,Y0,X1,Y1 (pixels), got {text!r}", source="--roi")
    return v


def settings_from_args(args):
    """Validated ``ProxSettings`` of the command line; errors name the flag."""
    from dualsight.errors import ConfigError
    from dualsight.jobs.kinds import hil_prox as hp

    ths = hp.parse_sweep(args.sweep) if args.sweep is not None else (
        args.threshold if args.threshold is not None else hp.DEFAULT_THRESHOLD,)
    d = {"thresholds": list(ths), "invert": args.invert, "open_px": args.open_px, "close_px": args.close_px,
         "border_px": args.border_px, "roi_px": _roi(args.roi_px), "undistort": args.undistort, "estimator": args.estimator, "blob": args.blob,
         "area_curve": args.area_curve, "min_pixels": args.min_pixels, "table_samples": args.table_samples}
    try:
        return hp.settings_from_dict(d, source="hil prox")
    except ConfigError as e:
        key = (e.field or "").split(".")[0]
        flag = _FLAGS.get(key, "--sweep" if key == "thresholds" and args.sweep else None)
        raise ConfigError(e.detail, field=flag or e.field) from None


def cmd_hil_prox(args) -> int:
    from dualsight.errors import InputError
    from dualsight.jobs.kinds import hil_prox as hp
    from dualsight.jobs.reports import hil_prox as rep
    from dualsight.jobs.cli.args import done_message, engine_lake, expand_inputs, run_engine
    from dualsight.jobs.kinds.hil_truth import load_range_truth
    from dualsight.scene.camera import Camera
    from dualsight.warehouse.query import connect

    t_start = time.perf_counter()
    settings = settings_from_args(args)
    camera = Camera.from_toml(args.camera)
    paths = expand_inputs(args.images)
    if not paths:
        raise InputError("no image files given", source="IMAGES")
    truths, truth_kind = load_range_truth(args.range_truth, paths)
    target = hp.target_spec(args.target)
    spec = hp.spec_from_dict(hp.build_spec(paths, camera, target, settings, truths, truth_kind),
                             source="hil prox")        # every check before the lake is touched

    with engine_lake(args) as (lake, kept):
        manifest = run_engine("hil_prox", spec.to_dict(), hp.n_cases(spec), lake, args, label="hil prox")
        run_id = manifest["run_id"]
        con = connect(lake)
        data = rep.fetch(con, run_id)
        text = None if args.json else rep.text_report(con, run_id, data, spec.settings)
        con.close()
    for c in data["cases"]:
        if c["error"]:
            print(f"dualsight: {c['path']}: {c['error']}", file=sys.stderr)
    if args.plot is not None:
        hil_prox_figure(data, args.plot, title=f"{target['name']}: {len(paths)} image(s)" + (f", run {run_id}" if kept else ""))
    if args.json:
        a0 = next((r["A0_m2"] for r in data["rows"] if r["A0_m2"] is not None), None)
        tgt = dict(spec.target.to_dict(), file=str(args.target), A0_m2=a0, table_samples=spec.settings.table_samples)
        print(json.dumps(rep.json_document(data, run_id=run_id if kept else None, camera=spec.camera, target=tgt,
                                           settings=spec.settings.to_dict()), indent=1))
    else:
        print(text)
    n_err = sum(1 for c in data["cases"] if c["error"])
    msg = done_message(f"{len(paths)} images x {len(spec.settings.thresholds)} threshold(s): {n_err} could not be "
                       "processed", time.perf_counter() - t_start, run_id, lake, kept, tuple(hp.SCHEMAS),
                       query="hil_prox")
    if args.plot is not None:
        msg += f"\nfigure: {args.plot}"
    print(msg, file=sys.stderr)
    return 1 if n_err else 0
