"""Projected-area tables for the blobber's range estimate (reference Sec. 2.1, Fig. 1).

For many orientations of the target drawn uniformly on SO(3) (Shoemake 1992), the orthographic
projected area ``A`` of the target relative to ``A0`` (its smallest face; for the 3U CubeSat
0.1 x 0.1 m = 0.01 m^2) is tabulated against the silhouette's axis ratio.  The axis ratio is
``sqrt(lambda_max / lambda_min)`` of the 2x2 covariance (second central moments) of the filled
silhouette -- the same definition the blobber applies to the observed blob -- so a face-on 3U CubeSat
(a 0.1 x 0.1 square) has ratio 1 and A/A0 = 1, broadside (0.1 x 0.3) ratio 3 and A/A0 = 3.

Binned by axis ratio (``bin_width``), each bin holds the curves

* ``min``, ``mean``, ``max`` -- the reference's A_min, A_mean, A_max (Eq. 1 with A_mean is ``paper``);
* ``median``;
* ``relopt`` -- ``(E[A^-1/2] / E[A^-1])^2``: the area that minimises the mean squared *relative*
  range error of Eq. 1 over the bin's orientations (rho_est / rho = sqrt(A_c / A), and
  d/dA_c E[(sqrt(A_c/A) - 1)^2] = 0 gives that A_c).

Methods
-------
``exact`` (single convex component): the front faces of a closed convex mesh tile its silhouette
without overlap, so the silhouette's area and second moments are the sums over the front-facing
triangles' orthographic projections (area |cross|/2, second moment A/12 (sum p_i p_i^T +
(sum p_i)(sum p_i)^T)).  For a cuboid that is exact and its area equals the closed form
A = 1/2 sum_i |n_i . v| A_i; a cylinder uses a 256-sided prism with the true cap area; a sphere is
pi r^2 at ratio 1.
``scanline`` (several components, not convex): ``rows`` scanlines across the body's bounding disc;
on each, every convex component's silhouette is one interval -- for a polytope (cuboid; cylinder as
a 128-sided prism with the true cap area) the extreme crossings of the plane through the scanline
and the viewing direction with the polytope's edges, for a sphere the exact circle chord -- and
the union of the components' intervals is integrated exactly along the row (length, int x,
int x^2); the rows are combined by the midpoint rule (each row adding its own dy^2 / 12 variance).

Tables are built once per shape and cached as Parquet in ``<cache>/areas/`` (DUALSIGHT_CACHE or
~/.cache/dualsight; temporary file + atomic rename), keyed by a hash of the geometry and settings.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from dualsight.catalogs.cache import resolve_cache_dir, short_hash
from dualsight.catalogs.parquet_cache import read_parquet_or_none, write_parquet_atomic
from dualsight.scene import primitives as prim
from dualsight.scene.attitude import quat_to_dcm, random_quaternions
from dualsight.scene.motion import euler_deg_to_local_to_parent

TABLE_VERSION = 1
CURVES = ("min", "mean", "max", "median", "relopt")
_META_KEY = b"dualsight.areas"


@dataclass(frozen=True)
class AreaTable:
    """Projected area (relative to A0) against silhouette axis ratio.

    Attributes
    ----------
    key : cache key (hash of geometry and settings).
    A0_m2 : normalising area (m^2): the smallest face of a cuboid, else the smallest sampled area.
    method : "exact" or "scanline".
    n_samples : number of random orientations.
    ratio_lo, ratio_hi, ratio : (K,) bin edges and centres (axis ratio >= 1).
    count : (K,) samples per bin.
    a_min, a_mean, a_max, a_median, a_relopt : (K,) A/A0 per bin (NaN in empty bins).
    samples_ratio, samples_area : (N,) the raw samples (axis ratio, A/A0) -- the reference's Fig. 1.
    """

    key: str
    A0_m2: float
    method: str
    n_samples: int
    ratio_lo: np.ndarray
    ratio_hi: np.ndarray
    ratio: np.ndarray
    count: np.ndarray
    a_min: np.ndarray
    a_mean: np.ndarray
    a_max: np.ndarray
    a_median: np.ndarray
    a_relopt: np.ndarray
    samples_ratio: np.ndarray = field(repr=False)
    samples_area: np.ndarray = field(repr=False)

    def curve(self, name: str) -> np.ndarray:
        if name not in CURVES:
            raise ValueError(f"unknown area curve {name!r}; allowed: {', '.join(CURVES)}")
        return getattr(self, f"a_{name}")

    def lookup(self, ratio, curve: str = "mean") -> np.ndarray:
        """A/A0 at observed axis ratios: linear interpolation between the centres of non-empty bins,
        held constant beyond the first/last; NaN ratios give NaN."""
        y = self.curve(curve)
        ok = np.isfinite(y)
        r = np.asarray(ratio, dtype=np.float64)
        return np.interp(r, self.ratio[ok], y[ok]) + np.where(np.isfinite(r), 0.0, np.nan)

    def area_m2(self, ratio, curve: str = "mean") -> np.ndarray:
        """Projected area (m^2) = lookup(ratio, curve) * A0."""
        return self.lookup(ratio, curve) * self.A0_m2


# ----------------------------------------------------------------------------- shape description
def shape_spec(shape) -> list[dict]:
    """Normalise a SatelliteConfig, a sequence of ComponentConfig, one ComponentConfig or a
    ``(shape, size)`` tuple into a list of ``{shape, size, position, orientation_deg}`` (body frame,
    frame-0 relative poses)."""
    comps = getattr(shape, "components", None)
    if comps is None:
        if isinstance(shape, tuple) and len(shape) == 2 and isinstance(shape[0], str):
            comps = [dict(shape=shape[0], size=tuple(float(x) for x in np.atleast_1d(shape[1])))]
        elif hasattr(shape, "shape") and hasattr(shape, "size"):
            comps = [shape]
        else:
            comps = list(shape)
    out = []
    for c in comps:
        get = (lambda k, d=None: c.get(k, d)) if isinstance(c, dict) else (lambda k, d=None: getattr(c, k, d))
        s = get("shape")
        if s not in prim.SHAPES:
            raise ValueError(f"unknown shape {s!r}; allowed: {', '.join(prim.SHAPES)}")
        out.append(dict(shape=s, size=[float(x) for x in np.atleast_1d(get("size"))],
                        position=[float(x) for x in (get("position") or (0.0, 0.0, 0.0))],
                        orientation_deg=[float(x) for x in (get("orientation_deg") or (0.0, 0.0, 0.0))]))
    if not out:
        raise ValueError("a shape needs at least one component")
    return out


def _pose(c: dict):
    return euler_deg_to_local_to_parent(np.asarray(c["orientation_deg"])), np.asarray(c["position"], float)


def _view_frames(n: int, seed: int):
    """(n, 3, 3) rows e1, e2, d: image axes and viewing direction in the body frame, uniform on SO(3)."""
    R = quat_to_dcm(random_quaternions(np.random.default_rng(seed), n))   # body -> camera (active)
    return R  # rows of R are the camera axes expressed in the body frame


def _ratio_from_cov(cxx, cxy, cyy):
    tr = 0.5 * (cxx + cyy)
    det = np.sqrt(np.maximum(0.25 * (cxx - cyy) ** 2 + cxy * cxy, 0.0))
    lmax, lmin = tr + det, np.maximum(tr - det, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.sqrt(lmax / lmin)
    return np.where(lmax > 0, r, 1.0)


# ----------------------------------------------------------------------------- exact (convex)
def _exact_samples(c: dict, views: np.ndarray, chunk: int = 256):
    s = c["size"]
    if c["shape"] == "sphere":
        n = views.shape[0]
        return np.ones(n), np.full(n, math.pi * (s[0] / 2) ** 2)
    if c["shape"] == "cuboid":
        mesh = prim.cuboid_mesh(s)
    else:
        mesh = prim.cylinder_mesh(s[0], s[1], 256)
    Q, q = _pose(c)
    V = mesh.vertices @ Q.T + q                                      # (T, 3, 3) body frame
    g = np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])               # outward, |g| = 2 * area
    ratios, areas = [], []
    for i in range(0, views.shape[0], chunk):                        # chunks of orientations
        Rv = views[i:i + chunk]                                      # (n, 3, 3)
        d = Rv[:, 2]                                                 # viewing direction (into the scene)
        front = (g @ d.T).T < 0                                      # (n, T): faces towards the camera
        P = np.einsum("nij,tvj->ntvi", Rv[:, :2], V)                 # (n, T, 3, 2) projected vertices
        a = 0.5 * np.abs((P[..., 1, 0] - P[..., 0, 0]) * (P[..., 2, 1] - P[..., 0, 1])
                         - (P[..., 2, 0] - P[..., 0, 0]) * (P[..., 1, 1] - P[..., 0, 1])) * front
        Sp = P.sum(axis=2)                                           # (n, T, 2)
        m1 = (a[..., None] * Sp / 3.0).sum(axis=1)                   # first moments
        PP = np.einsum("ntvi,ntvj->ntij", P, P) + np.einsum("nti,ntj->ntij", Sp, Sp)
        m2 = (a[..., None, None] * PP / 12.0).sum(axis=1)            # second moments about the origin
        A = a.sum(axis=1)
        mu = m1 / A[:, None]
        C = m2 / A[:, None, None] - np.einsum("ni,nj->nij", mu, mu)
        ratios.append(_ratio_from_cov(C[:, 0, 0], C[:, 0, 1], C[:, 1, 1]))
        areas.append(A)
    return np.concatenate(ratios), np.concatenate(areas)


# ----------------------------------------------------------------------------- scanline (any)
def _bound_radius(spec: list[dict]) -> float:
    """Radius (m) about the body origin of a sphere containing every component."""
    r = 0.0
    for c in spec:
        s = np.asarray(c["size"])
        if c["shape"] == "cuboid":
            rc = 0.5 * float(np.linalg.norm(s))
        elif c["shape"] == "sphere":
            rc = 0.5 * s[0]
        else:
            rc = math.hypot(0.5 * s[0], 0.5 * s[1])
        r = max(r, float(np.linalg.norm(c["position"])) + rc)
    return r


def _polytope(c: dict):
    """Vertices (V, 3) in the body frame and edges (E, 2) of a component's convex polytope (None for a sphere)."""
    s = c["size"]
    if c["shape"] == "sphere":
        return None, None
    Q, q = _pose(c)
    if c["shape"] == "cuboid":
        h = np.asarray(s) / 2
        V = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T * h
        i, j = np.nonzero(np.triu(np.abs(V[:, None] - V[None]).astype(bool).sum(-1) == 1))
        E = np.stack([i, j], axis=1)                                 # 12 edges: vertices differing in one axis
    else:
        m = prim.cylinder_mesh(s[0], s[1], 128)                      # prism with the true cap area
        ring = m.vertices[:128, 1]                                   # cap -z ring vertices
        V = np.concatenate([ring, ring + [0, 0, s[1]]])
        k = np.arange(128)
        E = np.concatenate([np.stack([k, (k + 1) % 128], 1), np.stack([k + 128, (k + 1) % 128 + 128], 1),
                            np.stack([k, k + 128], 1)])
    return V @ Q.T + q, E


def _scanline_samples(spec: list[dict], views: np.ndarray, rows: int = 256, chunk: int = 32):
    Rb = _bound_radius(spec) * 1.001
    dy = 2 * Rb / rows
    yk = (np.arange(rows) + 0.5) * dy - Rb                           # row centres
    polys = [_polytope(c) for c in spec]
    ratios, areas = [], []
    for i in range(0, views.shape[0], chunk):                        # chunks of orientations
        Rv = views[i:i + chunk]
        n = Rv.shape[0]
        los, his = [], []
        for c, (V, E) in zip(spec, polys):                           # a handful of components
            if V is None:                                            # sphere: exact circle slices
                ctr = Rv[:, :2] @ np.asarray(c["position"], float)   # (n, 2)
                r = c["size"][0] / 2
                h2 = r * r - (yk[None] - ctr[:, 1:2]) ** 2
                half = np.sqrt(np.maximum(h2, 0))
                lo = np.where(h2 > 0, ctr[:, :1] - half, np.inf)
                hi = np.where(h2 > 0, ctr[:, :1] + half, -np.inf)
            else:                                                    # polytope: plane slice through its edges
                X = np.einsum("nj,vj->nv", Rv[:, 0], V)
                Y = np.einsum("nj,vj->nv", Rv[:, 1], V)
                xa, xb, ya, yb = X[:, E[:, 0]], X[:, E[:, 1]], Y[:, E[:, 0]], Y[:, E[:, 1]]   # (n, E)
                ya_, yb_ = ya[:, None], yb[:, None]
                cross = ((ya_ - yk[None, :, None]) * (yb_ - yk[None, :, None]) <= 0) & (ya_ != yb_)
                with np.errstate(divide="ignore", invalid="ignore"):
                    x = xa[:, None] + (yk[None, :, None] - ya_) * ((xb - xa) / (yb - ya))[:, None]
                lo = np.where(cross, x, np.inf).min(axis=-1)
                hi = np.where(cross, x, -np.inf).max(axis=-1)
            los.append(lo)
            his.append(hi)
        lo, hi = np.stack(los, -1), np.stack(his, -1)                # (n, rows, C)
        o = np.argsort(lo, axis=-1)
        lo, hi = np.take_along_axis(lo, o, -1), np.take_along_axis(hi, o, -1)
        L = np.zeros((n, rows)); Sx = np.zeros((n, rows)); Sxx = np.zeros((n, rows))

        def add(a, b, m):
            ok = m & (b > a)
            a, b = np.where(ok, a, 0.0), np.where(ok, b, 0.0)
            L.__iadd__(b - a)
            Sx.__iadd__(0.5 * (b * b - a * a))
            Sxx.__iadd__((b ** 3 - a ** 3) / 3.0)

        cl, cr = lo[..., 0], hi[..., 0]
        for k in range(1, lo.shape[-1]):                             # union of the components' intervals
            l, h = lo[..., k], hi[..., k]
            new = l > cr
            add(cl, cr, new)
            cl = np.where(new, l, cl)
            cr = np.where(new, h, np.maximum(cr, h))
        add(cl, cr, np.ones_like(cr, bool))
        A = L.sum(1) * dy
        mx = Sx.sum(1) * dy / A
        my = (L * yk).sum(1) * dy / A
        cxx = Sxx.sum(1) * dy / A - mx * mx
        cxy = (Sx * yk).sum(1) * dy / A - mx * my
        cyy = (L * (yk * yk + dy * dy / 12)).sum(1) * dy / A - my * my
        ratios.append(_ratio_from_cov(cxx, cxy, cyy))
        areas.append(A)
    return np.concatenate(ratios), np.concatenate(areas)


def silhouette_stats(shape, rotations, method: str = "auto", rows: int = 256):
    """(axis ratio (n,), orthographic projected area (n,) m^2) for given orientations.

    ``rotations`` : (n, 3, 3) body -> camera rotations (rows: image x axis, image y axis, viewing
    direction, in the body frame).  ``method`` as :func:`projected_area_samples`.
    """
    spec = shape_spec(shape)
    views = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    if method == "auto":
        method = "exact" if len(spec) == 1 else "scanline"
    if method == "exact":
        if len(spec) != 1:
            raise ValueError("method 'exact' needs a single convex component; use 'scanline'")
        return _exact_samples(spec[0], views)
    if method == "scanline":
        return _scanline_samples(spec, views, rows=rows)
    raise ValueError(f"unknown method {method!r}; allowed: auto, exact, scanline")


def projected_area_samples(shape, n: int = 20000, seed: int = 0, method: str = "auto", rows: int = 256):
    """(axis ratio (n,), projected area (n,) m^2) for n orientations uniform on SO(3).

    ``method``: "exact" (one convex component), "scanline" (any) or "auto" (exact when possible).
    """
    return silhouette_stats(shape, _view_frames(int(n), int(seed)), method=method, rows=rows)


def _smallest_face(spec: list[dict]) -> float | None:
    if len(spec) == 1 and spec[0]["shape"] == "cuboid":
        s = sorted(spec[0]["size"])
        return s[0] * s[1]
    return None


def bin_table(ratio, area_m2, A0_m2: float, bin_width: float = 0.05, *, key: str = "", method: str = "",
              ) -> AreaTable:
    """Bin samples into the min/mean/max/median/relopt curves of A/A0 against axis ratio."""
    r = np.asarray(ratio, dtype=np.float64)
    a = np.asarray(area_m2, dtype=np.float64) / A0_m2
    ok = np.isfinite(r) & np.isfinite(a) & (a > 0)
    r, a = r[ok], a[ok]
    top = max(1.0 + bin_width, math.ceil((r.max() - 1.0) / bin_width - 1e-9) * bin_width + 1.0)
    edges = 1.0 + bin_width * np.arange(int(round((top - 1.0) / bin_width)) + 1)
    edges[-1] = max(edges[-1], r.max() + 1e-12)
    k = np.clip(np.searchsorted(edges, r, side="right") - 1, 0, edges.size - 2)
    K = edges.size - 1
    count = np.bincount(k, minlength=K)
    order = np.lexsort((a, k))                                     # per bin, sorted by area
    ks, as_ = k[order], a[order]
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    nz = count > 0
    a_min = np.full(K, np.nan); a_max = np.full(K, np.nan); a_med = np.full(K, np.nan)
    a_min[nz] = as_[start[nz]]
    a_max[nz] = as_[start[nz] + count[nz] - 1]
    lo_mid = start[nz] + (count[nz] - 1) // 2
    hi_mid = start[nz] + count[nz] // 2
    a_med[nz] = 0.5 * (as_[lo_mid] + as_[hi_mid])
    with np.errstate(invalid="ignore", divide="ignore"):
        a_mean = np.bincount(ks, as_, minlength=K) / count
        e_isqrt = np.bincount(ks, as_ ** -0.5, minlength=K) / count
        e_inv = np.bincount(ks, 1.0 / as_, minlength=K) / count
        a_rel = (e_isqrt / e_inv) ** 2
    a_mean[~nz] = np.nan
    a_rel[~nz] = np.nan
    return AreaTable(key=key, A0_m2=float(A0_m2), method=method, n_samples=int(r.size), ratio_lo=edges[:-1],
                     ratio_hi=edges[1:], ratio=0.5 * (edges[:-1] + edges[1:]), count=count, a_min=a_min,
                     a_mean=a_mean, a_max=a_max, a_median=a_med, a_relopt=a_rel, samples_ratio=r, samples_area=a)


def _to_arrow(t: AreaTable):
    meta = {_META_KEY: t.key.encode(), b"A0_m2": repr(t.A0_m2).encode(), b"method": t.method.encode(),
            b"n_samples": str(t.n_samples).encode()}
    curves = pa.table({"ratio_lo": t.ratio_lo, "ratio_hi": t.ratio_hi, "ratio": t.ratio,
                       "count": t.count.astype(np.int64), "a_min": t.a_min, "a_mean": t.a_mean, "a_max": t.a_max,
                       "a_median": t.a_median, "a_relopt": t.a_relopt}).replace_schema_metadata(meta)
    samples = pa.table({"ratio": t.samples_ratio, "area_rel": t.samples_area}).replace_schema_metadata(
        {_META_KEY: t.key.encode()})
    return curves, samples


def _from_arrow(curves: pa.Table, samples: pa.Table) -> AreaTable:
    m = curves.schema.metadata
    col = {n: curves.column(n).to_numpy() for n in curves.column_names}
    return AreaTable(key=m[_META_KEY].decode(), A0_m2=float(m[b"A0_m2"]), method=m[b"method"].decode(),
                     n_samples=int(m[b"n_samples"]), ratio_lo=col["ratio_lo"], ratio_hi=col["ratio_hi"],
                     ratio=col["ratio"], count=col["count"], a_min=col["a_min"], a_mean=col["a_mean"],
                     a_max=col["a_max"], a_median=col["a_median"], a_relopt=col["a_relopt"],
                     samples_ratio=samples.column("ratio").to_numpy(),
                     samples_area=samples.column("area_rel").to_numpy())


def area_table(shape, *, n: int = 20000, seed: int = 0, bin_width: float = 0.05, method: str = "auto",
               rows: int = 256, A0_m2: float | None = None, cache: bool = True,
               cache_dir: str | Path | None = None) -> AreaTable:
    """The projected-area table of ``shape`` (built once, then read from the Parquet cache).

    Parameters
    ----------
    shape : SatelliteConfig, ComponentConfig(s) or ("cuboid", (lx, ly, lz)) etc. (see :func:`shape_spec`).
    n, seed : number of random orientations and their seed.
    bin_width : axis-ratio bin width.
    method : "auto" | "exact" | "scanline";  rows : scanlines across the body's bounding disc.
    A0_m2 : normalising area; default the smallest face of a cuboid, else the smallest sampled area.
    cache, cache_dir : use/write ``<cache_dir or DUALSIGHT_CACHE or ~/.cache/dualsight>/areas/<key>.parquet``.
    """
    spec = shape_spec(shape)
    if method == "auto":
        method = "exact" if len(spec) == 1 else "scanline"
    settings = dict(version=TABLE_VERSION, spec=spec, n=int(n), seed=int(seed), bin_width=float(bin_width),
                    method=method, rows=int(rows) if method == "scanline" else None, A0_m2=A0_m2)
    key = short_hash(json.dumps(settings, sort_keys=True))
    if cache:
        folder = resolve_cache_dir(cache_dir) / "areas"
        cpath, spath = folder / f"{key}.parquet", folder / f"{key}.samples.parquet"
        cur = read_parquet_or_none(cpath, _META_KEY, key.encode())
        smp = read_parquet_or_none(spath, _META_KEY, key.encode())
        if cur is not None and smp is not None:
            return _from_arrow(cur, smp)
    ratio, area = projected_area_samples(spec, n=n, seed=seed, method=method, rows=rows)
    if A0_m2 is None:
        A0_m2 = _smallest_face(spec) or float(np.min(area))
    table = bin_table(ratio, area, A0_m2, bin_width, key=key, method=method)
    if cache:
        curves, samples = _to_arrow(table)
        write_parquet_atomic(samples, spath)
        write_parquet_atomic(curves, cpath)
    return table
