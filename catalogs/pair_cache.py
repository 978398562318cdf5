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
from dualsight.catalogs.build_progress import build_bar
from dualsight.catalogs.cache import atomic_file, cache_dir as default_cache_dir, resolve_cache_dir, short_hash
from dualsight.catalogs.cache_budget import enforce_limit, mark_in_use
from dualsight.catalogs.pair_estimate import PairEstimate, PairLimits, check_pair_budget, estimate_pairs
from dualsight.catalogs.pairs import (COLUMNS, DEFAULT_MAX_BYTES, FORMAT_VERSION, PairCatalog, check_max_angle,
                                      column_path)

try:
    import fcntl                                                     # POSIX: the build lock
except ImportError:                                                  # pragma: no cover (Windows)
    fcntl = None

__all__ = ["load_pair_catalog", "pair_cache_path", "pair_cache_files", "check_new_pair_catalog"]


def pair_cache_path(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None) -> Path:
    """The cache manifest ``<cache>/pairs-v<FORMAT_VERSION>-<key>.json``, keyed by the star catalog's content
    and the angle; the arrays are ``pairs-v<FORMAT_VERSION>-<key>.{i,j,angle}.npy`` beside it."""
    return resolve_cache_dir(cache_dir) / f"pairs-v{FORMAT_VERSION}-{_pair_key(star_catalog, max_angle_rad)}.json"


def pair_cache_files(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None) -> list[Path]:
    """Every file of a cache entry: the three arrays, then the manifest."""
    man = pair_cache_path(star_catalog, max_angle_rad, cache_dir)
    stem = man.with_suffix("")
    return [column_path(stem, name) for name, _ in COLUMNS] + [man]


def check_new_pair_catalog(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None, *,
                           limits: PairLimits | None = None, source: str | None = None) -> PairEstimate | None:
    """None when the pair catalog of ``star_catalog`` to ``max_angle_rad`` is in the cache (its manifest exists:
    reading it costs nothing); else its :class:`~dualsight.catalogs.pair_estimate.PairEstimate`, or
    :class:`~dualsight.catalogs.pair_estimate.PairCatalogTooLarge` (one line naming ``source``) when it exceeds
    ``limits`` (default: the environment's, :func:`~dualsight.catalogs.pair_estimate.pair_limits`).  Writes
    nothing, creates no folder."""
    theta = check_max_angle(max_angle_rad)
    folder = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    if (folder / f"pairs-v{FORMAT_VERSION}-{_pair_key(star_catalog, theta)}.json").is_file():
        return None
    return check_pair_budget(star_catalog.unit, theta, _mag_limit(star_catalog), limits=limits, source=source,
                             vmag=getattr(star_catalog, "vmag", None))


def _mag_limit(star_catalog) -> float | None:
    """The V limit of a StarCatalog (None for another object with ``unit`` and ``fingerprint()``)."""
    return getattr(getattr(star_catalog, "config", None), "mag_limit", None)


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
                      max_bytes: int = DEFAULT_MAX_BYTES, limits: PairLimits | None = None,
                      source: str | None = None, progress: bool | None = None) -> PairCatalog:
    """Pair catalog of a :class:`~dualsight.catalogs.stars.StarCatalog`, cached as memory-mapped ``.npy``.

    The cache key is the star catalog's content fingerprint (HIP numbers and unit vectors) plus
    ``max_angle_rad`` and :data:`FORMAT_VERSION`, so any change in the stars rebuilds the pairs.  The
    arrays come back read-only memory maps (``np.load(..., mmap_mode="r")``).  A damaged entry (a file
    missing, truncated, of another size or shape, or whose sampled values differ from the manifest's
    digest) is rebuilt with a one-line warning on stderr.  The build holds ``<stem>.lock`` so that
    processes starting together build it once; it needs ``max_bytes`` of memory at most.

    Before a build, its cost is estimated (:func:`check_new_pair_catalog`): over ``limits`` (default from
    ``$DUALSIGHT_MAX_PAIR_GB`` / ``$DUALSIGHT_MAX_PAIR_SECONDS``) it is refused with
    :class:`~dualsight.catalogs.pair_estimate.PairCatalogTooLarge` naming ``source``, and nothing is written;
    a build expected to last more than ~2 s shows a progress bar on stderr (``progress``: None = then, when
    stderr is a terminal; True / False = always / never; :mod:`dualsight.catalogs.build_progress`).  After a
    build the cache is held under its size limit (:func:`dualsight.catalogs.cache_budget.enforce_limit`; this
    entry is marked in use by this process and is never the one removed).
    """
    theta = check_max_angle(max_angle_rad)
    folder = Path(cache_dir).expanduser() if cache_dir is not None else default_cache_dir()
    stem = folder / f"pairs-v{FORMAT_VERSION}-{_pair_key(star_catalog, theta)}"
    man = stem.with_suffix(".json")
    meta = {"key": _pair_key(star_catalog, theta), "format": FORMAT_VERSION, "max_angle_rad": theta,
            "n_stars": len(star_catalog)}
    arrays, why = _open_cached(stem, meta) if folder.is_dir() else (None, None)
    built = False
    if arrays is None:
        mag = _mag_limit(star_catalog)
        if why is None and not man.is_file():                        # a new entry (a damaged one is rebuilt)
            est = check_pair_budget(star_catalog.unit, theta, mag, limits=limits, source=source,
                                    vmag=getattr(star_catalog, "vmag", None))
        else:
            est = estimate_pairs(star_catalog.unit, theta, mag)
        resolve_cache_dir(folder)
        mark_in_use(folder, man)
        with _build_lock(stem):
            arrays, why = _open_cached(stem, meta)                   # another process may have built it
            if arrays is None:
                if why is not None:
                    print(f"dualsight: warning: pair catalog cache {man.name} is damaged ({why}); rebuilding",
                          file=sys.stderr)
                man.unlink(missing_ok=True)                          # the manifest goes first, comes back last
                _remove_stale(stem)
                bar = build_bar(f"pair catalog ({est.field_deg:.1f} deg, {len(star_catalog):,} stars)",
                                2 * est.pairs, est.seconds, progress)
                try:
                    cat = pairs.build_pair_catalog(star_catalog.unit, theta, max_bytes=max_bytes, out=stem,
                                                   progress=bar)
                finally:
                    bar.close()
                arrays = {"i": cat.i, "j": cat.j, "angle": cat.angle}
                doc = {**meta, "pairs": len(cat), "digest": _sample_digest(arrays),
                       "files": {name: column_path(stem, name).name for name, _ in COLUMNS}}
                with atomic_file(man, "w") as f:
                    json.dump(doc, f, sort_keys=True, indent=1)
                built = True
    mark_in_use(folder, man)
    if built:
        enforce_limit(folder)
    return PairCatalog(i=arrays["i"], j=arrays["j"], angle=arrays["angle"], limit_rad=theta)
