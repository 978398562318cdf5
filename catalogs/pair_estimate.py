"""Size and time of a pair catalog before it is built, and the bound beyond which a build is refused.

A pair catalog (:mod:`dualsight.catalogs.pairs`) holds every pair of catalog stars closer than the field's
diagonal; its size grows like the square of the star count and, for a field far wider than a star camera's (a
camera file with a focal length of a few pixels: a field of ~170 deg), reaches every pair of the sky, ~10^9 at
V 8: hours and tens of GB.  :func:`estimate_pairs` says what a build would cost without building it, and
:func:`check_pair_budget` refuses one over the bound with one line saying what to do.

Pair count, on the star catalog itself (not a count-magnitude law): the number of pairs is half the sum over
the stars of each one's neighbours within ``theta``, ``M = 1/2 sum_i deg_i``.  Every star's neighbours are
counted exactly (``N`` x ``N`` dot products in row chunks) when ``N^2 <= SAMPLE_DOTS``: then ``M`` is the
build's count exactly (the same angle test: :func:`dualsight.scene.units.angle_between` ``< theta`` wherever
the dot product is within 1e-9 of ``cos theta``).  For a larger catalog ``K = SAMPLE_DOTS / N`` rows, evenly
spaced over the stars sorted by declination (a stratified sample, no random state), give
``M ~ N / (2K) sum_k deg_k`` (relative error ~ the spread of ``deg`` over sqrt(K): about 1 % at V 8).  With a
star count alone, stars uniform on the sphere: ``M = N (N - 1) / 2 x (1 - cos theta) / 2``.

Work of the build's first pass (its dot products: each declination chunk against the stars within ``theta`` in
declination above it): ``D = sum_i #{j >= i: dec_j - dec_i <= theta}`` over the stars sorted by declination,
counted exactly by a binary search (for a star count alone, on the quantiles of a uniform sphere's declination).

Costs, measured on this project's 2-core machine (``benchmarks/``-style runs of ``load_pair_catalog`` then
``VotingIndex.load_or_build`` on the Hipparcos catalog, one process, load ~2):

* time ``T = SECONDS_PER_PAIR x M + SECONDS_PER_DOT x D`` (build + the voting's derived arrays);
* disk ``DISK_BYTES_PER_PAIR`` per pair: the i, j, angle arrays (16 B) and the voting's two interleaved
  arrays (16 B; 32 B when they need int64: more than ~536 M pairs);
* memory: the build's budget (``min(DEFAULT_MAX_BYTES, SORT_BYTES_PER_PAIR x M)``) plus the pages of the
  mapped arrays the voting derivation reads (16 B a pair) and its chunk temporaries
  (``pair_voting_cache.CHUNK_PAIRS`` x 50 B at most): V 8 over 30 deg, 61.4 M pairs, estimated 1.7 GB, peak
  RSS measured 1.63 GB (whole process).

Bound (:func:`pair_limits`): ``$DUALSIGHT_MAX_PAIR_GB`` (default :data:`DEFAULT_MAX_PAIR_GB`, GB = 10^9 bytes
on disk) and ``$DUALSIGHT_MAX_PAIR_SECONDS`` (default :data:`DEFAULT_MAX_PAIR_SECONDS`); 0 lifts a bound.
An entry already in the cache is never refused (it costs nothing to read).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from dualsight.catalogs.pair_voting_cache import CHUNK_PAIRS
from dualsight.catalogs.pairs import DEFAULT_MAX_BYTES, SORT_BYTES_PER_PAIR, check_max_angle
from dualsight.errors import InputError
from dualsight.scene.units import angle_between

__all__ = ["SAMPLE_DOTS", "SECONDS_PER_PAIR", "SECONDS_PER_DOT", "DISK_BYTES_PER_PAIR", "DEFAULT_MAX_PAIR_GB",
           "DEFAULT_MAX_PAIR_SECONDS", "MAX_PAIR_GB_ENV", "MAX_PAIR_SECONDS_ENV", "PairEstimate", "PairLimits",
           "PairCatalogTooLarge", "estimate_pairs", "pair_limits", "check_pair_budget", "suggest_mag_limit"]

SAMPLE_DOTS = 1 << 25
"""Most dot products the estimate computes (~0.2 s): every star's neighbours are counted below ~5,800 stars."""

SECONDS_PER_PAIR = 6.0e-7
"""Seconds per catalog pair: the build's routing and sort (~0.3 us) and the voting's derived arrays (~0.25 us),
measured at V 7-8 over 10-30 deg (2.1 M to 61 M pairs: 0.54-0.72 us a pair in all)."""

SECONDS_PER_DOT = 8.0e-9
"""Seconds per dot product of the build's first pass (fit to V 8 at 10 deg: 41k stars, 7.2 M pairs, 6.2 s)."""

DISK_BYTES_PER_PAIR = 32
"""Bytes on disk per pair with int32 voting arrays (16 for i, j, angle; 16 for the voting's two arrays)."""

DEFAULT_MAX_PAIR_GB = 2.0
"""Default bound on a new pair catalog's size on disk (GB, 10^9 bytes): ~62 M pairs, e.g. V 8 over a 30 deg
diagonal (a star camera's field is 10-25 deg)."""

DEFAULT_MAX_PAIR_SECONDS = 60.0
"""Default bound on a new pair catalog's estimated build time (s)."""

MAX_PAIR_GB_ENV = "DUALSIGHT_MAX_PAIR_GB"
MAX_PAIR_SECONDS_ENV = "DUALSIGHT_MAX_PAIR_SECONDS"

_ROW_ELEMENTS = 1 << 22          # dot products per chunk of rows (32 MiB of float64)
_INT64_PAIRS = (np.iinfo(np.int32).max // 2 - 4096) // 2     # beyond: the voting arrays are int64


@dataclass(frozen=True)
class PairEstimate:
    """What building one pair catalog would cost.

    n_stars : stars of the catalog.  max_angle_rad : the catalog's angle limit (rad).
    mag_limit : the star catalog's V limit (mag), None when not known.
    pairs : expected pair count (exact when ``exact``).  exact : every star's neighbours were counted.
    dots : dot products of the build's first pass.
    disk_bytes : the entry on disk (pairs and the voting's arrays).  memory_bytes : peak memory of the build and
    the voting derivation (bytes).  seconds : expected wall time of both (s, this machine's rates).
    """

    n_stars: int
    max_angle_rad: float
    mag_limit: float | None
    pairs: float
    exact: bool
    dots: float
    disk_bytes: int
    memory_bytes: int
    seconds: float

    @property
    def field_deg(self) -> float:
        """The angle limit in degrees (the field's diagonal for a camera)."""
        return math.degrees(self.max_angle_rad)


@dataclass(frozen=True)
class PairLimits:
    """Bounds on a new pair catalog: ``max_bytes`` on disk and ``max_seconds`` to build (None: no bound)."""

    max_bytes: float | None
    max_seconds: float | None

    def exceeded(self, est: PairEstimate) -> bool:
        """Whether ``est`` is over either bound."""
        return ((self.max_bytes is not None and est.disk_bytes > self.max_bytes)
                or (self.max_seconds is not None and est.seconds > self.max_seconds))


class PairCatalogTooLarge(InputError):
    """A pair catalog whose estimated size or build time exceeds :class:`PairLimits` (one line: what, the
    estimate, the bound and how to proceed).  ``estimate`` is the :class:`PairEstimate`."""

    def __init__(self, message: str, estimate: PairEstimate, *, source: str | None = None):
        self.estimate = estimate
        super().__init__(message, source=source)


def _neighbour_counts(u: np.ndarray, rows: np.ndarray, theta: float) -> np.ndarray:
    """(K,) int64: for each of ``rows``, the stars of ``u`` (N, 3) other than itself closer than ``theta``
    (the build's test: ``angle_between < theta``, checked exactly where the dot product is ambiguous)."""
    n = u.shape[0]
    cos_t = math.cos(theta)
    out = np.empty(rows.size, np.int64)
    step = max(1, _ROW_ELEMENTS // max(n, 1))
    for a in range(0, rows.size, step):                              # chunks of rows, not single stars
        r = rows[a:a + step]
        dots = u[r] @ u.T                                            # (k, N)
        cnt = np.count_nonzero(dots > cos_t + 1e-9, axis=1)
        if np.count_nonzero(dots >= cos_t - 1e-9) > cnt.sum():       # some too close to the edge for the dot
            ri, cj = np.nonzero((dots >= cos_t - 1e-9) & (dots <= cos_t + 1e-9))
            ok = angle_between(u[r[ri]], u[cj]) < theta
            cnt += np.bincount(ri[ok], minlength=r.size)
        del dots
        if theta > 0:
            cnt -= 1                                                  # the star itself (angle 0 < theta)
        out[a:a + step] = cnt
    return out


def _band_dots(dec_sorted: np.ndarray, theta: float) -> float:
    """Dot products of the build's first pass: per star (declination ascending) the stars from it up to
    ``theta`` above it in declination."""
    hi = np.searchsorted(dec_sorted, dec_sorted + theta + 1e-9, side="right")
    return float(np.sum(hi - np.arange(dec_sorted.size)))


def estimate_pairs(stars, max_angle_rad: float, mag_limit: float | None = None) -> PairEstimate:
    """Pair count, disk, memory and time of the pair catalog of ``stars`` to ``max_angle_rad`` (module docstring).

    Parameters
    ----------
    stars : (N, 3) float64 unit vectors (a StarCatalog's ``unit``), or the star count N (an int: stars taken
        uniform on the sphere).
    max_angle_rad : the catalog's angle limit (rad) in (0, pi]: the field's diagonal.
    mag_limit : the star catalog's V limit (mag), carried into the result for messages.

    Pure and cheap: at most :data:`SAMPLE_DOTS` dot products (~0.2 s), nothing written.
    """
    theta = check_max_angle(max_angle_rad)
    if isinstance(stars, (int, np.integer)) and not isinstance(stars, bool):
        n = int(stars)
        if n < 0:
            raise ValueError(f"a star count must be >= 0, got {n}")
        pairs = n * (n - 1) / 2 * (1.0 - math.cos(theta)) / 2
        exact = False
        dec = np.arcsin(np.clip(2.0 * (np.arange(n) + 0.5) / max(n, 1) - 1.0, -1.0, 1.0))
    else:
        u = np.ascontiguousarray(np.asarray(stars, dtype=np.float64).reshape(-1, 3))
        n = u.shape[0]
        dec = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
        order = np.argsort(dec, kind="stable")
        dec = dec[order]
        k = n if n * n <= SAMPLE_DOTS else max(1, SAMPLE_DOTS // max(n, 1))
        exact = k == n
        rows = order if exact else order[((np.arange(k) + 0.5) * n / k).astype(np.int64)]
        deg = _neighbour_counts(u, rows, theta) if n >= 2 else np.zeros(0, np.int64)
        pairs = float(deg.sum()) / 2 if exact else n / (2.0 * k) * float(deg.sum())
    dots = _band_dots(dec, theta)
    per_pair = DISK_BYTES_PER_PAIR + (16 if pairs > _INT64_PAIRS else 0)
    memory = (min(DEFAULT_MAX_BYTES, SORT_BYTES_PER_PAIR * pairs) + 16 * pairs + 50 * min(pairs, CHUNK_PAIRS))
    return PairEstimate(n_stars=n, max_angle_rad=theta, mag_limit=None if mag_limit is None else float(mag_limit),
                        pairs=pairs, exact=exact, dots=dots, disk_bytes=int(per_pair * pairs),
                        memory_bytes=int(memory), seconds=SECONDS_PER_PAIR * pairs + SECONDS_PER_DOT * dots)


def _env_bound(name: str, default: float, scale: float) -> float | None:
    text = os.environ.get(name)
    if text is None or not text.strip():
        return default * scale
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and 0 <= x <= 1e6):
        raise InputError(f"must be a number in [0, 1e6] (0: no bound), got {text!r}", source=f"${name}")
    return None if x == 0 else x * scale


def pair_limits() -> PairLimits:
    """The bounds of a new pair catalog from the environment: ``$DUALSIGHT_MAX_PAIR_GB`` (GB on disk, default
    :data:`DEFAULT_MAX_PAIR_GB`) and ``$DUALSIGHT_MAX_PAIR_SECONDS`` (default :data:`DEFAULT_MAX_PAIR_SECONDS`);
    0 lifts a bound, anything but a number in [0, 1e6] is an InputError naming the variable."""
    return PairLimits(max_bytes=_env_bound(MAX_PAIR_GB_ENV, DEFAULT_MAX_PAIR_GB, 1e9),
                      max_seconds=_env_bound(MAX_PAIR_SECONDS_ENV, DEFAULT_MAX_PAIR_SECONDS, 1.0))


def suggest_mag_limit(vmag, est: PairEstimate, limits: PairLimits) -> float | None:
    """The faintest V limit (0.1 mag grid, rounded down) at which the catalog would fit ``limits``, from the star
    catalog's V magnitudes ``vmag`` (N,) ascending, with pairs ~ N^2 at a fixed field; None when none would."""
    v = np.asarray(vmag, dtype=np.float64)
    if not v.size or est.pairs <= 0:
        return None
    f = 1.0
    if limits.max_bytes is not None:
        f = min(f, limits.max_bytes / max(est.disk_bytes, 1))
    if limits.max_seconds is not None:
        f = min(f, limits.max_seconds / max(est.seconds, 1e-9))
    n_ok = int(v.size * math.sqrt(max(f, 0.0)) * 0.9)                # 10 % margin: the count is an estimate
    if n_ok < 2:
        return None
    return math.floor(float(v[min(n_ok, v.size) - 1]) * 10) / 10


def _size(nbytes: float) -> str:
    return f"{nbytes / 1e9:.1f} GB" if nbytes >= 1e8 else f"{nbytes / 1e6:.0f} MB"


def _duration(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.1f} h"


def check_pair_budget(stars, max_angle_rad: float, mag_limit: float | None = None, *,
                      limits: PairLimits | None = None, source: str | None = None,
                      vmag=None) -> PairEstimate:
    """The :func:`estimate_pairs` of a new pair catalog, or :class:`PairCatalogTooLarge` when it exceeds
    ``limits`` (default :func:`pair_limits`): one line naming ``source`` (the camera file), the field (deg), the
    magnitude limit, the estimated pairs, GB, memory and time, the bound, and how to proceed (a brighter magnitude
    limit, from ``vmag`` when given, or the environment variables)."""
    limits = pair_limits() if limits is None else limits
    est = estimate_pairs(stars, max_angle_rad, mag_limit)
    if not limits.exceeded(est):
        return est
    bound = ", ".join(b for b in (f"{limits.max_bytes / 1e9:g} GB" if limits.max_bytes is not None else "",
                                     f"{limits.max_seconds:g} s" if limits.max_seconds is not None else "") if b)
    v = f"V {est.mag_limit:g}" if est.mag_limit is not None else "its magnitude limit"
    hint = []
    if est.field_deg > 60:
        hint.append("check the camera's fx, fy and size (a star camera's field is 5-30 deg)")
    lim = suggest_mag_limit(vmag, est, limits) if vmag is not None else None
    if lim is not None and (est.mag_limit is None or lim < est.mag_limit):
        hint.append(f"give a brighter magnitude limit (--mag-limit {lim:g} or less)")
    else:
        hint.append("give a brighter magnitude limit (--mag-limit)")
    need_gb = math.ceil(est.disk_bytes / 1e9 * 1.2)
    need_s = math.ceil(est.seconds * 1.5)
    hint.append(f"or allow it: {MAX_PAIR_GB_ENV}={need_gb} {MAX_PAIR_SECONDS_ENV}={need_s} (0: no bound)")
    msg = (f"the pair catalog of a {est.field_deg:.1f} deg field (the image diagonal) to {v} ({est.n_stars:,} "
           f"stars) would hold ~{est.pairs:.2g} pairs: ~{_size(est.disk_bytes)} on disk, ~{_size(est.memory_bytes)} "
           f"of memory, ~{_duration(est.seconds)} to build, over the bound ({bound}): not built; "
           + ", ".join(hint))
    raise PairCatalogTooLarge(msg, est, source=source)
