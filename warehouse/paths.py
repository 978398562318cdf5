"""Where the lake is and how its runs are named, without opening it (no pyarrow: the command line builds its
parser, ``--lake`` help and ``--run`` check from this module alone): the default lake folder, the run-id rule,
and an OS error as one line naming the path.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from dualsight.errors import InputError

__all__ = ["RUN_ID_PATTERN", "RUN_ID_RE", "default_lake", "is_run_id", "check_run_id", "os_error_text"]

RUN_ID_PATTERN = r"[A-Za-z0-9._-]{1,64}"
"""What a run id is, in full: letters, digits, '.', '_', '-'; 1 to 64 characters (and never "." or "..")."""
RUN_ID_RE = re.compile(RUN_ID_PATTERN)


def default_lake() -> Path:
    """``$DUALSIGHT_LAKE`` or ``./lake``."""
    return Path(os.environ.get("DUALSIGHT_LAKE", "lake"))


def is_run_id(run_id) -> bool:
    """Whether ``run_id`` is a string matching :data:`RUN_ID_PATTERN` in full, other than "." and ".."."""
    return isinstance(run_id, str) and bool(RUN_ID_RE.fullmatch(run_id)) and run_id not in (".", "..")


def check_run_id(run_id) -> str:
    """``run_id`` if it matches ``[A-Za-z0-9._-]{1,64}`` in full (no newline, no path), else InputError."""
    if not is_run_id(run_id):
        raise InputError(f"run id {run_id!r} must match {RUN_ID_PATTERN} in full (letters, digits, '.', '_', '-'; "
                         "1 to 64 characters)", source="--run")
    return run_id


def os_error_text(e: OSError) -> str:
    """``No space left on device`` etc. for an OSError, naming the path when known."""
    what = e.strerror or type(e).__name__
    return f"{e.filename}: {what}" if getattr(e, "filename", None) else what
