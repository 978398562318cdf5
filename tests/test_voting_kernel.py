"""Geometric voting as Taichi kernels (kernels/voting.py, ``identify(..., engine="taichi")``) against the
numpy stages (``engine="numpy"``, the reference), bit for bit, on rendered star fields.

* Every output of :func:`dualsight.nav.starid.identify` (ids, accepted, T, vote_ids, votes,
  verify_votes, rejected, n_attitude_matches) is equal, dtype included, for the paper and robust
  configs of the star preset "paper" on 500 rendered cases (V 5.5 catalog) and 64 rendered cases
  with a V 7.0 catalog (4M pairs); for option sets that reach every branch of the kernels (strict
  maxima without candidate cliques, two candidates, once-per-pair with the fraction rule, one vote
  row for the whole batch) on 200 cases; and for degenerate batches (empty, no valid star, one or
  two stars, NaN padding).
* ``p_chance`` too: its hypothesis count reads the vote's own windows (``window_counts``), checked
  against a brute-force count of the catalog pairs within the tolerance, and searched anew when the
  verification tolerance differs from the voting one.
* The window search (bucketed binary search) equals ``np.searchsorted`` on both sides, with keys
  equal to catalog angles, repeated angles, keys outside the range and useless buckets.
* The comparison has teeth: kernels/voting.py with a planted bug (loaded from a patched copy, the
  shared file is never touched) must give different results on the same cases: an off-by-one
  window, the second star of every catalog pair not voted for, the tie rule of the argmax reversed,
  verification votes counted on one side only, the clique's tie-break reversed, ties to the higher row
  in the whole-row scan (V 7).
"""


import importlib.util
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import dualsight.kernels
from dualsight.jobs.kinds import star
from dualsight.kernels import voting as kvoting
from dualsight.kernels import voting_select as kselect
from dualsight.nav.pair_index import voting_index
from dualsight.nav.starid import identify
from dualsight.nav.voting_config import VotingConfig

FIELDS = ("ids", "accepted", "T", "vote_ids", "votes", "verify_votes", "rejected", "n_attitude_matches",
          "p_chance")     # p_chance: its hypothesis count reads the vote's own windows (NaN = no answer, equal)


def _rendered(mag_limit: float, n: int):
    """``n`` cases of the star preset "paper" (rendered and detected), with the catalog to ``mag_limit``."""
    spec_dict, _ = star.resolve_spec("paper", None)
    spec_dict["catalog"]["mag_limit"] = mag_limit
    spec = star.spec_from_dict(spec_dict)
    ctx = star.make_context(spec)
    out = star.compute_batch(spec, ctx, np.arange(n))
    return SimpleNamespace(obs=out["obs"].vec, valid=out["obs"].valid, cat=ctx.catalog.unit, pairs=ctx.pairs,
                           configs={"paper": spec.voting, "robust": spec.robust})


@pytest.fixture(scope="module")
def v55():
    return _rendered(5.5, 500)


@pytest.fixture(scope="module")
def v70():
    return _rendered(7.0, 64)


def _run(w, cfg, engine, obs=None, valid=None):
    p = w.pairs
    return identify(w.obs if obs is None else obs, w.valid if valid is None else valid, w.cat, p.i, p.j, p.angle,
                    cfg, engine=engine)


def _differences(a, b) -> list[str]:
    return [f for f in FIELDS if not (getattr(a, f).dtype == getattr(b, f).dtype
                                      and np.array_equal(getattr(a, f), getattr(b, f),
                                                         equal_nan=getattr(a, f).dtype.kind == "f"))]


def _assert_same(w, cfg, obs=None, valid=None):
    ref = _run(w, cfg, "numpy", obs, valid)
    got = _run(w, cfg, "taichi", obs, valid)
    assert _differences(ref, got) == []
    return ref


@pytest.mark.parametrize("config", ["paper", "robust"])
def test_bit_identical_v55(v55, config):
    ref = _assert_same(v55, v55.configs[config])
    # not vacuous: most cases solved, many stars voting, the robust checks did run
    assert v55.obs.shape[0] == 500 and (ref.T > 0).mean() > 0.9 and (ref.votes > 0).sum() > 4000
    if config == "robust":
        assert (ref.n_attitude_matches >= 0).sum() > 400


@pytest.mark.parametrize("config", ["paper", "robust"])
def test_bit_identical_v70(v70, config):
    assert len(v70.pairs.angle) > 1_000_000                              # the V 7.0 pair catalog
    ref = _assert_same(v70, v70.configs[config])
    assert (ref.T > 0).mean() > 0.9


OPTIONS = {   # option sets that reach the kernels' other branches
    "unique_m1": ("paper", dict(require_unique_max=True)),                # select: strict max, duplicates
    "unique_clique": ("paper", dict(require_unique_max=True, accept_rule="clique", min_accepted=3)),
    "two_candidates": ("robust", dict(candidates_per_star=2, max_vote_cells=5000)),   # small blocks
    "once_fraction": ("paper", dict(vote_once_per_pair=True, tolerance_rad=1e-4)),
    "one_row_few_stars": ("robust", dict(max_vote_cells=1, max_stars=6)),   # one vote row for the batch
    "wide_reject": ("paper", dict(tolerance_rad=3e-4, min_accepted=8)),
}


@pytest.mark.parametrize("name", list(OPTIONS))
def test_bit_identical_options(v55, name):
    preset, kw = OPTIONS[name]
    cfg = getattr(VotingConfig, preset)(**{"tolerance_rad": v55.configs["paper"].tolerance_rad, **kw})
    _assert_same(v55, cfg, v55.obs[:200], v55.valid[:200])


@pytest.mark.parametrize("config", ["paper", "robust"])
def test_bit_identical_degenerate_batches(v55, config):
    cfg = v55.configs[config]
    obs, valid = v55.obs[:12].copy(), v55.valid[:12].copy()
    valid[0] = False                     # no star
    valid[1, 1:] = False                 # one star
    valid[2, 2:] = False                 # two stars
    valid[3, 3:] = False                 # three stars
    obs[4, 1] = np.nan                   # a non-finite entry marked valid
    obs[~valid] = np.nan
    _assert_same(v55, cfg, obs, valid)
    _assert_same(v55, cfg, obs[:0], valid[:0])                          # empty batch
    _assert_same(v55, cfg, obs[:1], valid[:1])                          # nothing valid at all
    _assert_same(v55, cfg, obs[1:2], valid[1:2])                        # one star slot (no pair)
    _assert_same(v55, cfg, obs[:, :0], valid[:, :0])                     # no star slot


@pytest.mark.parametrize("config", ["paper", "robust"])
def test_bit_identical_single_cases(v55, config):
    # one case per call (a single frame): the select / verify kernels' serial variants
    for b in range(8):
        ref = _assert_same(v55, v55.configs[config], v55.obs[b:b + 1], v55.valid[b:b + 1])
        assert ref.T[0] > 0                                              # solved: every stage ran


def test_engine_argument(v55):
    with pytest.raises(ValueError, match="engine"):
        _run(v55, v55.configs["paper"], "cuda")


# ------------------------------------------------------------------------------ window search

def test_window_search_is_searchsorted():
    """``_search`` (bucketed, branch-free) equals ``np.searchsorted`` on both sides: keys equal to
    catalog angles (ties decide the side), runs of repeated angles, keys below and above every angle;
    with the buckets of :func:`bucket_starts`, and with useless buckets (the exact fallback)."""
    ti = dualsight.kernels.taichi_runtime.ensure_init()
    F1, F2, I1 = (ti.types.ndarray(dtype=t, ndim=n) for t, n in ((ti.f64, 1), (ti.f64, 2), (ti.i32, 1)))

    @ti.kernel
    def search(angle: F1, starts: I1, inv_w: ti.f64, keys: F1, right: ti.i32, out: I1):
        for e in range(keys.shape[0]):
            out[e] = kvoting._search(angle, starts, inv_w, keys[e], right)

    rng = np.random.default_rng(5)
    angle = np.sort(np.concatenate([rng.uniform(0.0, 0.3, 5000), np.full(40, 0.1), np.full(7, 0.0),
                                    rng.uniform(0.0, 0.3, 9).repeat(3)]))
    keys = np.concatenate([angle[rng.integers(0, angle.size, 3000)], rng.uniform(-0.05, 0.35, 3000),
                           [0.0, -1.0, 0.1, 0.3, angle[-1], 5.0, np.nextafter(angle[-1], 1), np.nextafter(0.1, 0)]])
    starts, inv_w = kvoting.bucket_starts(angle)
    bad = np.linspace(0, angle.size, starts.size).astype(np.int32)[::-1].copy()   # decreasing: never right
    for st, iw in ((starts, inv_w), (starts, 0.0), (starts, 1e9), (bad, inv_w)):
        for side in ("right", "left"):
            out = np.zeros(keys.size, np.int32)
            search(angle, st, iw, keys, int(side == "right"), out)
            np.testing.assert_array_equal(out, np.searchsorted(angle, keys, side=side), err_msg=side)


# ------------------------------------------------------------------------------ planted bugs

PLANTED = {   # name: (text of kernels/voting.py or voting_select.py, its replacement)
    "window_off_by_one": ("c = ti.max(hi - lo, 0)", "c = ti.max(hi - lo - 1, 0)"),
    "second_star_not_voted": (   # entries 2m, 2m + 1 = stars i, j of catalog pair m: count only i
        "for e in range(2 * l, 2 * (l + c)):\n                            # a plain load",
        "for e2 in range(l, l + c):\n                            e = 2 * e2  # a plain load"),
    "argmax_ties_to_higher_row": ("(v == cs[k - 1] and v > 0 and s < ids[k - 1])",
                                  "(v == cs[k - 1] and v > 0 and s > ids[k - 1])"),
    "verify_one_sided": ("for y in range(K):\n                    c += ti.cast(cons[b, x, y]",
                         "for y in range(x):\n                    c += ti.cast(cons[b, x, y]"),
    "clique_tie_to_lower_index": ("if d < bd or (d == bd and sc <= bs):", "if d < bd or (d == bd and sc < bs):"),
    "row_scan_ties_to_higher_row": (          # the whole-row scan lets a tie displace the lower row kept
        "if v > cs[k - 1]:        # ascending rows", "if v >= cs[k - 1] and v > 0:        # ascending rows"),
    "row_walk_ties_to_higher_row": (          # the walk over the touched counts keeps the higher row on a tie
        "(v == cs[k - 1] and v > 0 and s < ids[k - 1])", "(v == cs[k - 1] and v > 0 and s > ids[k - 1])"),
}
PLANTED_ON = {"row_scan_ties_to_higher_row": "v70"}   # the whole-row scan runs for V 7 (the others: V 5.5)


def _patched_kernels(tmp_path: Path, name: str):
    """(module name, the kernels module -- voting or voting_select -- with one planted bug), as a separate module
    (its own kernels)."""
    old, new = PLANTED[name]
    where = [m for m in (kvoting, kselect) if Path(m.__file__).read_text().count(old) == 1]
    assert len(where) == 1, f"{name}: the text to patch must occur once in the voting kernels"
    short = where[0].__name__.rsplit(".", 1)[1]
    path = tmp_path / f"{short}_planted_{name}.py"
    path.write_text(Path(where[0].__file__).read_text().replace(old, new))
    spec = importlib.util.spec_from_file_location(f"dualsight.kernels._{short}_planted_{name}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return short, mod


@pytest.mark.parametrize("name", list(PLANTED))
def test_planted_bug_is_caught(request, tmp_path, monkeypatch, name):
    """The bit-identity check fails on kernels with a planted bug (paper or robust config, the 500 V 5.5
    cases, or the 64 V 7.0 cases for a bug in the whole-row scan)."""
    w = request.getfixturevalue(PLANTED_ON.get(name, "v55"))
    refs = {c: _run(w, w.configs[c], "numpy") for c in ("paper", "robust")}
    monkeypatch.setattr(dualsight.kernels, *_patched_kernels(tmp_path, name))
    differ = {c: _differences(refs[c], _run(w, w.configs[c], "taichi")) for c in refs}
    assert differ["paper"] or differ["robust"], f"planted bug {name} not detected"
    monkeypatch.undo()
    assert all(_differences(refs[c], _run(w, w.configs[c], "taichi")) == [] for c in refs)   # the real kernels


def test_voting_index_buckets_follow_the_catalog(v55):
    """The window buckets are cached per :class:`VotingIndex` and built from its angles."""
    from dualsight.nav import votes

    index = voting_index(v55.pairs.i, v55.pairs.j, v55.pairs.angle)
    _run(v55, v55.configs["paper"], "taichi", v55.obs[:4], v55.valid[:4])
    starts, inv_w = votes._BUCKETS[index]
    ref_starts, ref_inv = kvoting.bucket_starts(index.angle)
    np.testing.assert_array_equal(starts, ref_starts)
    assert inv_w == ref_inv and starts[-1] == len(index)


@pytest.mark.parametrize("config", ["paper", "robust"])
def test_vote_window_counts_are_the_catalog_pairs_within_tolerance(v55, config):
    """Both engines' ``window_counts`` (what the chance probability's hypothesis count reads) are, for every
    observed pair, the number of catalog pairs with d - tol < angle < d + tol, counted by brute force."""
    from dualsight.nav.votes import observed_pairs, vote, vote_taichi

    cfg = v55.configs[config]
    index = voting_index(v55.pairs.i, v55.pairs.j, v55.pairs.angle)
    K = 8
    use = v55.valid[:40, :K]
    pairs = observed_pairs(np.where(use[..., None], v55.obs[:40, :K], 0.0), use)
    d = pairs.angle[:, None]
    tol = cfg.tolerance_rad
    truth = np.count_nonzero((index.angle[None, :] > d - tol) & (index.angle[None, :] < d + tol), axis=1)
    assert pairs.angle.size > 500 and truth.sum() > 1000 and (truth > 1).mean() > 0.5
    for fn in (vote, vote_taichi):
        counts = fn(pairs, use, index, len(v55.cat), cfg, window_counts=True)[2]
        np.testing.assert_array_equal(counts, truth, err_msg=fn.__name__)


@pytest.mark.parametrize("engine", ["numpy", "taichi"])
@pytest.mark.parametrize("verify_factor", [1.0, 3.0])
def test_round_hypotheses_count_the_pairs_within_the_verify_tolerance(v55, engine, verify_factor):
    """A round's hypothesis count is 2 x the catalog pairs within ``verify_tol`` of each voting pair (brute
    force), whether it equals the voting tolerance (the vote's windows are reused) or not (searched anew)."""
    import dataclasses

    from dualsight.nav import starid
    from dualsight.scene.units import angle_between

    base = v55.configs["robust"]
    cfg = dataclasses.replace(base, verify_tolerance_rad=verify_factor * base.tolerance_rad)
    index = voting_index(v55.pairs.i, v55.pairs.j, v55.pairs.angle)
    S = 6                                                   # fewer than first_stars: every valid star votes
    obs, valid = v55.obs[:30, :S], v55.valid[:30, :S]
    out = starid._round(obs, valid, valid, v55.cat, index, cfg, engine)
    truth = np.zeros(len(obs))
    for b in range(len(obs)):
        idx = np.flatnonzero(valid[b])
        for x in range(idx.size):
            for y in range(x + 1, idx.size):
                d = float(angle_between(obs[b, idx[x]], obs[b, idx[y]]))
                truth[b] += 2 * np.count_nonzero(np.abs(index.angle - d) < cfg.verify_tol)
    assert truth.sum() > 0
    np.testing.assert_array_equal(out["hypotheses"], truth)
