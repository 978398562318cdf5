"""Primitive shapes as point clouds (reference Sec. 2.2.2) and as triangle meshes (accurate renderer).

Point clouds follow the reference's construction exactly:

* **cuboid** -- the reference's "pixel pitch" is the number of points per unit length,
  ``sqrt(surface_resolution)`` (surface resolution in points per m^2), so neighbouring points are
  ``d = 1 / sqrt(surface_resolution)`` metres apart.  Points lie on each of the 12 edges ``d`` apart
  (plus the 8 corners), with a **zero normal** (they reflect ambient light only, standing for the
  discontinuity of the normal along an edge); each of the 6 faces carries a grid of interior points
  ``d`` apart in both in-face directions with the face's outward unit normal.  Along a side of length
  ``L`` the grid is ``floor(L/d) + 1`` points at exactly ``d`` spacing, centred on the side (the margin
  ``(L - floor(L/d) d)/2`` at both ends is the only deviation from the reference's "evenly
  distributed"; grid points that land on an edge belong to the edge).
* **sphere** -- Deserno (2004), "How to generate equidistributed points on the surface of a sphere",
  regular placement: N = round(4 pi r^2 res) wanted, area per point a = 4 pi / N (unit sphere),
  d = sqrt(a), M_theta = round(pi / d) circles of latitude at theta_m = pi (m + 1/2) / M_theta,
  M_phi(m) = round(2 pi sin(theta_m) / (a / d_theta)) points on circle m at phi_n = 2 pi n / M_phi.
  Normals are the radial unit vectors.
* **cylinder** (axis along local z) -- caps by the 2-D version of Deserno's placement (concentric
  rings at r_m = (m + 1/2) d_r, M_phi(m) = round(2 pi r_m / (a / d_r)) points each), normals +-z; the
  side "laid out" flat as a grid (round(2 pi r / d) columns around, rows ``d`` apart along z), radial
  normals.

Each cloud is then rotated and translated (``rotation`` maps local vectors into the parent frame,
``position`` is the local origin in the parent frame).

Meshes (for the ``accurate`` renderer and the exact projected-area tables): closed, convex,
outward-wound triangles (``(v1 - v0) x (v2 - v0)`` points outward) with per-vertex shading normals.
Curved shapes are tessellated with their size corrected so that the areas that matter are exact:
the cylinder's polygonal caps have the true cap area pi r^2, and the sphere's polyhedron has the true
surface area 4 pi r^2, so that by Cauchy's surface-area formula its projected area averaged over
orientations is exactly pi r^2.

Units: metres.  All arrays float64 unless stated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

SHAPES = ("cuboid", "sphere", "cylinder")


@dataclass(frozen=True)
class PointCloud:
    """Points with normals.

    Attributes
    ----------
    points : (P, 3) float64 positions (m).
    normals : (P, 3) float64 unit outward normals, or exactly zero (cuboid edge points: ambient only).
    component : (P,) int32 component index of each point.
    """

    points: np.ndarray
    normals: np.ndarray
    component: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_surface(self) -> int:
        """Number of points with a non-zero normal (face points)."""
        return int(np.count_nonzero(np.any(self.normals != 0, axis=1)))


@dataclass(frozen=True)
class Mesh:
    """Triangles with per-vertex normals.

    Attributes
    ----------
    vertices : (T, 3, 3) float64, triangle t's vertices (m), wound so that (v1 - v0) x (v2 - v0) is outward.
    normals : (T, 3, 3) float64 unit shading normals at the three vertices (flat faces: the face normal).
    component : (T,) int32 component index of each triangle.
    """

    vertices: np.ndarray
    normals: np.ndarray
    component: np.ndarray

    def __len__(self) -> int:
        return int(self.vertices.shape[0])


# ----------------------------------------------------------------------------- helpers
def spacing(surface_resolution: float) -> float:
    """Point spacing d = 1 / sqrt(surface_resolution) (m) for a resolution in points per m^2."""
    return 1.0 / math.sqrt(float(surface_resolution))


def centred_grid(length: float, d: float) -> np.ndarray:
    """(floor(L/d) + 1,) float64 coordinates (m) exactly ``d`` apart, centred on [-L/2, L/2] (L = ``length``, m)."""
    n = int(math.floor(length / d + 1e-9))
    return (np.arange(n + 1) - n / 2.0) * d


def strictly_inside(c: np.ndarray, half: float, d: float) -> np.ndarray:
    """The coordinates of ``c`` (m) not on the end points +-``half`` (grid points on an edge belong to the edge;
    ``d`` the grid's spacing, m, sets the tolerance)."""
    return c[np.abs(c) < half - 1e-9 * max(d, 1.0)]


def _place(points: np.ndarray, normals: np.ndarray, rotation, position):
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    t = np.zeros(3) if position is None else np.asarray(position, dtype=np.float64).reshape(3)
    return points @ R.T + t, normals @ R.T


def _cloud(points, normals, component_id, rotation, position) -> PointCloud:
    p, n = _place(np.asarray(points, dtype=np.float64).reshape(-1, 3),
                  np.asarray(normals, dtype=np.float64).reshape(-1, 3), rotation, position)
    return PointCloud(p, n, np.full(p.shape[0], int(component_id), dtype=np.int32))


# ----------------------------------------------------------------------------- point clouds
def cuboid_points(size, surface_resolution: float, *, rotation=None, position=None,
                  component_id: int = 0) -> PointCloud:
    """Point cloud of a rectangular cuboid centred on its local origin (reference Sec. 2.2.2).

    Parameters
    ----------
    size : (lx, ly, lz) full edge lengths (m).
    surface_resolution : points per m^2; spacing d = 1/sqrt(surface_resolution) m.
    rotation : (3, 3) local-to-parent rotation (default identity).
    position : (3,) local origin in the parent frame (m).

    Returns
    -------
    PointCloud: 8 corners and the points along the 12 edges (normal 0) followed by the 6 faces'
    interior grids (outward unit normals +-x, +-y, +-z).
    """
    L = np.asarray(size, dtype=np.float64).reshape(3)
    d = spacing(surface_resolution)
    half = L / 2.0
    grids = [centred_grid(L[i], d) for i in range(3)]
    inner = [strictly_inside(grids[i], half[i], d) for i in range(3)]
    pts, nrm = [], []
    # corners
    corners = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij")).reshape(3, -1).T * half
    pts.append(corners)
    nrm.append(np.zeros_like(corners))
    # 12 edges: along axis a, the other two coordinates at +-half
    for a in range(3):  # three edge directions (4 edges each), vectorised along the edge
        b, c = (a + 1) % 3, (a + 2) % 3
        s = inner[a]
        for sb in (-1, 1):
            for sc in (-1, 1):
                e = np.zeros((s.size, 3))
                e[:, a] = s
                e[:, b] = sb * half[b]
                e[:, c] = sc * half[c]
                pts.append(e)
                nrm.append(np.zeros_like(e))
    # 6 faces: coordinate a held at +-half, interior grid in the other two
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        gb, gc = np.meshgrid(inner[b], inner[c], indexing="ij")
        for sa in (-1, 1):
            f = np.zeros((gb.size, 3))
            f[:, a] = sa * half[a]
            f[:, b] = gb.ravel()
            f[:, c] = gc.ravel()
            n = np.zeros_like(f)
            n[:, a] = sa
            pts.append(f)
            nrm.append(n)
    return _cloud(np.concatenate(pts), np.concatenate(nrm), component_id, rotation, position)


def deserno_sphere(n_target: int) -> np.ndarray:
    """Deserno's (2004) regular placement of about ``n_target`` points on the unit sphere.

    Returns (N, 3) unit vectors, N close to n_target (0 points if n_target < 1).
    """
    n_target = int(n_target)
    if n_target < 1:
        return np.zeros((0, 3))
    a = 4.0 * math.pi / n_target
    d = math.sqrt(a)
    m_theta = max(int(round(math.pi / d)), 1)
    d_theta = math.pi / m_theta
    d_phi = a / d_theta
    theta = math.pi * (np.arange(m_theta) + 0.5) / m_theta
    m_phi = np.rint(2.0 * math.pi * np.sin(theta) / d_phi).astype(np.int64)
    ring = np.repeat(np.arange(m_theta), m_phi)
    start = np.concatenate([[0], np.cumsum(m_phi)[:-1]])
    k = np.arange(ring.size) - np.repeat(start, m_phi)
    phi = 2.0 * math.pi * k / np.repeat(np.maximum(m_phi, 1), m_phi)
    th = theta[ring]
    return np.stack([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)], axis=1)


def deserno_disc(n_target: int) -> np.ndarray:
    """2-D version of Deserno's placement: about ``n_target`` points on the unit disc in concentric rings.

    Area per point a = pi / N, ring spacing d_r = 1 / round(1 / sqrt(a)), ring m at radius
    (m + 1/2) d_r with round(2 pi r_m / (a / d_r)) points.  Returns (N, 2).
    """
    n_target = int(n_target)
    if n_target < 1:
        return np.zeros((0, 2))
    a = math.pi / n_target
    m_r = max(int(round(1.0 / math.sqrt(a))), 1)
    d_r = 1.0 / m_r
    d_phi = a / d_r
    r = (np.arange(m_r) + 0.5) * d_r
    m_phi = np.maximum(np.rint(2.0 * math.pi * r / d_phi).astype(np.int64), 1)
    ring = np.repeat(np.arange(m_r), m_phi)
    start = np.concatenate([[0], np.cumsum(m_phi)[:-1]])
    k = np.arange(ring.size) - np.repeat(start, m_phi)
    phi = 2.0 * math.pi * k / np.repeat(m_phi, m_phi)
    rr = r[ring]
    return np.stack([rr * np.cos(phi), rr * np.sin(phi)], axis=1)


def sphere_points(diameter: float, surface_resolution: float, *, rotation=None, position=None,
                  component_id: int = 0) -> PointCloud:
    """Point cloud of a sphere (Deserno 2004 regular placement), radial unit normals.

    N = round(pi d^2 * surface_resolution) points are asked for (surface area pi d^2).
    """
    r = 0.5 * float(diameter)
    u = deserno_sphere(int(round(4.0 * math.pi * r * r * float(surface_resolution))))
    return _cloud(u * r, u, component_id, rotation, position)


def cylinder_points(diameter: float, length: float, surface_resolution: float, *, rotation=None,
                    position=None, component_id: int = 0) -> PointCloud:
    """Point cloud of a closed cylinder with its axis along local z, centred on the local origin.

    Caps: 2-D Deserno placement of round(pi r^2 res) points each, normals +-z.  Side: the unrolled
    rectangle (2 pi r by length) as a grid, round(2 pi r / d) columns around and rows ``d`` apart
    along z (centred), radial normals.
    """
    r = 0.5 * float(diameter)
    L = float(length)
    d = spacing(surface_resolution)
    disc = deserno_disc(int(round(math.pi * r * r * float(surface_resolution)))) * r
    pts, nrm = [], []
    for s in (-1.0, 1.0):
        c = np.column_stack([disc, np.full(disc.shape[0], s * L / 2)])
        n = np.zeros_like(c)
        n[:, 2] = s
        pts.append(c)
        nrm.append(n)
    n_around = int(round(2.0 * math.pi * r / d))
    zs = centred_grid(L, d)
    if n_around >= 1 and zs.size:
        phi = 2.0 * math.pi * np.arange(n_around) / n_around
        P, Z = np.meshgrid(phi, zs, indexing="ij")
        P, Z = P.ravel(), Z.ravel()
        radial = np.column_stack([np.cos(P), np.sin(P), np.zeros_like(P)])
        pts.append(np.column_stack([r * radial[:, :2], Z]))
        nrm.append(radial)
    return _cloud(np.concatenate(pts), np.concatenate(nrm), component_id, rotation, position)


# ----------------------------------------------------------------------------- meshes
def _orient_outward(v: np.ndarray, n: np.ndarray, centre=np.zeros(3)):
    """Swap v1/v2 of triangles whose geometric normal points towards ``centre`` (convex shapes)."""
    g = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flip = np.einsum("ij,ij->i", g, v.mean(axis=1) - centre) < 0
    v[flip] = v[flip][:, [0, 2, 1]]
    n[flip] = n[flip][:, [0, 2, 1]]
    return v, n


def _mesh(v, n, component_id, rotation, position) -> Mesh:
    v = np.asarray(v, dtype=np.float64)
    n = np.asarray(n, dtype=np.float64)
    v, n = _orient_outward(v, n)
    R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    t = np.zeros(3) if position is None else np.asarray(position, dtype=np.float64).reshape(3)
    return Mesh(v @ R.T + t, n @ R.T, np.full(v.shape[0], int(component_id), dtype=np.int32))


def cuboid_mesh(size, *, rotation=None, position=None, component_id: int = 0) -> Mesh:
    """12 outward-wound triangles of a cuboid (flat normals), centred on the local origin."""
    h = np.asarray(size, dtype=np.float64).reshape(3) / 2.0
    verts, norms = [], []
    for a in range(3):  # 6 faces, 2 triangles each
        b, c = (a + 1) % 3, (a + 2) % 3
        for s in (-1.0, 1.0):
            q = np.zeros((4, 3))
            q[:, a] = s * h[a]
            q[:, b] = np.array([-1, 1, 1, -1]) * h[b]
            q[:, c] = np.array([-1, -1, 1, 1]) * h[c]
            nn = np.zeros(3)
            nn[a] = s
            verts += [q[[0, 1, 2]], q[[0, 2, 3]]]
            norms += [np.tile(nn, (3, 1))] * 2
    return _mesh(np.array(verts), np.array(norms), component_id, rotation, position)


def sphere_mesh(diameter: float, segments: int = 48, *, rotation=None, position=None,
                component_id: int = 0) -> Mesh:
    """UV-sphere with ``segments`` meridians and ``segments // 2`` latitude bands, radial vertex normals.

    The vertex radius is scaled so that the polyhedron's surface area is exactly 4 pi r^2; by
    Cauchy's formula (mean projected area = surface area / 4) its projected area averaged over
    orientations is then exactly pi r^2 (the per-view deviation is below 0.2 % for 48 segments).
    """
    r = 0.5 * float(diameter)
    n_lon = max(int(segments), 6)
    n_lat = max(n_lon // 2, 3)
    th = np.linspace(0.0, math.pi, n_lat + 1)
    ph = np.linspace(0.0, 2.0 * math.pi, n_lon + 1)[:-1]
    T, P = np.meshgrid(th, ph, indexing="ij")
    grid = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1)  # (n_lat+1, n_lon, 3)
    i, j = np.meshgrid(np.arange(n_lat), np.arange(n_lon), indexing="ij")
    j1 = (j + 1) % n_lon
    a, b, c, d = grid[i, j], grid[i, j1], grid[i + 1, j1], grid[i + 1, j]
    tri1 = np.stack([a, c, b], axis=-2)[1:]          # skip the degenerate triangles at the north pole
    tri2 = np.stack([a, d, c], axis=-2)[:-1]         # ... and at the south pole
    unit = np.concatenate([tri1.reshape(-1, 3, 3), tri2.reshape(-1, 3, 3)])
    area = 0.5 * np.linalg.norm(np.cross(unit[:, 1] - unit[:, 0], unit[:, 2] - unit[:, 0]), axis=1).sum()
    scale = r * math.sqrt(4.0 * math.pi / area)
    return _mesh(unit * scale, unit.copy(), component_id, rotation, position)


def cylinder_mesh(diameter: float, length: float, segments: int = 64, *, rotation=None, position=None,
                  component_id: int = 0) -> Mesh:
    """Closed prism approximating a cylinder (axis local z): 2 caps as triangle fans, side as quads.

    The polygon's circumradius is r sqrt((2 pi / N) / sin(2 pi / N)) so that each cap has exactly the
    area pi r^2.  Side vertex normals are radial (smooth shading), cap normals +-z.
    """
    r = 0.5 * float(diameter)
    h = 0.5 * float(length)
    n = max(int(segments), 6)
    rr = r * math.sqrt((2.0 * math.pi / n) / math.sin(2.0 * math.pi / n))
    ph = 2.0 * math.pi * np.arange(n) / n
    ring = np.column_stack([np.cos(ph), np.sin(ph), np.zeros(n)])
    nxt = np.roll(ring, -1, axis=0)
    tris, nrms = [], []
    for s in (-1.0, 1.0):  # the two caps
        centre = np.tile([0.0, 0.0, s * h], (n, 1))
        tris.append(np.stack([centre, rr * ring + [0, 0, s * h], rr * nxt + [0, 0, s * h]], axis=1))
        nrms.append(np.tile([0.0, 0.0, s], (n, 3, 1)))
    lo0, lo1 = rr * ring + [0, 0, -h], rr * nxt + [0, 0, -h]
    hi0, hi1 = rr * ring + [0, 0, h], rr * nxt + [0, 0, h]
    tris += [np.stack([lo0, lo1, hi1], axis=1), np.stack([lo0, hi1, hi0], axis=1)]
    nrms += [np.stack([ring, nxt, nxt], axis=1), np.stack([ring, nxt, ring], axis=1)]
    return _mesh(np.concatenate(tris), np.concatenate(nrms), component_id, rotation, position)


# ----------------------------------------------------------------------------- combining
def concat_clouds(clouds) -> PointCloud:
    clouds = list(clouds)
    return PointCloud(np.concatenate([c.points for c in clouds]), np.concatenate([c.normals for c in clouds]),
                      np.concatenate([c.component for c in clouds]).astype(np.int32))


def concat_meshes(meshes) -> Mesh:
    meshes = list(meshes)
    return Mesh(np.concatenate([m.vertices for m in meshes]), np.concatenate([m.normals for m in meshes]),
                np.concatenate([m.component for m in meshes]).astype(np.int32))


def inside(shape: str, size, p_local: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """(...,) bool: local-frame points strictly inside the primitive (grown by ``margin`` m)."""
    p = np.asarray(p_local, dtype=np.float64)
    s = np.asarray(size, dtype=np.float64).ravel()
    if shape == "cuboid":
        return np.all(np.abs(p) < s / 2 + margin, axis=-1)
    if shape == "sphere":
        return np.linalg.norm(p, axis=-1) < s[0] / 2 + margin
    if shape == "cylinder":
        return (np.hypot(p[..., 0], p[..., 1]) < s[0] / 2 + margin) & (np.abs(p[..., 2]) < s[1] / 2 + margin)
    raise ValueError(f"unknown shape {shape!r}; allowed: {', '.join(SHAPES)}")
