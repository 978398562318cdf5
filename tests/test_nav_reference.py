"""Geometric voting against a plain slow reference written in the test (loops, no vectorisation), and the
identities against the truth of which catalog star made each observed star."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dualsight.nav.attitude import solve_identified
from dualsight.nav.pair_index import VotingIndex, voting_index
from dualsight.nav.starid import identify
from dualsight.nav.voting_config import VotingConfig
from dualsight.scene.units import ARCSEC, angle_between

from helpers import CAM, TOL, pair_catalog, sphere_catalog, star_fields


# ------------------------------------------------------------------------------ slow reference
#
# A straightforward per-case implementation of the whole method (loops over stars, pairs and
# nodes; no chunking, no vote tables, no index), written from the definitions in the docstrings of
# nav/votes.py, candidates.py, verify.py and attitude_check.py.  identify() must give bit-identical
# outputs on the inputs below.  Floating-point predicates are the same expressions (angles by
# scene.units.angle_between, window ``pa > d - tol`` and ``pa < d + tol``, cosine bounds), so only an
# exact tie with a threshold could tell the two apart.  Both are also checked against the truth of
# the fields (test_identities_are_the_true_stars), so they cannot drift together unnoticed.


def _slow_clique(cons, score):
    """Greedy pruning (drop the lonely members, else the one with the fewest consistent members,
    then the lowest score, then the highest index) until the members are mutually consistent."""
    n = len(score)
    member = [bool(np.any(cons[i])) for i in range(n)]
    for _ in range(n):
        mem = [i for i in range(n) if member[i]]
        deg = {i: sum(bool(cons[i][j]) for j in mem) for i in mem}
        if all(deg[i] == len(mem) - 1 for i in mem):
            break
        lonely = [i for i in mem if deg[i] == 0]
        for i in lonely:
            member[i] = False
        if not lonely:
            member[min(mem, key=lambda i: (deg[i], score[i], -i))] = False
    return member


def _slow_drop_duplicates(ids, prio):
    """An identity claimed twice stays only with a strict winner by ``prio``."""
    return [i if i < 0 or all(ids[j] != i or prio[j] < prio[x] for j in range(len(ids)) if j != x) else -1
            for x, i in enumerate(ids)]


def _slow_identify(obs, valid, cat, pi, pj, pa, cfg):
    B, S, _ = obs.shape
    N = len(cat)
    tol, vtol, m = cfg.tolerance_rad, cfg.verify_tol, cfg.candidates_per_star
    r = dict(ids=np.full((B, S), -1), accepted=np.zeros((B, S), bool), T=np.zeros(B, int),
             vote_ids=np.full((B, S), -1), votes=np.zeros((B, S), int), verify_votes=np.zeros((B, S), int),
             rejected=np.zeros(B, bool), n_attitude_matches=np.full(B, -1))
    for b in range(B):
        ok_s = [s for s in range(S) if valid[b, s] and np.all(np.isfinite(obs[b, s]))]
        use = ok_s[:cfg.max_stars]
        n = len(use)
        d = {(x, y): float(angle_between(obs[b, use[x]], obs[b, use[y]])) for x in range(n) for y in range(n)
             if x != y}
        # 1. voting
        votes = np.zeros((n, N), int)
        for x in range(n):
            for y in range(x + 1, n):
                win = (pa > d[x, y] - tol) & (pa < d[x, y] + tol)
                stars = np.concatenate([pi[win], pj[win]])
                if cfg.vote_once_per_pair:
                    stars = np.unique(stars)
                np.add.at(votes[x], stars, 1)
                np.add.at(votes[y], stars, 1)
        # 2. assignment: best identities (most votes, then lowest row)
        ranked = [sorted(np.nonzero(votes[x])[0], key=lambda i: (-votes[x, i], i)) for x in range(n)]
        vid, top = [-1] * n, [0] * n
        for x in range(n):
            c = [int(votes[x, i]) for i in ranked[x][:2]] + [0, 0]
            if (c[0] > c[1]) if cfg.require_unique_max else ranked[x]:
                vid[x], top[x] = int(ranked[x][0]), c[0]
        if m > 1:
            nodes = [(x, int(i), int(votes[x, i])) for x in range(n) for i in ranked[x][:m]]
            cons = [[x != y and d[x, y] > -1 and
                     np.cos(min(d[x, y] + vtol, np.pi)) < float(cat[a] @ cat[c]) <
                     (np.cos(d[x, y] - vtol) if d[x, y] > vtol else 2.0)
                     for (y, c, _) in nodes] for (x, a, _) in nodes]
            member = _slow_clique(cons, [v for (_, _, v) in nodes])
            chosen = [False] * n
            for (x, a, v), mem in zip(nodes, member):
                if mem and not chosen[x]:
                    chosen[x], vid[x], top[x] = True, a, v
            vid = _slow_drop_duplicates(vid, [(c, t) for c, t in zip(chosen, top)])
        if cfg.require_unique_max:
            vid = _slow_drop_duplicates(vid, top)
        top = [t if i >= 0 else 0 for i, t in zip(vid, top)]
        # 3-4. verification and match threshold
        cons = [[x != y and vid[x] >= 0 and vid[y] >= 0 and
                 abs(angle_between(cat[vid[x]], cat[vid[y]]) - d[x, y]) < vtol for y in range(n)] for x in range(n)]
        vv = [sum(row) for row in cons]
        T = max(vv, default=0)
        # 5. acceptance
        if cfg.accept_rule == "fraction":
            acc = [v > 0 and v >= cfg.accept_fraction * T for v in vv]
        else:
            acc = _slow_clique(cons, top)
        reject = T > 0 and sum(acc) < cfg.min_accepted
        for x, s in enumerate(use):
            r["vote_ids"][b, s], r["votes"][b, s], r["verify_votes"][b, s] = vid[x], top[x], vv[x]
            r["accepted"][b, s] = acc[x] and not reject
        r["ids"][b] = r["vote_ids"][b]
        # attitude check
        if cfg.verify_attitude and T > 0 and not reject:
            A, ok = solve_identified(obs[b:b + 1], r["ids"][b:b + 1], r["accepted"][b:b + 1], cat)
            A = A[0] if ok[0] else np.eye(3)
            c_tol = np.cos(cfg.attitude_tol)
            match = [-1] * S
            for s in ok_s:
                v = obs[b, s] @ A
                dots = cat @ v
                k = int(np.argmax(dots))
                cos1, cos2 = dots[k], np.max(np.delete(dots, k), initial=-np.inf)
                i = r["ids"][b, s]
                own = r["accepted"][b, s] and i >= 0 and v[0] * cat[i, 0] + v[1] * cat[i, 1] + v[2] * cat[i, 2] > c_tol
                if ok[0] and (own or (cos1 > c_tol and not cos2 > c_tol)):
                    match[s] = i if own else k
            match = _slow_drop_duplicates(match, [0] * S)
            r["n_attitude_matches"][b] = n_match = sum(i >= 0 for i in match)
            reject = n_match < cfg.min_verified
            if cfg.reidentify and not reject:
                r["ids"][b] = match
                r["accepted"][b] = np.array(match) >= 0
            r["accepted"][b] &= not reject
        r["rejected"][b] = reject
        r["T"][b] = 0 if reject else T
    return r


SLOW_CASES = {   # name: (preset, options) of the reference comparison
    "paper": ("paper", dict(tolerance_rad=TOL)),
    "robust": ("robust", dict(tolerance_rad=TOL)),
    "wide_once": ("paper", dict(tolerance_rad=1e-3, vote_once_per_pair=True, max_stars=8)),
    "unique_clique": ("paper", dict(tolerance_rad=4e-4, require_unique_max=True, accept_rule="clique",
                                    min_accepted=3)),
    "robust_tiny_memory": ("robust", dict(tolerance_rad=2e-4, max_stars=6, max_vote_cells=1)),
    "robust_two_cands": ("robust", dict(tolerance_rad=3e-4, candidates_per_star=2, reidentify=False,
                                        min_verified=3, max_vote_cells=5000)),
    "paper_reject": ("paper", dict(tolerance_rad=1.5e-4, min_accepted=8)),
    "robust_reject": ("robust", dict(tolerance_rad=1.5e-4, max_stars=12, min_verified=10)),
}

@pytest.fixture(scope="module")
def slow_inputs():
    """12 fields on a 3000-star sphere (~13 stars in view): false stars, drops, a NaN-padded case,
    an empty case, a two-star case and a three-star case."""
    cat = sphere_catalog(31, 3000)
    pi, pj, pa = pair_catalog(cat, CAM.fov_rad[2])
    rng = np.random.default_rng(32)
    A, obs, valid, truth = star_fields(rng, cat, 12, S=16, sigma=2.0 * ARCSEC)
    obs[~valid] = np.nan
    valid[3] = False
    valid[4, 2:] = False
    valid[5, 3:] = False
    return SimpleNamespace(cat=cat, i=pi, j=pj, angle=pa, obs=obs, valid=valid, truth=np.where(valid, truth, -1))


@pytest.mark.parametrize("name", list(SLOW_CASES))
def test_identify_matches_slow_reference(slow_inputs, name):
    """Every output, bit for bit, against the loop implementation: ties, repeated stars in a window,
    unique maxima, candidate sets, rejections, re-identification, a one-row memory bound."""
    preset, kw = SLOW_CASES[name]
    cfg = getattr(VotingConfig, preset)(**kw)
    x = slow_inputs
    ident = identify(x.obs, x.valid, x.cat, x.i, x.j, x.angle, cfg)
    ref = _slow_identify(x.obs, x.valid, x.cat, x.i, x.j, x.angle, cfg)
    for f, want in ref.items():
        np.testing.assert_array_equal(getattr(ident, f), want, err_msg=f"{name}: {f}")


@pytest.mark.parametrize("name", list(SLOW_CASES))
def test_identities_are_the_true_stars(slow_inputs, name):
    """Against the truth of the fields: which catalog star made each observed star (-1 = a false
    star), not against any output of the code.

    For every option set: an accepted identity is the star's true catalog row (so no false star is
    accepted); two or fewer true stars give no solution (one angle matches many catalog pairs); a
    star's verification votes come from the other true stars only, so T <= n_true - 1.  For the two
    presets at 10 arcsec (observed pair angles err by ~3 arcsec, 1 sigma): every case with >= 3 true
    stars is solved, T = n_true - 1 (each true star verified by every other one), and exactly the
    true stars are accepted.  With re-identification from the attitude, every true star of a solved
    case is accepted, also those beyond ``max_stars``.
    """
    preset, kw = SLOW_CASES[name]
    cfg = getattr(VotingConfig, preset)(**kw)
    x = slow_inputs
    ident = identify(x.obs, x.valid, x.cat, x.i, x.j, x.angle, cfg)
    is_true = x.truth >= 0
    voting = np.cumsum(x.valid, axis=1) <= cfg.max_stars                # the first max_stars valid stars
    n_true = (is_true & voting).sum(axis=1)
    assert (n_true >= 3).sum() >= 8 and (n_true <= 2).sum() >= 3 and (x.valid & ~is_true).any()   # not vacuous
    acc = ident.accepted
    np.testing.assert_array_equal(ident.ids[acc], x.truth[acc])
    assert (ident.T[n_true <= 2] == 0).all() and not acc[n_true <= 2].any()
    assert (ident.T <= np.maximum(n_true - 1, 0)).all()
    solved = ident.T > 0
    if name in ("paper", "robust"):
        np.testing.assert_array_equal(ident.T, np.where(n_true >= 3, n_true - 1, 0))
        np.testing.assert_array_equal(acc, is_true & (n_true >= 3)[:, None])
    if cfg.verify_attitude and cfg.reidentify:
        np.testing.assert_array_equal(acc, is_true & solved[:, None])


def test_voting_index_is_built_once_and_reused(slow_inputs):
    x = slow_inputs
    cfg = VotingConfig.robust(TOL)
    plain = identify(x.obs, x.valid, x.cat, x.i, x.j, x.angle, cfg)
    index = voting_index(x.i, x.j, x.angle)
    assert voting_index(x.i, x.j, x.angle) is index                    # cached by the arrays' identity
    assert voting_index(SimpleNamespace(i=x.i, j=x.j, angle=x.angle)) is index
    assert voting_index(index) is index
    with_index = identify(x.obs, x.valid, x.cat, index, cfg=cfg)
    for f in ("ids", "accepted", "T", "vote_ids", "votes", "verify_votes", "rejected", "n_attitude_matches"):
        np.testing.assert_array_equal(getattr(with_index, f), getattr(plain, f), err_msg=f)
    # other arrays (a copy, or the same objects holding another catalog): another index
    assert voting_index(x.i.copy(), x.j, x.angle) is not index
    i2 = x.i.copy()
    first = voting_index(i2, x.j, x.angle)
    i2[:] = i2[::-1]
    assert voting_index(i2, x.j, x.angle) is not first
    # the previous-occurrence table: the last earlier pair with the same star
    M = len(index)
    stars = np.stack([index.i, index.j], axis=1).ravel()
    np.testing.assert_array_equal(index.stars_plus_one[:2 * M] - 1, stars)
    assert not index.stars_plus_one[2 * M:].any()
    prev = index.prev
    rng = np.random.default_rng(33)
    for e in rng.integers(0, 2 * M, 200):
        earlier = np.nonzero(stars[:e - e % 2] == stars[e])[0]
        assert prev[e] == (earlier[-1] // 2 if earlier.size else -1)
    with pytest.raises(ValueError, match="sorted"):
        VotingIndex(x.i, x.j, x.angle[::-1])


def test_voting_index_of_memory_maps(slow_inputs, tmp_path):
    """Memory-mapped pair arrays (the cached catalogs): read-only maps are reused by identity (they cannot change);
    a writable map edited in place still gets a new index (its values are sampled, as for any array)."""
    x = slow_inputs
    maps = {}
    for mode in ("r", "r+"):
        folder = tmp_path / mode.replace("+", "plus")     # one file set per map (never rewrite a mapped file)
        folder.mkdir()
        for name in ("i", "j", "angle"):
            np.save(folder / f"{name}.npy", getattr(x, name))
        maps[mode] = [np.load(folder / f"{n}.npy", mmap_mode=mode) for n in ("i", "j", "angle")]
        first = voting_index(*maps[mode])
        assert voting_index(*maps[mode]) is first
        np.testing.assert_array_equal(first.stars_plus_one, voting_index(x.i, x.j, x.angle).stars_plus_one)
        if mode == "r+":
            maps[mode][0][:] = maps[mode][0][::-1]
            assert voting_index(*maps[mode]) is not first
