"""The satellite configuration file (reference Sec. 2.2.3): camera, body, components.

A TOML file with the reference's three parts (``examples/satellites/README.md`` documents every key)::

    name = "3U CubeSat"          # optional
    frames = 50                  # optional, number of frames of the movie (default 1)

    [camera]                     # part 1: camera geometry, light, camera position and motion
    width = 1024                 # same keys as a camera file (scene/camera.py) ...
    height = 768
    pixel_pitch_um = 4.65
    focal_length_mm = 6.0        # or fx/fy (px), cx/cy, distortion, bit_depth
    light_direction = [1, -1, 1] # towards the light, world frame (any length, not zero)
    I_a = 0.3                    # ambient intensity near the body (>= 0)
    I_l = 1.0                    # intensity of the directional light (>= 0)
    position = [0, 0, 0]         # m, world frame          (defaults: zeros)
    orientation_deg = [0, 0, 0]  # 1-2-3 Euler angles, world -> camera
    velocity = [0, 0, 0]         # m/frame
    rotation_deg = [0, 0, 0]     # deg/frame

    [body]                       # part 2: the satellite as a whole
    components = 1               # optional; if given must equal the number of [[component]] entries
    position = [0, 0, 1.0]       # m, world frame (required)
    orientation_deg = [0, 0, 0]  # body -> world is the transpose of the 1-2-3 DCM
    velocity = [0.02, 0.02, 0.4] # m/frame  (reference Table 2)
    rotation_deg = [5, 5, 5]     # deg/frame (reference Table 2)
    surface_resolution = 1e6     # points per m^2 for the point clouds (spacing 1/sqrt = 1 mm)

    [[component]]                # part 3: one entry per primitive
    name = "bus"
    shape = "cuboid"             # cuboid | sphere | cylinder
    size = [0.1, 0.1, 0.3]       # cuboid [lx, ly, lz]; sphere [diameter] (or a number); cylinder [diameter, length]
    k_a = 1.0                    # ambient, Lambertian, specular coefficients (>= 0)
    k_l = 0.8
    k_s = 0.3
    n = 10                       # specular exponent (> 0)
    position = [0, 0, 0]         # m, relative to the body origin, body frame
    orientation_deg = [0, 0, 0]  # relative to the body
    velocity = [0, 0, 0]         # m/frame relative to the body
    rotation_deg = [0, 0, 0]     # deg/frame relative to the body
    surface_resolution = 1e6     # optional per-component override

Every problem raises :class:`~dualsight.errors.ConfigError` naming the file, the key (e.g.
``component[1].size``) and what is allowed.  The layout and every range are the pydantic models below
(:class:`SatelliteTable`, :class:`SatCameraTable`, :class:`BodyTable`, :class:`ComponentTable`),
validated by ``dualsight.config.validate``; the point clouds are bounded by
:data:`MAX_SURFACE_POINTS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import pydantic
from pydantic import Field

from dualsight.errors import ConfigError
from dualsight.scene import primitives as prim
from dualsight.scene.camera import Camera, CameraTable, read_toml, validate_table
from dualsight.scene.example_files import shipped_path
from dualsight.scene.motion import frame_poses

Vec3 = tuple[float, float, float]
_ZERO3: Vec3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CameraSetup:
    """Part 1: the camera, the light and the camera's motion.

    Attributes
    ----------
    camera : intrinsics (scene/camera.py).
    light_direction : (3,) unit vector towards the light source, world frame.
    I_a, I_l : ambient and directional light intensities (Eq. 3).
    position : (3,) m, world;  orientation_deg : 1-2-3 angles (world -> camera);
    velocity : m/frame;  rotation_deg : deg/frame.
    """

    camera: Camera
    light_direction: Vec3
    I_a: float = 0.3
    I_l: float = 1.0
    position: Vec3 = _ZERO3
    orientation_deg: Vec3 = _ZERO3
    velocity: Vec3 = _ZERO3
    rotation_deg: Vec3 = _ZERO3


@dataclass(frozen=True)
class BodyConfig:
    """Part 2: the satellite as a whole (position m, 1-2-3 angles deg, m/frame, deg/frame, points/m^2)."""

    position: Vec3
    orientation_deg: Vec3 = _ZERO3
    velocity: Vec3 = _ZERO3
    rotation_deg: Vec3 = _ZERO3
    surface_resolution: float = 1.0e6


@dataclass(frozen=True)
class ComponentConfig:
    """Part 3: one primitive.

    Attributes
    ----------
    shape : "cuboid" | "sphere" | "cylinder".
    size : cuboid (lx, ly, lz); sphere (diameter,); cylinder (diameter, length) -- metres, > 0.
    k_a, k_l, k_s : ambient, Lambertian, specular reflection coefficients (Eq. 3), >= 0.
    n : specular exponent (> 0).
    position, orientation_deg, velocity, rotation_deg : relative to the body (body frame).
    surface_resolution : points per m^2 of this component's point cloud.
    name : label.
    """

    shape: str
    size: tuple[float, ...]
    k_a: float = 1.0
    k_l: float = 0.8
    k_s: float = 0.3
    n: float = 10.0
    position: Vec3 = _ZERO3
    orientation_deg: Vec3 = _ZERO3
    velocity: Vec3 = _ZERO3
    rotation_deg: Vec3 = _ZERO3
    surface_resolution: float = 1.0e6
    name: str = ""

    def point_cloud(self, component_id: int = 0) -> prim.PointCloud:
        """The component's point cloud in its own local frame."""
        s, res = self.size, self.surface_resolution
        if self.shape == "cuboid":
            return prim.cuboid_points(s, res, component_id=component_id)
        if self.shape == "sphere":
            return prim.sphere_points(s[0], res, component_id=component_id)
        return prim.cylinder_points(s[0], s[1], res, component_id=component_id)

    def mesh(self, segments: int = 48, component_id: int = 0) -> prim.Mesh:
        """The component's triangle mesh in its own local frame (``segments`` for curved shapes)."""
        s = self.size
        if self.shape == "cuboid":
            return prim.cuboid_mesh(s, component_id=component_id)
        if self.shape == "sphere":
            return prim.sphere_mesh(s[0], segments, component_id=component_id)
        return prim.cylinder_mesh(s[0], s[1], max(segments, 6), component_id=component_id)

    @property
    def bounding_radius(self) -> float:
        """Radius (m) of a sphere about the local origin containing the component."""
        s = self.size
        if self.shape == "cuboid":
            return 0.5 * math.sqrt(sum(x * x for x in s))
        if self.shape == "sphere":
            return 0.5 * s[0]
        return math.hypot(0.5 * s[0], 0.5 * s[1])


@dataclass(frozen=True)
class SatelliteConfig:
    """A whole satellite configuration file.

    Attributes
    ----------
    camera : part 1.  body : part 2.  components : part 3 (at least one).
    frames : number of frames of the movie (frames 0 .. frames-1).
    name : label.  source : the file it came from.
    """

    camera: CameraSetup
    body: BodyConfig
    components: tuple[ComponentConfig, ...]
    frames: int = 1
    name: str = ""
    source: str = field(default="", compare=False)

    def point_cloud(self) -> prim.PointCloud:
        """All components' point clouds, each in its own local frame, tagged with the component index."""
        return prim.concat_clouds(c.point_cloud(i) for i, c in enumerate(self.components))

    def mesh(self, segments: int = 48) -> prim.Mesh:
        """All components' meshes, each in its own local frame, tagged with the component index."""
        return prim.concat_meshes(c.mesh(segments, i) for i, c in enumerate(self.components))

    def materials(self) -> np.ndarray:
        """(C, 4) float64 optical coefficients [k_a, k_l, k_s, n] per component."""
        return np.array([[c.k_a, c.k_l, c.k_s, c.n] for c in self.components], dtype=np.float64)

    @property
    def bounding_radius(self) -> float:
        """Radius (m) about the body origin containing every component at its frame-0 position."""
        return max(float(np.linalg.norm(c.position)) + c.bounding_radius for c in self.components)


# ----------------------------------------------------------------------------- the file's layout (pydantic)
MAX_DISTANCE_M = 1e5
"""Largest coordinate (m) of a position, and of a velocity (m/frame): at 100 km even a 10 m spacecraft
is ~0.1 px for the reference's 6 mm / 4.65 um camera, far beyond what a proximity camera resolves."""
MAX_SIZE_M = 1000.0
"""Largest dimension (m) of a component (the largest spacecraft, the ISS, is ~110 m across)."""
MAX_RESOLUTION = 1e12
"""Largest surface resolution (points/m^2): 1 um point spacing."""
MAX_SURFACE_POINTS = 10_000_000
"""Most surface points the satellite's point clouds may hold (all components together; ~0.5 GB of
float64 positions and normals): e.g. 10 m^2 of surface at 1e6 points/m^2 (1 mm spacing)."""
MAX_COMPONENTS = 1000
"""Most components of one satellite (each is a mesh, a point cloud and a row of the materials table)."""
MAX_FRAMES = 10_000_000
"""Most frames of a movie (as the prox spec's ``frames``)."""

_Coord = Annotated[float, Field(ge=-MAX_DISTANCE_M, le=MAX_DISTANCE_M)]
_Vec3 = Annotated[tuple[_Coord, ...], Field(min_length=3, max_length=3)]
_Deg3 = Annotated[tuple[Annotated[float, Field(ge=-360.0, le=360.0)], ...], Field(min_length=3, max_length=3)]
_Direction = Annotated[tuple[float, ...], Field(min_length=3, max_length=3)]
_Resolution = Annotated[float, Field(gt=0, le=MAX_RESOLUTION)]
_Coefficient = Annotated[float, Field(ge=0, le=10.0)]
_Intensity = Annotated[float, Field(ge=0, le=1000.0)]
_Count = Annotated[int, Field(ge=1, le=MAX_COMPONENTS)]


class _Table(pydantic.BaseModel):
    model_config = pydantic.ConfigDict(extra="forbid", frozen=True)


class SatCameraTable(CameraTable):
    """``[camera]``: the camera file's keys (:class:`dualsight.scene.camera.CameraTable`) and the scene's.

    light_direction : 3 numbers, not all zero (checked after), towards the light (world frame, any
    length).  I_a, I_l : intensities in [0, 1000] (relative units; the reference uses 0.3 and 1).
    position (m) and velocity (m/frame) : 3 numbers in [-1e5, 1e5] (:data:`MAX_DISTANCE_M`).
    orientation_deg (deg) and rotation_deg (deg/frame) : 3 numbers in [-360, 360].
    """

    light_direction: _Direction | None = None
    I_a: _Intensity = 0.3
    I_l: _Intensity = 1.0
    position: _Vec3 = _ZERO3
    orientation_deg: _Deg3 = _ZERO3
    velocity: _Vec3 = _ZERO3
    rotation_deg: _Deg3 = _ZERO3


class BodyTable(_Table):
    """``[body]``: components (an integer in [1, 1000], must equal the [[component]] count), position
    (m, required), orientation_deg, velocity, rotation_deg (ranges as :class:`SatCameraTable`),
    surface_resolution (points/m^2, in (0, 1e12])."""

    components: _Count | None = None
    position: _Vec3
    orientation_deg: _Deg3 = _ZERO3
    velocity: _Vec3 = _ZERO3
    rotation_deg: _Deg3 = _ZERO3
    surface_resolution: _Resolution = 1.0e6
    name: str | None = None
    notes: str | None = None


class ComponentTable(_Table):
    """``[[component]]``: shape; size (m), 1-3 numbers in (0, 1000] (the count the shape needs is
    checked after); k_a, k_l, k_s in [0, 10] (fractions of the light, <= 1 physically; up to 10 for
    unnormalised use); n (specular exponent) in (0, 1e4]; poses as :class:`SatCameraTable`;
    surface_resolution (points/m^2) in (0, 1e12], default the body's."""

    shape: Literal["cuboid", "sphere", "cylinder"]
    size: Annotated[tuple[Annotated[float, Field(gt=0, le=MAX_SIZE_M)], ...], Field(min_length=1, max_length=3)]
    k_a: _Coefficient = 1.0
    k_l: _Coefficient = 0.8
    k_s: _Coefficient = 0.3
    n: Annotated[float, Field(gt=0, le=1e4)] = 10.0
    position: _Vec3 = _ZERO3
    orientation_deg: _Deg3 = _ZERO3
    velocity: _Vec3 = _ZERO3
    rotation_deg: _Deg3 = _ZERO3
    surface_resolution: _Resolution | None = None
    name: str | None = None
    notes: str | None = None


class SatelliteTable(_Table):
    """Top level: name, notes, frames (an integer in [1, 1e7]), and the three parts (their own models)."""

    name: str = ""
    notes: str | None = None
    frames: Annotated[int, Field(ge=1, le=MAX_FRAMES)] = 1
    camera: dict
    body: dict
    component: Annotated[list[dict], Field(min_length=1, max_length=MAX_COMPONENTS)]


class _Reader:
    def __init__(self, source: str):
        self.source = source

    def err(self, key: str, msg: str):
        return ConfigError(msg, source=self.source, field=key or None)

    def validate(self, model, table, section: str | None):
        return validate_table(model, table, source=self.source, section=section)

    def table(self, data: dict, key: str) -> dict:
        t = data.get(key)
        if t is None:
            raise self.err(key, f"missing table [{key}]; a satellite file needs [camera], [body] and at least "
                                "one [[component]]")
        if not isinstance(t, dict):
            raise self.err(key, f"must be a table [{key}], got {type(t).__name__}")
        return t


_SIZE_LEN = {"cuboid": (3, "[lx, ly, lz]"), "sphere": (1, "[diameter] or a number"),
             "cylinder": (2, "[diameter, length]")}


def _component(rd: _Reader, t, i: int, body_res: float) -> ComponentConfig:
    where = f"component[{i}]"
    if not isinstance(t, dict):
        raise rd.err(where, f"must be a table ([[component]]), got {type(t).__name__}")
    t = dict(t)
    shape = t.get("shape")
    if isinstance(shape, str) and shape in _SIZE_LEN:   # the size's form depends on the shape
        n_need, form = _SIZE_LEN[shape]
        size = t.get("size")
        if size is None:
            raise rd.err(f"{where}.size", f"missing key; a {shape} needs size = {form} (m)")
        if shape == "sphere" and isinstance(size, (int, float)) and not isinstance(size, bool):
            t["size"] = size = [size]
        if not isinstance(size, list) or len(size) != n_need:
            raise rd.err(f"{where}.size", f"a {shape} needs size = {form} of numbers (m), got {size!r}")
    m = rd.validate(ComponentTable, t, where)
    comp = ComponentConfig(
        shape=m.shape, size=tuple(m.size), k_a=m.k_a, k_l=m.k_l, k_s=m.k_s, n=m.n, position=m.position,
        orientation_deg=m.orientation_deg, velocity=m.velocity, rotation_deg=m.rotation_deg,
        surface_resolution=m.surface_resolution if m.surface_resolution is not None else body_res,
        name=m.name if m.name is not None else f"component{i}")
    res_key = f"{where}.surface_resolution" if m.surface_resolution is not None else "body.surface_resolution"
    # memory: estimate the points from the areas first, never build or count grids beyond the bound
    est = _surface_point_estimate(comp)
    if est > MAX_SURFACE_POINTS:
        raise rd.err(res_key, f"the {comp.shape} of size {list(comp.size)} m would have about {est:.3g} surface "
                              f"points at surface_resolution = {comp.surface_resolution:g} points/m^2, over the "
                              f"{MAX_SURFACE_POINTS:.0e} allowed per satellite; lower surface_resolution")
    # enough surface points at this resolution?
    if _surface_point_count(comp) == 0:
        need = _min_resolution(comp)
        raise rd.err(f"{where}.{'surface_resolution' if m.surface_resolution is not None else 'size'}",
                     f"the {comp.shape} of size {list(comp.size)} m has no surface points at surface_resolution = "
                     f"{comp.surface_resolution:g} points/m^2 "
                     f"(point spacing {prim.spacing(comp.surface_resolution):g} m); "
                     + (f"use at least ~{need:.3g} points/m^2 or a larger size" if math.isfinite(need) else
                        f"no resolution within {MAX_SURFACE_POINTS:.0e} points gives it any; use a larger size"))
    return comp


def _surface_point_estimate(c: ComponentConfig) -> float:
    """Upper estimate of the points of ``c``'s point cloud, from its dimensions alone (no arrays)."""
    res = c.surface_resolution
    per_m = math.sqrt(res)                     # grid points per metre along a line (1 / spacing)
    if c.shape == "cuboid":
        n = [x * per_m + 2 for x in c.size]
        return 8 + 4 * sum(n) + 2 * (n[0] * n[1] + n[1] * n[2] + n[0] * n[2])
    if c.shape == "sphere":
        return 1.1 * math.pi * c.size[0] ** 2 * res + 2 * math.pi * c.size[0] * per_m + 10
    d, L = c.size
    return 1.1 * 0.5 * math.pi * d * d * res + (math.pi * d * per_m + 2) * (L * per_m + 2) + 10


def _surface_point_count(c: ComponentConfig) -> int:
    """Number of points with a normal in ``c``'s point cloud (computed from the grids, not built)."""
    d = prim.spacing(c.surface_resolution)
    if c.shape == "cuboid":
        L = np.asarray(c.size)
        n_in = [prim.strictly_inside(prim.centred_grid(L[i], d), L[i] / 2, d).size for i in range(3)]
        return 2 * (n_in[0] * n_in[1] + n_in[1] * n_in[2] + n_in[0] * n_in[2])
    if c.shape == "sphere":
        r = c.size[0] / 2
        return len(prim.deserno_sphere(int(round(4 * math.pi * r * r * c.surface_resolution))))
    r, L = c.size[0] / 2, c.size[1]
    caps = 2 * len(prim.deserno_disc(int(round(math.pi * r * r * c.surface_resolution))))
    side = int(round(2 * math.pi * r / d)) * prim.centred_grid(L, d).size
    return caps + side


def _min_resolution(c: ComponentConfig) -> float:
    """Smallest surface resolution (points/m^2, by doubling) giving ``c`` at least one surface point;
    inf when none does within :data:`MAX_SURFACE_POINTS` (counting never builds more)."""
    res = c.surface_resolution
    for _ in range(200):
        res *= 2.0
        trial = ComponentConfig(c.shape, c.size, surface_resolution=res)
        if res > MAX_RESOLUTION or _surface_point_estimate(trial) > MAX_SURFACE_POINTS:
            return float("inf")
        if _surface_point_count(trial) > 0:
            return res
    return float("inf")


def satellite_from_dict(data: dict, source: str = "<dict>") -> SatelliteConfig:
    """Validate a parsed satellite file (see module docstring) and build a :class:`SatelliteConfig`.

    The layout is the pydantic models :class:`SatelliteTable`, :class:`SatCameraTable`,
    :class:`BodyTable` and :class:`ComponentTable`, validated by ``dualsight.config.validate``
    (types, ranges, unknown keys); the rules between keys (size per shape, surface points, component
    count, light not zero, camera outside the body) are checked here."""
    rd = _Reader(source)
    if not isinstance(data, dict):
        raise rd.err("", "must be a TOML document")
    cam_t, body_t = rd.table(data, "camera"), rd.table(data, "body")
    comps_t = data.get("component")
    if comps_t is None or (isinstance(comps_t, list) and len(comps_t) == 0):
        raise rd.err("component", "no [[component]] entries; at least one primitive (shape = "
                                  f"{' | '.join(prim.SHAPES)}) is required")
    if not isinstance(comps_t, list):
        raise rd.err("component", "must be an array of tables, written [[component]]")
    top = rd.validate(SatelliteTable, {**data, "component": [{} for _ in comps_t]}, None)

    cam = rd.validate(SatCameraTable, cam_t, "camera")
    camera = Camera.from_table(cam, source=source)
    if cam.light_direction is None:
        raise rd.err("camera.light_direction", "missing key: direction towards the light source, a list of 3 "
                                               "numbers in the world frame")
    L = np.asarray(cam.light_direction, dtype=np.float64)
    if not np.linalg.norm(L) > 0:
        raise rd.err("camera.light_direction", f"must not be the zero vector, got {list(cam.light_direction)}")
    setup = CameraSetup(camera=camera, light_direction=tuple(float(x) for x in L / np.linalg.norm(L)),
                        I_a=cam.I_a, I_l=cam.I_l, position=cam.position, orientation_deg=cam.orientation_deg,
                        velocity=cam.velocity, rotation_deg=cam.rotation_deg)

    b = rd.validate(BodyTable, body_t, "body")
    body = BodyConfig(position=b.position, orientation_deg=b.orientation_deg, velocity=b.velocity,
                      rotation_deg=b.rotation_deg, surface_resolution=b.surface_resolution)

    comps = tuple(_component(rd, t, i, body.surface_resolution) for i, t in enumerate(comps_t))
    if b.components is not None and b.components != len(comps):
        raise rd.err("body.components", f"says {b.components!r} components but the file has {len(comps)} "
                                        "[[component]] entries")
    total = sum(_surface_point_estimate(c) for c in comps)
    if total > MAX_SURFACE_POINTS:
        raise rd.err("body.surface_resolution", f"the components would have about {total:.3g} surface points "
                                                f"together, over the {MAX_SURFACE_POINTS:.0e} allowed; lower "
                                                "surface_resolution")
    cfg = SatelliteConfig(camera=setup, body=body, components=comps, frames=top.frames, name=top.name,
                          source=source)
    _check_camera_outside(cfg, rd)
    return cfg


def _check_camera_outside(cfg: SatelliteConfig, rd: _Reader):
    fp = frame_poses(cfg, [0])
    for i, c in enumerate(cfg.components):  # handful of components
        R, t = fp.R[0, i], fp.t[0, i]
        cam_local = -R.T @ t          # camera origin in the component's frame
        if prim.inside(c.shape, c.size, cam_local):
            raise rd.err("camera.position",
                         f"the camera is inside component[{i}] ({c.name}, a {c.shape}) at frame 0; "
                         "place the body in front of the camera (e.g. body.position = [0, 0, 1])")


def load_satellite(path: str | Path) -> SatelliteConfig:
    """Read and validate a satellite configuration file (TOML; see the module docstring); a relative path
    is looked up by :func:`dualsight.scene.example_files.shipped_path`.  Errors name the path as given."""
    return satellite_from_dict(read_toml(shipped_path(path)), source=str(path))
