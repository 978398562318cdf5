"""Geometric-voting speed (``nav.starid.identify``): ms per case for the paper and robust presets.

Run by hand (never a timed test):

    .venv/bin/python benchmarks/bench_voting.py                    # simulated batch + V 7.0 frames
    .venv/bin/python benchmarks/bench_voting.py --ref /tmp/starid_old.py   # side by side, results compared

Workloads:

* ``sim``: one batch of ``--cases`` (256) simulated cases of the star preset "paper" (the reference's
  camera, V 5.5 catalog: 2867 stars / 138k pairs, ~11 detections per case), voting configs of the preset
  (paper, and robust as ``compare_robust`` runs it).
* ``v7``: ``--frames`` (32) synthetic frames for the HIL configuration: V 7.0 catalog (15.6k stars / 2.0M
  pairs within 14 deg), an 11.4 x 8.4 deg camera of 40.3 arcsec pixels, the stars of V <= 7.3 in view,
  brightest first, 5 arcsec noise, 1-3 stars dropped and 0-3 false stars; 25 stars vote, tolerance
  20 arcsec, ``max_vote_cells`` 4M (as ``jobs.hil_star`` sets them).

For each, ``cold`` is the first call on fresh copies of the pair arrays (it includes building what
is derived from the catalog once, :class:`dualsight.nav.starid.VotingIndex`) and ``warm`` the best
of ``--repeats`` later calls (the machine may be shared: take the best of a few runs).  With ``--ref``
another implementation of the module (a file, e.g. ``git show 89b6355:nav/starid.py > /tmp/old.py``)
runs on the same inputs, every output array is compared for bit equality, and the warm speed-up
is printed.

Measured (2-core Xeon VM, numpy 2.4, one process), warm ms per case (per frame for v7), before
(``nav/starid.py`` as of commit 89b6355) -> after, ranges over runs on a noisy VM:

========  =======  ===========  ===========  =========================
workload  config   before       after        speed-up within one run
========  =======  ===========  ===========  =========================
sim       paper    0.18 - 0.26  0.11 - 0.14  1.7x
sim       robust   0.42 - 0.60  0.24 - 0.30  2.0 - 2.2x
v7        paper    19 - 24      5.7 - 6.8    3.4x
v7        robust   30 - 38      7.5 - 9.6    3.8 - 3.9x
========  =======  ===========  ===========  =========================

Cold (first call on a catalog): v7 robust 16-21 ms per frame including the catalog index (~0.4 s
once), where before every call paid 0.3-0.5 s for the previous-occurrence table.

The split of ``nav/starid.py`` into one module per stage (votes, candidates, verify, attitude_check)
changed no arithmetic of the voting round: against the single file before it, on the same inputs
(256 sim cases, 64 v7 frames; best of 7 interleaved rounds on a loaded VM), warm time within
0.95-1.11x, every output bit-identical.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time

import numpy as np

from dualsight.scene.units import ARCSEC, DEG

FIELDS = ("ids", "accepted", "T", "vote_ids", "votes", "verify_votes", "rejected", "n_attitude_matches")


def load_impl(path):
    """The module at ``path`` as a sibling of ``dualsight.nav.starid`` (its relative imports work)."""
    if path is None:
        from dualsight.nav import starid
        return starid
    spec = importlib.util.spec_from_file_location("dualsight.nav._bench_voting_ref", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod                             # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def sim_workload(cases):
    from dualsight.jobs import star

    spec, _ = star.resolve_spec("paper", None)
    spec = star.spec_from_dict(spec)
    ctx = star.make_context(spec)
    out = star.compute_batch(spec, ctx, np.arange(cases))
    return dict(obs=out["obs"].vec, valid=out["obs"].valid, cat=ctx.catalog.unit, pairs=ctx.pairs,
                configs={"paper": spec.voting, "robust": spec.robust})


def v7_frames(cat, frames, seed=5):
    """Synthetic frames of the V 7.0 catalog: brightest first, noise, drops and false stars."""
    from dualsight.scene.attitude import quat_to_dcm, random_quaternions
    from dualsight.scene.camera import Camera

    cam = Camera.pinhole(1024, 756, 4.65e-6, 4.65e-6 / (40.3 * ARCSEC))
    rng = np.random.default_rng(seed)
    A = quat_to_dcm(random_quaternions(rng, frames))
    S = 100
    obs = np.full((frames, S, 3), np.nan)
    valid = np.zeros((frames, S), bool)
    bright = np.nonzero(cat.vmag <= 7.3)[0]
    for b in range(frames):                                  # input generation, not timed
        v = cat.unit[bright] @ A[b].T
        px, front = cam.project(v)
        inn = np.nonzero(front & cam.in_image(px))[0]        # catalog rows are ascending in V
        drop = rng.choice(len(inn), size=min(len(inn), rng.integers(1, 4)), replace=False)
        inn = np.delete(inn, drop)
        tv = v[inn] + rng.normal(scale=5 * ARCSEC, size=(len(inn), 3))
        tv /= np.linalg.norm(tv, axis=1, keepdims=True)
        nf = rng.integers(0, 4)
        fv = cam.backproject(np.stack([rng.uniform(0, cam.width, nf), rng.uniform(0, cam.height, nf)], -1))
        allv = np.concatenate([tv, fv])
        rank = np.concatenate([np.arange(len(tv)), rng.uniform(0, len(tv), nf)])  # false stars anywhere
        allv = allv[np.argsort(rank, kind="stable")][:S]
        obs[b, :len(allv)], valid[b, :len(allv)] = allv, True
    return obs, valid


def v7_workload(frames):
    from dualsight.catalogs.pairs import load_pair_catalog
    from dualsight.catalogs.stars import StarCatalogConfig, load_star_catalog
    from dualsight.nav.starid import VotingConfig

    cat = load_star_catalog(StarCatalogConfig(mag_limit=7.0))
    pairs = load_pair_catalog(cat, 14 * DEG)
    obs, valid = v7_frames(cat, frames)
    common = dict(max_stars=25, max_vote_cells=4_000_000)
    tol = 20 * ARCSEC
    return dict(obs=obs, valid=valid, cat=cat.unit, pairs=pairs,
                configs={"paper": VotingConfig.paper(tol, **common), "robust": VotingConfig.robust(tol, **common)})


def fresh_pairs(pairs):
    """Copies of the pair arrays (new objects: any per-catalog cache starts cold)."""
    return pairs.i.copy(), pairs.j.copy(), pairs.angle.copy()


def run(mod, w, name, cfg, repeats):
    pi, pj, pa = fresh_pairs(w["pairs"])
    B = w["obs"].shape[0]
    t0 = time.perf_counter()
    res = mod.identify(w["obs"], w["valid"], w["cat"], pi, pj, pa, cfg)
    cold = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        mod.identify(w["obs"], w["valid"], w["cat"], pi, pj, pa, cfg)
        warm.append(time.perf_counter() - t0)
    return res, cold / B * 1e3, min(warm) / B * 1e3


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", type=int, default=256)
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--ref", default=None, help="another starid.py to time and compare against")
    ap.add_argument("--only", choices=("sim", "v7"), default=None)
    args = ap.parse_args()
    impls = {"current": load_impl(None)}
    if args.ref:
        impls["ref"] = load_impl(args.ref)
    loads = {"sim": lambda: sim_workload(args.cases), "v7": lambda: v7_workload(args.frames)}
    print(f"{'workload':8s} {'config':7s} {'impl':8s} {'cold ms/case':>13s} {'warm ms/case':>13s}")
    for wname, load in loads.items():
        if args.only and wname != args.only:
            continue
        w = load()
        for cname, cfg in w["configs"].items():
            outs, times = {}, {}
            for iname, mod in impls.items():
                res, cold, warm = run(mod, w, cname, cfg, args.repeats)
                outs[iname], times[iname] = res, warm
                print(f"{wname:8s} {cname:7s} {iname:8s} {cold:13.3f} {warm:13.3f}", flush=True)
            if "ref" in outs:
                same = all(np.array_equal(getattr(outs["ref"], f), getattr(outs["current"], f)) for f in FIELDS)
                n_ok = int((outs["current"].T > 0).sum())
                print(f"{'':8s} {cname:7s} identical: {same}  speed-up (warm) x{times['ref'] / times['current']:.1f}"
                      f"  (confident cases {n_ok}/{w['obs'].shape[0]})")
                if not same:
                    raise SystemExit("results differ")


if __name__ == "__main__":
    main()
