"""``dualsight nightly``: run a suite into the lake, compare every metric with the accepted baseline, keep verdicts.

    dualsight nightly [--suite standard|quick|FILE.toml] [--lake DIR] [--accept] [--html FILE] [--json]
                      [--workers N] [--fresh-seed S] [--no-progress]
    dualsight nightly history [--lake DIR] [--json] [--html FILE]

The night itself is jobs/nightly/run.py's ``run_nightly`` (the suite: jobs/nightly/suite.py); the lines printed
come from jobs/nightly/text.py, the page from viz/nightly_html.py over the verdicts kept in the lake
(jobs/nightly/store.py).

Exit status: 0 green (every verdict identical, ok, improved, info or skipped; or the night was accepted),
1 red (a REGRESSION, or a job "not comparable" / without baseline: accept the new suite deliberately),
2 the night could not run or be compared (bad suite, a job failed, no baseline accepted yet, lake unusable).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from dualsight.errors import InputError
from dualsight.jobs.cli.args import add_lake_arg, open_lake, positive_int
from dualsight.jobs.nightly.text import history_text, json_safe, verdicts_text


def register(sub) -> None:
    """Add the ``nightly`` command (and ``nightly history``) to the top-level sub-parsers."""
    p = sub.add_parser("nightly", help="run the nightly suite, compare with the accepted baseline, keep verdicts",
                       description="Run a suite of jobs into the lake as a new night, compare every metric with "
                                   "the accepted baseline (identical rows, Fisher exact tests of rates, bootstrap "
                                   "tests of error distributions, throughput ratio) and store the verdicts as the "
                                   "dataset nightly_verdicts.  Exit 0 green, 1 regression, 2 could not run.")
    p.add_argument("--suite", default="standard",
                   help="standard (built-in, default), quick (examples/nightly/quick.toml) or a suite TOML file")
    add_lake_arg(p)
    p.add_argument("--accept", action="store_true", help="make this night the accepted baseline")
    p.add_argument("--html", type=Path, default=None, help="write a self-contained HTML page (verdicts, trends) and "
                                                           "the trend figure as PNG beside it")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the verdict lines")
    p.add_argument("--workers", type=positive_int(1, 512), default=None,
                   help="local worker processes per job (default: one per core)")
    p.add_argument("--fresh-seed", type=positive_int(0, 2**63 - 1), default=None,
                   help="seed of the fresh samples (default: from the clock; recorded either way)")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cmd_nightly)
    hsub = p.add_subparsers(dest="nightly_action", metavar="ACTION")
    h = hsub.add_parser("history", help="every metric's trend over the nights (from nightly_verdicts, by SQL)")
    add_lake_arg(h)
    h.add_argument("--json", action="store_true", help="print one JSON object")
    h.add_argument("--html", type=Path, default=None, help="write the self-contained HTML page (and its PNG)")
    h.set_defaults(func=cmd_history)


def _say(msg: str):
    print(msg, file=sys.stderr, flush=True)


def cmd_nightly(args) -> int:
    from dualsight.jobs.nightly.run import run_nightly          # pyarrow, DuckDB (the engine and the lake)

    if args.html is not None and not Path(args.html).parent.is_dir():
        raise InputError(f"folder {Path(args.html).parent} does not exist", source="--html")
    lake = open_lake(args)
    s = run_nightly(args.suite, lake, accept=args.accept, workers=args.workers, fresh_seed=args.fresh_seed,
                    progress=not args.no_progress and sys.stderr.isatty())
    if args.html is not None:
        png = _write_html(lake, args.html, night=s["night"])
        _say(f"page: {args.html} (figure {png})")
    if args.json:
        print(json.dumps(json_safe(s), indent=1, default=str))
    else:
        print(f"night {s['night']} (suite {s['suite']}, baseline {s['baseline'] or 'none'}, fresh seed "
              f"{s['fresh_seed']}; {s['tests']} tests at alpha {s['alpha']:.2g} each, family-wise "
              f"<= {s['family_alpha']:g})")
        print(verdicts_text(s["verdicts"]))
        print(s["message"])
    _say(f"nightly {s['night']}: exit {s['exit']} after {s['elapsed_s']:.0f} s; "
         f"history: dualsight nightly history --lake {lake.root}")
    return s["exit"]


def _write_html(lake, path: Path, night: str | None = None) -> Path:
    """The nightly page of ``night`` (default: the last) with every night's trends; returns its PNG's path."""
    from dualsight.jobs.nightly import store                    # pyarrow
    from dualsight.viz.nightly_html import write_page           # matplotlib

    rows, nights = store.history(lake)
    last = night or (nights[-1]["night"] if nights else None)
    m = lake.read_manifest(store.run_id(last, "verdicts")) if last else None
    info = (m or {}).get("nightly") or {}
    outcome = (info["exit"], info.get("message", "")) if "exit" in info else None
    return write_page(Path(path), [r for r in rows if r["night"] == last], rows, nights,
                      title=f"dualsight nightly, {lake.root}", outcome=outcome)


def cmd_history(args) -> int:
    from dualsight.jobs.nightly import store                    # pyarrow

    if args.html is not None and not Path(args.html).parent.is_dir():
        raise InputError(f"folder {Path(args.html).parent} does not exist", source="--html")
    lake = open_lake(args)
    rows, nights = store.history(lake)
    trends = store.trends(rows)
    if args.html is not None:
        png = _write_html(lake, args.html)
        _say(f"page: {args.html} (figure {png})")
    if args.json:
        print(json.dumps(json_safe({"nights": nights, "trends": trends}), indent=1, default=str))
    else:
        print(history_text(trends, nights))
    return 0
