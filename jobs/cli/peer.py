"""``dualsight peer import ANSWERS.json [--method NAME] [--run ID] [--lake DIR]``: a peer solver's per-frame answers
into the lake as dataset ``peer_star`` (job kind ``peer_star``: the answers file's layout, its checks and the run
are jobs/kinds/peer_star.py).  Exit 0 imported, 2 bad input (one line, the lake untouched).
"""

from __future__ import annotations

import sys
from pathlib import Path

from dualsight.jobs.cli.args import add_lake_arg, open_lake, run_id_arg


def register(sub) -> None:
    """Add the ``peer`` command group (``peer import``) to the top-level sub-parsers."""
    peer = sub.add_parser("peer", help="another solver's answers in the lake (joined to hil star runs by SQL)")
    psub = peer.add_subparsers(dest="peer_action", metavar="ACTION")
    p = psub.add_parser("import", help="import a peer solver's per-frame answers (JSON) as dataset peer_star",
                        description="Import a peer solver's per-frame answers (JSON) into the lake as dataset "
                                    "peer_star.")
    p.add_argument("answers", type=Path, help="answers file (JSON; layout: jobs/kinds/peer_star.py)")
    p.add_argument("--method", default=None, help="peer name, e.g. cedar-solve (when the file does not name it)")
    p.add_argument("--run", type=run_id_arg, default=None, help="run id (default peer-star-<spec hash>)")
    add_lake_arg(p)
    p.set_defaults(func=cmd_peer_import)
    peer.set_defaults(func=lambda a: (peer.print_help(), 0)[1])


def cmd_peer_import(args) -> int:
    from dualsight.jobs.kinds.peer_star import import_answers    # pyarrow (the engine and the lake)

    lake = open_lake(args)
    m = import_answers(lake, args.answers, run_id=args.run, method=args.method)
    st = m.get("stats") or {}
    print(f"{m['spec']['method']}: {st.get('frames', m['n_cases'])} frames, {st.get('solved', '?')} solved; run "
          f"{m['run_id']} in {lake.root} (dataset peer_star)\n"
          f"query: dualsight sql \"SELECT * FROM peer_star WHERE run = '{m['run_id']}'\" --lake {lake.root}",
          file=sys.stderr)
    return 0
