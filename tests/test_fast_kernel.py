"""The short kernel launcher (kernels/taichi_runtime.py FastKernel): the kernel must see exactly the arguments
Taichi's own launcher would give it, call after call, with new arrays, shapes and scalars each time."""

import numpy as np
import pytest

from dualsight.kernels import taichi_runtime


def _cache():
    ti = taichi_runtime.ensure_init()
    I32, F64x2, U64 = (ti.types.ndarray(dtype=d, ndim=n) for d, n in ((ti.i32, 1), (ti.f64, 2), (ti.u64, 1)))

    def build(dtype=None):
        @ti.kernel
        def affine(a: I32, m: F64x2, s: ti.f64, n: ti.i32, bits: U64, out: F64x2):
            # out[i, j] = a[i] * s + m[i, j] + n + popcount-free check of the u64 array: bits[i] & 7
            for i, j in out:
                out[i, j] = ti.cast(a[i], ti.f64) * s + m[i, j] + ti.cast(n, ti.f64) + ti.cast(bits[i] & 7, ti.f64)
        return affine

    cache = taichi_runtime.KernelCache()
    cache.builders["affine"] = build
    return cache


def _expected(a, m, s, n, bits):
    return a[:, None].astype(np.float64) * s + m + n + (bits & 7).astype(np.float64)[:, None]


def _args(rng, rows, cols):
    """Integer-valued floats: every result is exact, whatever order (or fused multiply-add) the kernel uses."""
    return (rng.integers(-1000, 1000, rows).astype(np.int32), rng.integers(-10**6, 10**6, (rows, cols)) / 4.0,
            float(rng.integers(-100, 100)), int(rng.integers(-50, 50)), rng.integers(0, 2 ** 63, rows, dtype=np.uint64))


def test_fast_launches_equal_numpy_call_after_call():
    k = _cache().get("affine")
    assert isinstance(k, taichi_runtime.FastKernel)
    rng = np.random.default_rng(3)
    for call, (rows, cols) in enumerate([(5, 3), (17, 4), (1, 9), (40, 2), (17, 4)]):
        a, m, s, n, bits = _args(rng, rows, cols)
        out = np.full((rows, cols), np.nan)
        k(a, m, s, n, bits, out)
        np.testing.assert_array_equal(out, _expected(a, m, s, n, bits), err_msg=f"call {call}")
        if call == 0:                    # the first call planned the signature: later ones skip Taichi's launcher
            assert any(p for p in k._plans.values())


def test_planned_calls_do_not_go_through_taichis_launcher():
    k = _cache().get("affine")
    rng = np.random.default_rng(4)
    a, m, s, n, bits = _args(rng, 6, 3)
    k(a, m, s, n, bits, np.empty((6, 3)))

    def refuse(*args):
        raise AssertionError("Taichi's launcher was used for a planned signature")

    taichi_launcher, k.kernel = k.kernel, refuse
    try:
        a, m, s, n, bits = _args(rng, 8, 2)
        out = np.empty((8, 2))
        k(a, m, s, n, bits, out)
        np.testing.assert_array_equal(out, _expected(a, m, s, n, bits))
        with pytest.raises(AssertionError, match="launcher was used"):   # a new signature: Taichi's launcher
            k(a.astype(np.int64), m, s, n, bits, out)
    finally:
        k.kernel = taichi_launcher


def test_unplanned_arguments_take_taichis_launcher():
    k = _cache().get("affine")
    rng = np.random.default_rng(5)
    a, m, s, n, bits = _args(rng, 7, 5)
    k(a, m, s, n, bits, np.empty((7, 5)))
    out_f = np.asfortranarray(np.zeros((7, 5)))          # not C-contiguous: Taichi copies it in and back out
    k(a, np.asfortranarray(m), s, n, bits, out_f)
    np.testing.assert_array_equal(out_f, _expected(a, m, s, n, bits))
    with pytest.raises(Exception):                       # Taichi's own type check, not a silent launch
        k(a.astype(np.float32), m, s, n, bits, np.empty((7, 5)))


def test_launcher_switch(monkeypatch):
    monkeypatch.setenv("DUALSIGHT_TI_LAUNCHER", "taichi")
    k = _cache().get("affine")
    assert not isinstance(k, taichi_runtime.FastKernel)
    rng = np.random.default_rng(6)
    a, m, s, n, bits = _args(rng, 4, 4)
    out = np.empty((4, 4))
    k(a, m, s, n, bits, out)
    np.testing.assert_array_equal(out, _expected(a, m, s, n, bits))


def test_read_only_and_empty_arrays_pass_through_the_short_launcher():
    """An array the buffer protocol will not export writable (read-only: a cached catalog array) and an empty one
    take the other address route; the kernel still reads the right values (and an empty output stays empty)."""
    k = _cache().get("affine")
    rng = np.random.default_rng(5)
    a, m, s, n, bits = _args(rng, 6, 3)
    k(a, m, s, n, bits, np.empty((6, 3)))                       # plan the signature
    for frozen in ("a", "m", "bits"):
        args = dict(a=a.copy(), m=m.copy(), bits=bits.copy())
        args[frozen].flags.writeable = False
        out = np.full((6, 3), np.nan)
        k(args["a"], args["m"], s, n, args["bits"], out)
        np.testing.assert_array_equal(out, _expected(a, m, s, n, bits), err_msg=frozen)
    empty = np.empty((0, 3))
    k(a[:0], m[:0], s, n, bits[:0], empty)
    assert empty.shape == (0, 3)
