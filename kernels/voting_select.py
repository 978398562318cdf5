"""Steps 2-5 of geometric voting (Kolomenkin et al. 2008) as Taichi CPU kernels, batched over cases (a leaf:
arrays in, arrays out); step 1, the vote counting, is :mod:`dualsight.kernels.voting`.

Bit for bit the numpy stages :mod:`dualsight.nav.candidates` and :mod:`dualsight.nav.verify`: every
floating-point value a decision reads (catalog cosines, cosine bounds of the observed pairs) is computed by
the caller with numpy; the kernels only compare and count.

``select`` (step 2), parallel over the cases of a block: strict maximum, the tie-aware candidate clique
(greedy pruning, :func:`_greedy_clique`), duplicate identities (:func:`_drop_duplicates`).

``verify_accept`` (steps 3-5), parallel over cases: verification votes, T, acceptance (fraction rule or
greedy clique) and rejection, from the consistency of the identified pairs.

Memory: candidate cliques ``(b, K m, K m)`` int8 for a block of b cases (the caller's blocks); verification
``(B, K, K)`` int8; scratch ``(B, 7, max(K m, K))`` int32.
"""

import numpy as np
import taichi as ti

from dualsight.kernels.taichi_runtime import KernelCache, task_stride

__all__ = ["select_identities", "verify_accept"]

_I8x3 = ti.types.ndarray(dtype=ti.i8, ndim=3)
_I32x2, _I32x3, _I32x4 = (ti.types.ndarray(dtype=ti.i32, ndim=n) for n in (2, 3, 4))
_F64x3 = ti.types.ndarray(dtype=ti.f64, ndim=3)

# fields of the per-case scratch rows ``work[b, field, node]`` of the clique and duplicate funcs
_SCORE, _MEMBER, _DEG, _LIST, _CHOSEN, _LOSE, _NFIELD = 0, 1, 2, 3, 4, 5, 6


# ============================================================================ Taichi funcs
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
def _build_select(_dtype=None, serial: bool = False):
    @ti.kernel
    def select(cand: _I32x4, b0: ti.i32, m: ti.i32, unique: ti.i32, cos_cat: _F64x3, c_lo: _F64x3,
               c_hi: _F64x3, cons: _I8x3, work: _I32x3, out: _I32x3, stride: ti.i32):
        K = cand.shape[2]
        ti.loop_config(serialize=serial)
        for it in range(cos_cat.shape[0] * stride):  # one case of the block per ``stride`` (task_stride)
            if it % stride != 0:
                continue
            bl = it // stride
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


def _build_verify_accept(_dtype=None, serial: bool = False):
    @ti.kernel
    def verify_accept(cons: _I8x3, top: _I32x2, clique: ti.i32, frac: ti.f64, min_acc: ti.i32, work: _I32x3,
                      out_k: _I32x3, out_b: _I32x2, stride: ti.i32):
        B = cons.shape[0]
        K = cons.shape[1]
        ti.loop_config(serialize=serial)
        for it in range(B * stride):                 # one case per ``stride`` (task_stride)
            if it % stride != 0:
                continue
            b = it // stride
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


_KERNELS = KernelCache({"select": _build_select, "verify_accept": _build_verify_accept})


# ============================================================================ entry points
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
    kern = _KERNELS.get("select", serial=B == 1)                     # one case: no thread-pool round trip
    if m <= 1:
        dummy = np.zeros((B, 1, 1))                  # one "block" of all cases, no nodes
        blocks = [(0, dummy, dummy, dummy)]
    n = K * m if m > 1 else 1
    for b0, cos_cat, c_lo, c_hi in blocks:
        nb = cos_cat.shape[0]
        kern(cand, int(b0), int(m), int(bool(unique)), np.ascontiguousarray(cos_cat, np.float64),
             np.ascontiguousarray(c_lo, np.float64), np.ascontiguousarray(c_hi, np.float64),
             np.empty((nb, n, n), np.int8), np.empty((nb, _NFIELD, max(n, K)), np.int32), out, task_stride(nb))
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
        kern = _KERNELS.get("verify_accept", serial=B == 1)         # one case: no thread-pool round trip
        kern(cons.view(np.int8), np.ascontiguousarray(top, np.int32), int(bool(clique)), float(accept_fraction),
             int(min_accepted), np.empty((B, _NFIELD, K), np.int32), out_k, out_b, task_stride(B))
    return out_k[0], out_b[0], out_k[1].astype(bool), out_b[1].astype(bool)
