"""``dualsight hil prox``, the command itself (its options: jobs/cli/hil_prox.py, which imports this module when the
command runs): the settings, camera, images, truths and target into a ``hil_prox`` spec (every check before the
lake is touched), the run through the engine, and its report (jobs/reports/hil_prox.py) and Figure 8
(viz/threshold_sweep.py) from the lake.
"""

from __future__ import annotations

import json
import sys
import time

from dualsight.errors import ConfigError, InputError
from dualsight.jobs.cli.args import done_message, engine_lake, run_engine
from dualsight.jobs.kinds import hil_prox as hp
from dualsight.jobs.kinds.hil_common import expand_inputs, n_cases
from dualsight.jobs.kinds.hil_defaults import DEFAULT_THRESHOLD
from dualsight.jobs.kinds.hil_truth import load_range_truth
from dualsight.jobs.reports import hil_prox as rep
from dualsight.scene.camera import Camera
from dualsight.warehouse.query import connect

_FLAGS = {"thresholds": "--threshold", "open_px": "--open", "close_px": "--close", "border_px": "--border",
          "roi_px": "--roi",
          "estimator": "--estimator", "blob": "--blob", "area_curve": "--area-curve", "min_pixels": "--min-pixels",
          "table_samples": "--table-samples", "bin_width": "--bin-width"}


def _roi(text):
    """``"X0,Y0,X1,Y1"`` -> four ints (None stays None); a malformed value is a one-line error."""
    if text is None:
        return None
    try:
        v = [int(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 4:
        raise InputError(f"must be four integers X0,Y0,X1,Y1 (pixels), got {text!r}", source="--roi")
    return v


def settings_from_args(args):
    """Validated ``ProxSettings`` of the command line; errors name the flag."""
    ths = hp.parse_sweep(args.sweep) if args.sweep is not None else (
        args.threshold if args.threshold is not None else DEFAULT_THRESHOLD,)
    d = {"thresholds": list(ths), "invert": args.invert, "open_px": args.open_px, "close_px": args.close_px,
         "border_px": args.border_px, "roi_px": _roi(args.roi_px), "undistort": args.undistort, "estimator": args.estimator, "blob": args.blob,
         "area_curve": args.area_curve, "min_pixels": args.min_pixels, "table_samples": args.table_samples}
    try:
        return hp.settings_from_dict(d, source="hil prox")
    except ConfigError as e:
        key = (e.field or "").split(".")[0]
        flag = _FLAGS.get(key, "--sweep" if key == "thresholds" and args.sweep else None)
        raise ConfigError(e.detail, field=flag or e.field) from None


def run(args) -> int:
    """``dualsight hil prox``: the images as a ``hil_prox`` run, the report (text, ``--json``, ``--plot``) read back
    from the lake; exit status 1 when an image could not be processed."""
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
        manifest = run_engine("hil_prox", spec.to_dict(), n_cases(spec), lake, args, label="hil prox")
        run_id = manifest["run_id"]
        con = connect(lake)
        data = rep.fetch(con, run_id)
        text = None if args.json else rep.text_report(con, run_id, data, spec.settings)
        con.close()
    for c in data["cases"]:
        if c["error"]:
            print(f"dualsight: {c['path']}: {c['error']}", file=sys.stderr)
    if args.plot is not None:
        from dualsight.viz.threshold_sweep import hil_prox_figure      # matplotlib (~0.4 s): only with --plot

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
