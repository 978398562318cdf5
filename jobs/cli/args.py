"""Command-line building blocks shared by every command group (so that no group imports ``jobs/cli/main.py``):
the one-line-error parser, typed option parsers, the lake option and the shared run options; and what the HIL
commands (``hil star``, ``hil prox``, ``calibrate``) share: their image and engine options, the engine call with a
temporary lake for ``--no-lake`` and the closing line.  Imports only what ``dualsight --help`` needs (no numpy)."""

from __future__ import annotations

import argparse
import contextlib
import shutil
import sys
import tempfile
from pathlib import Path

from dualsight.errors import InputError
from dualsight.warehouse.paths import RUN_ID_PATTERN, check_run_id, default_lake


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (the usage is one ``--help`` away)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def run_id_arg(text: str) -> str:
    """argparse type for --run: the full-match run id check (an empty or multi-line id is refused)."""
    try:
        return check_run_id(text)
    except InputError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a run id: it must match {RUN_ID_PATTERN} in full") \
            from None


def positive_int(lo: int, hi: int):
    """argparse type: an integer in [lo, hi] (also written as 1e6 or 1_000_000)."""
    def parse(text: str) -> int:
        try:
            v = float(text.replace("_", "")) if any(c in text for c in "eE.") else int(text.replace("_", ""))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if v != int(v) or not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"must be an integer in [{lo}, {hi:,}], got {text}")
        return int(v)
    return parse


def add_lake_arg(p: argparse.ArgumentParser):
    """``--lake DIR`` (its help names the default lake now: ``$DUALSIGHT_LAKE`` or ``./lake``)."""
    p.add_argument("--lake", type=Path, default=None,
                   help=f"lake folder (default: $DUALSIGHT_LAKE or ./lake, now {default_lake()})")


def open_lake(args):
    """The ``Lake`` of ``--lake`` (``args.lake``), else of the default lake folder."""
    from dualsight.warehouse.lake import Lake          # pyarrow

    return Lake(args.lake if args.lake is not None else default_lake())


def add_run_args(p: argparse.ArgumentParser, *, cases: bool = True, default_preset: str = "paper",
                 presets: tuple[str, ...] = ()):
    """Options shared by every Monte Carlo command (``default_preset`` and ``presets`` for ``--preset``'s help)."""
    names = f"{', '.join(presets)}; " if presets else ""
    p.add_argument("--preset", default=None, help=f"named preset ({names}default: {default_preset})")
    p.add_argument("--config", type=Path, default=None, help="TOML file overriding the preset")
    if cases:
        p.add_argument("--cases", type=positive_int(1, 10**9), default=None,
                       help="number of cases, 1 to 1e9 (default: the preset's)")
    p.add_argument("--seed", type=positive_int(0, 2**63 - 1), default=None,
                   help="run seed: case i draws from default_rng([seed, i])")
    add_lake_arg(p)
    p.add_argument("--run", type=run_id_arg, default=None,
                   help="run id, [A-Za-z0-9._-]{1,64} (default: <job>-<seed>-<cases>-<spec hash>); the same id "
                        "with the same settings resumes, with other settings is refused")
    p.add_argument("--workers", type=positive_int(1, 512), default=None,
                   help="local worker processes (default: one per core)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786) to run shards on "
                   "a cluster; the lake must be on storage every worker can write")
    p.add_argument("--shard-size", type=positive_int(1, 10**6), default=None,
                   help="cases per shard file (default: from the case count, 25 to 1000)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def print_run_end(manifest: dict, run_id: str, n_cases: int, lake, report: str, *, unit: str = "cases",
                  rate_digits: int = 0) -> None:
    """The two stderr lines a Monte Carlo command ends with: the run's status, size and rate
    (``run R: complete, N cases in LAKE, X cases/s``) and the command that reports it."""
    ex = manifest["executions"][-1]
    el = ex.get("elapsed_s")
    rate = f", {ex.get('cases_run', n_cases) / el:.{rate_digits}f} {unit}/s" if el else ""
    print(f"run {run_id}: {manifest['status']}, {n_cases} {unit} in {lake.root}{rate}", file=sys.stderr)
    print(f"report: {report} --lake {lake.root} --run {run_id}", file=sys.stderr)


def latest_run(lake, kinds) -> str:
    """Id of the newest run (by creation time) of one of the job ``kinds`` in ``lake``; InputError when none."""
    runs = [m for m in lake.list_manifests() if m.get("kind") in kinds]
    if not runs:
        raise InputError(f"no {'/'.join(kinds)} run in {lake.root}; run one first", source="--run")
    return max(runs, key=lambda m: m.get("created_unix", 0))["run_id"]


def add_image_args(p: argparse.ArgumentParser):
    """The positional ``images`` (files or folders) and ``--camera``."""
    p.add_argument("images", nargs="+", type=Path, help="image files (PNG, JPEG, TIFF, FITS) or folders of them")
    p.add_argument("--camera", type=Path, required=True, help="camera file (TOML with a [camera] table)")


def add_engine_args(p: argparse.ArgumentParser, *, prefix: str):
    """``--lake``, ``--run``, ``--no-lake``, ``--workers``, ``--scheduler``, ``--shard-size``, ``--no-progress``."""
    g = p.add_argument_group("engine and lake")
    add_lake_arg(g)
    g.add_argument("--run", default=None,
                   help=f"run id (default {prefix}-<hash of the spec and code version>: the same images, settings "
                        "and code resume the same run)")
    g.add_argument("--no-lake", action="store_true",
                   help="run into a temporary lake that is deleted afterwards (nothing kept)")
    g.add_argument("--workers", type=int, default=None, help="local worker processes (default: one per core)")
    g.add_argument("--scheduler", default=None, help="Dask scheduler address (tcp://host:8786) to run the shards "
                   "on a cluster; the lake and the images must be on storage every worker can read and write")
    g.add_argument("--shard-size", type=int, default=None, help="images per shard file (default: automatic)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")


@contextlib.contextmanager
def engine_lake(args):
    """The lake of a HIL command: ``--lake`` / $DUALSIGHT_LAKE / ./lake, or with ``--no-lake`` a temporary
    folder deleted on exit.  Yields (Lake, kept: bool)."""
    from dualsight.warehouse.lake import Lake          # pyarrow

    if not getattr(args, "no_lake", False):
        yield open_lake(args), True
        return
    tmp = tempfile.mkdtemp(prefix="dualsight-nolake-")
    try:
        yield Lake(Path(tmp)), False
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def run_engine(kind: str, spec: dict, n_cases: int, lake, args, *, label: str, progress_default: bool = True) -> dict:
    """``run_job`` with the command's engine options; returns the manifest."""
    from dualsight.jobs.engine.runner import run_job   # pyarrow

    progress = progress_default and not getattr(args, "no_progress", False) and sys.stderr.isatty()
    return run_job(kind, spec, n_cases=n_cases, lake=lake, run_id=getattr(args, "run", None),
                   workers=getattr(args, "workers", None), scheduler=getattr(args, "scheduler", None),
                   shard_size=getattr(args, "shard_size", None), progress=progress, label=label,
                   source=label)


def done_message(summary: str, elapsed_s: float, run_id: str, lake, kept: bool, datasets: tuple[str, ...],
                 query: str) -> str:
    """The closing stderr line of a HIL command: ``summary``, the time, and (lake kept) where the rows are,
    with an SQL example over dataset ``query``."""
    msg = f"{summary} ({elapsed_s:.1f} s)"
    if kept:
        msg += (f"; run {run_id} in {lake.root} (datasets {', '.join(datasets)})\n"
                f"query: dualsight sql \"SELECT * FROM {query} WHERE run = '{run_id}'\" --lake {lake.root}")
    return msg
