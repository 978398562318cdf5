"""Proximity scene: primitives, satellite configuration file, motion, projected-area tables, resolvable range.

Truth used here, none of it computed by the code under test:
- geometry: point spacing 1/sqrt(res), edge/face/corner positions and counts of a grid, sphere and
  cylinder surfaces (|p| = r, radial normals), closed-surface identities (sum of outward area vectors = 0);
- rotation matrices written out by hand for the Table 2 trajectory;
- projected area of a convex body, A = 1/2 sum_i |n_i . v| A_i, and the largest projection of a box,
  sqrt(A_xy^2 + A_yz^2 + A_xz^2); face-on and broadside silhouettes of the 3U CubeSat (squares and
  rectangles, covariance diag(a^2, b^2) / 12);
- the resolvable range by similar triangles, f h / (n p), with the Table 1 numbers.
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from dualsight.catalogs import areas as areas_mod
from dualsight.errors import ConfigError
from dualsight.nav.range import resolvable_range
from dualsight.scene import primitives as prim
from dualsight.scene.camera import Camera
from dualsight.scene.motion import frame_poses, place_body
from dualsight.scene.satellite import load_satellite, satellite_from_dict

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples" / "satellites"


# ----------------------------------------------------------------------------- primitives
def test_cuboid_points_grid_edges_and_normals():
    size = (0.1, 0.06, 0.3)
    res = 1.0e4                                   # spacing 1 cm
    d = 0.01
    pc = prim.cuboid_points(size, res)
    h = np.array(size) / 2
    p, n = pc.points, pc.normals
    edge = np.all(n == 0, axis=1)
    # edge points lie on an edge: at least two coordinates at +-half
    on_bound = np.isclose(np.abs(p), h, atol=1e-12)
    assert np.all(on_bound[edge].sum(axis=1) >= 2)
    # per-axis grid along a side of length L: floor(L/d)+1 points exactly d apart (11, 7, 31 here)
    ncoord = [11, 7, 31]
    inner = [k - 2 for k in ncoord]               # grid points strictly inside (ends lie on edges)
    n_edges = 4 * sum(inner) + 8
    n_faces = 2 * (inner[0] * inner[1] + inner[1] * inner[2] + inner[0] * inner[2])
    assert edge.sum() == n_edges
    assert (~edge).sum() == n_faces
    # face points: unit outward normals along one axis, on that face
    f = ~edge
    assert np.allclose(np.linalg.norm(n[f], axis=1), 1.0)
    ax = np.argmax(np.abs(n[f]), axis=1)
    assert np.allclose(p[f][np.arange(f.sum()), ax] * n[f][np.arange(f.sum()), ax], h[ax])
    # spacing: neighbours on the +z face are d apart
    top = p[f & (n[:, 2] > 0)]
    xs = np.unique(np.round(top[:, 0], 9))
    assert np.allclose(np.diff(xs), d)


def test_cuboid_points_rotated_and_translated():
    R = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])       # 90 deg about z
    t = np.array([1.0, 2.0, 3.0])
    a = prim.cuboid_points((0.1, 0.2, 0.3), 1e4)
    b = prim.cuboid_points((0.1, 0.2, 0.3), 1e4, rotation=R, position=t)
    assert np.allclose(b.points, a.points @ R.T + t)
    assert np.allclose(b.normals, a.normals @ R.T)


def test_sphere_points_deserno():
    r, res = 0.2, 2.0e4
    pc = prim.sphere_points(2 * r, res)
    n_target = 4 * math.pi * r * r * res          # ~10053
    assert abs(len(pc) - n_target) / n_target < 0.02
    assert np.allclose(np.linalg.norm(pc.points, axis=1), r)
    assert np.allclose(pc.normals, pc.points / r)
    # equidistributed: each octant holds 1/8 of the points, each hemisphere 1/2
    octant = (pc.points > 0).astype(int) @ np.array([1, 2, 4])
    counts = np.bincount(octant, minlength=8)
    assert np.all(np.abs(counts / len(pc) - 1 / 8) < 0.01)
    # points on circles of latitude (Deserno): few distinct z values, about sqrt(pi N / 4)
    nz = np.unique(np.round(pc.points[:, 2], 9)).size
    assert abs(nz - math.sqrt(math.pi * n_target / 4)) <= 3


def test_cylinder_points_caps_and_side():
    D, L, res = 0.2, 0.5, 1.0e4
    r = D / 2
    pc = prim.cylinder_points(D, L, res)
    p, n = pc.points, pc.normals
    cap = np.abs(n[:, 2]) > 0.5
    side = ~cap
    assert np.allclose(np.abs(p[cap, 2]), L / 2)
    assert np.allclose(n[cap, 2], np.sign(p[cap, 2]))
    assert np.all(np.hypot(p[cap, 0], p[cap, 1]) < r)
    assert np.allclose(np.hypot(p[side, 0], p[side, 1]), r)
    assert np.allclose(n[side, :2], p[side, :2] / r) and np.allclose(n[side, 2], 0)
    # counts: caps pi r^2 res each; side round(2 pi r / d) x (floor(L/d)+1)
    assert abs(cap.sum() / 2 - math.pi * r * r * res) / (math.pi * r * r * res) < 0.03
    assert side.sum() == round(2 * math.pi * r * 100) * 51


@pytest.mark.parametrize("mesh", [prim.cuboid_mesh((0.1, 0.2, 0.3)), prim.sphere_mesh(0.3, 48),
                                  prim.cylinder_mesh(0.2, 0.5, 64)], ids=["cuboid", "sphere", "cylinder"])
def test_meshes_closed_and_outward(mesh):
    V = mesh.vertices
    g = 0.5 * np.cross(V[:, 1] - V[:, 0], V[:, 2] - V[:, 0])
    assert np.allclose(g.sum(axis=0), 0, atol=1e-12)                       # closed surface
    assert np.all(np.einsum("ij,ij->i", g, V.mean(axis=1)) > 0)            # outward winding


def test_mesh_areas_exact():
    c = prim.cuboid_mesh((0.1, 0.2, 0.3))
    area = lambda m: 0.5 * np.linalg.norm(np.cross(m.vertices[:, 1] - m.vertices[:, 0],
                                                   m.vertices[:, 2] - m.vertices[:, 0]), axis=1)
    assert np.isclose(area(c).sum(), 2 * (0.02 + 0.06 + 0.03))
    s = prim.sphere_mesh(0.3, 48)
    assert np.isclose(area(s).sum(), 4 * math.pi * 0.15 ** 2)             # Cauchy: mean projection pi r^2
    cy = prim.cylinder_mesh(0.2, 0.5, 64)
    a = area(cy)
    cap = np.abs(cy.normals[:, 0, 2]) > 0.5
    assert np.isclose(a[cap].sum() / 2, math.pi * 0.1 ** 2)


# ----------------------------------------------------------------------------- configuration file
def test_example_files_load():
    cs = load_satellite(EXAMPLES / "cubesat_3u.toml")
    cam = cs.camera.camera
    assert (cam.width, cam.height) == (1024, 768)
    assert math.isclose(cam.pixel_pitch_m, 4.65e-6) and math.isclose(cam.focal_length_m, 6e-3)
    assert len(cs.components) == 1 and cs.components[0].size == (0.1, 0.1, 0.3)
    assert cs.body.velocity == (0.02, 0.02, 0.4) and cs.body.rotation_deg == (5.0, 5.0, 5.0)
    comp = load_satellite(EXAMPLES / "composite.toml")
    assert {c.shape for c in comp.components} == {"cuboid", "sphere", "cylinder"}
    assert len(comp.components) == 5
    assert comp.point_cloud().component.max() == 4
    assert comp.mesh().component.max() == 4


def _base(**over) -> str:
    parts = dict(
        top="",
        camera="""
            [camera]
            width = 1024
            height = 768
            pixel_pitch_um = 4.65
            focal_length_mm = 6.0
            light_direction = [0.0, 0.0, -1.0]
        """,
        body="""
            [body]
            position = [0.0, 0.0, 1.0]
        """,
        component="""
            [[component]]
            shape = "cuboid"
            size = [0.1, 0.1, 0.3]
        """)
    parts.update(over)
    return "\n".join(textwrap.dedent(parts[k]) for k in ("top", "camera", "body", "component"))


def _write(tmp_path, text, name="sat.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_minimal_file_and_defaults(tmp_path):
    cfg = load_satellite(_write(tmp_path, _base()))
    assert cfg.frames == 1 and cfg.body.surface_resolution == 1e6
    assert cfg.camera.I_a == 0.3 and cfg.camera.light_direction == (0.0, 0.0, -1.0)
    assert cfg.components[0].k_a == 1.0


def _comp(shape: str, size: str, extra: str = "") -> str:
    """One [[component]] table."""
    return f'[[component]]\nshape = "{shape}"\nsize = {size}' + (f"\n{extra}" if extra else "")


CUBOID_3U = "[0.1, 0.1, 0.3]"
CAM64 = "[camera]\nwidth = 64\nheight = 48\npixel_pitch_um = 5.0\nfocal_length_mm = 6.0"      # no light direction

BAD = {
    "unknown shape": (dict(component=_comp("cone", "[0.1]")), "component[0].shape",
                      "'cuboid', 'sphere' or 'cylinder'"),
    "negative size": (dict(component=_comp("cuboid", "[0.1, -0.2, 0.3]")), "component[0].size.1",
                      "greater than 0, got -0.2"),
    "zero size": (dict(component=_comp("sphere", "0.0")), "component[0].size.0", "greater than 0, got 0.0"),
    "size wrong length": (dict(component=_comp("cylinder", "[0.1]")), "component[0].size", "[diameter, length]"),
    "size wrong type": (dict(component=_comp("cuboid", '"big"')), "component[0].size", "[lx, ly, lz]"),
    "no points": (dict(component=_comp("sphere", "[0.0003]")), "component[0].size", "no surface points"),
    "no points (override)": (dict(component=_comp("cylinder", "[0.01, 0.01]", "surface_resolution = 100.0")),
                             "component[0].surface_resolution", "no surface points"),
    "missing camera": (dict(camera=""), "camera", "[camera]"),
    "missing body": (dict(body=""), "body", "[body]"),
    "no component": (dict(component=""), "component", "at least one"),
    "camera inside body": (dict(body="[body]\nposition = [0.0, 0.0, 0.1]"), "camera.position", "inside"),
    "k_a wrong type": (dict(component=_comp("cuboid", CUBOID_3U, 'k_a = "shiny"')), "component[0].k_a",
                       "valid number, got 'shiny'"),
    "k_s negative": (dict(component=_comp("cuboid", CUBOID_3U, "k_s = -1")), "component[0].k_s",
                     "greater than or equal to 0 (allowed [0, 10]), got -1"),
    "position wrong length": (dict(body="[body]\nposition = [0.0, 1.0]"), "body.position", "at least 3 items"),
    "light missing": (dict(camera=CAM64), "camera.light_direction", "missing"),
    "light zero": (dict(camera=CAM64 + "\nlight_direction = [0, 0, 0]"), "camera.light_direction", "zero"),
    "camera width wrong type": (dict(camera=CAM64.replace("64", '"wide"') + "\nlight_direction = [0, 0, -1]"),
                                "camera.width", "integer"),
    "unknown key": (dict(component=_comp("cuboid", CUBOID_3U, 'colour = "red"')), "component[0].colour",
                    "unknown key"),
    "frames not integer": (dict(top="frames = 1.5"), "frames", "integer"),
    "component count mismatch": (dict(body="[body]\nposition = [0.0, 0.0, 1.0]\ncomponents = 2"),
                                 "body.components", "1 [[component]]"),
    "component not a table": (dict(top="component = 3", component=""), "component", "array of tables"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_config_errors_name_file_key_and_allowed(tmp_path, case):
    over, key, allowed = BAD[case]
    path = _write(tmp_path, _base(**over), name="bad.toml")
    with pytest.raises(ConfigError) as ei:
        load_satellite(path)
    msg = str(ei.value)
    assert str(path) in msg
    assert f"[{key}]" in msg, msg
    assert allowed in msg, msg


def test_config_not_toml_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_satellite(_write(tmp_path, "[camera\nwidth = 3"))
    with pytest.raises(ConfigError, match="file not found"):
        load_satellite(tmp_path / "nope.toml")


# ----------------------------------------------------------------------------- motion
def _R1(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, s], [0, -s, c]])


def _R2(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])


def _R3(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])


def test_table2_trajectory():
    cfg = load_satellite(EXAMPLES / "cubesat_3u.toml")
    k = np.arange(0, 40, 7)
    fp = frame_poses(cfg, k)
    # camera fixed at the origin, identity attitude: body origin at p0 + k v (Table 2 velocity)
    assert np.allclose(fp.t_body, np.array([0, 0, 1.0]) + k[:, None] * np.array([0.02, 0.02, 0.4]))
    assert np.allclose(fp.true_range, np.linalg.norm(fp.t_body, axis=1))
    for i, kk in enumerate(k):
        a = math.radians(5.0 * kk)                    # Table 2 rotation: 5 deg/frame on each angle
        A = _R3(a) @ _R2(a) @ _R1(a)                  # 1-2-3 direction-cosine matrix
        assert np.allclose(fp.R_body[i], A.T)         # body -> camera (= world) rotation
        assert np.allclose(fp.R[i, 0], A.T)
    L = np.array([0.4, -0.5, -1.0])
    assert np.allclose(fp.light, L / np.linalg.norm(L))


def test_component_and_camera_motion_compose():
    doc = {
        "camera": dict(width=64, height=48, pixel_pitch_um=5.0, focal_length_mm=6.0, light_direction=[0, 0, -1],
                       position=[0.0, 0.0, -1.0], velocity=[0.0, 0.0, 0.1], rotation_deg=[0.0, 0.0, 10.0]),
        "body": dict(position=[0.0, 0.0, 2.0], rotation_deg=[0.0, 0.0, 90.0]),
        "component": [dict(shape="cuboid", size=[0.1, 0.1, 0.1], position=[0.5, 0.0, 0.0],
                           velocity=[0.1, 0.0, 0.0], rotation_deg=[0.0, 0.0, -90.0])],
    }
    cfg = satellite_from_dict(doc)
    fp = frame_poses(cfg, [1])
    A_cam = _R3(math.radians(10))                               # world -> camera
    B = _R3(math.radians(90)).T                                 # body -> world
    Q = _R3(math.radians(-90)).T                                # component -> body
    t_expect = A_cam @ (np.array([0, 0, 2.0]) + B @ np.array([0.6, 0, 0]) - np.array([0, 0, -0.9]))
    assert np.allclose(fp.t[0, 0], t_expect)
    assert np.allclose(fp.R[0, 0], A_cam @ B @ Q)
    # place_body: same component pose relative to a body placed directly in the camera frame
    pb = place_body(cfg, fp.R_body, fp.t_body, fp.light, frames=1)
    assert np.allclose(pb.t, fp.t) and np.allclose(pb.R, fp.R)


# ----------------------------------------------------------------------------- projected-area tables
def _box_area(size, v):
    """1/2 sum |n_i . v| A_i for a box (both faces of each pair)."""
    lx, ly, lz = size
    return np.abs(v[:, 0]) * ly * lz + np.abs(v[:, 1]) * lx * lz + np.abs(v[:, 2]) * lx * ly


def test_area_samples_match_convex_projection_formula():
    size = (0.1, 0.1, 0.3)
    rng = np.random.default_rng(3)
    q = rng.normal(size=(500, 4))
    from dualsight.scene.attitude import quat_to_dcm
    R = quat_to_dcm(q / np.linalg.norm(q, axis=1, keepdims=True))
    ratio, area = areas_mod.silhouette_stats(("cuboid", size), R)
    assert np.allclose(area, _box_area(size, R[:, 2]), rtol=1e-12)
    # face-on: a 0.1 x 0.1 square (A/A0 = 1, ratio 1); broadside: 0.1 x 0.3 (A/A0 = 3, ratio 3)
    face_on = np.eye(3)[None]
    broad = np.array([[[0, 1.0, 0], [0, 0, 1.0], [1.0, 0, 0]]])        # view along body x
    r0, a0 = areas_mod.silhouette_stats(("cuboid", size), face_on)
    r1, a1 = areas_mod.silhouette_stats(("cuboid", size), broad)
    assert np.isclose(a0[0] / 0.01, 1.0) and np.isclose(r0[0], 1.0)
    assert np.isclose(a1[0] / 0.01, 3.0) and np.isclose(r1[0], 3.0)


def test_area_table_3u(tmp_path):
    t = areas_mod.area_table(("cuboid", (0.1, 0.1, 0.3)), n=20000, cache_dir=tmp_path)
    assert t.A0_m2 == pytest.approx(0.01)
    # A/A0 never below the smallest face nor above the largest projection of a box
    amax = math.sqrt(0.01 ** 2 + 0.03 ** 2 + 0.03 ** 2) / 0.01
    assert t.samples_area.min() >= 1.0 - 1e-12 and t.samples_area.max() <= amax + 1e-12
    assert t.samples_area.max() > amax - 0.01                         # reached by some orientation
    assert t.lookup(1.0, "min") == pytest.approx(1.0, abs=0.03)       # face-on end of the table
    assert t.lookup(3.0, "min") <= 3.0 <= t.lookup(3.0, "max")        # broadside
    assert np.all(t.a_min[t.count > 0] <= t.a_mean[t.count > 0])
    assert np.all(t.a_mean[t.count > 0] <= t.a_max[t.count > 0])
    # mean over all orientations: Cauchy, E[A] = surface area / 4
    assert t.samples_area.mean() * 0.01 == pytest.approx(2 * (0.01 + 0.03 + 0.03) / 4, rel=0.01)
    # cached: same key read back from Parquet
    files = sorted(p.name for p in (tmp_path / "areas").iterdir())
    assert files == [f"{t.key}.parquet", f"{t.key}.samples.parquet"]
    t2 = areas_mod.area_table(("cuboid", (0.1, 0.1, 0.3)), n=20000, cache_dir=tmp_path)
    assert np.array_equal(t2.a_mean, t.a_mean, equal_nan=True) and t2.A0_m2 == t.A0_m2


def test_area_scanline_agrees_with_exact():
    for shape in [("cuboid", (0.1, 0.1, 0.3)), ("cylinder", (0.2, 0.5)), ("sphere", (0.3,))]:
        r1, a1 = areas_mod.projected_area_samples(shape, n=200, method="exact")
        r2, a2 = areas_mod.projected_area_samples(shape, n=200, method="scanline", rows=512)
        assert np.max(np.abs(a2 / a1 - 1)) < 0.003, shape
        assert np.max(np.abs(r2 / r1 - 1)) < 0.005, shape
    # a sphere is pi r^2 at ratio 1 from every view
    r, a = areas_mod.projected_area_samples(("sphere", (0.3,)), n=50)
    assert np.allclose(a, math.pi * 0.15 ** 2) and np.allclose(r, 1.0)


def test_area_table_composite_union(tmp_path):
    # two unit-separated spheres: union area = 2 pi r^2 unless they overlap in projection
    spec = [dict(shape="sphere", size=[0.2], position=[0.5, 0, 0]),
            dict(shape="sphere", size=[0.2], position=[-0.5, 0, 0])]
    ratio, area = areas_mod.projected_area_samples(spec, n=300, method="scanline", rows=512)
    from dualsight.scene.attitude import quat_to_dcm, random_quaternions
    d = quat_to_dcm(random_quaternions(np.random.default_rng(0), 300))[:, 2]  # same views (seed 0)
    sep = np.sqrt(1.0 - d[:, 0] ** 2)                                  # projected centre distance (m)
    far = sep > 0.2
    assert np.allclose(area[far], 2 * math.pi * 0.01, rtol=3e-3)
    assert np.all(area[~far] < 2 * math.pi * 0.01)


# ----------------------------------------------------------------------------- resolvable range
def test_resolvable_range_table1():
    cam = Camera.pinhole(1024, 768, 4.65e-6, 6e-3)
    rr = resolvable_range(cam, 0.1)
    assert rr.far_m == pytest.approx(6e-3 * 0.1 / (2 * 4.65e-6))      # 64.5 m
    assert rr.far_m == pytest.approx(64.516, abs=1e-3)
    assert rr.near_fit_m == pytest.approx(6e-3 * 0.1 / (768 * 4.65e-6))   # 16.8 cm: fills the height
    assert rr.near_fill_m == pytest.approx(6e-3 * 0.1 / (1024 * 4.65e-6))  # 12.6 cm: fills the width
    assert rr.reference_near_m == pytest.approx(0.0840, abs=5e-5)          # the reference's 8.4 cm
    assert rr.near_m == rr.near_fit_m
