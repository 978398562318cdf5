"""The folder where derived catalogs are cached, content keys, and atomic file writes.

Environment:
    DUALSIGHT_CACHE   cache folder (default ``$XDG_CACHE_HOME/dualsight``, else ``~/.cache/dualsight``)

Files are written to a temporary name in the destination folder and renamed into place
(``os.replace`` is atomic on POSIX and Windows within one file system), so a reader never sees
a half-written file and two processes building the same entry at once both end with a whole one.
Cached Parquet tables (star catalogs, area tables) are read and written by
:mod:`dualsight.catalogs.parquet_cache`; this module imports no pyarrow, so the pair catalog's cache and
the voting's derived arrays (:mod:`dualsight.catalogs.pair_voting_cache`, used by ``nav``) do not either.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from pathlib import Path

__all__ = ["cache_dir", "resolve_cache_dir", "short_hash", "atomic_file"]


def cache_dir() -> Path:
    """Folder for dualsight's cached catalogs (not created here).

    ``DUALSIGHT_CACHE`` if set, else ``$XDG_CACHE_HOME/dualsight``, else ``~/.cache/dualsight``.
    """
    env = os.environ.get("DUALSIGHT_CACHE")
    if env:
        return Path(env).expanduser()
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg).expanduser() if xdg else Path.home() / ".cache"
    return base / "dualsight"


def resolve_cache_dir(folder: str | os.PathLike | None) -> Path:
    """``folder`` if given, else :func:`cache_dir`; created if missing."""
    d = Path(folder).expanduser() if folder is not None else cache_dir()
    d.mkdir(parents=True, exist_ok=True)
    return d


def short_hash(payload: dict | str | bytes, n: int = 16) -> str:
    """First ``n`` hex digits of the SHA-256 of ``payload`` (dicts as canonical JSON)."""
    if isinstance(payload, dict):
        payload = json.dumps(payload, sort_keys=True, separators=(",", ":"))
    if isinstance(payload, str):
        payload = payload.encode()
    return hashlib.sha256(payload).hexdigest()[:n]


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb"):
    """Open a temporary file ``.<name>.*.tmp`` beside ``path`` for writing; on a clean exit flush, fsync and rename
    it to ``path`` (a reader sees the old file or the new one, never half), else remove it and re-raise."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise

