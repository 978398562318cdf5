"""Speed of the rendezvous job kind per approach and per frame (issue 23, point 5), by stage, in one process.

    python benchmarks/bench_rendezvous.py [--preset far|close] [--cases 20] [--seed 1]

Builds the kind's context once (catalogs and voting index, or the proximity renderer's mesh and area table; not
timed), then computes ``--cases`` approaches with ``jobs/kinds/rendezvous.compute_case`` and prints the wall time per
approach and per frame, split into drawing + truth + geometry, rendering + detection + identification + bearing
(``measure_star`` / ``measure_prox``), and the filter; the first approach (Taichi's kernel compilation) is left out.
The budget of issue 23.5: ~10-20 ms per frame, so that 1,000 approaches x ~60 frames take 10-20 min on 2 cores.

Measured 2026-11-27 (2 cores shared with other engineers' jobs, load average 12.4-12.6 during the runs, so
these are upper bounds; one process, nice 5, seed 1):

    far   (star camera, paper sensor: noise-free, whole 1024 x 768 frames; 20 approaches x 64 frames):
          543 ms per approach, 8.5 ms per frame = 0.08 truth + 6.1 render/detect/identify/bearing + 2.3 filter
    close (proximity camera, exact-coverage render + blobber "subpixel"; 10 approaches x 61 frames):
          853 ms per approach, 14.0 ms per frame = 0.12 truth + 10.7 render/blobber/bearing + 3.2 filter

The filter's share (iterated EKF, 3 iterations, one 6-state filter per call) is numpy's per-call overhead on small
matrices; approaches are independent, so a batched filter over a shard would amortise it (not done: a case's rows
must not depend on its shard).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from dualsight.jobs.kinds import (rendezvous as rz, rendezvous_filter, rendezvous_measure, rendezvous_spec,
                                  rendezvous_truth)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="far", choices=sorted(rendezvous_spec.PRESETS))
    p.add_argument("--cases", type=int, default=20)
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args()
    d, _ = rendezvous_spec.resolve_spec(args.preset, None, seed=args.seed)
    spec = rz.spec_from_dict(d)
    t0 = time.perf_counter()
    ctx = rz.make_context(spec)
    t_ctx = time.perf_counter() - t0
    measure = rendezvous_measure.measure_star if spec.is_star else rendezvous_measure.measure_prox
    rows = []
    for i in range(args.cases + 1):
        a = time.perf_counter()
        draw = rendezvous_truth.draw_case(spec, i)
        truth = rendezvous_truth.truth_trajectory(spec, draw)
        geo = rendezvous_truth.geometry(spec, draw, truth)
        b = time.perf_counter()
        m, _ = measure(spec, ctx, draw, geo)
        c = time.perf_counter()
        rendezvous_filter.run_filter(spec, ctx, draw, m)
        e = time.perf_counter()
        if i:                                           # the first approach compiles Taichi's kernels
            rows.append((b - a, c - b, e - c))
    t = np.array(rows)
    T = spec.cfg.frames
    tot = t.sum(1)
    print(f"preset {args.preset}: {args.cases} approaches x {T} frames, one process (context {t_ctx:.1f} s)")
    print(f"  per approach: {1e3 * tot.mean():.0f} ms (median {1e3 * np.median(tot):.0f}, max {1e3 * tot.max():.0f})")
    print(f"  per frame:    {1e3 * tot.mean() / T:.2f} ms = truth+geometry {1e3 * t[:, 0].mean() / T:.3f} + "
          f"render/detect/identify/bearing {1e3 * t[:, 1].mean() / T:.2f} + filter {1e3 * t[:, 2].mean() / T:.3f}")
    print(f"  1,000 approaches on 2 workers (2 free cores): ~{1000 * tot.mean() / 2 / 60:.1f} min")


if __name__ == "__main__":
    main()
