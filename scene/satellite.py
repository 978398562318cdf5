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
``component[1].size``) and what is allowed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualsight.errors import ConfigError
from dualsight.scene import primitives as prim
from dualsight.scene.camera import Camera, read_toml
from dualsight.scene.motion import frame_poses

CAMERA_INTRINSIC_KEYS = ("width", "height", "pixel_pitch_um", "focal_length_mm", "fx", "fy", "cx", "cy",
                         "distortion", "bit_depth", "name", "notes")
CAMERA_SCENE_KEYS = ("light_direction", "I_a", "I_l", "position", "orientation_deg", "velocity", "rotation_deg")
BODY_KEYS = ("components", "position", "orientation_deg", "velocity", "rotation_deg", "surface_resolution",
             "name", "notes")
COMPONENT_KEYS = ("name", "shape", "size", "k_a", "k_l", "k_s", "n", "position", "orientation_deg", "velocity",
                  "rotation_deg", "surface_resolution", "notes")
TOP_KEYS = ("name", "notes", "frames", "camera", "body", "component")

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


# ----------------------------------------------------------------------------- validation helpers
def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))


class _Reader:
    def __init__(self, source: str):
        self.source = source

    def err(self, key: str, msg: str):
        return ConfigError(msg, source=self.source, field=key)

    def table(self, data: dict, key: str) -> dict:
        t = data.get(key)
        if t is None:
            raise self.err(key, f"missing table [{key}]; a satellite file needs [camera], [body] and at least "
                                "one [[component]]")
        if not isinstance(t, dict):
            raise self.err(key, f"must be a table [{key}], got {type(t).__name__}")
        return t

    def unknown(self, t: dict, allowed, where: str):
        extra = sorted(set(t) - set(allowed))
        if extra:
            raise self.err(where, f"unknown key(s) {extra}; allowed: {', '.join(allowed)}")

    def num(self, t: dict, key: str, where: str, default=None, lo=None, lo_open=False, hi=None):
        if key not in t:
            if default is None:
                raise self.err(f"{where}.{key}", "missing key (a number is required)")
            return float(default)
        v = t[key]
        if not _is_num(v):
            raise self.err(f"{where}.{key}", f"must be a finite number, got {v!r}")
        v = float(v)
        if lo is not None and (v <= lo if lo_open else v < lo):
            raise self.err(f"{where}.{key}", f"must be {'>' if lo_open else '>='} {lo}, got {v!r}")
        if hi is not None and v > hi:
            raise self.err(f"{where}.{key}", f"must be <= {hi}, got {v!r}")
        return v

    def vec3(self, t: dict, key: str, where: str, default=None, nonzero=False) -> Vec3:
        if key not in t:
            if default is None:
                raise self.err(f"{where}.{key}", "missing key (a list of 3 numbers is required)")
            return tuple(float(x) for x in default)
        v = t[key]
        if not isinstance(v, list) or len(v) != 3 or not all(_is_num(x) for x in v):
            raise self.err(f"{where}.{key}", f"must be a list of 3 finite numbers, got {v!r}")
        out = tuple(float(x) for x in v)
        if nonzero and not any(out):
            raise self.err(f"{where}.{key}", "must not be the zero vector")
        return out

    def string(self, t: dict, key: str, where: str, default=None) -> str:
        if key not in t:
            if default is None:
                raise self.err(f"{where}.{key}", "missing key (a string is required)")
            return default
        v = t[key]
        if not isinstance(v, str):
            raise self.err(f"{where}.{key}", f"must be a string, got {v!r}")
        return v


_SIZE_LEN = {"cuboid": (3, "[lx, ly, lz]"), "sphere": (1, "[diameter] or a number"),
             "cylinder": (2, "[diameter, length]")}


def _component(rd: _Reader, t, i: int, body_res: float) -> ComponentConfig:
    where = f"component[{i}]"
    if not isinstance(t, dict):
        raise rd.err(where, f"must be a table ([[component]]), got {type(t).__name__}")
    rd.unknown(t, COMPONENT_KEYS, where)
    shape = rd.string(t, "shape", where)
    if shape not in prim.SHAPES:
        raise rd.err(f"{where}.shape", f"unknown shape {shape!r}; allowed: {', '.join(prim.SHAPES)}")
    if "size" not in t:
        raise rd.err(f"{where}.size", f"missing key; a {shape} needs size = {_SIZE_LEN[shape][1]} (m)")
    size = t["size"]
    if shape == "sphere" and _is_num(size):
        size = [size]
    n_need, form = _SIZE_LEN[shape]
    if not isinstance(size, list) or len(size) != n_need or not all(_is_num(x) for x in size):
        raise rd.err(f"{where}.size", f"a {shape} needs size = {form} of finite numbers (m), got {t['size']!r}")
    if any(float(x) <= 0 for x in size):
        raise rd.err(f"{where}.size", f"every dimension must be > 0 m, got {t['size']!r}")
    comp = ComponentConfig(
        shape=shape, size=tuple(float(x) for x in size),
        k_a=rd.num(t, "k_a", where, 1.0, lo=0.0), k_l=rd.num(t, "k_l", where, 0.8, lo=0.0),
        k_s=rd.num(t, "k_s", where, 0.3, lo=0.0), n=rd.num(t, "n", where, 10.0, lo=0.0, lo_open=True),
        position=rd.vec3(t, "position", where, _ZERO3), orientation_deg=rd.vec3(t, "orientation_deg", where, _ZERO3),
        velocity=rd.vec3(t, "velocity", where, _ZERO3), rotation_deg=rd.vec3(t, "rotation_deg", where, _ZERO3),
        surface_resolution=rd.num(t, "surface_resolution", where, body_res, lo=0.0, lo_open=True, hi=1e12),
        name=rd.string(t, "name", where, f"component{i}"))
    # enough surface points at this resolution?  (count, do not build, for huge resolutions)
    n_pts = _surface_point_count(comp)
    if n_pts == 0:
        need = _min_resolution(comp)
        src_key = "surface_resolution" if "surface_resolution" in t else None
        raise rd.err(f"{where}.{src_key or 'size'}",
                     f"the {shape} of size {list(comp.size)} m has no surface points at surface_resolution = "
                     f"{comp.surface_resolution:g} points/m^2 "
                     f"(point spacing {prim.spacing(comp.surface_resolution):g} m);"
                     f" use at least ~{need:.3g} points/m^2 or a larger size")
    return comp


def _surface_point_count(c: ComponentConfig) -> int:
    """Number of points with a normal in ``c``'s point cloud (computed from the grids, not built)."""
    d = prim.spacing(c.surface_resolution)
    if c.shape == "cuboid":
        L = np.asarray(c.size)
        n_in = [prim._strictly_inside(prim._grid(L[i], d), L[i] / 2, d).size for i in range(3)]
        return 2 * (n_in[0] * n_in[1] + n_in[1] * n_in[2] + n_in[0] * n_in[2])
    if c.shape == "sphere":
        r = c.size[0] / 2
        return len(prim.deserno_sphere(int(round(4 * math.pi * r * r * c.surface_resolution))))
    r, L = c.size[0] / 2, c.size[1]
    caps = 2 * len(prim.deserno_disc(int(round(math.pi * r * r * c.surface_resolution))))
    side = int(round(2 * math.pi * r / d)) * prim._grid(L, d).size
    return caps + side


def _min_resolution(c: ComponentConfig) -> float:
    """Smallest surface resolution (points/m^2, by doubling) giving ``c`` at least one surface point."""
    res = c.surface_resolution
    for _ in range(200):
        res *= 2.0
        if _surface_point_count(ComponentConfig(c.shape, c.size, surface_resolution=res)) > 0:
            return res
    return float("inf")


def satellite_from_dict(data: dict, source: str = "<dict>") -> SatelliteConfig:
    """Validate a parsed satellite file (see module docstring) and build a :class:`SatelliteConfig`."""
    rd = _Reader(source)
    if not isinstance(data, dict):
        raise rd.err("", "must be a TOML document")
    rd.unknown(data, TOP_KEYS, "(top level)")
    frames = data.get("frames", 1)
    if not (isinstance(frames, int) and not isinstance(frames, bool) and frames >= 1):
        raise rd.err("frames", f"must be an integer >= 1, got {frames!r}")
    name = rd.string(data, "name", "(top level)", "")

    cam_t = rd.table(data, "camera")
    rd.unknown(cam_t, CAMERA_INTRINSIC_KEYS + CAMERA_SCENE_KEYS, "camera")
    camera = Camera.from_dict({k: v for k, v in cam_t.items() if k in CAMERA_INTRINSIC_KEYS}, source=source)
    if "light_direction" not in cam_t:
        raise rd.err("camera.light_direction", "missing key: direction towards the light source, a list of 3 "
                                               "numbers in the world frame")
    L = np.asarray(rd.vec3(cam_t, "light_direction", "camera", nonzero=True))
    setup = CameraSetup(
        camera=camera, light_direction=tuple(float(x) for x in L / np.linalg.norm(L)),
        I_a=rd.num(cam_t, "I_a", "camera", 0.3, lo=0.0), I_l=rd.num(cam_t, "I_l", "camera", 1.0, lo=0.0),
        position=rd.vec3(cam_t, "position", "camera", _ZERO3),
        orientation_deg=rd.vec3(cam_t, "orientation_deg", "camera", _ZERO3),
        velocity=rd.vec3(cam_t, "velocity", "camera", _ZERO3),
        rotation_deg=rd.vec3(cam_t, "rotation_deg", "camera", _ZERO3))

    body_t = rd.table(data, "body")
    rd.unknown(body_t, BODY_KEYS, "body")
    body = BodyConfig(
        position=rd.vec3(body_t, "position", "body"),
        orientation_deg=rd.vec3(body_t, "orientation_deg", "body", _ZERO3),
        velocity=rd.vec3(body_t, "velocity", "body", _ZERO3),
        rotation_deg=rd.vec3(body_t, "rotation_deg", "body", _ZERO3),
        surface_resolution=rd.num(body_t, "surface_resolution", "body", 1.0e6, lo=0.0, lo_open=True, hi=1e12))

    comps_t = data.get("component")
    if comps_t is None or (isinstance(comps_t, list) and len(comps_t) == 0):
        raise rd.err("component", "no [[component]] entries; at least one primitive (shape = "
                                  f"{' | '.join(prim.SHAPES)}) is required")
    if not isinstance(comps_t, list):
        raise rd.err("component", "must be an array of tables, written [[component]]")
    comps = tuple(_component(rd, t, i, body.surface_resolution) for i, t in enumerate(comps_t))
    if "components" in body_t:
        nc = body_t["components"]
        if not (isinstance(nc, int) and not isinstance(nc, bool)) or nc != len(comps):
            raise rd.err("body.components", f"says {nc!r} components but the file has {len(comps)} "
                                            "[[component]] entries")
    cfg = SatelliteConfig(camera=setup, body=body, components=comps, frames=int(frames), name=name,
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
    """Read and validate a satellite configuration file (TOML; see the module docstring)."""
    path = Path(path)
    return satellite_from_dict(read_toml(path), source=str(path))
