"""Plain helpers shared by the test modules (fixtures live in ``conftest.py``).

``tests/`` is on ``sys.path`` while pytest runs (it holds ``conftest.py``), so a test module imports these with
``from helpers import ...``.  Keep here only what more than one test module uses; a helper of one module stays
in that module.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
from pathlib import Path

import numpy as np

from dualsight.scene.attitude import euler123_to_dcm, random_euler123
from dualsight.scene.camera import Camera
from dualsight.scene.units import ARCSEC

ROOT = Path(__file__).resolve().parents[1]
"""The repository's root (the folder holding ``pyproject.toml``)."""


def shared_real() -> Path:
    """The real data: ``$DUALSIGHT_SHARED/data/real``, else ``../shared/data/real`` next to the repository.

    The folder may be absent: each test module names what it needs and skips with its own reason."""
    env = os.environ.get("DUALSIGHT_SHARED")
    return (Path(env) if env else ROOT.parent / "shared") / "data" / "real"


def run_cli(argv) -> tuple[int, str, str]:
    """``dualsight <argv>`` in this process -> (exit status, stdout, stderr), captured by hand (so that
    module-scoped fixtures can use it too).  An argparse error (``SystemExit``) gives its exit status."""
    from dualsight.jobs.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = main([str(a) for a in argv])
        except SystemExit as e:             # argparse errors (2), --help (0)
            rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    return rc, out.getvalue(), err.getvalue()


def snapshot(root: Path) -> dict:
    """{file relative to ``root``: (size, mtime in ns)} of every file under ``root`` ({} when it does not
    exist): equal before and after a command that must not write."""
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")
            if p.is_file()}


def lake_rows(lake: Path, run_id: str, order: dict[str, str], timing=()) -> dict[str, list[dict]]:
    """Every row of the datasets ``order`` ({dataset: ORDER BY}) of a run (SQL over the lake), ``timing``
    columns dropped."""
    from dualsight.warehouse.query import connect

    con = connect(lake)
    out = {}
    for ds, by in order.items():
        cur = con.execute(f"SELECT * EXCLUDE (run) FROM {ds} WHERE run = ? ORDER BY {by}", [run_id])
        cols = [d[0] for d in cur.description]
        out[ds] = [{c: v for c, v in zip(cols, r) if c not in timing} for r in cur.fetchall()]
    return out


def esa_spec(names=None) -> dict:
    """The ``hil star`` job spec of the ESA tetra3 frames (all, or those ``names``) with their truth file and the
    tripod's site, default settings at epoch 2019.6.  The caller skips when the frames are absent."""
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.kinds.hil_star_spec import settings_from_table
    from dualsight.jobs.kinds.hil_truth import Site, resolve_star_truths
    from dualsight.scene.skytruth import load_truth_json

    esa = shared_real() / "esa_tetra3"
    paths = [esa / n for n in names] if names else sorted(esa.glob("*.tiff"))
    settings = settings_from_table(None, epoch_jyear=2019.6)
    truths = resolve_star_truths(paths, load_truth_json(esa / "truth.json"), Site(52.08, 4.37))
    return hs.build_spec(paths, Camera.from_toml(ROOT / "examples" / "cameras" / "esa_tetra3.toml"), settings, truths)


def hil_star_rows(lake: Path, run_id: str) -> dict[str, list[dict]]:
    """The ``hil_star`` and ``hil_star_stars`` rows of a run (:func:`lake_rows`), timing columns dropped."""
    from dualsight.jobs.kinds import hil_star as hs

    return lake_rows(lake, run_id, {"hil_star": "case_id", "hil_star_stars": "case_id, det_index"}, hs.TIMING_COLUMNS)


def phi(x: float) -> float:
    """The standard normal distribution function."""
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


def unit(v):
    """``v`` scaled to unit length along its last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ------------------------------------------------------------- synthetic star fields (the star-identification tests)
CAM = Camera.pinhole(1024, 768, 4.65e-6, 17e-3)     # the reference's star SIL camera: 15.9 x 12.0 deg
TOL = 5e-5                                            # 10 arcsec: ~1 arcsec perturbations in the fields


def rotation(axis, angle):
    """Active rotation matrix (Rodrigues) of ``angle`` about unit ``axis``."""
    k = unit(np.asarray(axis, float))
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def sphere_catalog(seed, n):
    return unit(np.random.default_rng(seed).normal(size=(n, 3)))


def pair_catalog(cat, max_angle):
    """All pairs i < j closer than ``max_angle``, ascending by angle (plain numpy, no dualsight code)."""
    n = len(cat)
    dots = np.clip(cat @ cat.T, -1.0, 1.0)
    i, j = np.nonzero(np.triu(dots > np.cos(max_angle), k=1))
    ang = np.arctan2(np.linalg.norm(np.cross(cat[i], cat[j]), axis=1), np.sum(cat[i] * cat[j], axis=1))
    keep = ang < max_angle
    o = np.argsort(ang[keep], kind="stable")
    assert n < 2**31
    return i[keep][o].astype(np.int32), j[keep][o].astype(np.int32), ang[keep][o]


def star_fields(rng, cat, B, S=24, sigma=1.0 * ARCSEC, n_false=(0, 3), n_drop=(1, 2), only=None):
    """Random attitudes and the observed stars of a 1024x768, 17 mm camera.

    Returns A_true (B,3,3), obs (B,S,3), valid (B,S), truth (B,S) catalog row or -1 (false star).
    Every true star is perturbed by ``sigma`` (rad, per axis); ``n_drop`` stars are removed (keeping
    >= 3), ``n_false`` false stars are added at random pixels; order = random "brightness".
    ``only`` = keep exactly this many true stars and no false ones.
    """
    A = euler123_to_dcm(random_euler123(rng, B))          # the reference's attitude sampling
    obs = np.zeros((B, S, 3))
    valid = np.zeros((B, S), bool)
    truth = np.full((B, S), -1)
    for b in range(B):                                   # test-data generation, not a hot path
        v = cat @ A[b].T
        px, front = CAM.project(v)
        inn = rng.permutation(np.nonzero(front & CAM.in_image(px))[0])
        if only is not None:
            inn, nf = inn[:only], 0
        else:
            nd = rng.integers(n_drop[0], n_drop[1] + 1)
            inn = inn[:max(len(inn) - nd, min(len(inn), 3))]
            nf = rng.integers(n_false[0], n_false[1] + 1)
        tv = unit(v[inn] + rng.normal(scale=sigma, size=(len(inn), 3)))
        fv = CAM.backproject(np.stack([rng.uniform(0, CAM.width, nf), rng.uniform(0, CAM.height, nf)], -1))
        allv = np.concatenate([tv, fv])
        ids = np.concatenate([inn, np.full(nf, -1)])
        o = rng.permutation(len(allv))[:S]
        obs[b, :len(o)], valid[b, :len(o)], truth[b, :len(o)] = allv[o], True, ids[o]
    return A, obs, valid, truth


def orion_field(camera: Camera):
    """The synthetic round trip's scene (tests/test_hil_star.py, test_api.py, test_hil_star_objects.py): ``camera``
    pointed at RA 84, Dec -3 deg (Orion: many bright stars) with 30 deg roll; Hipparcos to V 7 at epoch 2019.6 (the
    ESA tests' catalog); a noisy sensor (0.3 s, shot noise, 15 e- read noise, 300 e- sky, hot pixels).
    Returns (A (3, 3) inertial -> camera, the catalog, the SensorConfig, the stars in the field)."""
    from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
    from dualsight.jobs.kinds.star import psf_margin_px
    from dualsight.kernels.sensor_config import SensorConfig, flux_from_magnitude
    from dualsight.scene.attitude import radec_to_unit, rot_axis
    from dualsight.scene.starfield_geometry import stars_in_field

    z = radec_to_unit(math.radians(84.0), math.radians(-3.0))
    east = np.cross([0.0, 0.0, 1.0], z)
    east /= np.linalg.norm(east)
    north = np.cross(z, east)
    A = rot_axis(3, math.radians(30.0))[0] @ np.stack([np.cross(-north, z), -north, z])
    cat = load_star_catalog(StarCatalogConfig(mag_limit=7.0, epoch_jyear=2019.6))
    sensor = SensorConfig(exposure_s=0.3, shot_noise=True, read_noise_e=15.0, sky_background_e=300.0,
                          hot_pixel_fraction=2e-4, hot_pixel_e=3000.0, hot_pixel_seed=7, bias_adu=20.0)
    field_ = stars_in_field(A[None], cat.unit, flux_from_magnitude(cat.vmag, sensor), camera, psf_margin_px(sensor))
    return A, cat, sensor, field_


def noisy_block_sequence(camera: Camera, seed: int = 15):
    """A 60-frame sequence at 10 fps turning at 0.3 deg/s about a random axis over a random sphere catalog (3,000
    stars, seed 21): detections are the catalog stars in the image with Gaussian centroid noise of 0.05 px, except
    the first two frames and four blocks of 4 frames (8, 20, 32, 44) at 0.6 px, each stated honestly per detection.
    Returns SimpleNamespace(t (T,), A (T, 3, 3) true attitudes, w (3,) rad/s, xy (K, 2), sg (K,), off (T + 1,),
    noisy (T,) bool, cat (N, 3), pairs: the pair catalog's i, j, angle)."""
    from types import SimpleNamespace
    rng = np.random.default_rng(seed)
    cat = sphere_catalog(21, 3000)
    pi, pj, pa = pair_catalog(cat, camera.fov_rad[2] * 1.05)
    T = 60
    noisy = np.zeros(T, bool)
    noisy[:2] = True
    for s0 in (8, 20, 32, 44):
        noisy[s0: s0 + 4] = True
    A0 = euler123_to_dcm(random_euler123(rng, 1))[0]
    w = unit(rng.normal(size=3)) * math.radians(0.3)
    t = np.arange(T) / 10.0
    A = np.stack([rotation(w, np.linalg.norm(w) * tk).T @ A0 for tk in t])
    xys, sgs, counts = [], [], []
    for k in range(T):
        px, front = camera.project(cat @ A[k].T)
        inn = np.flatnonzero(front & camera.in_image(np.nan_to_num(px, nan=-1.0)))
        s_k = 0.6 if noisy[k] else 0.05
        xys.append(px[inn] + rng.normal(scale=s_k, size=(inn.size, 2)))
        sgs.append(np.full(inn.size, s_k))
        counts.append(inn.size)
    return SimpleNamespace(t=t, A=A, w=w, xy=np.concatenate(xys), sg=np.concatenate(sgs),
                           off=np.concatenate([[0], np.cumsum(counts)]), noisy=noisy, cat=cat,
                           pairs=SimpleNamespace(i=pi, j=pj, angle=pa))


def angle_deg(a, b):
    """(...,) degrees between the vectors a and b (..., 3), any lengths."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def sky_geometry(boresight, r_km, sun_km, moon_km):
    """The truth of the keep-out and shadow columns by brute-force geometry from astropy's positions.

    boresight : (N, 3) the camera's +z in ICRS.  r_km, sun_km, moon_km : (N, 3) the spacecraft's, the Sun's and the
    Moon's geocentric positions (km).  Returns dict of (N,) arrays: sun_deg, moon_deg (angles from the boresight,
    seen from the spacecraft), limb_deg (to the Earth's limb, R = 6378.137 km), umbra (the Sun, 0.27 deg, wholly
    behind the Earth's disk), clear (neither umbra nor within 0.3 deg of the limb: the frames a shadow test judges).
    """
    rho = np.degrees(np.arcsin(6378.137 / np.linalg.norm(r_km, axis=1)))
    sep = angle_deg(sun_km - r_km, -r_km)
    umbra = sep < rho - 0.27
    return {"sun_deg": angle_deg(boresight, sun_km - r_km), "moon_deg": angle_deg(boresight, moon_km - r_km),
            "limb_deg": angle_deg(boresight, -r_km) - rho, "umbra": umbra,
            "clear": ~umbra & (np.abs(sep - rho) > 0.3)}
