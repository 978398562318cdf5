"""Star identification with a spacecraft in the field vs the same cases without it (issue 23, point 2).

    DUALSIGHT_TI_THREADS=1 taskset -c 0 python benchmarks/bench_target_in_field.py [--cases 10000] [--preset paper]
        [--config examples/star/target_in_field.toml] [--seed 1] [--shard 1000]

The same cases (same seed: the same attitudes and noise seeds, ``jobs/kinds/star.draw_cases``) run through the
star job's ``compute_shard`` twice: the preset alone, and the preset with the ``[target]`` table of ``--config``
(default: a 3U CubeSat at 100 m - 10 km, anywhere in the inner 90 % of the image, random Sun at phase 0-90 deg).
Prints, for the reference's method and the robust one: success and confident-wrong rates with and without the
target, the paired difference with its binomial 1-sigma (discordant pairs), the confident-wrong answers that the
target caused (confident-wrong with it, not without), how often an identity was accepted for the target's own
blob, and how the target's blob went (excluded as larger than any star, voted, not detected), by resolved /
point-like.  Nothing is written to the lake.
"""

from __future__ import annotations

import argparse
import math
import os
import time

os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")

import numpy as np  # noqa: E402
import pyarrow as pa  # noqa: E402

from dualsight.jobs.kinds import star  # noqa: E402
from dualsight.jobs.engine.specs import preset_and_config  # noqa: E402


def run(spec, n: int, shard: int) -> pa.Table:
    ctx = star.make_context(spec)
    parts = [star.compute_shard(spec, np.arange(s, min(n, s + shard), dtype=np.int64), ctx)["star_cases"]
             for s in range(0, n, shard)]
    return pa.concat_tables(parts)


def col(t: pa.Table, name: str) -> np.ndarray:
    return np.asarray(t.column(name).to_pylist(), dtype=object)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10_000)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--config", default="examples/star/target_in_field.toml")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--shard", type=int, default=1000)
    a = ap.parse_args()
    d, _ = preset_and_config(star.PRESETS, a.preset, a.config)
    d["seed"] = a.seed
    with_t = star.spec_from_dict(d, source=a.config)
    without = star.spec_from_dict({k: v for k, v in d.items() if k != "target"}, source=a.preset)
    t0 = time.perf_counter()
    base = run(without, a.cases, a.shard)
    t1 = time.perf_counter()
    tgt = run(with_t, a.cases, a.shard)
    t2 = time.perf_counter()
    n = a.cases
    print(f"preset {a.preset}, {n} cases, seed {a.seed}, target: {a.config}; 1 process "
          f"(DUALSIGHT_TI_THREADS={os.environ.get('DUALSIGHT_TI_THREADS', 'unset')}); "
          f"without {t1 - t0:.1f} s, with {t2 - t1:.1f} s")
    res = col(tgt, "target_resolved").astype(bool)
    pres = col(tgt, "target_present").astype(bool)
    exc = col(tgt, "target_excluded")
    voted = col(tgt, "target_voted").astype(bool)
    vmag = col(tgt, "target_vmag").astype(float)
    print(f"target present {pres.sum()}, resolved {res.sum()}, point-like {(pres & ~res).sum()}; "
          f"V {np.nanmin(vmag):.1f} .. {np.nanmax(vmag):.1f}, median {np.nanmedian(vmag):.1f}")
    det = np.array([v is not None for v in exc])
    for name, m in (("resolved", pres & res), ("point-like", pres & ~res)):
        print(f"  {name:10s}: detected {int((det & m).sum())}, excluded as larger than any star "
              f"{int((det & m & (exc == True)).sum())}, voted {int((voted & m).sum())}")  # noqa: E712
    for method, suffix in (("reference", ""), ("robust", "_robust")):
        sb, st = col(base, "status" + suffix), col(tgt, "status" + suffix)
        if sb[0] is None:
            continue
        ok_b, ok_t = sb == "success", st == "success"
        cw_b, cw_t = sb == "confident_wrong", st == "confident_wrong"
        lost, gained = int((ok_b & ~ok_t).sum()), int((~ok_b & ok_t).sum())
        diff = 100.0 * (gained - lost) / n
        sig = 100.0 * math.sqrt(lost + gained) / n
        acc = col(tgt, "target_id_accepted" + suffix)
        fooled = int(np.sum(acc == True))  # noqa: E712
        print(f"{method:9s}: success {100 * ok_b.mean():.2f} % without, {100 * ok_t.mean():.2f} % with "
              f"(paired difference {diff:+.2f} +- {sig:.2f} points; {lost} lost, {gained} gained); "
              f"confident-wrong {int(cw_b.sum())} without, {int(cw_t.sum())} with, caused by the target "
              f"{int((cw_t & ~cw_b).sum())}; an identity accepted for the target's blob in {fooled} cases")


if __name__ == "__main__":
    main()
