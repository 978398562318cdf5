"""dualsight's star chain beside a peer solver (cedar-solve), on the same frames, one core each (run by hand).

    .venv/bin/python benchmarks/bench_peers.py                         # the 8 ESA frames (../shared/data/real/esa_tetra3)
    .venv/bin/python benchmarks/bench_peers.py --rendered 50           # 50 rendered 1024x1024 frames, 20 deg, noisy
    .venv/bin/python benchmarks/bench_peers.py --frames 'DIR/*.png' --camera CAM.toml --truth TRUTH.json
    .venv/bin/python benchmarks/bench_peers.py --lake DIR              # also both runs into a lake (hil_star, peer_star)

The peer is never a dependency of dualsight: on first use this script creates its own venv
(``benchmarks/.venv-cedar``, git-ignored; ``--cedar-venv``), pip-installs ``cedar-solve`` there (a tetra3 fork,
importable as ``tetra3``) and runs ``benchmarks/peers/cedar_worker.py`` with that venv's python.  They exchange
files only: a JSON job, one ``.npy`` of ADC counts per frame (decoded once, here, by dualsight's reader, so both
solvers see the same pixels and decoding is outside both timings) and JSON answers (``jobs/kinds/peer_star.py``'s
layout).  No pickles.

What is timed, per frame, warm (after one untimed run of the first frame), on one thread (OMP, OpenBLAS, MKL,
numba and Taichi capped at 1 for both processes; ``--cpu K`` pins both to core K):
  * dualsight: the functions ``dualsight hil star`` runs (jobs/kinds/hil_star.py ``_run_batch``): ``detect_frames``
    (background + detection/centroids), ``nav.observations``, ``nav.star_solution.identify`` (lost-in-space
    robust geometric voting) and ``solve`` (SVD attitude), one frame at a time and batched (``batch_size``
    frames per call, ms per frame = batch time / frames).  Its answers are checked to equal the job's own
    ``compute_shard`` on the same spec.
  * cedar-solve: its own centroider ``get_centroids_from_image`` then ``Tetra3.solve_from_centroids``, with the
    horizontal field of view from the camera file as ``fov_estimate`` (+- ``--fov-max-error``) and the database
    cedar-solve ships (``default_database``: Hipparcos to V 8.0, fields 10-30 deg; ``--cedar-database`` for
    another .npz).
Errors are against the truth file's ``R_icrs_to_cam`` (boresight angle and roll difference, arcsec).  The ESA
truth.json was itself made by cedar-solve 0.5.1 with its default database: on those frames cedar is scored
against its own answer and only the rendered frames are an independent truth for both.

``--rendered N`` renders N frames with dualsight's simulator (jobs/kinds/star.py ``compute_batch(..., keep_images=True)``,
uniform random attitudes, the sensor of examples/star/noisy_sensor.toml, 1024x1024 px, fx = 2904 px = 20.0 deg
horizontal field, Hipparcos to V 7) and writes them as 16-bit PNG (12-bit ADC counts, right-aligned) with a
camera file and a truth file in the format of esa_tetra3/truth.json, so ``dualsight hil star`` reads them too.
"""

from __future__ import annotations

import os

THREAD_VARS = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1",
               "DUALSIGHT_TI_THREADS": "1"}
os.environ.update(THREAD_VARS)                     # before numpy and Taichi start their pools

import argparse  # noqa: E402
import glob  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ["DUALSIGHT_SHARED"]) if os.environ.get("DUALSIGHT_SHARED") else ROOT.parent / "shared"
ESA = SHARED / "data" / "real" / "esa_tetra3"
WORKER = Path(__file__).resolve().parent / "peers" / "cedar_worker.py"
CEDAR_REQUIREMENT = "cedar-solve==0.5.1"
ARCSEC = math.pi / (180 * 3600)


class BenchError(Exception):
    """One line for the user; exit status 2."""


# ============================================================================================ the peer's venv
def ensure_cedar_venv(venv: Path, requirement: str) -> tuple[Path, dict]:
    """(python of the cedar venv, its stamp {requirement, venv_create_s, pip_install_s, freeze}); creates the venv
    and installs ``requirement`` when it is missing or was made for another requirement."""
    py = venv / "bin" / "python"
    stamp_path = venv / "dualsight-peer.json"
    try:
        stamp = json.loads(stamp_path.read_text())
        if py.exists() and stamp.get("requirement") == requirement:
            return py, stamp
    except (OSError, ValueError):
        pass
    print(f"bench_peers: creating {venv} and installing {requirement} (once)", file=sys.stderr)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "venv", "--clear", str(venv)], capture_output=True, text=True)
    if r.returncode != 0:
        raise BenchError(f"cannot create the peer venv {venv}: {_last_line(r.stderr)}")
    t1 = time.perf_counter()
    r = subprocess.run([str(py), "-m", "pip", "install", "--disable-pip-version-check", "-q", requirement],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise BenchError(f"pip install {requirement} into {venv} failed (is PyPI reachable?): {_last_line(r.stderr)}")
    t2 = time.perf_counter()
    freeze = subprocess.run([str(py), "-m", "pip", "freeze"], capture_output=True, text=True).stdout.split()
    stamp = {"requirement": requirement, "venv_create_s": round(t1 - t0, 1), "pip_install_s": round(t2 - t1, 1),
             "freeze": freeze, "created_unix": time.time()}
    stamp_path.write_text(json.dumps(stamp, indent=1))
    return py, stamp


def _last_line(text: str) -> str:
    lines = [ln for ln in (text or "").strip().splitlines() if ln.strip()]
    return lines[-1].strip() if lines else "no message"


# ============================================================================================ frames
def esa_inputs(args):
    if args.frames is None and not ESA.is_dir():
        raise BenchError(f"the ESA frames are not at {ESA}; give --frames and --camera (or set DUALSIGHT_SHARED)")
    from dualsight.scene.imageio import list_images

    pattern = args.frames or str(ESA / "*.tiff")
    paths = list_images(Path(pattern)) if Path(pattern).is_dir() else sorted(Path(p) for p in glob.glob(pattern))
    if not paths:
        raise BenchError(f"no frames match {pattern}")
    camera = Path(args.camera) if args.camera else ROOT / "examples" / "cameras" / "esa_tetra3.toml"
    truth = Path(args.truth) if args.truth else (paths[0].parent / "truth.json")
    return [p.resolve() for p in paths], camera, (truth if truth.exists() else None), "real frames, as recorded"


RENDER_CAMERA = {"name": "bench_peers_20deg", "notes": "bench_peers --rendered: 1024x1024, 20.0 deg horizontal",
                 "width": 1024, "height": 1024, "pixel_pitch_um": 5.5, "fx": 2904.0, "fy": 2904.0, "cx": 512.0,
                 "cy": 512.0, "distortion": [0.0, 0.0, 0.0, 0.0, 0.0], "bit_depth": 12}


def render_inputs(n: int, seed: int, out: Path, mag_limit: float):
    """Render ``n`` frames (cached in ``out``): (paths, camera file, truth file, noise description)."""
    import tomllib

    import cv2

    sensor_toml = ROOT / "examples" / "star" / "noisy_sensor.toml"
    cfg = tomllib.loads(sensor_toml.read_text())
    noise = "sensor of examples/star/noisy_sensor.toml: " + ", ".join(f"{k}={v}" for k, v in cfg["sensor"].items())
    out.mkdir(parents=True, exist_ok=True)
    camera_path, truth_path = out / "camera.toml", out / "truth.json"
    paths = [out / f"frame_{i:04d}.png" for i in range(n)]
    # the camera file, with the PSF width the frames are rendered with (a camera's calibrated PSF: hil star's
    # detector filters at it and checks it on each frame), written every time (a cache of older frames too)
    lines = ["# bench_peers --rendered: the camera of the rendered frames", "[camera]"]
    for k, v in RENDER_CAMERA.items():
        lines.append(f"{k} = {json.dumps(v)}")
    lines.append(f"psf_sigma_px = {float(cfg['sensor']['psf_sigma_px'])!r}")
    camera_path.write_text("\n".join(lines) + "\n")
    if all(p.exists() for p in paths) and truth_path.exists():
        return paths, camera_path, truth_path, noise
    from dualsight.jobs.kinds import star
    from dualsight.scene.attitude import unit_to_radec

    spec = star.spec_from_dict({"seed": seed, "batch_size": 16, "attitudes": "uniform", "error_frame": "camera",
                                "camera": RENDER_CAMERA, "catalog": {"mag_limit": mag_limit, "epoch_jyear": 2000.0},
                                "sensor": cfg["sensor"], "detect": cfg.get("detect", {}),
                                "voting": cfg.get("voting", {}), "compare_robust": False}, source="bench_peers")
    ctx = star.make_context(spec)
    cat = ctx.catalog
    truth = {}
    t0 = time.perf_counter()
    for s in range(0, n, 16):
        ids = np.arange(s, min(n, s + 16), dtype=np.int64)
        b = star.compute_batch(spec, ctx, ids, keep_images=True)
        imgs, A, fld = b["rendered"].images, b["draw"]["A_true"], b["field"]
        for j, i in enumerate(ids):
            px = np.clip(np.rint(imgs[j]), 0, 4095).astype(np.uint16)
            if not cv2.imwrite(str(paths[i]), px):
                raise BenchError(f"cannot write {paths[i]}")
            ra, dec = unit_to_radec(A[j, 2])
            keep = np.flatnonzero(fld.valid[j] & fld.inside[j])
            rows = fld.cat_row[j, keep]
            truth[paths[i].name] = {
                "ra_deg": math.degrees(float(ra)), "dec_deg": math.degrees(float(dec)),
                "R_icrs_to_cam": A[j].tolist(), "boresight_from_R_deg": [math.degrees(float(ra)),
                                                                         math.degrees(float(dec))],
                "source": f"dualsight star render, seed {seed}, case {int(i)}",
                "matched": [{"row": float(fld.y[j, k]), "col": float(fld.x[j, k]), "ra_deg": math.degrees(float(cat.ra[r])),
                             "dec_deg": math.degrees(float(cat.dec[r])), "mag": float(cat.vmag[r])}
                            for k, r in zip(keep, rows)]}
    print(f"bench_peers: rendered {n} frames into {out} in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    truth_path.write_text(json.dumps(truth, indent=1))
    return paths, camera_path, truth_path, noise


# ============================================================================================ dualsight
def dualsight_spec(paths, camera_path, truth_path, args):
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.kinds.hil_star_spec import settings_from_table
    from dualsight.jobs.kinds.hil_truth import resolve_star_truths
    from dualsight.scene.camera import Camera
    from dualsight.scene.skytruth import load_truth_json
    from dualsight.scene.timescale import observation_epoch

    camera = Camera.from_toml(camera_path)
    epoch = observation_epoch(paths) or 2000.0
    settings = settings_from_table(None, source="bench_peers", method="robust", compare=False,
                                   batch_size=args.batch_size, mag_limit=args.mag_limit, epoch_jyear=epoch,
                                   tolerance_arcsec=20.0, max_stars=25, k_sigma=5.0, min_pixels=3)
    truths = resolve_star_truths(paths, load_truth_json(truth_path) if truth_path else None, None)
    return hs.spec_from_dict(hs.build_spec(paths, camera, settings, truths), source="bench_peers")


def dualsight_chain(frames: np.ndarray, ctx):
    """detect -> observations -> identify -> solve of (B, H, W) frames, as hil_star's ``_run_batch`` calls them:
    [(A or None, stars detected, stars identified)] per frame."""
    from dualsight.jobs.kinds.hil_star import detect_frames
    from dualsight.nav.observations import observations
    from dualsight.nav.star_solution import centroid_weights, identify, solve

    rt, B = ctx.rt, frames.shape[0]
    _, _, det = detect_frames(frames, rt.settings, rt.detect, saturation_adu=float(2 ** rt.camera.bit_depth - 1),
                              residual=False)
    obs = observations(det, B, rt.camera, max_obs=rt.settings.max_obs)
    ident = identify(obs, ctx.catalog.unit, ctx.pairs, rt.voting, cat_vmag=ctx.catalog.vmag)
    floor = rt.settings.centroid_floor_px
    sol = solve(obs, ident, ctx.catalog.unit, None,
                weights=centroid_weights(det, obs, floor) if floor is not None else None)
    out = []
    for b in range(B):
        ok = bool(sol.ok[b]) and int(ident.T[b]) > 0
        out.append((sol.A_est[b].copy() if ok else None, int(det.counts[b]), int(ident.accepted[b].sum())))
    return out


def run_dualsight(spec, pixels: list[np.ndarray], repeats: int):
    """Per-frame answers and ms (single frames), batched ms per frame, and setup times."""
    from dualsight.jobs.kinds import hil_star as hs

    t0 = time.perf_counter()
    ctx = hs.make_context(spec)
    t_ctx = time.perf_counter() - t0
    t0 = time.perf_counter()
    dualsight_chain(pixels[0][None], ctx)                               # warm-up: Taichi compiles here
    t_warm = time.perf_counter() - t0
    answers, ms = [], []
    for px in pixels:
        runs = []
        for _ in range(repeats):
            a = time.perf_counter_ns()
            res = dualsight_chain(px[None], ctx)[0]
            runs.append((time.perf_counter_ns() - a) / 1e6)
        answers.append(res)
        ms.append(statistics.median(runs))
    bs = spec.settings.batch_size
    stack = np.stack(pixels)
    dualsight_chain(stack[:bs], ctx)                                    # warm-up of the batch shape
    batch_ms, batched = [], []
    for s in range(0, len(pixels), bs):
        runs = []
        for _ in range(repeats):
            a = time.perf_counter_ns()
            res = dualsight_chain(stack[s:s + bs], ctx)
            runs.append((time.perf_counter_ns() - a) / 1e6)
        batched.extend(res)
        batch_ms.append(statistics.median(runs) / len(res))
    total_batched_ms = sum(m * len(range(s, min(len(pixels), s + bs))) for m, s in
                           zip(batch_ms, range(0, len(pixels), bs)))
    return {"answers": answers, "ms": ms, "batched_answers": batched, "batch_ms_per_frame": batch_ms,
            "batched_ms_per_frame": total_batched_ms / len(pixels), "context_s": t_ctx, "warmup_s": t_warm}


def check_against_job(spec, answers) -> float:
    """Largest angle (arcsec) between our in-process boresights and the hil_star job's own compute_shard rows
    (the same spec): 0 when the benchmark runs exactly the job's chain; inf when one solved and the other not."""
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.scene.units import angle_between

    ctx = hs.make_context(spec)
    t = hs.compute_shard(spec, np.arange(len(answers), dtype=np.int64), ctx)["hil_star"]
    worst = 0.0
    for (A, _, _), ident, Aj in zip(answers, t.column("identified").to_pylist(), t.column("A_est").to_pylist()):
        if (A is not None) != bool(ident):
            return math.inf
        if A is not None:
            worst = max(worst, float(angle_between(A[2], np.asarray(Aj).reshape(3, 3)[2])) / ARCSEC)
    return worst


# ============================================================================================ cedar
def run_cedar(py: Path, paths, pixels, camera, args) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-peers-") as tmp:
        frames = []
        for i, (p, px) in enumerate(zip(paths, pixels)):
            f = Path(tmp) / f"{i:05d}.npy"
            np.save(f, px, allow_pickle=False)
            frames.append({"path": str(p), "npy": str(f)})
        job = {"frames": frames, "database": args.cedar_database or "default_database",
               "fov_estimate_deg": math.degrees(camera.fov_rad[0]), "fov_max_error_deg": args.fov_max_error,
               "distortion": 0.0, "centroid_kwargs": {}, "solve_kwargs": {}, "warmup": True, "repeats": args.repeats}
        (Path(tmp) / "job.json").write_text(json.dumps(job))
        out = Path(tmp) / "answers.json"
        r = subprocess.run([str(py), str(WORKER), str(Path(tmp) / "job.json"), str(out)], capture_output=True,
                           text=True, env=dict(os.environ, **THREAD_VARS), timeout=3600)
        if r.returncode != 0:
            raise BenchError(f"the cedar-solve worker failed: {_last_line(r.stderr)}")
        return json.loads(out.read_text())


# ============================================================================================ scoring, table
def errors_arcsec(A, A_true):
    """(boresight angle, roll difference) in arcsec of an ICRS -> camera matrix against the truth."""
    from dualsight.scene.pointing import roll_deg
    from dualsight.scene.units import angle_between

    if A is None or A_true is None:
        return None, None
    bore = float(angle_between(A[2], A_true[2])) / ARCSEC
    roll = abs((float(roll_deg(A)) - float(roll_deg(A_true)) + 180.0) % 360.0 - 180.0) * 3600.0
    return bore, roll


def fmt(v, spec="{:.1f}"):
    return "-" if v is None else spec.format(v)


def table(cols, rows) -> str:
    w = [max(len(c), *(len(r[i]) for r in rows)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.rjust(x) for c, x in zip(cols, w)), "  ".join("-" * x for x in w)]
    lines += ["  ".join(v.rjust(x) for v, x in zip(r, w)) for r in rows]
    return "\n".join(lines)


def med(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", default=None, help="folder or glob of frames (default: the 8 ESA tetra3 frames)")
    p.add_argument("--camera", default=None, help="camera TOML (default: examples/cameras/esa_tetra3.toml)")
    p.add_argument("--truth", default=None, help="truth JSON in esa_tetra3/truth.json's format (default: truth.json "
                   "beside the frames, if any)")
    p.add_argument("--rendered", type=int, default=None, metavar="N", help="render N frames and use them instead")
    p.add_argument("--seed", type=int, default=1, help="seed of the rendered frames (default 1)")
    p.add_argument("--render-dir", type=Path, default=None,
                   help="where rendered frames go (default: <cedar venv>/dualsight-frames/rendered-n<N>-s<seed>)")
    p.add_argument("--render-mag-limit", type=float, default=7.0, help="faintest rendered star, V (default 7.0)")
    p.add_argument("--mag-limit", type=float, default=7.0, help="dualsight catalog limit, V (default 7.0, as hil star)")
    p.add_argument("--batch-size", type=int, default=16, help="dualsight frames per batched call (default 16)")
    p.add_argument("--repeats", type=int, default=1, help="timed runs per frame, median kept (default 1)")
    p.add_argument("--cpu", type=int, default=None, help="pin both processes to this core")
    p.add_argument("--cedar-venv", type=Path, default=ROOT / "benchmarks" / ".venv-cedar")
    p.add_argument("--cedar-requirement", default=CEDAR_REQUIREMENT)
    p.add_argument("--cedar-database", default=None, help="cedar-solve database .npz (default: the one it ships)")
    p.add_argument("--fov-max-error", type=float, default=0.5, help="cedar's fov_max_error, deg (default 0.5)")
    p.add_argument("--lake", type=Path, default=None,
                   help="also write both answers into this lake: a hil_star run and a peer_star run")
    p.add_argument("--json", type=Path, default=None, help="write every number of the comparison here")
    args = p.parse_args(argv)
    try:
        return _main(args)
    except BenchError as e:
        print(f"bench_peers: error: {e}", file=sys.stderr)
        return 2
    except Exception as e:                                   # dualsight's InputError and friends: one line
        from dualsight.errors import InputError

        if isinstance(e, InputError):
            print(f"bench_peers: error: {' '.join(str(e).split())}", file=sys.stderr)
            return 2
        raise


def _main(args) -> int:
    if args.cpu is not None:
        os.sched_setaffinity(0, {args.cpu})
    load0 = os.getloadavg()
    py, stamp = ensure_cedar_venv(args.cedar_venv.resolve(), args.cedar_requirement)
    if args.rendered is not None:
        if not 1 <= args.rendered <= 10000:
            raise BenchError("--rendered must be in [1, 10000]")
        out = args.render_dir or args.cedar_venv / "dualsight-frames" / f"rendered-n{args.rendered}-s{args.seed}"
        paths, camera_path, truth_path, noise = render_inputs(args.rendered, args.seed, out.resolve(),
                                                              args.render_mag_limit)
    else:
        paths, camera_path, truth_path, noise = esa_inputs(args)
    spec = dualsight_spec(paths, camera_path, truth_path, args)
    from dualsight.jobs.kinds.hil_star import read_frame

    pixels = [read_frame(e, Camera_of(spec))[0] for e in spec.images]          # decoding: outside the timings
    ds = run_dualsight(spec, pixels, args.repeats)
    agree = check_against_job(spec, ds["answers"])
    cedar = run_cedar(py, paths, pixels, Camera_of(spec), args)
    load1 = os.getloadavg()

    truth = [spec.truth(k).matrix("A") for k in range(len(paths))]
    rows, rec = [], []
    for k, path in enumerate(paths):
        A, n_det, n_id = ds["answers"][k]
        c = cedar["frames"][k]
        Ac = np.asarray(c["A"]).reshape(3, 3) if c.get("A") else None
        eb, er = errors_arcsec(A, truth[k])
        cb, cr = errors_arcsec(Ac, truth[k])
        r = {"frame": path.name, "ds_ms": ds["ms"][k], "cedar_ms": c["time_ms"], "ds_solved": A is not None,
             "cedar_solved": bool(c["solved"]), "ds_bore": eb, "ds_roll": er, "cedar_bore": cb, "cedar_roll": cr,
             "ds_stars": n_id, "cedar_stars": c.get("stars_matched"), "cedar_status": c.get("status"),
             "cedar_detect_ms": c.get("detect_ms"), "cedar_solve_ms": c.get("solve_ms"),
             "cedar_prob": c.get("prob_false_match")}
        rec.append(r)
        name = path.name if len(path.name) <= 34 else path.name[:31] + "..."
        rows.append([name, f"{r['ds_ms']:.1f}", f"{r['cedar_ms']:.1f}", f"{r['ds_ms'] / r['cedar_ms']:.2f}",
                     "yes" if r["ds_solved"] else "NO", fmt(eb), fmt(er), str(n_id),
                     "yes" if r["cedar_solved"] else f"NO ({r['cedar_status']})", fmt(cb), fmt(cr),
                     fmt(r["cedar_stars"], "{}")])
    cols = ["frame", "ds ms", "cedar ms", "ds/cedar", "ds solved", "ds bore\"", "ds roll\"", "ds stars",
            "cedar solved", "cedar bore\"", "cedar roll\"", "cedar stars"]
    print(table(cols, rows))
    m_ds, m_dsb, m_c = med(ds["ms"]), med(ds["batch_ms_per_frame"]), med([r["cedar_ms"] for r in rec])
    n = len(rec)
    print()
    print(f"median ms/frame: dualsight {m_ds:.1f} (one frame per call), {m_dsb:.1f} (batches of "
          f"{spec.settings.batch_size}); cedar-solve {m_c:.1f} (detect {med([r['cedar_detect_ms'] for r in rec]):.1f}"
          f" + solve {med([r['cedar_solve_ms'] for r in rec]):.1f})")
    print(f"ratio of medians dualsight/cedar: {m_ds / m_c:.2f} (single), {m_dsb / m_c:.2f} (batched)")
    print(f"solved: dualsight {sum(r['ds_solved'] for r in rec)}/{n}, cedar-solve {sum(r['cedar_solved'] for r in rec)}"
          f"/{n}; median error vs truth (solved frames) boresight / roll arcsec: dualsight "
          f"{fmt(med([r['ds_bore'] for r in rec]), '{:.2f}')} / {fmt(med([r['ds_roll'] for r in rec]), '{:.1f}')}, "
          f"cedar {fmt(med([r['cedar_bore'] for r in rec]), '{:.2f}')} / {fmt(med([r['cedar_roll'] for r in rec]), '{:.1f}')}")
    from dualsight.version import code_version

    cam = Camera_of(spec)
    conditions = {
        "frames": f"{n} x {cam.width}x{cam.height} px, {math.degrees(cam.fov_rad[0]):.2f} deg horizontal "
                  f"({'rendered, seed ' + str(args.seed) if args.rendered else paths[0].parent})",
        "noise": noise, "truth": str(truth_path) if truth_path else "none",
        "threads": "1 per process (" + ", ".join(f"{k}=1" for k in THREAD_VARS) + ")"
                   + (f", pinned to core {args.cpu}" if args.cpu is not None else ", not pinned"),
        "machine": f"{os.cpu_count()} cores, load average {load0[0]:.2f} at start, {load1[0]:.2f} at end",
        "timing": f"warm (after one untimed frame), median of {args.repeats} run(s) per frame, decoding excluded",
        "dualsight": f"{code_version()}, hil star robust voting, V <= {args.mag_limit}, tolerance 20 arcsec, "
                     f"25 stars vote; context {ds['context_s']:.1f} s, first frame (JIT) {ds['warmup_s']:.1f} s; "
                     f"in-process answers vs hil_star compute_shard: max {agree:.3g} arcsec",
        "cedar-solve": f"{cedar['method_version']}, database {cedar['settings']['database']} (V <= "
                       f"{cedar['settings']['database_properties'].get('star_max_magnitude'):.2f}, fov "
                       f"{cedar['settings']['database_properties'].get('min_fov')}-"
                       f"{cedar['settings']['database_properties'].get('max_fov')} deg), load "
                       f"{cedar['environment']['database_load_ms']:.0f} ms; fov_estimate "
                       f"{cedar['settings']['fov_estimate_deg']:.2f} +- {cedar['settings']['fov_max_error_deg']} deg; "
                       f"venv {stamp.get('venv_create_s')} s + pip {stamp.get('pip_install_s')} s (first use)",
    }
    print("conditions:")
    for k, v in conditions.items():
        print(f"  {k}: {v}")

    answers_doc = dict(cedar, environment=dict(cedar["environment"], bench_conditions=conditions))
    if args.lake is not None:
        _to_lake(args.lake, spec, answers_doc, args.cedar_venv / "dualsight-answers")
    if args.json is not None:
        args.json.write_text(json.dumps({"rows": rec, "conditions": conditions, "medians": {
            "dualsight_ms": m_ds, "dualsight_batched_ms": m_dsb, "cedar_ms": m_c}, "cedar_answers": cedar},
            indent=1))
    return 0


def Camera_of(spec):
    from dualsight.scene.camera import Camera

    return Camera.from_dict(spec.camera, source="spec")


def _to_lake(lake_dir: Path, spec, answers: dict, keep: Path):
    """Both solvers' answers into one lake: dualsight's as a hil_star run (the engine, one worker), the peer's as
    a peer_star run (jobs/kinds/peer_star.py); prints the runs and a query joining them."""
    from dualsight.jobs.kinds.peer_star import import_answers
    from dualsight.jobs.engine.runner import run_job
    from dualsight.warehouse.lake import Lake

    lake = Lake(lake_dir)
    m = run_job("hil_star", spec.to_dict(), n_cases=len(spec.images), lake=lake, workers=1, progress=False,
                label="bench_peers dualsight")
    keep.mkdir(parents=True, exist_ok=True)
    f = keep / f"cedar-{time.strftime('%Y%m%dT%H%M%S')}.json"
    f.write_text(json.dumps(answers, indent=1))
    pm = import_answers(lake, f)
    print(f"lake {lake_dir}: hil_star run {m['run_id']}, peer_star run {pm['run_id']}")
    print(f"join: dualsight sql --lake {lake_dir} \"SELECT h.image, h.identified, p.solved, "
          f"h.boresight_error_rad / (pi()/648000) AS ds_err_arcsec, p.time_ms FROM hil_star h JOIN peer_star p "
          f"USING (path) WHERE h.run = '{m['run_id']}' AND p.run = '{pm['run_id']}' ORDER BY h.case_id\"")


if __name__ == "__main__":
    sys.exit(main())
