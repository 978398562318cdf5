"""Per-case random streams, vectorised over a batch: the exact draws of ``numpy.random.default_rng([seed, i])``.

Every case ``i`` of a run draws its inputs from its own generator, ``default_rng([seed, i])`` (a case never
depends on its batch).  Making B generators one by one costs ~35 us each (SeedSequence hashing and PCG64
seeding in Python calls); this module does the same arithmetic for the whole batch in numpy, bit for bit:

* ``SeedSequence([seed, i]).generate_state(4, uint64)``: O'Neill's seed_seq mixing as numpy implements it
  (``numpy/random/bit_generator.pyx``: ``hashmix``, ``mix``, ``mix_entropy``, ``generate_state``; 32-bit
  words, pool size 4, constants INIT_A, MULT_A, INIT_B, MULT_B, MIX_MULT_L, MIX_MULT_R, XSHIFT);
* PCG64 seeding and steps (O'Neill 2014, "PCG: a family of simple fast space-efficient statistically good
  algorithms for random number generation", setseq 128-bit LCG with the XSL-RR 64-bit output; numpy's
  ``pcg64.h``: ``state = 0; inc = initseq << 1 | 1; step; state += initstate; step``), in 128-bit
  arithmetic on (hi, lo) uint64 pairs;
* ``Generator.uniform(low, high)`` = ``low + (high - low) * ((next >> 11) * 2^-53)`` and
  ``Generator.integers(0, 2**63, dtype=uint64)`` = ``next >> 1`` (Lemire's bounded method with a power-of-two
  range never rejects).

Tests compare every function with numpy's own generators (tests/test_case_rng.py).
"""

from __future__ import annotations

import numpy as np

__all__ = ["seed_states", "Streams", "streams"]

_M32 = np.uint64(0xFFFFFFFF)
_INIT_A, _MULT_A = 0x43B0D7E5, 0x931E8875
_INIT_B, _MULT_B = 0x8B51F9DD, 0x58F38DED
_MIX_L, _MIX_R = 0xCA01F9DD, 0x4973F715
_XSHIFT = 16
_POOL = 4
_PCG_MULT_HI, _PCG_MULT_LO = np.uint64(2549297995355413924), np.uint64(4865540595714422341)


def _words(n: int) -> list[int]:
    """numpy's ``_int_to_uint32_array``: a non-negative int as little-endian 32-bit words ([0] for 0)."""
    if n < 0:
        raise ValueError(f"seeds must be non-negative, got {n}")
    out = [n & 0xFFFFFFFF]
    n >>= 32
    while n:
        out.append(n & 0xFFFFFFFF)
        n >>= 32
    return out


def _u32(x):
    return np.asarray(x, np.uint64) & _M32


def seed_states(seed: int, case_ids: np.ndarray) -> np.ndarray:
    """``SeedSequence([seed, i]).generate_state(4, np.uint64)`` for every ``i``.

    seed : int >= 0.  case_ids : (B,) non-negative integers below 2^32 (one 32-bit word each).
    Returns (B, 4) uint64.
    """
    ids = np.asarray(case_ids, np.int64)
    if ids.size and (ids.min() < 0 or ids.max() >= 2 ** 32):
        raise ValueError("case ids must be in [0, 2^32)")
    B = ids.size
    entropy = [np.full(B, w, np.uint64) for w in _words(int(seed))] + [ids.astype(np.uint64)]
    with np.errstate(over="ignore"):
        hash_const = _INIT_A

        def hashmix(v):
            nonlocal hash_const
            v = _u32(v ^ np.uint64(hash_const))
            hash_const = (hash_const * _MULT_A) & 0xFFFFFFFF
            v = _u32(v * np.uint64(hash_const))
            return v ^ (v >> np.uint64(_XSHIFT))

        def mix(x, y):
            r = _u32(_u32(np.uint64(_MIX_L) * x) - _u32(np.uint64(_MIX_R) * y))
            return r ^ (r >> np.uint64(_XSHIFT))

        zero = np.zeros(B, np.uint64)
        mixer = [hashmix(entropy[i] if i < len(entropy) else zero) for i in range(_POOL)]
        for i_src in range(_POOL):
            for i_dst in range(_POOL):
                if i_src != i_dst:
                    mixer[i_dst] = mix(mixer[i_dst], hashmix(mixer[i_src]))
        for i_src in range(_POOL, len(entropy)):
            for i_dst in range(_POOL):
                mixer[i_dst] = mix(mixer[i_dst], hashmix(entropy[i_src]))
        hash_const = _INIT_B
        state32 = []
        for i_dst in range(8):
            v = _u32(mixer[i_dst % _POOL] ^ np.uint64(hash_const))
            hash_const = (hash_const * _MULT_B) & 0xFFFFFFFF
            v = _u32(v * np.uint64(hash_const))
            state32.append(v ^ (v >> np.uint64(_XSHIFT)))
    return np.stack([state32[2 * k] | (state32[2 * k + 1] << np.uint64(32)) for k in range(4)], axis=1)


def _mul64(a: np.ndarray, b) -> tuple[np.ndarray, np.ndarray]:
    """Full 64 x 64 -> 128-bit product of uint64 arrays: (hi, lo)."""
    b = np.asarray(b, np.uint64)
    a0, a1 = a & _M32, a >> np.uint64(32)
    b0, b1 = b & _M32, b >> np.uint64(32)
    with np.errstate(over="ignore"):
        p00, p01, p10, p11 = a0 * b0, a0 * b1, a1 * b0, a1 * b1
        mid = (p00 >> np.uint64(32)) + (p01 & _M32) + (p10 & _M32)
        hi = p11 + (p01 >> np.uint64(32)) + (p10 >> np.uint64(32)) + (mid >> np.uint64(32))
        lo = a * b
    return hi, lo


class Streams:
    """B independent PCG64 generators, stepped together.  Draws equal those of ``default_rng([seed, i])``
    called in the same order."""

    def __init__(self, seed: int, case_ids: np.ndarray):
        v = seed_states(seed, case_ids)
        init_hi, init_lo, seq_hi, seq_lo = v[:, 0], v[:, 1], v[:, 2], v[:, 3]
        # inc = (initseq << 1) | 1 over 128 bits
        self.inc_hi = (seq_hi << np.uint64(1)) | (seq_lo >> np.uint64(63))
        self.inc_lo = (seq_lo << np.uint64(1)) | np.uint64(1)
        self.hi = np.zeros_like(init_hi)
        self.lo = np.zeros_like(init_lo)
        self._step()
        with np.errstate(over="ignore"):
            lo = self.lo + init_lo
            self.hi = self.hi + init_hi + (lo < self.lo).astype(np.uint64)
            self.lo = lo
        self._step()

    def _step(self):
        """state = state * MULT + inc (mod 2^128)."""
        with np.errstate(over="ignore"):
            hi, lo = _mul64(self.lo, _PCG_MULT_LO)
            hi = hi + self.lo * _PCG_MULT_HI + self.hi * _PCG_MULT_LO
            lo2 = lo + self.inc_lo
            self.hi = hi + self.inc_hi + (lo2 < lo).astype(np.uint64)
            self.lo = lo2

    def next_uint64(self) -> np.ndarray:
        """(B,) uint64: one raw 64-bit output per stream (XSL-RR of the stepped state)."""
        self._step()
        x = self.hi ^ self.lo
        r = self.hi >> np.uint64(58)
        return (x >> r) | (x << ((np.uint64(64) - r) & np.uint64(63)))

    def random(self) -> np.ndarray:
        """(B,) float64, ``Generator.random()``: U[0, 1) with 53 random bits, (next >> 11) * 2^-53."""
        return (self.next_uint64() >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)

    def uniform(self, low: float, high: float) -> np.ndarray:
        """(B,) float64, ``Generator.uniform(low, high)``: low + (high - low) * U[0, 1) with 53 random bits."""
        return low + (high - low) * self.random()

    def integers_63(self) -> np.ndarray:
        """(B,) uint64, ``Generator.integers(0, 2**63, dtype=np.uint64)``."""
        return self.next_uint64() >> np.uint64(1)


def streams(seed: int, case_ids: np.ndarray) -> Streams:
    """The generators ``default_rng([seed, i])`` of every case ``i`` in ``case_ids``."""
    return Streams(int(seed), case_ids)
