"""Benchmark: speed of the star HIL chain on real frames (issue 13, point 4), one command per target.

  frame    ms per frame on ONE core (DUALSIGHT_TI_THREADS = OMP / OPENBLAS / MKL threads = 1, cv2 one thread),
           median over the ESA tetra3 frames (1024 x 768 16-bit), warm (each frame processed once before the
           timed repeats), per stage: decode (read_frame: TIFF decode, stat, ADC shift), background (tile
           statistics + interpolation), filter (matched filter and noise normalisation), labelling
           (foreground components, local maxima, deblending), centroid fit (hot-pixel test, PSF fits: the
           rest of the detector, including the PSF-width pass), observations (back-projection), voting
           (identify, robust method; the numpy and the Taichi engine), attitude (weighted SVD solve); each
           stage's median, and end to end the median (and quartiles) of the frames' sums of those stages.
           Target: <= 5 ms end to end without decoding (for a 1024 x 1024 frame with ~20 stars; the ESA
           frames have ~60 (global) to ~260 (local) detections each).  ``--rendered N`` runs the same on N
           frames rendered as ``bench_peers.py --rendered`` makes them (1024 x 1024 12-bit, here as 16-bit TIFFs,
           20 deg, the noise of examples/star/noisy_sensor.toml) with the stars to ``--render-mag-limit``
           (default 5.5: ~20 stars per frame), solved with the catalog to ``--mag-limit`` (default 6.0); the
           boresight error against the render's truth is printed with it.
  process  the whole ``dualsight hil star ONE.tiff --camera ... --no-lake`` process, median of 5 warm runs
           (one unmeasured run first), plus ``python -X importtime`` (the slowest top-level imports) and a
           cProfile summary of one in-process run.  Target: <= 1.5 s.
  batch    frames/s of ``dualsight hil star DIR --no-lake --workers N`` over the 8 ESA frames repeated to
           ``--images`` images (default 600; symlinks in a temporary folder), decode included, N = 1 and 2;
           steady state = (images(600) - images(64)) / (time(600) - time(64)), i.e. without the fixed cost of
           the process, the workers' start and the report (64 images = 4 batches of 16: both workers start in
           the short run too); also the steady-state CPU time per frame of all the run's processes (children's
           rusage), which a loaded machine does not inflate.  ``--hil-args`` adds options to both runs (e.g. "--detector global
           --no-compare", the throughput settings).  Target: >= 100 frames/s on 2 cores.

``--against COMMIT [--rounds N]`` runs the same command in a worktree of COMMIT too, alternating (this tree first).

Usage:  python benchmarks/bench_hil_speed.py [frame|process|batch|all] [--repeats 5] [--images 600] [--hil-args '...']
        python benchmarks/bench_hil_speed.py batch --workers 2 --against 0fd2b06 --rounds 2
        python benchmarks/bench_hil_speed.py frame --rendered 20 --detectors global     # the issue's frame
Prints the machine's cores and load average (``uptime``) with the numbers.
"""

from __future__ import annotations

import os

for _v in ("DUALSIGHT_TI_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import dataclasses
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CAMERA = ROOT / "examples" / "cameras" / "esa_tetra3.toml"
ESA = Path(os.environ.get("DUALSIGHT_SHARED", ROOT.parent / "shared")) / "data" / "real" / "esa_tetra3"
PY = sys.executable
DUALSIGHT = [PY, "-m", "dualsight"]


def conditions() -> str:
    up = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    return f"cores {os.cpu_count()}, python {sys.version.split()[0]}, {up}"


def frames() -> list[Path]:
    return sorted(ESA.glob("*.tiff"))


# ============================================================================================ frame
class Timers:
    """Wrap module functions to accumulate their CPU time of this process (``time.process_time``: with every
    library on one thread this is the one core's work, and it does not count the time other processes take
    the core away on a loaded machine), exclusive of nested timed calls."""

    clock = staticmethod(time.process_time)

    def __init__(self):
        self.t: dict[str, float] = {}
        self._stack: list[list] = []

    def wrap(self, mod, name, label):
        """Replace ``mod.name`` by a wrapper that times each call as :meth:`stage` ``label``; returns the original."""
        f = getattr(mod, name)

        def w(*a, **k):
            with self.stage(label):
                return f(*a, **k)
        setattr(mod, name, w)
        return f

    @contextmanager
    def stage(self, label):
        t0 = self.clock()
        self._stack.append([0.0])
        try:
            yield
        finally:
            dt = self.clock() - t0
            inner = self._stack.pop()[0]
            self.t[label] = self.t.get(label, 0.0) + dt - inner
            if self._stack:
                self._stack[-1][0] += dt


def bench_frame(repeats: int, extra: tuple[str, ...] = (), detectors=("local", "local-compiled", "global"), paths=None,
                camera=CAMERA, label="ESA 1024 x 768") -> dict:
    import cv2
    import numpy as np

    cv2.setNumThreads(1)
    from dualsight.config import validate
    from dualsight.jobs.kinds import hil_star as hs
    from dualsight.jobs.cli.main import main  # noqa: F401  (the package's normal import state)
    from dualsight.jobs.kinds.hil_common import ImageEntry  # noqa: F401
    from dualsight.kernels import detect_local as dl
    from dualsight.nav import star_solution as ss
    from dualsight.nav.observations import observations
    from dualsight.nav.starid import identify as vote_identify
    from dualsight.scene.camera import Camera

    from dualsight.scene.units import angle_between

    paths = frames() if paths is None else paths
    cam = Camera.from_toml(camera)
    from dualsight.jobs.cli.main import build_parser
    from dualsight.jobs.cli.hil_star_command import star_spec_from_args
    args = build_parser().parse_args(hil_cmd(paths, "--no-compare", *extra, camera=camera)[3:])
    spec = star_spec_from_args(args)                       # the CLI's own spec (robust voting, no comparison)
    ctx = hs.make_context(spec)
    rt = ctx.rt
    settings_global = rt.settings.model_copy(update={"detector": "global"})   # what `--detector global` sets
    sat = float(2 ** rt.camera.bit_depth - 1)
    T = Timers()
    from dualsight.kernels import detect as kd
    timed = [(mod, name, label) for mod, name, label in (
        (dl, "tile_background", "background"), (dl, "interpolate_tiles", "background"), (dl, "matched_filter", "filter"),
        (dl, "find_candidates", "labelling"), (dl, "_measure", "centroid fit"), (hs, "subtract_background", "background"),
        (hs, "background_model", "background"), (kd, "detect_stars", "labelling"), (hs, "detect_stars", "labelling"))]
    originals = [(mod, name, T.wrap(mod, name, label)) for mod, name, label in timed]
    results = {}

    def chain(px, detector, engine):
        """One decoded frame through detection, observations, voting and the attitude (the timed stages)."""
        if detector.startswith("local"):
            cfg = validate(dl.LocalDetectConfig, rt.settings.detect_local, source="spec",
                           section="settings.detect_local")
            if detector == "local-compiled":
                cfg = dataclasses.replace(cfg, fit_engine="taichi")
            det = dl.detect_real(px[None], cfg, saturation_adu=sat)
        else:
            det = hs.detect_frames(px[None], settings_global, rt.detect, residual=False)[2]
        obs = observations(det, 1, cam, max_obs=rt.settings.max_obs)
        ident = vote_identify(obs.vec, obs.valid, ctx.catalog.unit, ctx.pairs.i, ctx.pairs.j, ctx.pairs.angle,
                              rt.voting, cat_vmag=ctx.catalog.vmag, engine=engine)
        w = ss.centroid_weights(det, obs, rt.settings.centroid_floor_px)
        return ss.solve(obs, ident, ctx.catalog.unit, None, weights=w)

    for detector, engine in ((d, e) for d in detectors for e in ("numpy", "taichi")):
        per = {}
        for rep in range(repeats + 1):                     # repeat 0 warms up (kernels, caches)
            for k, p in enumerate(paths):
                T.t.clear()
                w0 = time.perf_counter()
                with T.stage("decode"):
                    px, _ = hs.read_frame(spec.images[k], cam)
                with T.stage("detector other"):
                    if detector.startswith("local"):   # "local": the run's own engine (numpy below 1,024
                        #  images), "local-compiled": fit_engine "taichi" (what a run of >= 1,024 images uses)
                        cfg = validate(dl.LocalDetectConfig, rt.settings.detect_local, source="spec",
                                       section="settings.detect_local")
                        if detector == "local-compiled":
                            cfg = dataclasses.replace(cfg, fit_engine="taichi")
                        det = dl.detect_real(px[None], cfg, saturation_adu=sat)
                    else:     # the HIL's global path: smooth background, one threshold, Taichi labelling
                        det = hs.detect_frames(px[None], settings_global, rt.detect, residual=False)[2]
                with T.stage("observations"):
                    obs = observations(det, 1, cam, max_obs=rt.settings.max_obs)
                with T.stage("voting"):
                    ident = vote_identify(obs.vec, obs.valid, ctx.catalog.unit, ctx.pairs.i, ctx.pairs.j,
                                          ctx.pairs.angle, rt.voting, cat_vmag=ctx.catalog.vmag, engine=engine)
                with T.stage("attitude"):
                    w = ss.centroid_weights(det, obs, rt.settings.centroid_floor_px)
                    sol = ss.solve(obs, ident, ctx.catalog.unit, None, weights=w)
                wall = time.perf_counter() - w0
                if rep:
                    per.setdefault("wall", []).append(wall)
                    for s, v in T.t.items():
                        per.setdefault(s, []).append(v)
                    per.setdefault("total", []).append(sum(v for s, v in T.t.items() if s != "decode"))
                    per.setdefault("n_det", []).append(int(det.counts[0]))
                    per.setdefault("solved", []).append(bool(sol.ok[0]))
                    A_true = spec.truth(k).matrix("A")
                    if A_true is not None and sol.ok[0]:
                        err = float(angle_between(sol.A_est[0, 2], A_true[2]))
                        per.setdefault("err_arcsec", []).append(err * 180 / np.pi * 3600)
        # the same chain without the stage timers (their wrappers cost ~5 % of a frame): the end-to-end figure
        decoded = [hs.read_frame(spec.images[k], cam)[0] for k in range(len(paths))]
        for mod, name, f in originals:
            setattr(mod, name, f)
        try:
            for rep in range(repeats + 1):
                for px in decoded:
                    c0 = time.process_time()
                    chain(px, detector, engine)
                    if rep:
                        per.setdefault("bare", []).append(time.process_time() - c0)
        finally:
            for mod, name, label in timed:
                T.wrap(mod, name, label)
        results[(detector, engine)] = per
    order = ["decode", "background", "filter", "labelling", "centroid fit", "detector other", "observations",
             "voting", "attitude"]
    print(f"frame: CPU ms per frame, one core, median over {len(paths)} frames x {repeats} repeats "
          f"({label}; median detections: "
          + ", ".join(f"{d} {int(np.median(results[(d, 'numpy')]['n_det']))}" for d in detectors)
          + (f"; hil star options {' '.join(extra)}" if extra else "") + ")")
    from dualsight.jobs.kinds.hil_star_spec import COMPILED_DETECT_MIN_IMAGES
    run_engine = validate(dl.LocalDetectConfig, rt.settings.detect_local, source="spec",
                          section="settings.detect_local").engine
    print(f"  (detector 'local': the fit_engine `hil star` resolves for a run of these {len(paths)} images, "
          f"{run_engine}; 'local-compiled': fit_engine taichi, what a default run of >= {COMPILED_DETECT_MIN_IMAGES:,} "
          "images gets: the per-frame cost of a big batch)")
    for (detector, engine), per in results.items():
        med = {s: 1e3 * statistics.median(per[s]) for s in order if s in per}
        total = 1e3 * statistics.median(per["total"])       # the median frame's sum (not the sum of medians)
        q1, q3 = (1e3 * q for q in statistics.quantiles(per["total"], n=4)[::2])
        # the engine `hil star` itself picks for a short run: "taichi" when the detector has started Taichi (the
        # global one; the local one with fit_engine "taichi", its default since 822a98b), else "numpy"
        # (jobs/kinds/hil_star.py voting_engine)
        # (a short run resolves the local detector's engine to numpy, hil_star_spec.resolve_fit_engine)
        mark = " (hil star's own choice)" if (engine == "taichi") == (detector != "local") else ""
        print(f"  detector {detector}, voting engine {engine}{mark}: "
              + ", ".join(f"{s} {v:.2f}" for s, v in med.items())
              + f" | end to end without decode {total:.2f} ms (quartiles {q1:.2f}-{q3:.2f}),"
              f" with {total + med['decode']:.2f} ms"
              f" (wall with decode {1e3 * statistics.median(per['wall']):.2f} ms;"
              f" without the stage timers {1e3 * statistics.median(per['bare']):.2f} ms without decode);"
              f" solved {sum(per['solved'])}/{len(per['solved'])}"
              + (f", median boresight error {statistics.median(per['err_arcsec']):.1f} arcsec vs truth"
                 if per.get("err_arcsec") else ""))
    return results


# ============================================================================================ process
def hil_cmd(images, *extra, camera=CAMERA) -> list[str]:
    return [*DUALSIGHT, "hil", "star", *map(str, images), "--camera", str(camera), "--no-lake", "--no-progress",
            *extra]


def rendered_frames(n: int, mag_limit: float, seed: int = 1):
    """(paths, camera file, truth file) of ``n`` frames rendered by ``bench_peers.render_inputs`` (cached in the system's
    temporary folder, keyed by n, seed and depth)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_peers

    out = Path(tempfile.gettempdir()) / f"dualsight-bench-frames-n{n}-s{seed}-v{mag_limit:g}"
    paths, camera, truth, noise = bench_peers.render_inputs(n, seed, out, mag_limit)
    import cv2

    import json

    tiffs = []                          # uncompressed 16-bit TIFFs, as the ESA frames (bench_peers writes PNGs)
    for p in paths:
        t = p.with_suffix(".tiff")
        if not t.exists() and not cv2.imwrite(str(t), cv2.imread(str(p), cv2.IMREAD_UNCHANGED),
                                               [cv2.IMWRITE_TIFF_COMPRESSION, 1]):
            raise SystemExit(f"cannot write {t}")
        tiffs.append(t)
    truth_t = out / "truth_tiff.json"   # the same truth, keyed by the TIFFs' names
    truth_t.write_text(json.dumps({str(Path(k).with_suffix(".tiff")): v
                                   for k, v in json.loads(truth.read_text()).items()}))
    print(f"rendered frames: {out} (16-bit TIFF; {noise})")
    return tiffs, camera, truth_t


def bench_process(repeats: int) -> None:
    one = frames()[0]
    env = dict(os.environ)
    for v in ("DUALSIGHT_TI_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(v, None)                         # the process as a user runs it
    subprocess.run(hil_cmd([one]), capture_output=True, env=env, check=True)   # warm: caches, kernel cache
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(hil_cmd([one]), capture_output=True, env=env, check=True)
        ts.append(time.perf_counter() - t0)
    print(f"process: `dualsight hil star ONE.tiff --no-lake` median of {repeats} warm runs "
          f"{statistics.median(ts):.2f} s (min {min(ts):.2f}, max {max(ts):.2f})")
    tl = []
    for _ in range(repeats):                     # the same with its rows written: a fresh lake each time
        with tempfile.TemporaryDirectory(prefix="bench-hil-lake-") as lake:
            cmd = [c for c in hil_cmd([one]) if c != "--no-lake"] + ["--lake", lake]
            t0 = time.perf_counter()
            subprocess.run(cmd, capture_output=True, env=env, check=True)
            tl.append(time.perf_counter() - t0)
    print(f"process: `dualsight hil star ONE.tiff --lake NEW` median of {repeats} warm runs "
          f"{statistics.median(tl):.2f} s (min {min(tl):.2f}, max {max(tl):.2f})")
    r = subprocess.run([PY, "-X", "importtime", "-m", "dualsight", *hil_cmd([one])[3:]], capture_output=True,
                       text=True, env=env)
    rows = []
    for line in r.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            parts = line[len("import time:"):].split("|")
            try:
                cum = int(parts[1])
            except ValueError:
                continue
            name = parts[2]
            if len(name) - len(name.lstrip()) <= 3:          # top-level imports only
                rows.append((cum, name.strip()))
    rows.sort(reverse=True)
    print("  -X importtime, top-level imports by cumulative time: "
          + ", ".join(f"{n} {c / 1e3:.0f} ms" for c, n in rows[:10]))
    prof = subprocess.run([PY, "-c", (
        "import cProfile, pstats, sys, io\n"
        "from dualsight.jobs.cli.main import main\n"
        "pr = cProfile.Profile(); pr.enable()\n"
        f"main({hil_cmd([one])[3:]!r})\n"
        "pr.disable(); s = io.StringIO(); pstats.Stats(pr, stream=s).sort_stats('cumulative').print_stats(45)\n"
        "sys.stderr.write(s.getvalue())\n")], capture_output=True, text=True, env=env)
    print("  cProfile (in-process run after imports; cumulative):")
    keep = [ln for ln in prof.stderr.splitlines() if ln.strip() and ("{" in ln or "/" in ln or "ncalls" in ln)]
    for ln in keep[:46]:
        print("   ", ln[:150])


# ============================================================================================ batch
SMALL_IMAGES = 64          # the short run of the batch bench: 4 batches of 16, so 2 workers both start in it


def _children_cpu() -> float:
    """User + system CPU seconds of this process's finished children (and theirs): the work of a run, whatever
    else the machine runs."""
    import resource

    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def bench_batch(n_images: int, workers_list=(1, 2), extra: tuple[str, ...] = ()) -> None:
    src = frames()
    env = dict(os.environ)
    tmp = Path(tempfile.mkdtemp(prefix="bench_hil_"))
    try:
        small, big = tmp / "small", tmp / "big"
        small.mkdir()
        big.mkdir()
        n_small = min(SMALL_IMAGES, n_images // 2)       # every worker busy in both runs: the difference
        for i in range(n_images):                        # is frames, not a worker's start
            p = src[i % len(src)]
            (big / f"{i:04d}_{p.name}").symlink_to(p)
            if i < n_small:
                (small / f"{i:04d}_{p.name}").symlink_to(p)
        for workers in workers_list:
            env_w = dict(env)
            env_w["DUALSIGHT_TI_THREADS"] = "1"
            t, cpu = {}, {}
            for name, folder, n in (("small", small, n_small), ("big", big, n_images)):
                subprocess.run(hil_cmd([folder], "--workers", str(workers), *extra), capture_output=True, env=env_w)
                c0 = _children_cpu()
                t0 = time.perf_counter()
                r = subprocess.run(hil_cmd([folder], "--workers", str(workers), *extra), capture_output=True,
                                   env=env_w, text=True)
                t[name] = time.perf_counter() - t0
                cpu[name] = _children_cpu() - c0
                if r.returncode:
                    print(f"batch: --workers {workers}, {n} images FAILED: {r.stderr.strip()[-600:]}")
                    t[name] = float("nan")
            rate = (n_images - n_small) / max(t["big"] - t["small"], 1e-9)
            cpu_ms = 1e3 * (cpu["big"] - cpu["small"]) / (n_images - n_small)
            print(f"batch: --workers {workers} {' '.join(extra)}: {n_images} images {t['big']:.2f} s ({n_images / t['big']:.1f} "
                  f"frames/s whole process), {n_small} images {t['small']:.2f} s; steady state {rate:.1f} frames/s; "
                  f"CPU {cpu_ms:.1f} ms per frame (steady state, all the run's processes: {1e3 / cpu_ms:.0f} frames/s "
                  f"per core of work, whatever else the machine runs)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def against(a, argv: list[str]) -> None:
    """Run this benchmark with ``argv`` (its own options but ``--against``/``--rounds``) in this tree and in a
    worktree of ``a.against``, alternating ``a.rounds`` times (each run a fresh process with the tree's package
    first on PYTHONPATH, started in the tree: ``python -m dualsight`` is that tree's too), so a ratio is measured
    under the same load; prints each run's output.  Each tree runs its own copy of this script (its camera files
    and the rendered frames' camera file in its own temporary folder: an older tree may not read a newer camera
    file), on the same ESA frames."""
    tmp = Path(tempfile.mkdtemp(prefix="bench-hil-old-"))
    old = tmp / "tree"
    (tmp / "tmp").mkdir()
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(old), a.against], check=True,
                   capture_output=True)
    name = Path(__file__).name
    try:
        for i in range(a.rounds):
            for tag, tree in (("this", ROOT), (a.against[:7], old)):
                script = tree / "benchmarks" / name
                env = dict(os.environ, PYTHONPATH=str(tree), DUALSIGHT_SHARED=str(ESA.parents[2]),
                           **({"TMPDIR": str(tmp / "tmp")} if tree == old else {}))
                r = subprocess.run([PY, str(script if script.exists() else Path(__file__).resolve()), *argv],
                                   capture_output=True, text=True, env=env, cwd=str(tree))
                print(f"=== round {i + 1}, {tag} ({tree})")
                print(r.stdout.strip() + (f"\nFAILED: {r.stderr.strip()[-800:]}" if r.returncode else ""))
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(old)], capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", nargs="?", default="all", choices=["frame", "process", "batch", "all"])
    ap.add_argument("--repeats", type=int, default=5, help="frame: timed passes over the frames (after one warm-up pass); "
                    "process: warm runs (default 5)")
    ap.add_argument("--images", type=int, default=600)
    ap.add_argument("--hil-args", default="", help="extra `hil star` options for the frame and batch benches, e.g. "
                    "'--max-stars 12' (one string)")
    ap.add_argument("--detectors", nargs="+", default=["local", "local-compiled", "global"],
                    choices=["local", "local-compiled", "global"])
    ap.add_argument("--rendered", type=int, default=None, metavar="N",
                    help="frame: N rendered 1024 x 1024 frames instead of the ESA frames (1..1000)")
    ap.add_argument("--render-mag-limit", type=float, default=5.5, help="faintest rendered star, V (default 5.5)")
    ap.add_argument("--mag-limit", type=float, default=6.0, help="catalog of the rendered frames' solve, V (default 6.0)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="batch: worker counts (default 1 2)")
    ap.add_argument("--against", default=None, metavar="COMMIT",
                    help="also run in a worktree of COMMIT, alternating --rounds times (ratios under the same load)")
    ap.add_argument("--rounds", type=int, default=2, help="alternations with --against (default 2)")
    a = ap.parse_args()
    if a.rendered is not None and not 1 <= a.rendered <= 1000:
        ap.error("--rendered must be in [1, 1000]")
    if not 1 <= a.rounds <= 20 or not all(1 <= w <= 64 for w in a.workers):
        ap.error("--rounds in [1, 20], --workers in [1, 64]")
    if a.against and subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet",
                                     a.against + "^{commit}"], capture_output=True).returncode != 0:
        ap.error(f"--against {a.against!r}: not a commit of {ROOT} (leave it out to measure this tree alone)")
    if a.against:
        argv, skip = [], False
        for x in sys.argv[1:]:
            if skip:
                skip = False
            elif x in ("--against", "--rounds"):
                skip = True
            elif not x.startswith(("--against=", "--rounds=")):
                argv.append(x)
        against(a, argv)
        return
    print(conditions())
    if a.what in ("frame", "all"):
        if a.rendered:
            paths, camera, truth = rendered_frames(a.rendered, a.render_mag_limit)
            bench_frame(max(1, a.repeats), ("--mag-limit", str(a.mag_limit), "--truth", str(truth),
                                            *a.hil_args.split()),
                        tuple(a.detectors), paths=paths, camera=camera,
                        label=f"rendered 1024 x 1024, stars to V {a.render_mag_limit:g}, catalog V {a.mag_limit:g}")
        else:
            bench_frame(max(1, a.repeats), tuple(a.hil_args.split()), tuple(a.detectors))
    if a.what in ("process", "all"):
        bench_process(a.repeats)
    if a.what in ("batch", "all"):
        bench_batch(a.images, workers_list=tuple(a.workers), extra=tuple(a.hil_args.split()))
    print(conditions())


if __name__ == "__main__":
    main()
