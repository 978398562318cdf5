"""The frame digest stored in each row (kernels/digest.py) against an independent pure-Python definition,
the published splitmix64 outputs, and the sparse star path against the dense one."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from dualsight.kernels.digest import frame_digest, frame_digest_taichi, patch_digest, splitmix64, to_int64

M64 = (1 << 64) - 1


def ref_splitmix(i: int) -> int:
    """splitmix64 as published (Steele et al. 2014; Vigna's splitmix64.c), Python integers."""
    z = (i * 0x9E3779B97F4A7C15 + 0x9E3779B97F4A7C15) & M64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & M64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & M64
    return z ^ (z >> 31)


def ref_digest(frame: np.ndarray, sky) -> int:
    """The module docstring's formula, pixel by pixel with Python integers (tiny frames only)."""
    bits = {2: np.uint16, 4: np.uint32, 1: np.uint8, 8: np.uint64}[frame.dtype.itemsize]
    u = frame.ravel().view(bits) if frame.dtype.kind == "f" else frame.ravel()
    s = int(np.asarray(sky, frame.dtype).reshape(1).view(bits)[0]) if frame.dtype.kind == "f" else int(sky)
    return sum(((int(v) - s) & M64) * ref_splitmix(p) for p, v in enumerate(u)) & M64


def test_splitmix64_gives_the_published_sequence():
    # first outputs of splitmix64 seeded with 0 (Vigna's reference implementation)
    assert [int(v) for v in splitmix64(np.arange(3))] == [0xE220A8397B1DCDAF, 0x6E789E6AA1B965F4,
                                                          0x06C45D188009454F]


DIGESTS = pytest.mark.parametrize("digest", [frame_digest, frame_digest_taichi], ids=["numpy", "taichi"])


@DIGESTS
@settings(max_examples=40, deadline=None)
@given(arrays(np.uint16, st.tuples(st.integers(1, 3), st.integers(1, 9), st.integers(1, 9))),
       st.integers(0, 65535))
def test_digest_of_uint16_frames_matches_the_definition(digest, frames, sky):
    got = digest(frames, np.uint16(sky))
    assert [int(v) for v in got] == [ref_digest(f, sky) for f in frames]


@DIGESTS
@settings(max_examples=25, deadline=None)
@given(arrays(np.float32, st.tuples(st.just(2), st.integers(1, 7), st.integers(1, 7)),
              elements=st.floats(0, 4000, width=32)))
def test_digest_of_float32_frames_matches_the_definition(digest, frames):
    got = digest(frames, np.float32(100.0))
    assert [int(v) for v in got] == [ref_digest(f, np.float32(100.0)) for f in frames]


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint32, np.float64])
def test_taichi_digest_of_other_types_and_colour_frames_matches_the_definition(dtype):
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 200, (2, 5, 6, 3)).astype(dtype)       # colour: channels innermost in p
    sky = dtype(7)
    assert [int(v) for v in frame_digest_taichi(frames, sky)] == [ref_digest(f, sky) for f in frames]
    assert [int(v) for v in frame_digest_taichi(frames[..., 0], sky)] == [ref_digest(f, sky) for f in frames[..., 0]]


def test_any_changed_or_moved_pixel_changes_the_digest():
    f = np.random.default_rng(0).integers(0, 4096, (1, 64, 80), dtype=np.uint16)
    d0 = frame_digest(f)[0]
    g = f.copy()
    g[0, 10, 20] += 1
    assert frame_digest(g)[0] != d0
    h = f.copy()
    h[0, 3, 4], h[0, 4, 3] = f[0, 4, 3], f[0, 3, 4]
    assert f[0, 3, 4] != f[0, 4, 3] and frame_digest(h)[0] != d0
    assert to_int64(frame_digest(f)).dtype == np.int64


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_patches_on_a_constant_sky_give_the_whole_frame_digest(dtype):
    from dualsight.kernels.digest import patch_digest_taichi

    rng = np.random.default_rng(1)
    H, W, sky = 40, 50, dtype(7)
    frames = np.full((2, H, W), sky, dtype)
    boxes = np.array([[3, 9, 2, 6], [20, 31, 10, 25], [0, 4, 30, 40]])
    frame_of = np.array([0, 0, 1])
    vals = []
    for (c0, c1, r0, r1), b in zip(boxes, frame_of):
        v = (rng.integers(0, 999, (r1 - r0, c1 - c0)) * (0.37 if dtype is np.float32 else 1)).astype(dtype)
        frames[b, r0:r1, c0:c1] = v
        vals.append(v.ravel())
    poff = np.concatenate([[0], np.cumsum([len(v) for v in vals])])
    want = [ref_digest(f, sky) for f in frames]
    got = patch_digest(np.concatenate(vals), poff, boxes, frame_of, 2, W, sky)
    assert [int(v) for v in got] == want
    got_ti = patch_digest_taichi(np.concatenate(vals).astype(np.float32), dtype, poff, boxes, frame_of, 2, W, sky)
    assert [int(v) for v in got_ti] == want


def test_sparse_star_path_stores_the_digest_of_the_dense_frame():
    from dualsight.jobs.kinds import star

    spec, _ = star.resolve("paper", None, seed=5, cases=12)
    ctx = star.make_context(spec)
    ids = np.arange(12)
    sparse = star.compute_batch(spec, ctx, ids)
    dense = star.compute_batch(spec, ctx, ids, keep_images=True)
    assert sparse["rendered"].images is None and dense["rendered"].images is not None
    imgs = dense["rendered"].images
    sky = np.asarray(spec.sensor.empty_pixel_adu()).astype(imgs.dtype)
    want = [ref_digest_fast(f, sky) for f in imgs]
    assert [int(v) for v in sparse["rendered"].digest] == want
    col = sparse["tables"]["star_cases"].column("image_digest").to_numpy()
    assert [int(v) for v in col.view(np.uint64)] == want


def ref_digest_fast(frame: np.ndarray, sky) -> int:
    """The definition on a full frame: only non-sky pixels contribute (Python ints over those pixels)."""
    u = frame.ravel()
    nz = np.flatnonzero(u != sky)
    return sum(((int(u[p]) - int(sky)) & M64) * ref_splitmix(int(p)) for p in nz) & M64


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
