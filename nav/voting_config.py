"""Options of geometric-voting star identification (:func:`dualsight.nav.starid.identify`).

The reference (McBryde & Lightsey, Sec. 3.1) uses Kolomenkin et al. (2008) without saying how ties
are broken or which verification counts are "high"; those choices are the fields of
:class:`VotingConfig`, grouped in two presets:

- :meth:`VotingConfig.paper` (reference-faithful): every candidate pair votes, step 2 takes the
  ``argmax`` (ties go to the lowest catalog row, as numpy's ``argmax`` and MATLAB's ``max`` break
  them), step 5 accepts the stars whose verification votes are >= ``accept_fraction * T`` (0.5) and
  > 0.
- :meth:`VotingConfig.robust` (dualsight): a catalog star gets at most one vote per observed pair;
  step 2 keeps each star's 3 best-voted identities and picks, among all (star, identity)
  candidates, the largest set whose every pairwise angle matches the catalog (so a tie with a
  chance coincidence is settled by geometry, not by the catalog order); a remaining star takes an
  identity only with a strict vote maximum and an identity claimed twice stays with the strict
  winner; step 5 accepts the largest mutually consistent set (greedy pruning); finally the
  attitude from the accepted stars must place at least ``min_verified`` (4) observed stars within
  ``attitude_tolerance_rad`` of a catalog star, and then every observed star is re-identified from
  that attitude.  A confident but wrong answer needs four observed stars that all land on catalog
  stars under a wrong attitude.  Then identities of blended doubles are dropped and a 5-sigma residual
  test against the other stars' scatter rejects a wrong identity inside the match radius
  (:mod:`dualsight.nav.residual_check`); a case that fails votes again with the next 20 stars in
  brightness order, up to the 60 brightest (widening, :mod:`dualsight.nav.widen`), so bright false stars
  cannot crowd the true ones out of the vote.

Every answer of either preset carries ``p_chance``, the probability that it is a chance match
(:mod:`dualsight.nav.chance`); ``max_p_chance`` < 1 rejects improbable answers (off in both presets).

All angles are in radians (convert at the edge with :data:`dualsight.scene.units.ARCSEC`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal, get_args

from pydantic import Field

from dualsight.errors import ConfigError
from dualsight.config import check_fields

__all__ = ["VotingConfig", "ACCEPT_RULES", "MAX_TOLERANCE_RAD", "MAX_STARS"]

AcceptRule = Literal["fraction", "clique"]
ACCEPT_RULES = get_args(AcceptRule)

MAX_TOLERANCE_RAD = math.pi / 180
"""Largest angle tolerance (1 deg, in rad) of the voting, verification and attitude rounds.  A tolerance
covers the error of an observed pair angle, a fraction of a pixel to a few pixels: 0.1-200 arcsec for
any star tracker (pixels of ~5-150 arcsec).  At 1 deg every observed pair of a 16 deg field already
votes for ~10 % of the pair catalog (e.g. all pairs 9-11 deg apart), so identification is noise;
beyond it the windows only cost time."""

MAX_STARS = 1000
"""Most observed stars a case may vote with (and the largest count field): the HIL jobs keep at most 1000
detections (``max_obs``), and the voting, verification and consistent-set steps grow with its square."""

_Tol = Annotated[float, Field(gt=0, le=MAX_TOLERANCE_RAD)]
_Count = Annotated[int, Field(ge=2, le=MAX_STARS)]
_UNITS = {"tolerance_rad": "rad", "verify_tolerance_rad": "rad", "attitude_tolerance_rad": "rad",
          "max_stars": "stars", "min_accepted": "stars", "min_verified": "stars", "max_vote_cells": "cells",
          "max_stars_total": "stars", "widen_step": "stars", "widen_min_verified": "stars",
          "residual_k": "sigma", "residual_floor_rad": "rad"}


@dataclass(frozen=True)
class VotingConfig:
    """Options of :func:`dualsight.nav.starid.identify`.  Defaults: the reference-faithful :meth:`paper`.

    Every field's range is part of its type (pydantic ``Field``), checked when a TOML table is validated
    (``dualsight.config.validate``) and when the dataclass is built in Python; invalid values raise
    :class:`dualsight.errors.ConfigError` (a ``ValueError``) naming ``voting.<field>``, the value and
    the allowed range.

    Attributes
    ----------
    tolerance_rad : half-width (rad) of the angle window in the voting round, in (0, pi/180] (1 deg,
        :data:`MAX_TOLERANCE_RAD`): a catalog pair votes when ``|angle_ab - d_pq| < tolerance_rad``.
        Should cover the error of an observed pair angle (about sqrt(2) x the centroid error); the
        17 mm / 4.65 um camera has 56.4 arcsec pixels, so the default 1.5e-4 rad (31 arcsec, 0.55 px)
        suits ~0.1-0.2 px centroids.
    max_stars : use only the ``max_stars`` brightest valid observed stars (the first valid ones; the
        inputs are ordered brightest first) in voting and verification; an integer in [2, 1000]
        (:data:`MAX_STARS`).
    require_unique_max : step 2 assigns an identity only when its vote count is strictly above every
        other catalog row's (a tie leaves the star unidentified, id -1), and an identity claimed by
        two observed stars stays only with the star that has strictly more votes for it.  Off: ties
        go to the lowest catalog row and duplicates are left to verification.
    vote_once_per_pair : a catalog star gets at most one vote per observed pair, however many of its
        catalog pairs fall in the window (Kolomenkin 2008 counts every candidate pair, so a star
        with many neighbours, e.g. in a cluster, collects spurious votes).  Then a star's votes are
        at most the number of its observed pairs, and the true identity reaches that bound when
        all its partners are real stars.
    candidates_per_star : 1 = Kolomenkin's step 2 (each star takes its top-voted identity).  m > 1 =
        tie-aware step 2: keep each star's m best-voted identities (ties to the lower row) and pick,
        among all (star, identity) candidates, the largest set whose every pairwise catalog angle
        matches the observed one (greedy pruning); stars outside that set keep the plain maximum.
        Sparse fields, where the true identity often ties with chance coincidences, gain most.  An
        integer in [1, 5]: the consistency table of one case has (max_stars x m)^2 cells, at most
        2.5e7 with the bounds (the robust preset uses 3).
    accept_rule : "fraction" (verification votes >= accept_fraction * T, and > 0) or "clique"
        (largest mutually consistent set by greedy pruning; ``accept_fraction`` is unused).
    accept_fraction : see ``accept_rule``, in [0, 1].  The reference does not give its value; 0.5 by
        default.
    min_accepted : a case with fewer accepted stars is rejected (T = 0); an integer in [2, 1000].  2 is
        the minimum for an attitude; without the attitude check, 3 removes most confident-but-wrong
        answers.
    verify_tolerance_rad : tolerance (rad) of the verification round, None or in (0, pi/180];
        None = ``tolerance_rad``.
    verify_attitude : after voting, solve the attitude (SVD) from the accepted stars, rotate every valid
        observed star into the catalog frame and match it to the nearest catalog star within
        ``attitude_tolerance_rad``; reject the case when fewer than ``min_verified`` observed stars
        match.  Not in the reference (off in :meth:`paper`).
    attitude_tolerance_rad : match radius (rad) of the attitude check, None or in (0, pi/180];
        None = 2 x ``tolerance_rad``.
    min_verified : minimum number of observed stars matched by the attitude check (including the
        accepted ones), an integer in [2, 1000]: 4 = a pair needs two independent confirmations, a
        triple one.  3 solves a few more three- and four-star fields at a small risk of a wrong triple.
    reidentify : with ``verify_attitude``, replace the final ids by the attitude matches (this also
        identifies stars beyond ``max_stars`` or missed by voting) and accept exactly the matched stars.
    max_vote_cells : memory bound, an integer in [1, 2^28] (2^28 int64 cells = 2 GiB): a dense vote
        table holds at most this many int64 cells (tables are of max(1, min(max_vote_cells, 262144) // W)
        observed stars, W = N + 1 rounded up to 64), at most this many catalog stars are expanded at
        once (with 262144, or one tile), and the later steps work on blocks of cases of about this size.
    max_stars_total : widening (:mod:`dualsight.nav.widen`), None or an integer in [2, 1000]: a case
        whose answer fails verification (no answer, or fewer than ``widen_min_verified`` verified
        stars) votes again with the next block of ``max_stars`` stars in brightness order (valid ranks
        ``[r * widen_step, r * widen_step + max_stars)`` in round r, cut at ``max_stars_total``), and
        keeps the answer with the most verified stars.  None (the paper method) or <= ``max_stars`` =
        one round, the reference's.  Work bound: at most ``widen_rounds`` rounds of one block each.
    first_stars : a cheaper first round, None (off) or an integer in [2, 1000] (at or above ``max_stars``: off,
        so a preset's value stays valid when ``max_stars`` is lowered by a flag or a sweep): round 0
        votes with the ``first_stars`` brightest valid stars only (the voting's work grows with the square
        of the voters: 12 of 25 is ~1/4), and a case whose answer fails verification (as for widening) votes
        again with the ``max_stars`` brightest before any widening block (rounds ``(0, first_stars)``,
        ``(0, max_stars)``, then the widening blocks).  A case with no more than ``first_stars`` valid stars
        is not voted twice.  Omitted from the settings' table when None, so the runs of specs that do
        not use it keep their identity.
    widen_step : ranks between the first stars of two rounds' blocks, None (= ``max_stars``: disjoint
        blocks) or an integer in [1, 1000]; smaller = overlapping blocks, more rounds.
    widen_min_verified : a round's answer with fewer verified stars than this (None = ``min_verified``
        with the attitude check, else ``min_accepted``) sends the case to the next round (the answer is
        kept unless a later round verifies more stars); an integer in [2, 1000].
    residual_k : residual test (:mod:`dualsight.nav.residual_check`) after the attitude, in [0, 100]
        (0 = off, the paper method): the accepted star with the largest residual is rejected while that
        residual exceeds ``residual_k`` x sigma, sigma = the others' robust scatter (median residual /
        sqrt(2 ln 2), the Rayleigh median) floored at ``residual_floor``; the attitude is re-solved
        after each rejection.  5 = a star with Gaussian centroid errors is rejected with probability
        exp(-12.5) = 3.7e-6.
    residual_floor_rad : floor (rad) of that sigma, None (= ``tolerance_rad / 10``: the tolerance
        covers several sigma of a pair angle's error) or in (0, pi/180].
    reject_blends : after the attitude check, un-accept the identities whose catalog star has another
        catalog star closer than twice the match radius (a double merged into one detection: its
        identity is either star; :func:`dualsight.nav.residual_check.drop_blends`).  Off in the paper
        method.
    blend_max_dmag : with catalog magnitudes given to identify, a double whose stars differ by less than
        this (mag, in [0, 30]) is ambiguous for both; otherwise only its fainter star is (the brighter
        dominates the merged centroid).
    max_p_chance : an answer whose chance-match probability (:mod:`dualsight.nav.chance`) exceeds this
        is rejected (and widening tries the next block), in (0, 1]; 1 = never (the paper method).
    """

    tolerance_rad: _Tol = 1.5e-4
    max_stars: _Count = 20
    require_unique_max: bool = False
    vote_once_per_pair: bool = False
    candidates_per_star: Annotated[int, Field(ge=1, le=5)] = 1
    accept_rule: AcceptRule = "fraction"
    accept_fraction: Annotated[float, Field(ge=0.0, le=1.0)] = 0.5
    min_accepted: _Count = 2
    verify_tolerance_rad: _Tol | None = None
    verify_attitude: bool = False
    attitude_tolerance_rad: _Tol | None = None
    min_verified: _Count = 4
    reidentify: bool = True
    max_vote_cells: Annotated[int, Field(ge=1, le=2 ** 28)] = 250_000
    max_stars_total: _Count | None = None
    first_stars: _Count | None = field(default=None, metadata={"omit_if_default": True})
    widen_step: Annotated[int, Field(ge=1, le=MAX_STARS)] | None = None
    widen_min_verified: _Count | None = None
    residual_k: Annotated[float, Field(ge=0.0, le=100.0)] = 0.0
    residual_floor_rad: _Tol | None = None
    reject_blends: bool = False
    blend_max_dmag: Annotated[float, Field(ge=0.0, le=30.0)] = 1.0
    max_p_chance: Annotated[float, Field(gt=0.0, le=1.0)] = 1.0

    def __post_init__(self):
        check_fields(self, lambda name, msg: ConfigError(msg, field=f"voting.{name}"), _UNITS)

    @property
    def verify_tol(self) -> float:
        """Effective verification tolerance (rad)."""
        return self.tolerance_rad if self.verify_tolerance_rad is None else self.verify_tolerance_rad

    @property
    def attitude_tol(self) -> float:
        """Effective match radius (rad) of the attitude check."""
        return 2.0 * self.tolerance_rad if self.attitude_tolerance_rad is None else self.attitude_tolerance_rad

    @property
    def residual_floor(self) -> float:
        """Effective floor (rad) of the residual test's sigma."""
        return self.tolerance_rad / 10.0 if self.residual_floor_rad is None else self.residual_floor_rad

    @property
    def min_answer(self) -> int:
        """Fewest verified stars of an answer: ``min_verified`` with the attitude check, else ``min_accepted``."""
        return int(self.min_verified if self.verify_attitude else self.min_accepted)

    @property
    def widen_schedule(self) -> tuple[tuple[int, int], ...]:
        """The voting blocks of the widening rounds, ``((start, stop), ...)`` valid-star ranks (brightest
        = 0): round 0 is ``(0, max_stars)`` (with ``first_stars`` < ``max_stars``: ``(0, first_stars)`` then
        ``(0, max_stars)``); one round only without widening."""
        K = int(self.max_stars)
        total = K if self.max_stars_total is None else max(K, int(self.max_stars_total))
        step = K if self.widen_step is None else int(self.widen_step)
        first = [(0, int(self.first_stars))] if self.first_stars is not None and self.first_stars < K else []
        out, start = first + [(0, K)], step
        while total > K and start + 1 < total:                         # a block needs two stars
            out.append((start, min(start + K, total)))
            if start + K >= total:
                break
            start += step
        return tuple(out)

    @classmethod
    def paper(cls, tolerance_rad: float = 1.5e-4, **kw) -> "VotingConfig":
        """Reference-faithful method: plain argmax, accept >= T/2, no attitude check."""
        base = dict(tolerance_rad=tolerance_rad, require_unique_max=False, accept_rule="fraction",
                    accept_fraction=0.5, min_accepted=2, verify_attitude=False)
        base.update(kw)
        return cls(**base)

    @classmethod
    def robust(cls, tolerance_rad: float = 1.5e-4, **kw) -> "VotingConfig":
        """dualsight's method: unique maxima, consistent-set acceptance, attitude check (>= 4 stars), blend and
        5-sigma residual tests, widening to the 60 brightest stars in blocks of ``max_stars``."""
        base = dict(tolerance_rad=tolerance_rad, require_unique_max=True, vote_once_per_pair=True,
                    candidates_per_star=3, accept_rule="clique", min_accepted=2, verify_attitude=True,
                    min_verified=4, reidentify=True, max_stars_total=60, residual_k=5.0,
                    reject_blends=True)
        base.update(kw)
        return cls(**base)

    @property
    def candidates_kept(self) -> int:
        """Identities the voting round keeps per observed star, best first: ``candidates_per_star``
        (+1 to detect a tie with the last kept one), or 2 for a strict maximum, else 1."""
        m = int(self.candidates_per_star)
        return m + 1 if m > 1 else (2 if self.require_unique_max else 1)
