"""How much of the centre-of-brightness bias does the phase-angle correction remove?  (issue 23, point 6 (b))

    DUALSIGHT_TI_THREADS=1 taskset -c 0 python benchmarks/bench_phase_correction.py [--attitudes 400]
        [--range-m 30] [--segments 128] [--seed 1]

A target on the boresight of the paper preset's camera (fx 3656 px, a window of the camera around it), rendered by
the project's renderer (``kernels/prox_raster.render_mesh``: exact pixel coverage, Lambertian shading, no ambient,
no specular, no noise, no saturation), at phase angles 0-90 deg in 10 deg steps with the Sun at a random azimuth
about the line of sight.  The centre of brightness (COB) is the image's intensity-weighted centroid; the truth is
the projection of the body origin.  The bias is the mean of (COB - truth) over the cases of one phase angle, as a
2-D vector in the Sun's frame of the image (towards the Sun's projection, across it), its length in px and in units of the radius (the sphere's; the cuboid's bounding radius); "removed"
= 1 - |bias after| / |bias before|.  Cases:

* sphere (radius ``--sphere-radius-m``): one case per phase angle and Sun azimuth (a sphere has no attitude),
  corrected by ``scene/target_photometry.sphere_photocentre_offset`` along the Sun's direction in the image;
* cuboid of KNOWN attitude (the 3U CubeSat, 0.1 x 0.1 x 0.3 m; ``--attitudes`` attitudes uniform on SO(3)),
  corrected by ``photocentre_offset`` (its lit, visible facets);
* cuboid of UNKNOWN attitude (the same images), corrected by the mean of ``photocentre_table`` at the phase angle.

Also the per-case RMS of (COB - truth) after each correction (what is left for the covariance).  The sphere's mesh
has ``--segments`` segments (a polyhedron: its residual is the tessellation's).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")

import numpy as np  # noqa: E402

from dualsight.jobs.engine.specs import preset_and_config  # noqa: E402
from dualsight.jobs.kinds import star  # noqa: E402
from dualsight.kernels.prox_raster import render_mesh  # noqa: E402
from dualsight.scene.attitude import quat_to_dcm, quaternions_from_uniforms  # noqa: E402
from dualsight.scene.motion import place_body  # noqa: E402
from dualsight.scene.satellite import ComponentConfig, load_satellite  # noqa: E402
from dualsight.scene.target_photometry import (photocentre_offset, photocentre_table,  # noqa: E402
                                               sphere_photocentre_offset, target_shape)

PHASES_DEG = np.arange(0.0, 90.1, 10.0)


def render_cob(sat, R_body, pos, sun, camera, segments: int) -> np.ndarray:
    """(K, 2) intensity-weighted centroids (px, pixel centres at +0.5) of the target rendered in ``camera``."""
    mesh = sat.mesh(segments)
    mat = np.array([[0.0, c.k_l, 0.0, 1.0] for c in sat.components])
    poses = place_body(sat, R_body, pos, sun)
    img, _ = render_mesh(mesh, mat, poses.R, poses.t, poses.light, camera, I_a=0.0, I_l=1.0)
    img = img.astype(np.float64)
    ys, xs = np.arange(img.shape[1]) + 0.5, np.arange(img.shape[2]) + 0.5
    tot = img.sum((1, 2))
    tot = np.where(tot > 0, tot, np.nan)                  # NaN: nothing lit faces the camera
    return np.stack([(img.sum(1) * xs).sum(1) / tot, (img.sum(2) * ys).sum(1) / tot], -1)


def suns(alpha: float, psi: np.ndarray) -> np.ndarray:
    """(K, 3) unit vectors towards the Sun at phase ``alpha`` for a target on +z seen from the origin (target ->
    camera is -z), azimuth ``psi`` about the line of sight."""
    o = np.array([0.0, 0.0, -1.0])
    return (math.cos(alpha) * o + math.sin(alpha) * np.stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)], -1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--attitudes", type=int, default=400)
    ap.add_argument("--range-m", type=float, default=30.0)
    ap.add_argument("--sphere-radius-m", type=float, default=0.5)
    ap.add_argument("--segments", type=int, default=128)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    d, source = preset_and_config(star.PRESETS, "paper", None)
    cam = star.spec_from_dict(d, source=source).camera
    f = cam.fx
    cube = load_satellite("examples/satellites/cubesat_3u.toml")
    sphere = dataclasses.replace(cube, components=(ComponentConfig(shape="sphere", size=(2 * a.sphere_radius_m,),
                                                                   k_l=0.8),))
    shape = target_shape(cube.components)
    grid, tmean, _ = photocentre_table(shape)
    r = a.range_m
    half = int(math.ceil(max(sphere.bounding_radius, cube.bounding_radius) / r * f)) + 4
    win = dataclasses.replace(cam, width=2 * half + 1, height=2 * half + 1, cx=half + 0.5, cy=half + 0.5,
                              distortion=(0.0,) * 5)
    truth = np.array([win.cx, win.cy])                  # the body origin on the boresight
    pos1 = np.array([0.0, 0.0, r])
    rng = np.random.default_rng([a.seed, 23, 6])
    K = a.attitudes
    t0 = time.perf_counter()
    print(f"paper camera (fx {f:.0f} px), range {r:g} m, no noise, no saturation; sphere R = {a.sphere_radius_m:g} m "
          f"({2 * a.sphere_radius_m / r * f:.0f} px across, {a.segments}-segment mesh); 3U cuboid bounding radius "
          f"{cube.bounding_radius:.3f} m ({2 * cube.bounding_radius / r * f:.0f} px), {K} attitudes per phase angle")
    print("bias = |mean(COB - body origin)| in the Sun's frame of the image over the cases of a phase angle; "
          "'removed' = 1 - after / before; rms = per-case RMS of what is left (px)")
    hdr = (f"{'phase':>5} | {'sphere bias px':>14} {'/R':>6} {'after px':>9} {'removed':>8} | {'cuboid bias px':>14} "
           f"{'/R':>6} {'known px':>9} {'removed':>8} {'rms':>6} | {'table px':>9} {'removed':>8} {'rms':>6}")
    print(hdr)
    rows, dark = [], 0
    for deg in PHASES_DEG:
        al = math.radians(deg)
        psi = rng.uniform(0, 2 * np.pi, K)
        s = suns(al, psi)
        s_img = np.stack([np.cos(psi), np.sin(psi)], -1)          # the Sun's direction in the image (x, y)
        # sphere: a handful of azimuths is enough (no attitude)
        ks = min(K, 16)
        cob_s = render_cob(sphere, np.tile(np.eye(3), (ks, 1, 1)), np.tile(pos1, (ks, 1)), s[:ks], win, a.segments)
        e0 = cob_s - truth
        e1 = e0 - (sphere_photocentre_offset(a.sphere_radius_m, al) / r * f) * s_img[:ks]
        # cuboid: K random attitudes
        u = rng.random((3, K))
        R = quat_to_dcm(quaternions_from_uniforms(u[0], u[1], u[2]))
        cob_c = render_cob(cube, R, np.tile(pos1, (K, 1)), s, win, a.segments)
        lit = np.isfinite(cob_c).all(1)                   # attitudes showing a lit face (all below 90 deg)
        dark += int((~lit).sum())
        R, s, s_img, cob_c = R[lit], s[lit], s_img[lit], cob_c[lit]
        c0 = cob_c - truth
        off = photocentre_offset(shape, R, s, np.tile([0.0, 0.0, -1.0], (len(R), 1)))  # camera frame (m)
        c1 = c0 - off[:, :2] / r * f
        c2 = c0 - (np.interp(al, grid, tmean) / r * f) * s_img
        # each case's error in the Sun's frame of the image (towards the Sun, across): the bias is its mean there
        sun_frame = lambda e, sd: np.stack([(e * sd).sum(1), e[:, 1] * sd[:, 0] - e[:, 0] * sd[:, 1]], -1)  # noqa: E731
        e0, e1 = sun_frame(e0, s_img[:ks]), sun_frame(e1, s_img[:ks])
        c0, c1, c2 = sun_frame(c0, s_img), sun_frame(c1, s_img), sun_frame(c2, s_img)
        b = lambda e: float(np.linalg.norm(e.mean(0)))  # noqa: E731
        rms = lambda e: float(np.sqrt((e ** 2).sum(1).mean()))  # noqa: E731
        rem = lambda e_a, e_b: 1 - b(e_b) / b(e_a) if b(e_a) > 0 else float("nan")  # noqa: E731
        rows.append((deg, rem(e0, e1), rem(c0, c1), rem(c0, c2)))
        Rs, Rc = a.sphere_radius_m / r * f, cube.bounding_radius / r * f
        print(f"{deg:5.0f} | {b(e0):14.4f} {b(e0) / Rs:6.3f} {b(e1):9.4f} {100 * rem(e0, e1):7.1f}% | {b(c0):14.4f} "
              f"{b(c0) / Rc:6.3f} {b(c1):9.4f} {100 * rem(c0, c1):7.1f}% {rms(c1):6.3f} | {b(c2):9.4f} "
              f"{100 * rem(c0, c2):7.1f}% {rms(c2):6.3f}")
    rows = np.array(rows)
    judged = rows[:, 0] >= 10
    print(f"phase 10-90 deg: smallest share removed: sphere {100 * np.min(rows[judged, 1]):.1f} %, cuboid known "
          f"attitude {100 * np.min(rows[judged, 2]):.1f} %, cuboid unknown attitude (table) "
          f"{100 * np.min(rows[judged, 3]):.1f} % (target >= 90 %); {dark} dark cuboid cases left out (no lit face "
          f"towards the camera); {time.perf_counter() - t0:.0f} s, one process")


if __name__ == "__main__":
    main()
