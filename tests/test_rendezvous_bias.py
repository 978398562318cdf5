"""The rendezvous kind's hooks of the filter's centre-of-brightness bias states and its blobber range model
(jobs/kinds/rendezvous_filter.py, issue 23 point 6 c): the select hook's G along the Sun's projection across the line of
sight and its perpendicular with the statistics' sigmas, the white part on the same axes, the decay from the turn
of the predicted line of sight, the range's known bias removed, against hand-built expectations."""

import math

import numpy as np
import pytest

from dualsight.jobs.kinds import (rendezvous as rz, rendezvous_context, rendezvous_filter, rendezvous_measure,
                                  rendezvous_spec, rendezvous_truth)
from dualsight.scene.photocentre_bias import PhotocentreStatistics
from dualsight.scene.target_photometry import TargetShape


def _spec():
    d, _ = rendezvous_spec.resolve_spec("far", None)
    return rz.spec_from_dict(d)


def _stats(s_sun, s_cross, w_sun, w_cross, psi_sun, psi_cross):
    a = np.radians([0.0, 180.0])
    two = lambda v: np.array([v, v], float)  # noqa: E731
    return PhotocentreStatistics(a, two(0.0), two(s_sun), two(s_cross), two(math.hypot(w_sun, w_cross) / math.sqrt(2)),
                                 np.array([[psi_sun, psi_cross]] * 2), two(w_sun), two(w_cross))


def _meas(u):
    m = {"u": np.full((1, 3), np.nan), "C": np.zeros((1, 3, 3)), "u_used": np.full((1, 3), np.nan),
         "C_used": np.zeros((1, 3, 3)), "target_xy": np.full((1, 2), np.nan), "bearing_used": np.zeros(1, bool),
         "found_by": np.zeros(1, np.int8), "found_true": np.zeros(1, bool)}
    m["cand"] = {"frame": np.array([0]), "u": u[None], "C": np.zeros((1, 3, 3)), "xy": np.zeros((1, 2)),
                 "true": np.array([True])}
    return m


def _given_model(D_seen):
    """A CobBias with the numbers of :func:`_stats` below, built by hand: what reaches the selector is the model's."""
    def columns(k, v, D, alpha, r):
        D_seen.append(D)
        return D * np.array([0.03, 0.01])[None, None, :], np.tile([0.02, 0.005], (len(v), 1))
    return rendezvous_filter.CobBias(2, columns, lambda k, x, R: np.ones((1, 2)), lambda x, R: None)


@pytest.mark.parametrize("given", [False, True])
def test_select_hook_gives_the_bias_columns_along_the_sun_and_across_and_the_white_part_on_them(given):
    """The product's model (the statistics' sigma_sun 0.03, sigma_cross 0.01, white 0.02 / 0.005 m), or the same
    numbers from a model passed in (``cob``): G along the Sun's side across u and u x that, the white part on the
    same axes; the model is handed those axes."""
    spec = _spec()
    s = rendezvous_truth.sun_icrs(spec)
    e = np.cross(s, [0.0, 0.0, 1.0])
    e /= np.linalg.norm(e)
    al = np.radians(70.0)
    u = -np.cos(al) * s + np.sin(al) * e                        # chaser -> target, phase angle 70 deg
    shape = TargetShape(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)),
                        np.zeros(0), np.zeros(0), 0.2)
    a = np.radians(np.arange(0.0, 181.0, 5.0))
    table = (a, np.zeros_like(a), np.zeros_like(a))             # no mean offset: v = u
    ctx = rendezvous_context.RendezvousContext(None, shape, table, _stats(0.03, 0.01, 0.02, 0.005, 1.0, 0.5))
    m = _meas(u)
    seen = []
    sel = rendezvous_filter.target_selector(spec, ctx, m, _given_model(seen) if given else None)
    r = 1000.0
    R_k = np.stack([np.cross(u, s) / np.linalg.norm(np.cross(u, s)), u, s], axis=1)
    R_k[:, 2] = np.cross(R_k[:, 0], R_k[:, 1])
    x = np.r_[0.0, -r, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][None]
    u2, C2, G = sel(0, x, np.eye(8)[None], R_k)
    d_sun = (s - np.dot(s, u) * u) / np.linalg.norm(s - np.dot(s, u) * u)     # the Sun's side, across u
    d_cross = np.cross(u, d_sun)
    np.testing.assert_allclose(G[0, :, 0], 0.03 * d_sun, atol=1e-12)
    np.testing.assert_allclose(G[0, :, 1], 0.01 * d_cross, atol=1e-12)
    want = (0.02 ** 2 * np.outer(d_sun, d_sun) + 0.005 ** 2 * np.outer(d_cross, d_cross)) / r ** 2
    np.testing.assert_allclose(C2[0], want, atol=1e-18)
    np.testing.assert_allclose(u2[0], u, atol=1e-15)
    assert rendezvous_filter.cob_bias_states(spec, ctx) == 2
    if given:
        np.testing.assert_allclose(seen[0][0], np.stack([d_sun, d_cross], -1), atol=1e-12)


def test_bias_decay_is_exp_of_the_line_of_sights_turn_over_the_correlation_angle():
    spec = _spec()
    ctx = rendezvous_context.RendezvousContext(None, None, (), _stats(0.03, 0.01, 0.02, 0.005, 0.4, 0.1))
    decay, seed_los = rendezvous_filter.cob_bias_decay(spec, ctx)
    R = np.eye(3)
    seed_los(np.array([[0.0, -1000.0, 0.0]]), R)
    turn = 0.05
    x = np.array([[1000.0 * math.sin(turn), -1000.0 * math.cos(turn), 0.0]])
    np.testing.assert_allclose(decay(1, x, R), [[math.exp(-turn / 0.4), math.exp(-turn / 0.1)]], rtol=1e-9)


def test_range_model_removes_the_known_bias_and_takes_its_spread():
    ratio = (np.array([1.0, 3.0]), np.array([0.98, 0.96]), np.array([0.05, 0.07]))
    ctx = rendezvous_context.RendezvousContext(None, None, (), range_ratio=ratio)
    m = {"range_used": np.array([True, True, False]), "range": np.array([10.0, 20.0, np.nan]),
         "axis_ratio": np.array([1.0, 2.0, np.nan])}
    rendezvous_measure.range_model(ctx, m)
    np.testing.assert_allclose(m["range_filter"][:2], [10.0 / 0.98, 20.0 / 0.97])
    np.testing.assert_allclose(m["range_sigma"][:2], [10.0 * 0.05 / 0.98 ** 2, 20.0 * 0.06 / 0.97 ** 2])
    assert math.isnan(m["range_filter"][2]) and math.isnan(m["range_sigma"][2])
