"""Star identification (geometric voting), SVD attitude and the reference's error metrics.

Independent truths: known rotations, brute-force loops over pairs for the vote counts and the
catalog windows, synthetic star fields from a random-sphere catalog whose true identities are known
(which catalog star made each observed star), Monte Carlo noise against Markley's covariance.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from dualsight.nav.attitude import solve_identified
from dualsight.nav.errors import CONFIDENT_WRONG, SUCCESS, axis_errors, classify, total_error_angle
from dualsight.nav.starid import Identification, VotingConfig, VotingIndex, identify, voting_index
from dualsight.nav.votes import pair_windows
from dualsight.scene.attitude import euler123_to_dcm, random_euler123
from dualsight.scene.camera import Camera
from dualsight.scene.units import ARCSEC, angle_between

CAM = Camera.pinhole(1024, 768, 4.65e-6, 17e-3)     # the reference's star SIL camera: 15.9 x 12.0 deg
TOL = 5e-5                                            # 10 arcsec: ~1 arcsec perturbations in the fields


# ------------------------------------------------------------------------------------------ helpers


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rotation(axis, angle):
    """Active rotation matrix (Rodrigues) of ``angle`` about unit ``axis``."""
    k = _unit(np.asarray(axis, float))
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def _sphere_catalog(seed, n):
    return _unit(np.random.default_rng(seed).normal(size=(n, 3)))


def _pair_catalog(cat, max_angle):
    """All pairs i < j closer than ``max_angle``, ascending by angle (plain numpy, no dualsight code)."""
    n = len(cat)
    dots = np.clip(cat @ cat.T, -1.0, 1.0)
    i, j = np.nonzero(np.triu(dots > np.cos(max_angle), k=1))
    ang = np.arctan2(np.linalg.norm(np.cross(cat[i], cat[j]), axis=1), np.sum(cat[i] * cat[j], axis=1))
    keep = ang < max_angle
    o = np.argsort(ang[keep], kind="stable")
    assert n < 2**31
    return i[keep][o].astype(np.int32), j[keep][o].astype(np.int32), ang[keep][o]


def _fields(rng, cat, B, S=24, sigma=1.0 * ARCSEC, n_false=(0, 3), n_drop=(1, 2), only=None):
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
        tv = _unit(v[inn] + rng.normal(scale=sigma, size=(len(inn), 3)))
        fv = CAM.backproject(np.stack([rng.uniform(0, CAM.width, nf), rng.uniform(0, CAM.height, nf)], -1))
        allv = np.concatenate([tv, fv])
        ids = np.concatenate([inn, np.full(nf, -1)])
        o = rng.permutation(len(allv))[:S]
        obs[b, :len(o)], valid[b, :len(o)], truth[b, :len(o)] = allv[o], True, ids[o]
    return A, obs, valid, truth


def _outcome(ident, obs, cat, A_true):
    A, ok = solve_identified(obs, ident.ids, ident.accepted, cat)
    return classify(axis_errors(A, A_true), total_error_angle(A, A_true), ident.T)


@pytest.fixture(scope="module")
def sky():
    """~3000 random stars, ~13 in a 15.9 x 12.0 deg field, and their pairs within the diagonal FOV."""
    cat = _sphere_catalog(11, 3000)
    pi, pj, pa = _pair_catalog(cat, CAM.fov_rad[2])
    return SimpleNamespace(cat=cat, i=pi, j=pj, angle=pa)


# ------------------------------------------------------------------------------------------ voting


def _brute_votes(obs, valid, cat, pi, pj, pa, tol, once):
    """Kolomenkin's voting round by a plain loop over observed pairs and a scan of all catalog pairs."""
    S, N = len(obs), len(cat)
    votes = np.zeros((S, N), int)
    idx = [s for s in range(S) if valid[s]]
    for a in range(len(idx)):
        for b in range(a + 1, len(idx)):
            p, q = idx[a], idx[b]
            d = np.arccos(np.clip(obs[p] @ obs[q], -1, 1))
            hit = np.abs(pa - d) < tol
            ids = np.concatenate([pi[hit], pj[hit]])
            if once:
                ids = np.unique(ids)
            np.add.at(votes[p], ids, 1)
            np.add.at(votes[q], ids, 1)
    return votes


def test_pair_windows_match_brute_force(sky):
    """Each observed angle's window holds exactly the catalog pairs with d - tol < angle < d + tol."""
    rng = np.random.default_rng(15)
    tol = 2e-4
    d = np.concatenate([rng.uniform(0, sky.angle[-1], 200), sky.angle[[0, 5, 500]] + tol,   # near a boundary
                        sky.angle[[7, 70]] - tol, [sky.angle[-1] + 1.0]])
    lo, cnt = pair_windows(d, sky.angle, tol)
    for k in range(d.size):
        inside = np.flatnonzero((sky.angle > d[k] - tol) & (sky.angle < d[k] + tol))
        want = (inside[0], inside.size) if inside.size else (lo[k], 0)
        assert (lo[k], cnt[k]) == want, k
    assert cnt.sum() > 1000 and (cnt == 0).any()


@pytest.mark.parametrize("once", [False, True])
def test_voting_round_matches_brute_force(once):
    rng = np.random.default_rng(7)
    cat = _sphere_catalog(8, 1500)
    pi, pj, pa = _pair_catalog(cat, CAM.fov_rad[2])
    tol = 1e-3                                           # wide: many candidates, repeats and ties
    A, obs, valid, truth = _fields(rng, cat, 6, S=8, sigma=1e-5, n_false=(1, 1), n_drop=(0, 0))
    assert valid.sum(1).min() >= 3
    cfg = VotingConfig.paper(tol, vote_once_per_pair=once, max_stars=8)
    ident = identify(obs, valid, cat, pi, pj, pa, cfg)
    n_ties = 0
    for b in range(len(obs)):
        v = _brute_votes(obs[b], valid[b], cat, pi, pj, pa, tol, once)
        best = v.argmax(axis=1)                          # ties: lowest row
        top = v.max(axis=1)
        n_ties += int(np.sum((v == top[:, None]).sum(1) > 1))
        exp_ids = np.where(valid[b] & (top > 0), best, -1)
        np.testing.assert_array_equal(ident.vote_ids[b], exp_ids)
        np.testing.assert_array_equal(ident.votes[b], np.where(exp_ids >= 0, top, 0))
        # verification round by loops
        S = obs.shape[1]
        vv = np.zeros(S, int)
        for p in range(S):
            for q in range(S):
                if p != q and exp_ids[p] >= 0 and exp_ids[q] >= 0:
                    d_obs = np.arccos(np.clip(obs[b, p] @ obs[b, q], -1, 1))
                    d_cat = np.arccos(np.clip(cat[exp_ids[p]] @ cat[exp_ids[q]], -1, 1))
                    vv[p] += abs(d_cat - d_obs) < tol
        np.testing.assert_array_equal(ident.verify_votes[b], vv)
        assert ident.T[b] == vv.max()
    assert n_ties > 0                                    # the tie rule was exercised


@pytest.mark.parametrize("preset", ["paper", "robust"])
@pytest.mark.parametrize("sigma_arcsec, tol", [(1.0, TOL), (5.0, 1.5e-4)])
def test_identify_synthetic_fields(sky, preset, sigma_arcsec, tol):
    """200 random attitudes, ~12.7 true stars in view after dropping 1-2, plus 0-3 false stars.

    Measured (seed 8): 1 arcsec / tol 10 arcsec: paper and robust 99.5 % success, 0 confident but
    wrong, every accepted identity right; 5 arcsec / tol 31 arcsec: paper 98.5 %, robust 99.5 %, 0 wrong.
    """
    rng = np.random.default_rng(8)
    B = 200
    A, obs, valid, truth = _fields(rng, sky.cat, B, sigma=sigma_arcsec * ARCSEC)
    cfg = getattr(VotingConfig, preset)(tol)
    ident = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, cfg)
    assert isinstance(ident, Identification)
    assert ident.ids.shape == ident.accepted.shape == (B, obs.shape[1]) and ident.T.shape == (B,)
    acc = ident.accepted
    assert (acc & (ident.ids == truth)).sum() >= 0.99 * acc.sum()
    if preset == "robust":
        assert not (acc & (ident.ids != truth)).any()
    st = _outcome(ident, obs, sky.cat, A)
    assert np.mean(st == SUCCESS) >= 0.97
    assert np.mean(st == CONFIDENT_WRONG) <= (0.01 if preset == "paper" else 0.0)
    assert (ident.T[st == SUCCESS] > 0).all()
    assert (ident.T[~acc.any(axis=1)] == 0).all()


def test_pair_catalog_object_is_accepted(sky):
    rng = np.random.default_rng(9)
    A, obs, valid, truth = _fields(rng, sky.cat, 8)
    cfg = VotingConfig.robust(TOL)
    a = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, cfg)
    b = identify(obs, valid, sky.cat, SimpleNamespace(i=sky.i, j=sky.j, angle=sky.angle), cfg=cfg)
    for f in ("ids", "accepted", "T", "votes", "verify_votes"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


@pytest.mark.parametrize("preset", ["paper", "robust"])
def test_batch_equals_single_cases(sky, preset):
    rng = np.random.default_rng(10)
    B = 10
    A, obs, valid, truth = _fields(rng, sky.cat, B, S=16)
    obs[~valid] = np.nan                                  # padding may be NaN
    valid[3] = False                                      # an empty case
    # tiny memory bound: one case per chunk and the candidate lists split into pieces
    small = getattr(VotingConfig, preset)(TOL, max_vote_cells=16 * 3000)
    big = getattr(VotingConfig, preset)(TOL, max_vote_cells=50_000_000)
    whole = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, big)
    chunked = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, small)
    fields = ("ids", "accepted", "T", "vote_ids", "votes", "verify_votes", "rejected", "n_attitude_matches")
    for f in fields:
        np.testing.assert_array_equal(getattr(whole, f), getattr(chunked, f), err_msg=f)
    for b in range(B):
        one = identify(obs[b:b + 1], valid[b:b + 1], sky.cat, sky.i, sky.j, sky.angle, big)
        for f in fields:
            np.testing.assert_array_equal(getattr(one, f)[0], getattr(whole, f)[b], err_msg=f"{f} case {b}")
    assert whole.T[3] == 0 and (whole.ids[3] == -1).all() and not whole.accepted[3].any()


def test_two_star_fields_are_not_confidently_wrong(sky):
    """Two stars give one angle: tens of catalog pairs match it and every candidate ties.

    Measured (300 fields): paper and robust both 0 % confident, so 0 % confident but wrong.  The two
    stars get identical vote lists, so plain argmax gives both the same identity, which fails
    verification (T = 0); robust finds no strict maximum at all.
    """
    rng = np.random.default_rng(11)
    A, obs, valid, truth = _fields(rng, sky.cat, 300, S=4, only=2)
    for cfg in (VotingConfig.paper(TOL), VotingConfig.robust(TOL)):
        ident = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, cfg)
        st = _outcome(ident, obs, sky.cat, A)
        assert np.mean(st == CONFIDENT_WRONG) <= 0.01


def test_sparse_fields_robust_never_confidently_wrong(sky):
    """Three- and four-star fields (no false stars): robust answers or abstains, never wrongly.

    Measured (300 fields each): 3 stars: paper 47 % success and 1.7 % confident but wrong (a
    triangle matches several catalog triangles), robust abstains (its attitude check wants 4 matched
    stars); 4 stars: both 100 %.
    """
    rng = np.random.default_rng(12)
    for n in (3, 4):
        A, obs, valid, truth = _fields(rng, sky.cat, 150, S=6, only=n)
        ident = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, VotingConfig.robust(TOL))
        st = _outcome(ident, obs, sky.cat, A)
        assert (st != CONFIDENT_WRONG).all()
        assert not (ident.accepted & (ident.ids != truth)).any()
        if n == 4:
            assert np.mean(st == SUCCESS) >= 0.9


def test_false_stars_alone_give_no_solution(sky):
    rng = np.random.default_rng(13)
    B, S = 60, 12
    px = np.stack([rng.uniform(0, CAM.width, (B, S)), rng.uniform(0, CAM.height, (B, S))], -1)
    obs = CAM.backproject(px)
    valid = np.ones((B, S), bool)
    ident = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, VotingConfig.robust(TOL))
    assert (ident.T == 0).all() and not ident.accepted.any()


def test_attitude_check_reidentifies_faint_stars(sky):
    """With max_stars = 5 voting sees five stars; the attitude check identifies the rest."""
    rng = np.random.default_rng(14)
    A, obs, valid, truth = _fields(rng, sky.cat, 40, n_false=(0, 0), n_drop=(0, 0))
    many = valid.sum(1) >= 8
    cfg = VotingConfig.robust(TOL, max_stars=5)
    ident = identify(obs, valid, sky.cat, sky.i, sky.j, sky.angle, cfg)
    ok = ident.T > 0
    assert ok[many].mean() > 0.8
    assert (ident.accepted[ok].sum(1) == valid[ok].sum(1)).mean() > 0.9
    assert not (ident.accepted & (ident.ids != truth)).any()
    assert (ident.n_attitude_matches[ok] >= 4).all() and (ident.n_attitude_matches[~ok] <= 3).all()


def test_config_validation():
    from dualsight.errors import ConfigError
    with pytest.raises(ConfigError, match="voting.tolerance_rad"):
        VotingConfig(tolerance_rad=0.0)
    with pytest.raises(ConfigError, match="voting.accept_rule"):
        VotingConfig(accept_rule="most")
    with pytest.raises(ConfigError, match="voting.min_accepted"):
        VotingConfig(min_accepted=1)
    assert VotingConfig() == VotingConfig.paper()
    r = VotingConfig.robust(1e-4, min_verified=3)
    assert r.tolerance_rad == 1e-4 and r.min_verified == 3 and r.verify_attitude


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
    cat = _sphere_catalog(31, 3000)
    pi, pj, pa = _pair_catalog(cat, CAM.fov_rad[2])
    rng = np.random.default_rng(32)
    A, obs, valid, truth = _fields(rng, cat, 12, S=16, sigma=2.0 * ARCSEC)
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
