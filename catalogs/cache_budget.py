"""The cache folder's entries, its size limit (least recently used out first), and clearing it.

Entries (what :func:`list_entries` groups the folder's files into; anything else is listed as ``unknown`` and never
removed, so a ``$DUALSIGHT_CACHE`` pointed at a folder of other files loses none of them):

* ``pairs``: a pair catalog, ``pairs-v<F>-<key>.{i,j,angle}.npy`` + ``.json`` (:mod:`dualsight.catalogs.pair_cache`)
  and the voting's ``.vstars.npy``, ``.vprev.npy`` (:mod:`dualsight.catalogs.pair_voting_cache`); its ``.lock``
  (empty, the build lock) is kept, and its temporaries (``.pairs-v<F>-<key>.build-*`` bucket folders and
  ``.pairs-v<F>-<key>.*.tmp`` files, left by a killed build) belong to it;
* ``stars``: a star catalog ``stars-v<F>-V<mag>-<key>.parquet`` (:mod:`dualsight.catalogs.stars`);
* ``hip2-vmag``: the V magnitudes of every hip2 star, ``hip2-vmag-<key>.npy`` (:mod:`dualsight.catalogs.auto_limit`);
* ``areas``: a projected-area table ``areas/<key>.parquet`` + ``areas/<key>.samples.parquet``
  (:mod:`dualsight.catalogs.areas`).

Taichi's offline kernel cache (the ``taichi/`` sub-folder, :mod:`dualsight.kernels.taichi_runtime`) is not an
entry: it is neither counted nor evicted (``dualsight cache clear --taichi`` removes it).

Last use: the newest of the files' modification and access times; a cache hit marks its files' access time
(:func:`mark_in_use`, an explicit ``utime``, so that it holds whatever the mount's ``noatime``/``relatime``).

Limit: after a cache entry is written, :func:`enforce_limit` removes whole entries, least recently used first,
until the entries total at most ``$DUALSIGHT_CACHE_GB`` GiB (default :data:`DEFAULT_CACHE_GIB`; 0 = no limit).
An entry used by this process (:func:`mark_in_use`) is never removed, nor one whose build lock another process
holds (tried without waiting), nor a temporary modified in the last :data:`TEMP_GRACE_S` seconds (a write in
progress elsewhere).  A pair entry's manifest goes first, under its lock, so a reader sees it absent (and
rebuilds it) or whole, never half; deleting a file another process has mapped leaves its mapping intact (POSIX).
This module imports no numpy, so that ``dualsight cache`` starts fast.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import shutil
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

from dualsight.errors import InputError

try:
    import fcntl                                                     # POSIX: the pair entries' build locks
except ImportError:                                                  # pragma: no cover (Windows)
    fcntl = None

__all__ = ["DEFAULT_CACHE_GIB", "CACHE_GB_ENV", "TEMP_GRACE_S", "TAICHI_FOLDER", "CacheEntry", "cache_limit",
           "list_entries", "mark_in_use", "in_use", "remove_entry", "enforce_limit", "folder_size"]

DEFAULT_CACHE_GIB = 2.0
"""Default size limit of the cache's entries (GiB): the largest pair catalog allowed by default
(:data:`dualsight.catalogs.pair_estimate.DEFAULT_MAX_PAIR_GB`, 2 GB) fits."""

CACHE_GB_ENV = "DUALSIGHT_CACHE_GB"

TEMP_GRACE_S = 120.0
"""A temporary file or bucket folder modified within this many seconds is a write in progress: never removed."""

TAICHI_FOLDER = "taichi"
"""Taichi's kernel cache sub-folder (not an entry of this module)."""

_PAIRS = re.compile(r"^\.?(pairs-v\d+-[0-9a-f]+)\.")
_STARS = re.compile(r"^\.?(stars-v\d+-V([-0-9.]+)-[0-9a-f]+)\.parquet")
_HIP = re.compile(r"^\.?(hip2-vmag-[0-9a-f]+)\.npy")
_AREAS = re.compile(r"^\.?([0-9a-f]+)(?:\.samples)?\.parquet")

_IN_USE: set[tuple[str, str]] = set()         # (resolved cache folder, entry name) used by this process


@dataclass
class CacheEntry:
    """One entry of the cache folder.

    kind : "pairs", "stars", "hip2-vmag", "areas" or "unknown".  name : the files' common stem (for areas,
    ``areas/<key>``).  summary : what it holds, in words.  files : its paths (temporaries included).
    size : bytes on disk (folders summed).  last_used : Unix time (s) of its last use.  temporary : bytes of it
    that are a killed or running build's leftovers.
    """

    kind: str
    name: str
    summary: str = ""
    files: list[Path] = field(default_factory=list)
    size: int = 0
    last_used: float = 0.0
    temporary: int = 0
    newest_temp: float = 0.0

    @property
    def removable(self) -> bool:
        """Whether this module may ever remove it (a known kind)."""
        return self.kind != "unknown"


def cache_limit() -> int | None:
    """The cache's size limit (bytes) from ``$DUALSIGHT_CACHE_GB`` (GiB; default :data:`DEFAULT_CACHE_GIB`;
    0: no limit); anything but a number in [0, 1e6] is an InputError naming the variable."""
    text = os.environ.get(CACHE_GB_ENV)
    if text is None or not text.strip():
        return int(DEFAULT_CACHE_GIB * 2**30)
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and 0 <= x <= 1e6):
        raise InputError(f"must be a size in GiB in [0, 1e6] (0: no limit), got {text!r}", source=f"${CACHE_GB_ENV}")
    return None if x == 0 else int(x * 2**30)


def folder_size(path: Path) -> tuple[int, float]:
    """(bytes: the files' sizes, newest modification time) of a file, or of a folder's files (recursively;
    symbolic links not followed); (0, 0) when it vanished meanwhile."""
    try:
        st = path.lstat()
    except OSError:
        return 0, 0.0
    if not stat.S_ISDIR(st.st_mode):
        return st.st_size, st.st_mtime
    size, newest = 0, st.st_mtime
    for root, dirs, files in os.walk(path):
        for f in files:
            try:
                s = os.lstat(os.path.join(root, f))
            except OSError:
                continue
            size += s.st_size
            newest = max(newest, s.st_mtime)
    return size, newest


def _classify(rel: str) -> tuple[str, str] | None:
    """(kind, entry name) of a cache path relative to the folder, or None for a lock file (not listed)."""
    parts = rel.split("/")
    if len(parts) == 2 and parts[0] == "areas":
        m = _AREAS.match(parts[1])
        return ("areas", f"areas/{m.group(1)}") if m else ("unknown", rel)
    if len(parts) != 1:
        return "unknown", rel
    name = parts[0]
    if name.endswith(".lock") and _PAIRS.match(name):
        return None
    for kind, rx in (("pairs", _PAIRS), ("stars", _STARS), ("hip2-vmag", _HIP)):
        m = rx.match(name)
        if m:
            return kind, m.group(1)
    return "unknown", name


def _summary(entry: CacheEntry, folder: Path) -> str:
    if entry.kind == "pairs":
        man = folder / f"{entry.name}.json"
        try:
            doc = json.loads(man.read_text())
            return (f"{doc['pairs']:,} pairs of {doc['n_stars']:,} stars closer than "
                    f"{math.degrees(doc['max_angle_rad']):.2f} deg")
        except (OSError, ValueError, KeyError, TypeError):
            return "incomplete (no manifest): a killed or running build"
    if entry.kind == "stars":
        m = _STARS.match(Path(entry.name).name + ".parquet")
        return f"star catalog to V {m.group(2)}" if m else "star catalog"
    if entry.kind == "hip2-vmag":
        return "V of every hip2 star (automatic magnitude limit)"
    if entry.kind == "areas":
        return "projected-area table (proximity blobber)"
    return "not dualsight's: never removed"


def list_entries(folder: str | os.PathLike) -> list[CacheEntry]:
    """The entries of cache ``folder`` (not created; none when missing), least recently used first; the Taichi
    folder is left out (module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    items: list[Path] = []
    for p in folder.iterdir():
        if p.name == TAICHI_FOLDER and p.is_dir() and not p.is_symlink():
            continue
        if p.name == "areas" and p.is_dir() and not p.is_symlink():
            items.extend(p.iterdir())
        else:
            items.append(p)
    entries: dict[tuple[str, str], CacheEntry] = {}
    for p in items:
        c = _classify(p.relative_to(folder).as_posix())
        if c is None:
            continue
        e = entries.setdefault(c, CacheEntry(kind=c[0], name=c[1]))
        size, newest = folder_size(p)
        try:
            st = p.lstat()
            used = max(st.st_mtime, st.st_atime if not stat.S_ISDIR(st.st_mode) else st.st_mtime, newest)
        except OSError:
            continue
        e.files.append(p)
        e.size += size
        e.last_used = max(e.last_used, used)
        if p.name.startswith("."):
            e.temporary += size
            e.newest_temp = max(e.newest_temp, newest)
    out = list(entries.values())
    for e in out:
        e.summary = _summary(e, folder)
        e.files.sort()
    out.sort(key=lambda e: (e.last_used, e.name))
    return out


def _key(folder: Path, name: str) -> tuple[str, str]:
    return str(Path(folder).resolve()), name


def mark_in_use(folder: str | os.PathLike, path: str | os.PathLike) -> None:
    """Record that this process uses the entry of ``path`` (a file of cache ``folder``): never evicted by this
    process; and mark its last use (the access time of ``path``, set explicitly; failures ignored)."""
    folder, path = Path(folder), Path(path)
    try:
        rel = path.relative_to(folder).as_posix()
    except ValueError:
        return
    c = _classify(rel)
    if c is None:
        return
    _IN_USE.add(_key(folder, c[1]))
    with contextlib.suppress(OSError):
        st = path.stat()
        os.utime(path, ns=(time.time_ns(), st.st_mtime_ns))         # the modification time kept to the ns


def in_use(folder: str | os.PathLike, name: str) -> bool:
    """Whether this process marked entry ``name`` of cache ``folder`` in use (:func:`mark_in_use`)."""
    return _key(Path(folder), name) in _IN_USE


@contextlib.contextmanager
def _entry_lock(folder: Path, entry: CacheEntry):
    """Yields True when the entry's build lock was taken without waiting (or it has none), False when another
    process holds it."""
    if entry.kind != "pairs" or fcntl is None:
        yield True
        return
    lock = folder / f"{entry.name}.lock"
    if not lock.exists():                                            # never built here: no builder to wait for
        yield True
        return
    try:
        f = open(lock, "r+b")
    except OSError:
        yield False
        return
    with f:
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def remove_entry(folder: str | os.PathLike, entry: CacheEntry, *, now: float | None = None) -> bool:
    """Remove ``entry``'s files (a pair entry's manifest first, under its lock; its ``.lock`` kept).  False, and
    nothing removed, when it is not removable: unknown, in use by this process, locked by another process, or
    with a temporary modified in the last :data:`TEMP_GRACE_S` seconds."""
    folder = Path(folder)
    now = time.time() if now is None else now
    if not entry.removable or in_use(folder, entry.name):
        return False
    if entry.temporary and now - entry.newest_temp < TEMP_GRACE_S:
        return False
    with _entry_lock(folder, entry) as free:
        if not free:
            return False
        first = [p for p in entry.files if p.name.endswith(".json")]
        for p in first + [p for p in entry.files if p not in first]:
            with contextlib.suppress(OSError):
                if p.is_dir() and not p.is_symlink():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    p.unlink()
    return True


def enforce_limit(folder: str | os.PathLike, limit: int | None = None) -> list[CacheEntry]:
    """Remove least recently used entries of cache ``folder`` until its entries total at most ``limit`` bytes
    (default :func:`cache_limit`; None: no limit).  Entries that may not be removed (:func:`remove_entry`) are
    skipped, so the total can stay above the limit.  Returns the removed entries.  Called after a cache entry is
    written; an invalid ``$DUALSIGHT_CACHE_GB`` is then an InputError."""
    limit = cache_limit() if limit is None else limit
    if limit is None:
        return []
    entries = list_entries(folder)
    total = sum(e.size for e in entries)
    removed = []
    now = time.time()
    for e in entries:                                                # least recently used first
        if total <= limit:
            break
        if remove_entry(folder, e, now=now):
            total -= e.size
            removed.append(e)
    return removed
