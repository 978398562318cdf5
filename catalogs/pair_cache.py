"""The pair catalog's on-disk cache (:mod:`dualsight.catalogs.pairs` defines and builds the catalog).

:func:`load_pair_catalog` caches the arrays in the cache folder, keyed by the star catalog's content and
the angle, and opens them with ``np.load(..., mmap_mode="r")``: a run reads the pages it touches, and
several processes share one copy in the page cache.  One entry is the three ``.npy`` columns
(``pairs-v<FORMAT_VERSION>-<key>.{i,j,angle}.npy``, :data:`dualsight.catalogs.pairs.COLUMNS`) and the JSON
manifest ``pairs-v<FORMAT_VERSION>-<key>.json``, written last; a missing, truncated or altered file (sizes,
shapes, dtypes and a digest of sampled values are checked) is rebuilt under a lock with a one-line warning on
stderr, written to temporary names and renamed.  The voting's derived arrays of an entry live beside it
(``<stem>.vstars.npy``, ``<stem>.vprev.npy``: :mod:`dualsight.catalogs.pair_voting_cache`), checked against the
pairs whenever they are mapped.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np

from dualsight.catalogs import pairs       # pairs.build_pair_catalog looked up at call time (tests replace it)
from dualsight.catalogs.cache import atomic_file, resolve_cache_dir, short_hash
from dualsight.catalogs.pairs import (COLUMNS, DEFAULT_MAX_BYTES, FORMAT_VERSION, PairCatalog, check_max_angle,
                                      column_path)

try:
    import fcntl                                                     # POSIX: the build lock
except ImportError:                                                  # pragma: no cover (Windows)
    fcntl = None

__all__ = ["load_pair_catalog", "pair_cache_path", "pair_cache_files"]


def pair_cache_path(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None) -> Path:
    """The cache manifest ``<cache>/pairs-v<FORMAT_VERSION>-<key>.json``, keyed by the star catalog's content
    and the angle; the arrays are ``pairs-v<FORMAT_VERSION>-<key>.{i,j,angle}.npy`` beside it."""
    return resolve_cache_dir(cache_dir) / f"pairs-v{FORMAT_VERSION}-{_pair_key(star_catalog, max_angle_rad)}.json"


def pair_cache_files(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None) -> list[Path]:
    """Every file of a cache entry: the three arrays, then the manifest."""
    man = pair_cache_path(star_catalog, max_angle_rad, cache_dir)
    stem = man.with_suffix("")
    return [column_path(stem, name) for name, _ in COLUMNS] + [man]


def _pair_key(star_catalog, max_angle_rad: float) -> str:
    return short_hash({"format": FORMAT_VERSION, "stars": star_catalog.fingerprint(),
                       "max_angle_rad": repr(float(max_angle_rad))})


def _sample_digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 (16 hex) of 257 evenly spaced values of each array (the ends included).  Memory-mapped
    arrays are read with ``pread`` from their files, not through the map: touching a mapped page maps its
    whole (possibly large) folio into the process, ~1 MiB per sample on this machine."""
    h = hashlib.sha256()
    for name, _ in COLUMNS:
        a = arrays[name]
        if not a.size:
            continue
        k = np.unique(np.linspace(0, a.size - 1, min(a.size, 257)).astype(np.int64))
        fn = getattr(a, "filename", None)
        if isinstance(a, np.memmap) and fn is not None and a.base is not None and a.flags.c_contiguous:
            size = a.dtype.itemsize
            fd = os.open(fn, os.O_RDONLY)
            try:
                whole = os.fstat(fd).st_size == a.offset + a.nbytes       # the whole file's array, not a slice
                raw = b"".join(os.pread(fd, size, a.offset + int(x) * size) for x in k) if whole else None
            finally:
                os.close(fd)
            if raw is not None and len(raw) == size * k.size:
                h.update(np.frombuffer(raw, dtype=a.dtype).tobytes())
                continue
        h.update(np.ascontiguousarray(a[k]).tobytes())
    return h.hexdigest()[:16]


def _open_cached(stem: Path, meta: dict) -> tuple[dict | None, str | None]:
    """The memory-mapped arrays of a cache entry, or (None, reason) when missing or damaged
    (reason None: simply absent, or a manifest of another build)."""
    man = stem.with_suffix(".json")
    if not man.is_file():
        partial = any(column_path(stem, name).exists() for name, _ in COLUMNS)
        return None, ("incomplete: arrays without their manifest" if partial else None)
    try:
        stored = json.loads(man.read_text())
    except (OSError, ValueError):
        return None, "unreadable manifest"
    if not isinstance(stored, dict) or any(stored.get(k) != v for k, v in meta.items()):
        return None, None
    arrays = {}
    for name, dt in COLUMNS:
        p = column_path(stem, name)
        try:
            a = np.load(p, mmap_mode="r", allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            return None, f"{p.name}: {type(e).__name__}: {str(e)[:80]}"
        if a.dtype != dt or a.shape != (stored.get("pairs"),) or \
                p.stat().st_size != a.offset + a.nbytes:
            return None, f"{p.name}: {a.dtype} {a.shape}, {p.stat().st_size} bytes, expected {dt} " \
                         f"({stored.get('pairs')},)"
        arrays[name] = a
    if _sample_digest(arrays) != stored.get("digest"):
        return None, "sampled values differ from the manifest's digest"
    return arrays, None


def _remove_stale(stem: Path) -> None:
    """Remove what a killed build of this entry left (its bucket folder, temporary arrays), called while
    holding the entry's lock, so that no live build of it can own them."""
    for p in stem.parent.glob(f".{stem.name}.*"):
        if p.name.startswith(f".{stem.name}.build-") and p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        elif p.name.endswith(".tmp") and p.is_file():
            p.unlink(missing_ok=True)


@contextlib.contextmanager
def _build_lock(stem: Path):
    """An exclusive lock on ``<stem>.lock`` (POSIX ``flock``; none elsewhere): one process builds an
    entry while the others wait, then read it."""
    if fcntl is None:                                                # pragma: no cover (Windows)
        yield
        return
    with open(stem.with_suffix(".lock"), "a+b") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def load_pair_catalog(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None, *,
                      max_bytes: int = DEFAULT_MAX_BYTES) -> PairCatalog:
    """Pair catalog of a :class:`~dualsight.catalogs.stars.StarCatalog`, cached as memory-mapped ``.npy``.

    The cache key is the star catalog's content fingerprint (HIP numbers and unit vectors) plus
    ``max_angle_rad`` and :data:`FORMAT_VERSION`, so any change in the stars rebuilds the pairs.  The
    arrays come back read-only memory maps (``np.load(..., mmap_mode="r")``).  A damaged entry (a file
    missing, truncated, of another size or shape, or whose sampled values differ from the manifest's
    digest) is rebuilt with a one-line warning on stderr.  The build holds ``<stem>.lock`` so that
    processes starting together build it once; it needs ``max_bytes`` of memory at most.
    """
    theta = check_max_angle(max_angle_rad)
    man = pair_cache_path(star_catalog, theta, cache_dir)
    stem = man.with_suffix("")
    meta = {"key": _pair_key(star_catalog, theta), "format": FORMAT_VERSION, "max_angle_rad": theta,
            "n_stars": len(star_catalog)}
    arrays, why = _open_cached(stem, meta)
    if arrays is None:
        with _build_lock(stem):
            arrays, why = _open_cached(stem, meta)                   # another process may have built it
            if arrays is None:
                if why is not None:
                    print(f"dualsight: warning: pair catalog cache {man.name} is damaged ({why}); rebuilding",
                          file=sys.stderr)
                man.unlink(missing_ok=True)                          # the manifest goes first, comes back last
                _remove_stale(stem)
                cat = pairs.build_pair_catalog(star_catalog.unit, theta, max_bytes=max_bytes, out=stem)
                arrays = {"i": cat.i, "j": cat.j, "angle": cat.angle}
                doc = {**meta, "pairs": len(cat), "digest": _sample_digest(arrays),
                       "files": {name: column_path(stem, name).name for name, _ in COLUMNS}}
                with atomic_file(man, "w") as f:
                    json.dump(doc, f, sort_keys=True, indent=1)
    return PairCatalog(i=arrays["i"], j=arrays["j"], angle=arrays["angle"], limit_rad=theta)
