"""Catalog of star pairs closer than a maximum angle, sorted by angle (for geometric voting).

Kolomenkin et al. (2008) vote with every catalog pair whose angular distance matches an observed
pair's within a tolerance; with the pairs sorted by angle, the candidates for one observed angle are
one contiguous slice found by two binary searches (:func:`dualsight.nav.votes.pair_windows`).
Angles are :func:`dualsight.scene.units.angle_between` (atan2 of |a x b| and a . b), the same
function that measures the observed pairs.

Building (:func:`build_pair_catalog`) is O(N * band) rather than O(N^2): stars are sorted by
declination, and a chunk of rows is only dotted with the stars whose declination is within
``max_angle`` of the chunk's (two stars closer than theta differ in declination by at most theta).
Memory is bounded by ``max_block`` dot products per chunk.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from dualsight.catalogs.cache import read_parquet_or_none, resolve_cache_dir, short_hash, write_parquet_atomic
from dualsight.errors import ConfigError
from dualsight.scene.units import angle_between

FORMAT_VERSION = 2
"""Bump when the build or the stored layout changes: old cache files are then ignored.
(2: angles by ``scene.units.angle_between``; version 1's einsum sums could differ by an ulp.)"""


@dataclass(frozen=True, eq=False)
class PairCatalog:
    """Star pairs, ascending by angle.

    i, j : (M,) int32 row indices into the :class:`~dualsight.catalogs.stars.StarCatalog`, i < j.
    angle : (M,) float64 angular distance (rad), ascending (ties by i, then j).
    limit_rad : the maximum angle the catalog was built with (every ``angle < limit_rad``), or
        None when unknown (then :attr:`max_angle` is the largest angle present).
    """

    i: np.ndarray
    j: np.ndarray
    angle: np.ndarray
    limit_rad: float | None = None

    def __post_init__(self):
        if not (self.i.shape == self.j.shape == self.angle.shape and self.angle.ndim == 1):
            raise ValueError(f"i, j, angle must be 1-D of one length, got {self.i.shape}, {self.j.shape}, "
                             f"{self.angle.shape}")

    def __len__(self) -> int:
        return int(self.angle.shape[0])

    @property
    def nbytes(self) -> int:
        """Memory of the arrays (bytes): 16 per pair (two int32 and one float64)."""
        return int(self.i.nbytes + self.j.nbytes + self.angle.nbytes)

    @property
    def max_angle(self) -> float:
        """Build limit (rad) if known, else the largest angle present (0 for an empty catalog)."""
        if self.limit_rad is not None:
            return float(self.limit_rad)
        return float(self.angle[-1]) if len(self) else 0.0


def _check_max_angle(max_angle_rad) -> float:
    ok = isinstance(max_angle_rad, (int, float, np.integer, np.floating)) and not isinstance(max_angle_rad, bool)
    if not ok or not math.isfinite(max_angle_rad) or not 0.0 < max_angle_rad <= math.pi:
        raise ConfigError(f"must be a finite angle in (0, pi] rad, got {max_angle_rad!r}",
                          field="catalog.max_pair_angle")
    return float(max_angle_rad)


def build_pair_catalog(unit: np.ndarray, max_angle_rad: float, max_block: int = 1 << 22) -> PairCatalog:
    """Every pair of stars closer than ``max_angle_rad``.

    Parameters
    ----------
    unit : (N, 3) float64 unit vectors (the StarCatalog's ``unit``); row numbers become ``i``/``j``.
    max_angle_rad : keep pairs with angle < max_angle_rad (rad), in (0, pi].
    max_block : most dot products computed at once (memory ~ 9 bytes each); a tuning knob only.

    Returns
    -------
    :class:`PairCatalog` with i < j, sorted by angle (ties by i, j).
    """
    theta = _check_max_angle(max_angle_rad)
    u = np.ascontiguousarray(np.asarray(unit, dtype=np.float64).reshape(-1, 3))
    n = u.shape[0]
    dec = np.arcsin(np.clip(u[:, 2], -1.0, 1.0))
    order = np.argsort(dec, kind="stable")
    us, ds = u[order], dec[order]
    # cheap prefilter on the dot product, loosened so that no pair with angle < theta is lost;
    # the exact test is on the atan2 angle below
    cos_cut = math.cos(theta) - 1e-9
    rows = max(1, min(n, max_block // max(n, 1)))
    ii, jj, aa = [], [], []
    a = 0
    while a < n:  # loop over chunks of rows, not over stars
        b = min(n, a + rows)
        hi = int(np.searchsorted(ds, ds[b - 1] + theta + 1e-9, side="right"))  # (b-a)(hi-a) <= max_block
        dots = us[a:b] @ us[a:hi].T                                 # (b-a, hi-a)
        r, c = np.nonzero(dots >= cos_cut)
        keep = c > r                                                # column index is j_s - a, row is i_s - a
        r, c = r[keep] + a, c[keep] + a
        ang = angle_between(us[r], us[c])
        ok = ang < theta
        ii.append(order[r[ok]])
        jj.append(order[c[ok]])
        aa.append(ang[ok])
        a = b
    i = np.concatenate(ii) if ii else np.empty(0, np.int64)
    j = np.concatenate(jj) if jj else np.empty(0, np.int64)
    ang = np.concatenate(aa) if aa else np.empty(0, np.float64)
    lo, hi_ = np.minimum(i, j), np.maximum(i, j)
    s = np.lexsort((hi_, lo, ang))
    return PairCatalog(i=lo[s].astype(np.int32), j=hi_[s].astype(np.int32), angle=ang[s], limit_rad=theta)


_META_KEY = b"dualsight.pair_catalog"


def pair_cache_path(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None) -> Path:
    """``<cache>/pairs-v<FORMAT_VERSION>-<key>.parquet``, keyed by the star catalog's content and the angle."""
    return resolve_cache_dir(cache_dir) / f"pairs-v{FORMAT_VERSION}-{_pair_key(star_catalog, max_angle_rad)}.parquet"


def _pair_key(star_catalog, max_angle_rad: float) -> str:
    return short_hash({"format": FORMAT_VERSION, "stars": star_catalog.fingerprint(),
                       "max_angle_rad": repr(float(max_angle_rad))})


def load_pair_catalog(star_catalog, max_angle_rad: float, cache_dir: str | Path | None = None) -> PairCatalog:
    """Pair catalog of a :class:`~dualsight.catalogs.stars.StarCatalog`, cached as Parquet.

    The cache key is the star catalog's content fingerprint (HIP numbers and unit vectors) plus
    ``max_angle_rad`` and :data:`FORMAT_VERSION`, so any change in the stars rebuilds the pairs.
    """
    theta = _check_max_angle(max_angle_rad)
    key = _pair_key(star_catalog, theta)
    path = pair_cache_path(star_catalog, theta, cache_dir)
    meta = json.dumps({"key": key, "format": FORMAT_VERSION, "max_angle_rad": theta,
                       "n_stars": len(star_catalog)}, sort_keys=True).encode()
    table = read_parquet_or_none(path, _META_KEY, meta)
    if table is not None:
        return PairCatalog(i=np.ascontiguousarray(table.column("i").to_numpy(), dtype=np.int32),
                           j=np.ascontiguousarray(table.column("j").to_numpy(), dtype=np.int32),
                           angle=np.ascontiguousarray(table.column("angle").to_numpy(), dtype=np.float64),
                           limit_rad=theta)
    cat = build_pair_catalog(star_catalog.unit, theta)
    t = pa.table({"i": cat.i, "j": cat.j, "angle": cat.angle}).replace_schema_metadata({_META_KEY: meta})
    write_parquet_atomic(t, path)
    return cat
