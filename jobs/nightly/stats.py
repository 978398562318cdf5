"""The nightly's statistical tests (numpy only): each returns a p-value, the caller decides with its alpha.

* Rates (success, confident-wrong, identification, blob found, true range within [min, max]):
  :func:`fisher_exact`, the two-sided Fisher exact test of two proportions (exact for rare events such as a
  0.01 % confident-wrong rate, where a normal approximation would false-alarm).
* Error distributions (attitude error per axis, range relative error, centroid / direction errors):
  :func:`bootstrap_test` on the mean and the 95th percentile, z = (now - baseline) / sqrt(se_now^2 +
  se_base^2) with each standard error from a bootstrap (``B`` resamples, a fixed numpy seed, so the same
  data always give the same p); below :data:`MIN_BOOTSTRAP_N` values on either side the mean is tested by an
  exact (or, above 20,000 arrangements, seeded Monte Carlo) permutation test and the 95th percentile is not
  tested.
* Throughput (cases/s): :func:`throughput_tolerance`, a ratio tolerance from the run-to-run spread of the
  accepted nights (4 coefficients of variation, within [10 %, 90 %]), else :data:`DEFAULT_THROUGHPUT_TOL`.

:func:`decide` turns (p, alpha, the two values, the metric's good direction) into a verdict.
"""

from __future__ import annotations

import itertools
import math
import zlib

import numpy as np

BOOTSTRAP_B = 300
BOOTSTRAP_SEED = 20240601
MIN_BOOTSTRAP_N = 20
PERMUTATIONS = 20_000
DEFAULT_THROUGHPUT_TOL = 0.30
"""Throughput tolerance before three accepted nights give a measured spread (this 2-core machine's
run-to-run spread of a short run is easily 10-20 %)."""

RED = ("REGRESSION", "not comparable", "no baseline", "failed")
"""Verdicts that keep a night from being green."""


def _log_factorials(n: int) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.log(np.arange(1, n + 1, dtype=np.float64)))])


def fisher_exact(k1: int, n1: int, k2: int, n2: int) -> float:
    """Two-sided Fisher exact p-value of ``k1/n1`` against ``k2/n2`` (sum of the hypergeometric
    probabilities no larger than the observed table's)."""
    k1, n1, k2, n2 = int(k1), int(n1), int(k2), int(n2)
    if n1 <= 0 or n2 <= 0:
        return 1.0
    K, N = k1 + k2, n1 + n2
    lf = _log_factorials(N)
    lo, hi = max(0, K - n2), min(K, n1)
    x = np.arange(lo, hi + 1)
    logp = (lf[K] - lf[x] - lf[K - x]) + (lf[N - K] - lf[n1 - x] - lf[N - K - n1 + x]) - (lf[N] - lf[n1] - lf[N - n1])
    obs = logp[k1 - lo]
    p = float(np.exp(logp[logp <= obs + 1e-7]).sum())
    return min(1.0, p)


def _rng(tag: str) -> np.random.Generator:
    return np.random.default_rng([BOOTSTRAP_SEED, zlib.crc32(tag.encode())])


def bootstrap_se(x: np.ndarray, tag: str, B: int = BOOTSTRAP_B) -> tuple[float, float]:
    """Bootstrap standard errors of (mean, 95th percentile) of ``x`` (``B`` resamples, seeded by ``tag``)."""
    x = np.asarray(x, np.float64)
    n = len(x)
    rng = _rng(tag)
    means, p95s = [], []
    chunk = max(1, min(B, 4_000_000 // max(n, 1)))
    done = 0
    while done < B:
        b = min(chunk, B - done)
        s = x[rng.integers(0, n, size=(b, n))]
        means.append(s.mean(axis=1))
        p95s.append(np.quantile(s, 0.95, axis=1))
        done += b
    return float(np.std(np.concatenate(means), ddof=1)), float(np.std(np.concatenate(p95s), ddof=1))


def z_pvalue(diff: float, se: float) -> float:
    """Two-sided normal p-value of ``diff`` with standard error ``se`` (se 0: 1 if diff is 0, else 0)."""
    if not se > 0:
        return 1.0 if diff == 0 else 0.0
    return math.erfc(abs(diff) / se / math.sqrt(2.0))


def permutation_pvalue(a: np.ndarray, b: np.ndarray, tag: str) -> float:
    """Two-sided permutation p-value of the difference of means: exact when the arrangements number at most
    :data:`PERMUTATIONS`, else (1 + hits) / (1 + R) over R seeded random arrangements."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    pooled = np.concatenate([a, b])
    n, na = len(pooled), len(a)
    if na == 0 or len(b) == 0:
        return 1.0
    obs = abs(a.mean() - b.mean())
    tol = 1e-12 * max(1.0, abs(obs))
    total = pooled.sum()
    if math.comb(n, na) <= PERMUTATIONS:
        idx = np.array(list(itertools.combinations(range(n), na)))
        sa = pooled[idx].sum(axis=1)
        d = np.abs(sa / na - (total - sa) / (n - na))
        return float(np.mean(d >= obs - tol))
    rng = _rng(tag)
    hits, chunk = 0, max(1, min(PERMUTATIONS, 2_000_000 // n))
    for start in range(0, PERMUTATIONS, chunk):
        b = min(chunk, PERMUTATIONS - start)
        pick = np.argpartition(rng.random((b, n)), na - 1, axis=1)[:, :na]      # a random subset of na
        sa = pooled[pick].sum(axis=1)
        hits += int(np.sum(np.abs(sa / na - (total - sa) / (n - na)) >= obs - tol))
    return float((1 + hits) / (1 + PERMUTATIONS))


def distribution_tests(base: np.ndarray, now: np.ndarray, tag: str) -> dict:
    """{"mean": (base, now, p, test), "p95": (base, now, p | None, test)} for two samples of one metric."""
    base = np.asarray(base, np.float64)
    now = np.asarray(now, np.float64)
    out = {}
    mb = float(base.mean()) if len(base) else float("nan")
    mn = float(now.mean()) if len(now) else float("nan")
    qb = float(np.quantile(base, 0.95)) if len(base) else float("nan")
    qn = float(np.quantile(now, 0.95)) if len(now) else float("nan")
    if len(base) == 0 or len(now) == 0:
        return {"mean": (mb, mn, None, "no values"), "p95": (qb, qn, None, "no values")}
    if min(len(base), len(now)) < MIN_BOOTSTRAP_N:
        p = permutation_pvalue(base, now, tag)
        out["mean"] = (mb, mn, p, f"permutation test of means (n {len(base)} vs {len(now)})")
        out["p95"] = (qb, qn, None, f"not tested: fewer than {MIN_BOOTSTRAP_N} values")
        return out
    se_mb, se_qb = bootstrap_se(base, tag + "/base")
    se_mn, se_qn = bootstrap_se(now, tag + "/now")
    out["mean"] = (mb, mn, z_pvalue(mn - mb, math.hypot(se_mb, se_mn)),
                   f"bootstrap z of the mean (B={BOOTSTRAP_B}, n {len(base)} vs {len(now)})")
    out["p95"] = (qb, qn, z_pvalue(qn - qb, math.hypot(se_qb, se_qn)),
                  f"bootstrap z of the 95th percentile (B={BOOTSTRAP_B}, n {len(base)} vs {len(now)})")
    return out


def rate_test(k_base: int, n_base: int, k_now: int, n_now: int) -> tuple[float, float, float | None, str]:
    """(base rate, now rate, p, test name) of two counts."""
    rb = k_base / n_base if n_base else float("nan")
    rn = k_now / n_now if n_now else float("nan")
    if not n_base or not n_now:
        return rb, rn, None, "no cases"
    return rb, rn, fisher_exact(k_base, n_base, k_now, n_now), \
        f"Fisher exact two-sided ({k_base}/{n_base} vs {k_now}/{n_now})"


def worse(direction: str, base: float, now: float) -> bool:
    """Is ``now`` worse than ``base`` for a metric whose good direction is ``direction``
    ("higher", "lower", or "zero": closer to zero is better)?"""
    if direction == "higher":
        return now < base
    if direction == "lower":
        return now > base
    return abs(now) > abs(base)


def decide(p: float | None, alpha: float, base: float, now: float, direction: str) -> str:
    """Verdict of one test: "ok" (p >= alpha or untested), else "REGRESSION" or "improved"."""
    if p is None or not (p < alpha):
        return "ok" if p is not None else "info"
    return "REGRESSION" if worse(direction, base, now) else "improved"


def throughput_tolerance(history: list[float]) -> tuple[float, str]:
    """Ratio tolerance of a job's throughput: 4 x the coefficient of variation of the accepted nights'
    throughputs (at least 3 of them), clipped to [0.10, 0.90]; else the default 30 %."""
    h = np.asarray([v for v in history if v and v > 0], np.float64)
    if len(h) >= 3:
        cv = float(np.std(h, ddof=1) / np.mean(h))
        return float(np.clip(4 * cv, 0.10, 0.90)), f"4 x CV of {len(h)} accepted nights ({cv:.3f})"
    return DEFAULT_THROUGHPUT_TOL, f"default {DEFAULT_THROUGHPUT_TOL:.0%} (fewer than 3 accepted nights)"


def throughput_verdict(base: float, now: float, tol: float) -> str:
    """"REGRESSION" when now / base < 1 - tol, "improved" when > 1 + tol, else "ok"."""
    r = now / base
    return "REGRESSION" if r < 1 - tol else ("improved" if r > 1 + tol else "ok")
