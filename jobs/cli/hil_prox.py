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
from pathlib import Path

from dualsight.jobs.cli.args import add_engine_args, add_image_args
from dualsight.jobs.kinds.hil_defaults import DEFAULT_THRESHOLD
from dualsight.nav.blobber_names import ESTIMATORS, TARGETS


def add_parser(hsub) -> argparse.ArgumentParser:
    """Add ``hil prox`` to the ``hil`` group's sub-parsers (jobs/cli/hil_star.py)."""
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


def cmd_hil_prox(args) -> int:
    """``dualsight hil prox`` (the module docstring): run by jobs/cli/hil_prox_command.py, imported when the command
    runs (the hil_prox kind: Taichi)."""
    from dualsight.jobs.cli import hil_prox_command

    return hil_prox_command.run(args)
