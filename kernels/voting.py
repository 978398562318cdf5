"""Geometric voting (Kolomenkin et al. 2008) as Taichi CPU kernels, batched over cases (a leaf: arrays in,
arrays out).

The counting, selecting and comparing of the star identification chain of :mod:`dualsight.nav.starid`
(``engine="taichi"``).  Every floating-point value a decision reads (observed and catalog angles, window
keys, cosine bounds, catalog cosines) is computed by the caller with numpy and passed in, so the kernels
only compare and count: their results are bit for bit those of the numpy stages
(:mod:`dualsight.nav.votes`, :mod:`~dualsight.nav.candidates`, :mod:`~dualsight.nav.verify`), whatever
the number of threads or the order in which they take the work.

Kernels (built lazily, once per process, through :class:`~dualsight.kernels._runtime.KernelCache`):

``vote/<k>/<once>`` (step 1; k = identities kept per star, once = one vote per observed pair), two
parallel loops:

1. over observed pairs (case, p < q): the window ``[lo, lo + cnt)`` of catalog pairs with
   ``angle > d - tol`` and ``angle < d + tol`` (numpy ``searchsorted`` sides ``right`` / ``left``):
   a branch-free binary search within the few catalog angles of the key's bucket
   (:func:`bucket_starts`), checked, else over all angles; stored for (p, q) and (q, p);
2. over *slots*, one per thread, each taking observed stars (case, star) one at a time from a shared
   atomic counter: the star's pairs' windows vote for both stars of every catalog pair (with
   ``once``, an entry counts only when its previous occurrence lies before the window) in the slot's
   row of N int32 counts (plain loads and stores: the row is the thread's); then the k best (most
   votes, then the lowest catalog row) are kept in registers while the row is cleared for the next
   star: by a second walk over the same entries, each touched count read once (few entries), or by
   a scan of the whole row in catalog order (entries >= N / 2, e.g. V 7 catalogs).

``select`` (step 2), parallel over the cases of a block: strict maximum, the tie-aware candidate
clique (greedy pruning, :func:`_greedy_clique`), duplicate identities (:func:`_drop_duplicates`).

``verify_accept`` (steps 3-5), parallel over cases: verification votes, T, acceptance (fraction rule
or greedy clique) and rejection, from the consistency of the identified pairs.

Memory (bounded, all preallocated by the entry points): vote rows ``slots x N`` int32 with slots =
min(Taichi threads, max(1, max_cells // N), B K); windows ``(B, K, K, 2)`` int32 and observed pairs
``(E, 3)`` int32 + ``(E, 2)`` float64 (E <= B K (K - 1) / 2); candidates ``(2, B, K, k)`` int32;
buckets ``M / 4 + 1`` int32 per pair catalog; candidate cliques ``(b, K m, K m)`` int8 for a block of
b cases (the caller's blocks); verification ``(B, K, K)`` int8.  Nothing grows with the window sizes.
"""

import numpy as np
import taichi as ti

from dualsight.kernels._runtime import KernelCache, ensure_init

__all__ = ["vote_top_k", "bucket_starts", "select_identities", "verify_accept", "n_threads"]

_I8x3 = ti.types.ndarray(dtype=ti.i8, ndim=3)
_I32x1, _I32x2, _I32x3, _I32x4 = (ti.types.ndarray(dtype=ti.i32, ndim=n) for n in (1, 2, 3, 4))
_F64x1, _F64x2, _F64x3 = (ti.types.ndarray(dtype=ti.f64, ndim=n) for n in (1, 2, 3))

_KERNELS = KernelCache()      # builders registered below (and per (k, once) on first use)

# fields of the per-case scratch rows ``work[b, field, node]`` of the clique and duplicate funcs
_SCORE, _MEMBER, _DEG, _LIST, _CHOSEN, _LOSE, _NFIELD = 0, 1, 2, 3, 4, 5, 6


def n_threads() -> int:
    """CPU threads of the Taichi runtime (starts it if needed)."""
    ensure_init()
    from taichi.lang import impl

    return max(1, int(impl.current_cfg().cpu_max_num_threads))


# ============================================================================ Taichi funcs
@ti.func
def _past(v, key, right):
    """Whether angle v lies past the answer of ``searchsorted(., key, side)``: v > key (side "right"),
    v >= key (side "left")."""
    return v > key or (right == 0 and v == key)


@ti.func
def _first_past(arr: ti.template(), lo, hi, key, right):
    """The first index i in [lo, hi) with ``_past(arr[i])`` (``arr`` ascending), hi if none: the
    branch-free lower bound (a fixed number of halvings for a given length, each a conditional move)."""
    base = lo
    n = hi - lo
    if n > 0:
        while n > 1:
            half = n // 2
            base = ti.select(_past(arr[base + half], key, right), base, base + half)
            n -= half
        base += ti.select(_past(arr[base], key, right), 0, 1)
    return base


@ti.func
def _search(angle: ti.template(), starts: ti.template(), inv_w, key, right):
    """numpy ``searchsorted(angle, key, side)`` (side "right" when ``right`` != 0, else "left") on the
    ascending ``angle``: within the buckets around ``key * inv_w`` (``starts``, :func:`bucket_starts`),
    then checked (the answer r has ``angle[r - 1]`` not past the key and ``angle[r]`` past it), else
    over the whole array: exact whatever the rounding of the bucket number."""
    nb = starts.shape[0] - 1
    j = ti.cast(ti.max(ti.min(key * inv_w, ti.cast(nb, ti.f64)), 0.0), ti.i32)
    r = _first_past(angle, starts[ti.max(j - 1, 0)], starts[ti.min(j + 2, nb)], key, right)
    M = angle.shape[0]
    ok = True
    if r > 0:
        if _past(angle[r - 1], key, right):
            ok = False
    if r < M:
        if not _past(angle[r], key, right):
            ok = False
    if not ok:
        r = _first_past(angle, 0, M, key, right)
    return r


@ti.func
def _keep_best(ids: ti.template(), cs: ti.template(), s, v, k: ti.template()):
    """Offer catalog row ``s`` with ``v`` votes to the best-``k`` list (ids, cs), sorted by votes descending,
    ties to the lower row; one bubble pass upwards.  Rows offered in ascending order (the whole-row scan)
    never displace an equal count, so both vote walks keep exactly the numpy stage's candidates."""
    if v > cs[k - 1] or (v == cs[k - 1] and v > 0 and s < ids[k - 1]):
        ids[k - 1] = s
        cs[k - 1] = v
        for j in ti.static(range(k - 1, 0, -1)):
            if cs[j] > cs[j - 1] or (cs[j] == cs[j - 1] and ids[j] < ids[j - 1]):
                i_j = ids[j]
                c_j = cs[j]
                ids[j] = ids[j - 1]
                cs[j] = cs[j - 1]
                ids[j - 1] = i_j
                cs[j - 1] = c_j


@ti.func
def _greedy_clique(cons: ti.template(), work: ti.template(), b, n, nn):
    """Greedy pruning of :func:`dualsight.nav.cliques.greedy_clique` for case b of ``n`` nodes:
    ``cons[b, u, v]`` (i8, symmetric, 0 on the diagonal; read only between the ``nn`` nodes listed,
    ascending, in ``work[b, _LIST, :nn]``, the others have no consistent partner), the tie-break
    ``work[b, _SCORE, u]``; the members are left in ``work[b, _MEMBER, :n]`` (1 = member).  Start
    from the nodes with a consistent partner; while a member is inconsistent with another member,
    drop every member consistent with no member, or, if there is none, the member with the fewest
    consistent members (then the lowest score, then the highest index); at most n passes.  The
    members are kept as an ascending list (``work[b, _LIST, :size]``): a pass costs O(size^2)."""
    for u in range(n):
        work[b, _MEMBER, u] = 0
    size = 0
    for i in range(nn):
        u = work[b, _LIST, i]
        any_c = 0
        for j in range(nn):
            if cons[b, u, work[b, _LIST, j]] != 0:
                any_c = 1
        if any_c != 0:
            work[b, _MEMBER, u] = 1
            work[b, _LIST, size] = u                # size <= i: the list is compacted in place
            size += 1
    for _it in range(n):
        todo = 0
        for i in range(size):
            u = work[b, _LIST, i]
            d = 0
            for j in range(size):
                d += ti.cast(cons[b, u, work[b, _LIST, j]], ti.i32)
            work[b, _DEG, i] = d
            if d < size - 1:
                todo = 1
        if todo == 0:
            break
        kept = 0
        for i in range(size):                       # drop the lonely members (no consistent member)
            u = work[b, _LIST, i]
            d = work[b, _DEG, i]
            if d == 0:
                work[b, _MEMBER, u] = 0
            else:
                work[b, _LIST, kept] = u
                work[b, _DEG, kept] = d
                kept += 1
        if kept == size:                            # none lonely: drop the weakest member
            best = 0
            bd = work[b, _DEG, 0]
            bs = work[b, _SCORE, work[b, _LIST, 0]]
            for i in range(1, size):
                d = work[b, _DEG, i]
                sc = work[b, _SCORE, work[b, _LIST, i]]
                if d < bd or (d == bd and sc <= bs):   # ties: the later (higher) index
                    best = i
                    bd = d
                    bs = sc
            work[b, _MEMBER, work[b, _LIST, best]] = 0
            for i in range(best, size - 1):
                work[b, _LIST, i] = work[b, _LIST, i + 1]
            kept = size - 1
        size = kept


@ti.func
def _drop_duplicates(ids: ti.template(), top: ti.template(), work: ti.template(), b, bl, K, use_chosen):
    """:func:`dualsight.nav.candidates.drop_duplicates` for case b (``ids[0, b]``, ``top[1, b]``;
    scratch row ``bl``): an identity claimed by several stars stays only with the claimant of strictly
    highest priority, ``(work[bl, _CHOSEN, x], top)`` with ``use_chosen`` != 0, else ``top``."""
    for x in range(K):
        lx = 0
        ix = ids[0, b, x]
        if ix >= 0:
            cx = 0
            if use_chosen != 0:
                cx = work[bl, _CHOSEN, x]
            tx = top[1, b, x]
            for y in range(K):
                if y != x and ids[0, b, y] == ix:
                    cy = 0
                    if use_chosen != 0:
                        cy = work[bl, _CHOSEN, y]
                    if cy > cx or (cy == cx and top[1, b, y] >= tx):
                        lx = 1
        work[bl, _LOSE, x] = lx
    for x in range(K):
        if work[bl, _LOSE, x] != 0:
            ids[0, b, x] = -1


# ============================================================================ kernels (built lazily)
def _build_vote(k: int, once: bool):
    @ti.kernel
    def vote(pq: _I32x2, keys: _F64x2, angle: _F64x1, starts: _I32x1, inv_w: ti.f64, win: _I32x4,
             stars1: _I32x1, prev: _I32x1, table: _I32x2, counter: _I32x1, out: _I32x4):
        # 1. the window of every observed pair (case, p < q)
        for e in range(pq.shape[0]):
            lo = _search(angle, starts, inv_w, keys[e, 0], 1)      # angle > d - tol
            hi = _search(angle, starts, inv_w, keys[e, 1], 0)      # angle >= d + tol ends it
            c = ti.max(hi - lo, 0)
            b = pq[e, 0]
            p = pq[e, 1]
            q = pq[e, 2]
            win[b, p, q, 0] = lo
            win[b, p, q, 1] = c
            win[b, q, p, 0] = lo
            win[b, q, p, 1] = c
        # 2. the votes of every observed star, one slot (a row of N counts) per thread
        B = win.shape[0]
        K = win.shape[1]
        N = table.shape[1]
        R = B * K
        ti.loop_config(block_dim=1)
        for sl in range(table.shape[0]):
            while True:
                r = ti.atomic_add(counter[0], 1)
                if r >= R:
                    break
                b = r // K
                x = r % K
                n_e = 0
                for y in range(K):                   # count
                    c = win[b, x, y, 1]
                    if c > 0:
                        l = win[b, x, y, 0]
                        n_e += 2 * c
                        for e in range(2 * l, 2 * (l + c)):
                            # a plain load and store: the row is this thread's (``+=`` would be atomic)
                            s = stars1[e] - 1
                            if ti.static(once):
                                if prev[e] < l:              # the star's first pair in the window
                                    table[sl, s] = table[sl, s] + 1
                            else:
                                table[sl, s] = table[sl, s] + 1
                ids = ti.Vector([-1] * k, dt=ti.i32)
                cs = ti.Vector([0] * k, dt=ti.i32)
                if 2 * n_e >= N:
                    # many entries per catalog star: scan the whole row, ascending (a tie never displaces
                    # the lower row already kept), clear it
                    for s in range(N):
                        v = table[sl, s]
                        if v != 0:
                            table[sl, s] = 0
                            _keep_best(ids, cs, s, v, k)
                else:
                    # few entries: read each touched count once (then clear it), keep the k best
                    for y in range(K):
                        c = win[b, x, y, 1]
                        if c > 0:
                            l = win[b, x, y, 0]
                            for e in range(2 * l, 2 * (l + c)):
                                s = stars1[e] - 1
                                v = table[sl, s]
                                table[sl, s] = 0
                                _keep_best(ids, cs, s, v, k)
                for j in ti.static(range(k)):
                    out[0, b, x, j] = ids[j]
                    out[1, b, x, j] = cs[j]
    return vote


def _build_select(_dtype=None):
    @ti.kernel
    def select(cand: _I32x4, b0: ti.i32, m: ti.i32, unique: ti.i32, cos_cat: _F64x3, c_lo: _F64x3,
               c_hi: _F64x3, cons: _I8x3, work: _I32x3, out: _I32x3):
        K = cand.shape[2]
        for bl in range(cos_cat.shape[0]):           # one case of the block
            b = b0 + bl
            for x in range(K):
                ok1 = 0
                if unique != 0:
                    if cand[1, b, x, 0] > cand[1, b, x, 1]:
                        ok1 = 1
                elif cand[0, b, x, 0] >= 0:
                    ok1 = 1
                out[0, b, x] = -1
                out[1, b, x] = 0
                if ok1 != 0:
                    out[0, b, x] = cand[0, b, x, 0]
                    out[1, b, x] = cand[1, b, x, 0]
            if m > 1:
                n = K * m
                nn = 0
                for u in range(n):                    # nodes (star x, candidate j), u = x m + j
                    if cand[0, b, u // m, u % m] >= 0:   # those with a candidate
                        work[bl, _LIST, nn] = u
                        work[bl, _SCORE, u] = cand[1, b, u // m, u % m]
                        nn += 1
                for i in range(nn):                   # their consistency (different stars only)
                    u = work[bl, _LIST, i]
                    x = u // m
                    for j in range(nn):
                        w = work[bl, _LIST, j]
                        y = w // m
                        cc = 0
                        if x != y:
                            cs = cos_cat[bl, u, w]
                            if cs > c_lo[bl, x, y]:
                                if cs < c_hi[bl, x, y]:
                                    cc = 1
                        cons[bl, u, w] = ti.i8(cc)
                _greedy_clique(cons, work, bl, n, nn)
                for x in range(K):
                    ch = 0
                    for j in range(m):
                        if ch == 0 and work[bl, _MEMBER, x * m + j] != 0:
                            ch = 1
                            out[0, b, x] = cand[0, b, x, j]
                            out[1, b, x] = cand[1, b, x, j]
                    work[bl, _CHOSEN, x] = ch
                _drop_duplicates(out, out, work, b, bl, K, 1)     # priority: chosen, then votes
            if unique != 0:
                _drop_duplicates(out, out, work, b, bl, K, 0)
            for x in range(K):
                if out[0, b, x] < 0:
                    out[1, b, x] = 0
    return select


def _build_verify_accept(_dtype=None):
    @ti.kernel
    def verify_accept(cons: _I8x3, top: _I32x2, clique: ti.i32, frac: ti.f64, min_acc: ti.i32, work: _I32x3,
                      out_k: _I32x3, out_b: _I32x2):
        B = cons.shape[0]
        K = cons.shape[1]
        for b in range(B):                           # one case
            t = 0
            for x in range(K):
                c = 0
                for y in range(K):
                    c += ti.cast(cons[b, x, y], ti.i32)
                out_k[0, b, x] = c
                t = ti.max(t, c)
            out_b[0, b] = t
            n_acc = 0
            if clique != 0:
                for x in range(K):
                    work[b, _SCORE, x] = top[b, x]
                    work[b, _LIST, x] = x
                _greedy_clique(cons, work, b, K, K)
                for x in range(K):
                    out_k[1, b, x] = work[b, _MEMBER, x]
                    n_acc += work[b, _MEMBER, x]
            else:
                ft = frac * ti.cast(t, ti.f64)
                for x in range(K):
                    a = 0
                    if out_k[0, b, x] > 0 and ti.cast(out_k[0, b, x], ti.f64) >= ft:
                        a = 1
                    out_k[1, b, x] = a
                    n_acc += a
            rj = 0
            if t > 0 and n_acc < min_acc:
                rj = 1
            out_b[1, b] = rj
    return verify_accept


_KERNELS.builders.update({"select": _build_select, "verify_accept": _build_verify_accept})


def _vote_kernel(k: int, once: bool):
    name = f"vote/{k}/{int(once)}"
    if name not in _KERNELS.builders:
        _KERNELS.builders[name] = lambda _dtype=None: _build_vote(k, once)
    return _KERNELS.get(name)


# ============================================================================ entry points
def bucket_starts(angle: np.ndarray) -> tuple[np.ndarray, float]:
    """Buckets of the sorted catalog angles for :func:`vote_top_k`'s window searches: ``nb = M // 4``
    buckets of equal width w over [0, angle[-1]]; returns ``starts (nb + 1,)`` int32, the first index
    with angle >= j w (``starts[nb]`` = M), and ``1 / w`` (0 when undefined).  Any values give exact
    windows (the kernel checks each answer); these make the searches short.  O(M), once per catalog."""
    angle = np.asarray(angle, np.float64)
    M = angle.size
    nb = max(1, M // 4)
    top = float(angle[-1]) if M else 0.0
    w = top / nb
    inv_w = 1.0 / w if w > 0 and np.isfinite(w) else 0.0
    starts = np.empty(nb + 1, np.int32)
    starts[:nb] = np.searchsorted(angle, np.arange(nb) * w) if M else 0
    starts[nb] = M
    return starts, inv_w


def vote_top_k(case, p, q, lo_key, hi_key, angle, buckets, stars_plus_one, prev, n_slots, k: int, n_cat: int,
               max_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Voting round and each observed star's ``k`` best identities, for the (B, K) star slots.

    case, p, q : (E,) int the observed pairs (case, star slots p < q; p, q < K).
    lo_key, hi_key : (E,) float64 ``d - tol`` and ``d + tol`` (rad) of each pair's observed angle d.
    angle : (M,) float64 catalog pair angles, ascending.  buckets : :func:`bucket_starts` of them.
    stars_plus_one : (>= 2M,) int32 both stars of every catalog pair, interleaved, plus one.
    prev : (>= 2M,) int32 previous pair holding the same star (-1 = none), or None: every catalog
        pair votes (no once-per-pair rule).
    n_slots : (B, K) the shape of the star slots.  k : identities kept per star.
    n_cat : N, the star catalog's size (catalog rows < N).
    max_cells : memory bound of the vote rows: at most max(1, max_cells // N) rows of N int32 (and at
        most one per Taichi thread).
    Returns ``ids (B, K, k)`` int32 (most votes first, ties to the lower row; -1 = none) and
    ``votes (B, K, k)`` int32 (0 = none); a slot without pairs has none.
    """
    B, K = n_slots
    out = np.zeros((2, B, K, k), np.int32)
    out[0] = -1
    E = int(np.size(case))
    M = int(np.size(angle))
    if B == 0 or K == 0 or E == 0 or M == 0 or n_cat == 0:
        return out[0], out[1]
    if M >= 2 ** 30 or B * K >= 2 ** 31 - 1:
        raise ValueError("vote_top_k: catalog pairs < 2^30 and observed stars < 2^31 - 1 (int32 indices)")
    pq = np.empty((E, 3), np.int32)
    pq[:, 0], pq[:, 1], pq[:, 2] = case, p, q
    keys = np.empty((E, 2), np.float64)
    keys[:, 0], keys[:, 1] = lo_key, hi_key
    starts, inv_w = buckets
    win = np.zeros((B, K, K, 2), np.int32)
    slots = max(1, min(B * K, n_threads(), int(max_cells) // int(n_cat)))
    table = np.zeros((slots, int(n_cat)), np.int32)
    once = prev is not None
    prev_arr = np.ascontiguousarray(prev, np.int32) if once else np.zeros(1, np.int32)
    _vote_kernel(int(k), once)(pq, keys, np.ascontiguousarray(angle, np.float64),
                               np.ascontiguousarray(starts, np.int32), float(inv_w), win,
                               np.ascontiguousarray(stars_plus_one, np.int32), prev_arr, table,
                               np.zeros(1, np.int32), out)
    return out[0], out[1]


def select_identities(cand_ids, cand_votes, m: int, unique: bool, blocks=None):
    """Step 2 of geometric voting for a (B, K, k) batch of candidates (:func:`dualsight.nav.candidates.
    assign_identities`).

    cand_ids, cand_votes : (B, K, k) int best candidates, best first (-1 / 0 = none); k >= 2 when
        ``unique``, k >= m.
    m : candidates per star (> 1: the tie-aware clique).  unique : strict maxima, duplicates dropped.
    blocks : with m > 1, an iterable of ``(b0, cos_cat, c_lo, c_hi)`` covering every case once: the
        cases ``b0 .. b0 + nb - 1``, ``cos_cat (nb, K m, K m)`` float64 the catalog cosines of the nodes
        (read only where both nodes have a candidate), ``c_lo, c_hi (nb, K, K)`` float64 the cosine
        bounds of the observed pairs (read only for two used stars p != q).
    Returns ``vote_ids (B, K)`` and ``top (B, K)`` int32.
    """
    B, K, kk = np.shape(cand_ids)
    out = np.zeros((2, B, K), np.int32)
    out[0] = -1
    if B == 0 or K == 0:
        return out[0], out[1]
    if m <= 1 and not unique:                        # the best candidate (the vote kernel's argmax)
        out[0] = cand_ids[..., 0]
        out[1] = cand_votes[..., 0]
        return out[0], out[1]
    cand = np.empty((2, B, K, kk), np.int32)
    cand[0], cand[1] = cand_ids, cand_votes
    kern = _KERNELS.get("select")
    if m <= 1:
        dummy = np.zeros((B, 1, 1))                  # one "block" of all cases, no nodes
        blocks = [(0, dummy, dummy, dummy)]
    n = K * m if m > 1 else 1
    for b0, cos_cat, c_lo, c_hi in blocks:
        nb = cos_cat.shape[0]
        kern(cand, int(b0), int(m), int(bool(unique)), np.ascontiguousarray(cos_cat, np.float64),
             np.ascontiguousarray(c_lo, np.float64), np.ascontiguousarray(c_hi, np.float64),
             np.empty((nb, n, n), np.int8), np.empty((nb, _NFIELD, max(n, K)), np.int32), out)
    return out[0], out[1]


def verify_accept(cons, top, clique: bool, accept_fraction: float, min_accepted: int):
    """Steps 3-5 from the consistency of the identified pairs (:func:`dualsight.nav.verify.verify` and
    :func:`~dualsight.nav.verify.accept`).

    cons : (B, K, K) bool symmetric: stars p != q both identified with matching catalog angle.
    top : (B, K) int voting-round votes of the identities (the clique's tie-break).
    clique : accept the greedy clique, else verification votes >= accept_fraction * T (and > 0).
    Returns ``vv (B, K)`` int32, ``T (B,)`` int32, ``accepted (B, K)`` bool and ``reject (B,)`` bool
    (T > 0 but fewer than ``min_accepted`` accepted).
    """
    cons = np.ascontiguousarray(cons, dtype=bool)
    B, K = cons.shape[:2]
    out_k = np.zeros((2, B, K), np.int32)
    out_b = np.zeros((2, B), np.int32)
    if B and K:
        _KERNELS.get("verify_accept")(cons.view(np.int8), np.ascontiguousarray(top, np.int32), int(bool(clique)),
                                      float(accept_fraction), int(min_accepted),
                                      np.empty((B, _NFIELD, K), np.int32), out_k, out_b)
    return out_k[0], out_b[0], out_k[1].astype(bool), out_b[1].astype(bool)
