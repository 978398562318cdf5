"""The streak model of examples/star/track.toml (``nav.smear_weights.along_gain``, ``streak_psf_sigma_px``,
``smear_sigma_per_px``) against streaked stars rendered and detected by the ``realistic`` preset's own renderer and
local detector.

Truth: each rendered star's true pixel at the frame's attitude (the camera model on the catalog vector, the drawn
attitude) and its streak over the 100 ms exposure from the attitudes at +-50 ms, each a Rodrigues rotation of the
frame's by the true body rate (helpers.rotation, not the code's exponential map or pixel Jacobian); detections
paired with the true stars by nearest neighbour (within 1.5 px, both ways unique).  The along-streak error over
the sigma the model states must have an RMS near 1 on 4-9 px streaks, where the detector's own round-PSF sigma
states 0.5-0.65 of it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dualsight.nav.tracking_config import TrackingConfig
from dualsight.jobs.kinds import star_track
from dualsight.nav.smear_weights import along_gain
from helpers import rotation

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def streaks():
    d, _ = star_track.resolve_spec(None, ROOT / "examples" / "star" / "track.toml", seed=77)
    d["sequence"].update(frames=10, motion="constant", rate_max_deg_s=1.2, blinded=0, dropped=0)
    spec = star_track.spec_from_dict(d)
    ctx = star_track.make_context(spec)
    cam = spec.star.camera
    T = spec.sequence.exposure_s
    rows = []
    cases = [c for c in range(60) if star_track.draw_sequence(spec, c)["rate_deg_s"] > 0.85][:3]
    assert len(cases) == 3
    for c in cases:
        draw = star_track.draw_sequence(spec, c)
        r = star_track.render_sequence(spec, ctx, draw)
        off = r["offsets"]
        for k in range(spec.sequence.frames):
            A, w = draw["A_true"][k], draw["omega"][k]
            ends = []
            for h in (-0.5 * T, 0.5 * T):           # dA/dt = -[w x] A: the camera turns by +|w| h about w
                Ah = rotation(w, np.linalg.norm(w) * h).T @ A
                ends.append(cam.project(ctx.catalog.unit @ Ah.T)[0])
            px, front = cam.project(ctx.catalog.unit @ A.T)
            ok = front & np.isfinite(px).all(axis=1) & cam.in_image(np.nan_to_num(px, nan=-1.0))
            ok &= np.isfinite(ends[0]).all(axis=1) & np.isfinite(ends[1]).all(axis=1)
            idx = np.flatnonzero(ok)
            xy, sg = r["xy"][off[k]:off[k + 1]], r["sigma_px"][off[k]:off[k + 1]]
            d2 = ((xy[:, None] - px[idx][None]) ** 2).sum(-1)          # (D, S)
            j = d2.argmin(axis=1)
            i = np.arange(len(xy))
            mutual = (d2.argmin(axis=0)[j] == i) & (d2[i, j] < 1.5 ** 2)
            i, j = i[mutual], j[mutual]
            seg = ends[1][idx[j]] - ends[0][idx[j]]
            L = np.hypot(seg[:, 0], seg[:, 1])
            inside = ((np.minimum(ends[0][idx[j]], ends[1][idx[j]]) > 3).all(axis=1)
                      & (np.maximum(ends[0][idx[j]], ends[1][idx[j]]) < [cam.width - 3, cam.height - 3]).all(axis=1))
            i, j, seg, L = i[inside], j[inside], seg[inside], L[inside]
            u = seg / L[:, None]
            e = xy[i] - px[idx[j]]
            ea = (e * u).sum(axis=1)
            ec = e[:, 1] * u[:, 0] - e[:, 0] * u[:, 1]
            ea -= np.median(ea)                      # the frame's common shift (its attitude over the exposure)
            ec -= np.median(ec)
            rows.append(np.stack([L, sg[i], ea, ec], axis=1))
    return np.concatenate(rows), TrackingConfig(**{k: v for k, v in d["tracking"].items()})


def test_the_stated_along_streak_sigma_is_the_rendered_error(streaks):
    R, cfg = streaks
    L, sg, ea, ec = R.T
    assert cfg.streak_psf_sigma_px > 0
    stated = np.sqrt(sg ** 2 * (1 + along_gain(L, cfg.streak_psf_sigma_px)) + (cfg.smear_sigma_per_px * L) ** 2)
    long_ = (L >= 4) & (L <= 9)
    assert long_.sum() >= 300, long_.sum()
    z = ea[long_] / stated[long_]
    assert 0.85 <= math.sqrt(np.mean(z ** 2)) <= 1.2, math.sqrt(np.mean(z ** 2))
    assert np.mean(np.abs(z) > 3) < 0.01
    # the round-PSF sigma alone understates it: the model is needed
    assert math.sqrt(np.mean((ea[long_] / sg[long_]) ** 2)) > 1.35
    # across the streak the detector's sigma holds (conservative: 0.6-1.1 of the error)
    zc = ec[long_] / np.sqrt(sg[long_] ** 2 + (cfg.smear_cross_per_px * L[long_]) ** 2)
    assert 0.6 <= math.sqrt(np.mean(zc ** 2)) <= 1.1, math.sqrt(np.mean(zc ** 2))


def test_along_gain_is_the_variance_of_a_segment_blurred_by_the_psf():
    """The profile along a streak: a uniform segment of length L convolved with a Gaussian of sigma s, its variance
    from a million samples (uniform + normal), over s^2, minus 1."""
    rng = np.random.default_rng(3)
    for L, s in ((0.0, 1.0), (6.0, 1.28), (12.0, 0.7), (3.0, 2.5)):
        x = rng.uniform(-L / 2, L / 2, 1_000_000) + rng.normal(scale=s, size=1_000_000)
        assert along_gain(np.array([L]), s)[0] == pytest.approx(x.var() / s ** 2 - 1.0, abs=0.01 * (1 + L * L / s / s))
    assert np.all(along_gain(np.array([0.0, 5.0]), 0.0) == 0.0)           # off

