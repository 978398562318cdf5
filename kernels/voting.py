"""Geometric voting (Kolomenkin et al. 2008) as Taichi CPU kernels, batched over cases (a leaf: arrays in,
arrays out).

The counting, selecting and comparing of the star identification chain of :mod:`dualsight.nav.starid`
(``engine="taichi"``).  Every floating-point value a decision reads (observed and catalog angles, window
keys, cosine bounds, catalog cosines) is computed by the caller with numpy and passed in, so the kernels
only compare and count: their results are bit for bit those of the numpy stages
(:mod:`dualsight.nav.votes`, :mod:`~dualsight.nav.candidates`, :mod:`~dualsight.nav.verify`), whatever
the number of threads or the order in which they take the work.

Kernels (built lazily, once per process, through :class:`~dualsight.kernels.taichi_runtime.KernelCache`):

``vote/<k>/<once>/<serial pairs><serial slots>`` (step 1; k = identities kept per star, once = one vote per
observed pair), two loops, each parallel unless the call is small (:func:`_vote_kernel`):

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

Steps 2-5 (candidate selection, verification, acceptance) are in :mod:`dualsight.kernels.voting_select`.

Memory (bounded, all preallocated by the entry points): vote rows ``slots x N`` int32 with slots =
min(Taichi threads, max(1, max_cells // N), B K); windows ``(B, K, K, 2)`` int32 and observed pairs
``(E, 3)`` int32 + ``(E, 2)`` float64 (E <= B K (K - 1) / 2); candidates ``(2, B, K, k)`` int32;
buckets ``M / 4 + 1`` int32 per pair catalog; candidate cliques ``(b, K m, K m)`` int8 for a block of
b cases (the caller's blocks); verification ``(B, K, K)`` int8.  Nothing grows with the window sizes.
"""

import numpy as np
import taichi as ti

from dualsight.kernels.taichi_runtime import TASK_ITEMS, KernelCache, ensure_init

__all__ = ["vote_top_k", "bucket_starts", "n_threads"]

_I32x1, _I32x2, _I32x4 = (ti.types.ndarray(dtype=ti.i32, ndim=n) for n in (1, 2, 4))
_F64x1, _F64x2 = (ti.types.ndarray(dtype=ti.f64, ndim=n) for n in (1, 2))

_KERNELS = KernelCache()      # builders registered below (and per (k, once) on first use)


_THREADS: list = []       # [threads] once read: Taichi is initialised once per process (~60 us to read the config)


def n_threads() -> int:
    """CPU threads of the Taichi runtime (starts it if needed)."""
    if not _THREADS:
        ensure_init()
        from taichi.lang import impl

        _THREADS.append(max(1, int(impl.current_cfg().cpu_max_num_threads)))
    return _THREADS[0]


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
    ties to the lower row; one bubble pass upwards (the walk over the touched counts, in any row order; the
    whole-row scan offers rows in ascending order, where an equal count never displaces, and inserts only counts
    above the last kept one: the same lists, without a branch per row)."""
    if v > cs[k - 1] or (v == cs[k - 1] and v > 0 and s < ids[k - 1]):
        _insert(ids, cs, s, v, k)


@ti.func
def _insert(ids: ti.template(), cs: ti.template(), s, v, k: ti.template()):
    """Put catalog row ``s`` with ``v`` votes in the best-``k`` list's last place and bubble it up (more votes first,
    ties to the lower row)."""
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


# ============================================================================ kernels (built lazily)
def _build_vote(k: int, once: bool, serial_pairs: bool = False, serial_slots: bool = False):
    @ti.kernel
    def vote(pq: _I32x2, keys: _F64x2, angle: _F64x1, starts: _I32x1, inv_w: ti.f64, win: _I32x4,
             stars1: _I32x1, prev: _I32x1, table: _I32x2, counter: _I32x1, out: _I32x4):
        # 1. the window of every observed pair (case, p < q)
        ti.loop_config(serialize=serial_pairs)
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
        ti.loop_config(serialize=serial_slots)
        for t in range(table.shape[0] * TASK_ITEMS):          # slot t // TASK_ITEMS, one per Taichi task
            if t % TASK_ITEMS != 0:
                continue
            sl = t // TASK_ITEMS
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
                            if ti.static(once):              # + 1 where the star's first pair in the window:
                                # branch-free (the test is ~random; a branch took ~1.4x the time)
                                table[sl, s] = table[sl, s] + ti.cast(prev[e] < l, ti.i32)
                            else:
                                table[sl, s] = table[sl, s] + 1
                ids = ti.Vector([-1] * k, dt=ti.i32)
                cs = ti.Vector([0] * k, dt=ti.i32)
                if 2 * n_e >= N:
                    # many entries per catalog star: scan the whole row, ascending (a tie never displaces
                    # the lower row already kept), clear it
                    for s in range(N):
                        v = table[sl, s]
                        table[sl, s] = 0
                        if v > cs[k - 1]:        # ascending rows: a tie never displaces, only more votes do
                            _insert(ids, cs, s, v, k)
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


SERIAL_MAX_PAIRS = 4096
"""The window searches of at most this many observed pairs run serially (a single frame's: 66-300 pairs)."""


def _vote_kernel(k: int, once: bool, serial_pairs: bool = False, serial_slots: bool = False):
    """The vote kernel; ``serial_pairs`` / ``serial_slots``: its first / second loop serial (small calls: a
    parallel loop's launch is a thread-pool round trip, :class:`~dualsight.kernels.taichi_runtime.KernelCache`)."""
    name = f"vote/{k}/{int(once)}/{int(serial_pairs)}{int(serial_slots)}"
    if name not in _KERNELS.builders:
        _KERNELS.builders[name] = lambda _dtype=None: _build_vote(k, once, serial_pairs, serial_slots)
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
               max_cells: int, window_counts: bool = False) -> tuple[np.ndarray, ...]:
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
    ``votes (B, K, k)`` int32 (0 = none); a slot without pairs has none; with ``window_counts`` also
    ``(E,)`` int64 the size of each pair's window (the catalog pairs it voted with).
    """
    B, K = n_slots
    out = np.zeros((2, B, K, k), np.int32)
    out[0] = -1
    E = int(np.size(case))
    M = int(np.size(angle))
    if B == 0 or K == 0 or E == 0 or M == 0 or n_cat == 0:
        return (out[0], out[1], np.zeros(E, np.int64)) if window_counts else (out[0], out[1])
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
    kern = _vote_kernel(int(k), once, E <= SERIAL_MAX_PAIRS, slots == 1)
    kern(pq, keys, np.ascontiguousarray(angle, np.float64), np.ascontiguousarray(starts, np.int32), float(inv_w), win,
         np.ascontiguousarray(stars_plus_one, np.int32), prev_arr, table, np.zeros(1, np.int32), out)
    if window_counts:
        return out[0], out[1], win[case, p, q, 1].astype(np.int64)
    return out[0], out[1]
