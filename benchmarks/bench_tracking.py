"""Tracking vs lost-in-space per frame, on the same frames of one sequence (issue 22, point 6's speed target).

    DUALSIGHT_TI_THREADS=1 taskset -c 0 python benchmarks/bench_tracking.py [--frames 300] [--rate-deg-s 1]
        [--fps 10] [--sigma-px 0.1] [--false 2] [--seed 1]

The paper preset's star camera (1024 x 768, 17 mm) and catalog (Hipparcos to V 5.5, pair catalog and voting index
from the cache, as ``dualsight star run`` loads them).  The sequence turns at a constant rate about a random axis
(``scene/attitude_trajectory.constant_rate``); each frame's detections are the catalog stars in the image
(camera model), brightest first, with Gaussian centroid noise and ``--false`` false stars at random pixels: no
rendering, so only the two algorithms are timed, on the same detections.

* lost-in-space, every frame: back-projection, robust geometric voting (``nav/star_solution.identify``, Taichi
  engine, one frame per call as a flight tracker sees them) and the weighted SVD attitude;
* tracking, every frame after a fix: propagate with the rate from the last two fixes of either mode
  (``nav/angular_rate.rate_between``; zero with the config's rate sigma before there are two), predict, match, solve, verify
  (``nav/tracking``); lost-in-space answers frame 0 and the frame after a lost lock.  The tracking times are those
  of the frames that followed a fix (the ones tracking ran on).

Then the tracker as the product runs it (``nav/sequence.run_sequence``) on the same detections, with the attitude
filter (``nav/attitude_filter.py``, the default; it runs after either mode) and the smear weights of
``examples/star/track.toml`` (``nav/smear_weights.py``, exposure = the frame interval), and without either: the whole tracker's median
time per tracked frame, its predict + match + solve + verify part (the streaks from the filter's rate and the fit
with each star's 2 x 2 centroid covariance included: what tracking does in place of lost-in-space's identify +
solve + verify) and the filter's part (it fuses either mode's answer, and runs after lost-in-space too).

Prints per-frame median and mean wall times of each, their CPU time (``time.process_time``: what the machine's
other processes do not inflate; the mean, as the clock may tick coarsely), the load average (the first 5 frames of each are warm-up, not counted), the ratio,
the availability of each, the identities' agreement where both answer, and the attitude errors against the truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from pathlib import Path

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
ROOT = Path(__file__).resolve().parents[1]

import numpy as np  # noqa: E402

from dualsight.nav.tracking_config import TrackingConfig
from dualsight.jobs.kinds import star, star_track  # noqa: E402
from dualsight.nav.angular_rate import rate_between  # noqa: E402
from dualsight.nav.attitude import solve_identified  # noqa: E402
from dualsight.nav.errors import axis_errors  # noqa: E402
from dualsight.nav.observations import Observations  # noqa: E402
from dualsight.nav.sequence import TRACKING, run_sequence  # noqa: E402
from dualsight.nav.star_solution import identify  # noqa: E402
from dualsight.nav.tracking import predict, propagate, track  # noqa: E402
from dualsight.nav.voting_config import VotingConfig  # noqa: E402
from dualsight.scene.attitude import euler123_to_dcm, random_euler123  # noqa: E402
from dualsight.scene.attitude_trajectory import constant_rate  # noqa: E402
from dualsight.scene.units import ARCSEC  # noqa: E402


def frames(rng, cat, camera, A, sigma_px, n_false):
    """Per frame: (xy (D, 2) brightest first, truth catalog row or -1)."""
    out = []
    for Ak in A:
        px, front = camera.project(cat.unit @ Ak.T)
        inn = np.flatnonzero(front & camera.in_image(np.nan_to_num(px, nan=-1.0)))   # catalog = brightness order
        xy = px[inn] + rng.normal(scale=sigma_px, size=(inn.size, 2))
        fx = rng.uniform((0, 0), (camera.width, camera.height), (n_false, 2))
        pos = rng.integers(0, inn.size + 1, n_false)
        out.append((np.insert(xy, pos, fx, axis=0), np.insert(inn, pos, -1)))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--rate-deg-s", type=float, default=1.0)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--sigma-px", type=float, default=0.1)
    ap.add_argument("--false", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    spec, _ = star.resolve("paper", None)
    ctx = star.make_context(spec)
    cam, cat = spec.camera, ctx.catalog
    rng = np.random.default_rng([args.seed, 0])
    dt = 1.0 / args.fps
    t = np.arange(args.frames) * dt
    w = rng.normal(size=3)
    w *= math.radians(args.rate_deg_s) / np.linalg.norm(w)
    A_true, _ = constant_rate(t, euler123_to_dcm(random_euler123(rng, 1))[0], w)
    seq = frames(rng, cat, cam, A_true, args.sigma_px, args.false)
    voting = VotingConfig.robust(20 * ARCSEC)
    cfg = TrackingConfig(centroid_sigma_px=max(args.sigma_px, 0.05))
    s_rad = max(args.sigma_px, 0.05) / cam.fx

    def lis(xy):
        vec = cam.backproject(xy)[None]
        obs = Observations(vec, np.ones(vec.shape[:2], bool), xy[None, :, 0], xy[None, :, 1])
        ident = identify(obs, cat.unit, ctx.index, voting, cat_vmag=cat.vmag)
        A, ok, P = solve_identified(obs.vec, ident.ids, ident.accepted, cat.unit,
                                    np.full(vec.shape[:2], s_rad ** -2), return_cov=True)
        return np.where(ident.accepted[0], ident.ids[0], -1), A[0], P[0], bool(ok[0])

    lis(seq[0][0])                                                    # compile the Taichi kernels
    t_lis, t_trk, lis_rows, lis_err, lis_ok = [], [], [], [], 0
    c_lis, c_trk = [], []                     # CPU time of this process (robust to other processes on the cores)
    for k, (xy, truth) in enumerate(seq):
        t0, c0 = time.perf_counter(), time.process_time()
        rows, A, P, ok = lis(xy)
        t_lis.append(time.perf_counter() - t0)
        c_lis.append(time.process_time() - c0)
        lis_rows.append(rows)
        lis_ok += ok
        if ok:
            lis_err.append(axis_errors(A[None], A_true[k][None], frame="camera")[0])
    agree = disagree = locked = n_lis_fallback = 0
    trk_err = []
    A_prev = P_prev = None                     # the last fix of either mode, and its frame
    k_prev = -1
    omega, C_om = np.zeros(3), np.eye(3) * cfg.rate_sigma_rad_s ** 2
    for k, (xy, truth) in enumerate(seq):
        t0, c0 = time.perf_counter(), time.process_time()
        if A_prev is None or k - k_prev > 1:                          # (re-)acquire: lost-in-space
            rows, A, P, res_ok = lis(xy)
            n_lis_fallback += 1
        else:
            Ap, Pp = propagate(A_prev, P_prev, omega, C_om, dt)
            res = track(predict(Ap, Pp, cat.unit, cam, cfg), xy, None, cat.unit, cam, cfg)
            res_ok, rows, A, P = res.locked, res.det_row, res.A, res.cov
        if res_ok and A_prev is not None:                             # rate from the last two fixes, any mode
            omega, C_om = rate_between(A_prev, A, (k - k_prev) * dt, P_prev, P)
        dt_k, dc_k = time.perf_counter() - t0, time.process_time() - c0
        if A_prev is not None and k - k_prev == 1:
            t_trk.append(dt_k)
            c_trk.append(dc_k)
        if res_ok:
            locked += 1
            both = (rows >= 0) & (lis_rows[k] >= 0)
            agree += int(np.sum(rows[both] == lis_rows[k][both]))
            disagree += int(np.sum(rows[both] != lis_rows[k][both]))
            trk_err.append(axis_errors(A[None], A_true[k][None], frame="camera")[0])
            A_prev, P_prev, k_prev = A, P, k
    tl, tt = np.array(t_lis[5:]) * 1e3, np.array(t_trk[5:]) * 1e3
    n_det = np.mean([len(s[0]) for s in seq])
    print(f"conditions: {args.frames} frames at {args.fps:g} fps, rate {args.rate_deg_s:g} deg/s, centroid noise "
          f"{args.sigma_px:g} px, {args.false} false stars/frame, {n_det:.1f} detections/frame (V 5.5, paper camera), "
          f"TI threads {os.environ.get('DUALSIGHT_TI_THREADS', 'default')}, cpu affinity "
          f"{len(os.sched_getaffinity(0))} core(s)")
    print(f"lost-in-space ms/frame: median {np.median(tl):.3f}, mean {tl.mean():.3f}; answered {lis_ok}/{len(seq)}")
    print(f"tracking      ms/frame: median {np.median(tt):.3f}, mean {tt.mean():.3f}; locked {locked}/{len(seq)} "
          f"(frames run by lost-in-space: {n_lis_fallback})")
    print(f"speed-up (median): {np.median(tl) / np.median(tt):.1f}x")
    cl, ct = np.array(c_lis[5:]) * 1e3, np.array(c_trk[5:]) * 1e3
    print(f"CPU time of this process (process_time, its clock tick {time.get_clock_info('process_time').resolution:g} s"
          f"): lost-in-space median {np.median(cl):.3f} ms, mean {cl.mean():.3f}; tracking median {np.median(ct):.3f} "
          f"ms, mean {ct.mean():.3f}; speed-up (mean) {cl.mean() / ct.mean():.1f}x")
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")
    print(f"identities where both answer: {agree} equal, {disagree} different")
    for name, e in (("lost-in-space", lis_err), ("tracking", trk_err)):
        e = np.array(e) / ARCSEC
        print(f"{name} error RMS arcsec (x, y, roll): {np.sqrt(np.mean(e ** 2, axis=0)).round(2).tolist()}")
    # the tracker as the product runs it (nav/sequence.run_sequence) on the same detections: with the attitude
    # filter (the default) and without; per tracked frame the whole time and the filter's share
    xy_all = np.concatenate([s_[0] for s_ in seq])
    off = np.concatenate([[0], np.cumsum([len(s_[0]) for s_ in seq])])
    # "on": examples/star/track.toml's [tracking] table (the filter, the streak weights, the edge cut), from the file
    track_toml = ROOT / "examples" / "star" / "track.toml"
    on_cfg = dataclasses.replace(star_track.spec_from_dict(star_track.resolve_spec(None, track_toml)[0]).tracking,
                                 centroid_sigma_px=cfg.centroid_sigma_px)
    for on in (True, False):
        c = on_cfg if on else TrackingConfig(centroid_sigma_px=cfg.centroid_sigma_px, attitude_filter=False,
                                             smear_sigma_per_px=0.0, smear_cross_per_px=0.0)
        r = run_sequence(t, xy_all, None, off, cam, cat.unit, ctx.index, voting, c, cat_vmag=cat.vmag,
                         exposure_s=dt)
        trk = np.flatnonzero(r.mode == TRACKING)[5:]
        tot = r.t_total_ns[trk] / 1e6
        core = (r.t_predict_ns[trk] + r.t_track_ns[trk]) / 1e6
        filt = r.t_filter_ns[trk] / 1e6 if on else np.zeros(1)
        print(f"run_sequence, attitude filter and smear weights {'on ' if on else 'off'}: tracked frames {len(trk) + 5}/{len(seq)}; "
              f"ms/frame median: whole tracker {np.median(tot):.3f} (lost-in-space / it: "
              f"{np.median(tl) / np.median(tot):.1f}x), predict + match + solve + verify {np.median(core):.3f} "
              f"({np.median(tl) / np.median(core):.1f}x), filter {np.median(filt):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
