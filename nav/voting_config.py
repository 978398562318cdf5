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
  stars under a wrong attitude.

All angles are in radians (convert at the edge with :data:`dualsight.scene.units.ARCSEC`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualsight.errors import ConfigError

__all__ = ["VotingConfig", "ACCEPT_RULES"]

ACCEPT_RULES = ("fraction", "clique")


@dataclass(frozen=True)
class VotingConfig:
    """Options of :func:`dualsight.nav.starid.identify`.  Defaults: the reference-faithful :meth:`paper`.

    Invalid values raise :class:`dualsight.errors.ConfigError` (a ``ValueError``) naming
    ``voting.<field>``.

    Attributes
    ----------
    tolerance_rad : half-width (rad) of the angle window in the voting round: a catalog pair votes
        when ``|angle_ab - d_pq| < tolerance_rad``.  Should cover the error of an observed pair angle
        (about sqrt(2) x the centroid error); the 17 mm / 4.65 um camera has 56.4 arcsec pixels, so the
        default 1.5e-4 rad (31 arcsec, 0.55 px) suits ~0.1-0.2 px centroids.
    max_stars : use only the ``max_stars`` brightest valid observed stars (the first valid ones; the
        inputs are ordered brightest first) in voting and verification.
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
        Sparse fields, where the true identity often ties with chance coincidences, gain most.
    accept_rule : "fraction" (verification votes >= accept_fraction * T, and > 0) or "clique"
        (largest mutually consistent set by greedy pruning; ``accept_fraction`` is unused).
    accept_fraction : see ``accept_rule``.  The reference does not give its value; 0.5 by default.
    min_accepted : a case with fewer accepted stars is rejected (T = 0).  2 is the minimum for an
        attitude; without the attitude check, 3 removes most confident-but-wrong answers.
    verify_tolerance_rad : tolerance (rad) of the verification round; None = ``tolerance_rad``.
    verify_attitude : after voting, solve the attitude (SVD) from the accepted stars, rotate every valid
        observed star into the catalog frame and match it to the nearest catalog star within
        ``attitude_tolerance_rad``; reject the case when fewer than ``min_verified`` observed stars
        match.  Not in the reference (off in :meth:`paper`).
    attitude_tolerance_rad : match radius (rad) of the attitude check; None = 2 x ``tolerance_rad``.
    min_verified : minimum number of observed stars matched by the attitude check (including the
        accepted ones): 4 = a pair needs two independent confirmations, a triple one.  3 solves a few
        more three- and four-star fields at a small risk of a wrong triple.
    reidentify : with ``verify_attitude``, replace the final ids by the attitude matches (this also
        identifies stars beyond ``max_stars`` or missed by voting) and accept exactly the matched stars.
    max_vote_cells : memory bound: a dense vote table holds at most this many int64 cells (tables
        are of max(1, min(max_vote_cells, 262144) // W) observed stars, W = N + 1 rounded up to 64),
        at most this many catalog stars are expanded at once (with 262144, or one tile), and the
        later steps work on blocks of cases of about this size.
    """

    tolerance_rad: float = 1.5e-4
    max_stars: int = 20
    require_unique_max: bool = False
    vote_once_per_pair: bool = False
    candidates_per_star: int = 1
    accept_rule: str = "fraction"
    accept_fraction: float = 0.5
    min_accepted: int = 2
    verify_tolerance_rad: float | None = None
    verify_attitude: bool = False
    attitude_tolerance_rad: float | None = None
    min_verified: int = 4
    reidentify: bool = True
    max_vote_cells: int = 250_000

    def __post_init__(self):
        def bad(name, allowed):
            raise ConfigError(f"must be {allowed}, got {getattr(self, name)!r}", field=f"voting.{name}")

        def pos(name, optional=False):
            v = getattr(self, name)
            if optional and v is None:
                return
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (np.isfinite(v) and v > 0):
                bad(name, "a number > 0 (rad)" + (" or None" if optional else ""))

        def integer(name, lo):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
                bad(name, f"an integer >= {lo}")

        pos("tolerance_rad")
        pos("verify_tolerance_rad", optional=True)
        pos("attitude_tolerance_rad", optional=True)
        integer("max_stars", 2)
        integer("candidates_per_star", 1)
        integer("min_accepted", 2)
        integer("min_verified", 2)
        integer("max_vote_cells", 1)
        if self.accept_rule not in ACCEPT_RULES:
            bad("accept_rule", f"one of {ACCEPT_RULES}")
        if isinstance(self.accept_fraction, bool) or not (0.0 <= self.accept_fraction <= 1.0):
            bad("accept_fraction", "a number in [0, 1]")

    @property
    def verify_tol(self) -> float:
        """Effective verification tolerance (rad)."""
        return self.tolerance_rad if self.verify_tolerance_rad is None else self.verify_tolerance_rad

    @property
    def attitude_tol(self) -> float:
        """Effective match radius (rad) of the attitude check."""
        return 2.0 * self.tolerance_rad if self.attitude_tolerance_rad is None else self.attitude_tolerance_rad

    @classmethod
    def paper(cls, tolerance_rad: float = 1.5e-4, **kw) -> "VotingConfig":
        """Reference-faithful method: plain argmax, accept >= T/2, no attitude check."""
        base = dict(tolerance_rad=tolerance_rad, require_unique_max=False, accept_rule="fraction",
                    accept_fraction=0.5, min_accepted=2, verify_attitude=False)
        base.update(kw)
        return cls(**base)

    @classmethod
    def robust(cls, tolerance_rad: float = 1.5e-4, **kw) -> "VotingConfig":
        """dualsight's method: unique maxima, consistent-set acceptance, >= 3 stars, attitude check."""
        base = dict(tolerance_rad=tolerance_rad, require_unique_max=True, vote_once_per_pair=True,
                    candidates_per_star=3, accept_rule="clique", min_accepted=2, verify_attitude=True,
                    min_verified=4, reidentify=True)
        base.update(kw)
        return cls(**base)

    @property
    def candidates_kept(self) -> int:
        """Identities the voting round keeps per observed star, best first: ``candidates_per_star``
        (+1 to detect a tie with the last kept one), or 2 for a strict maximum, else 1."""
        m = int(self.candidates_per_star)
        return m + 1 if m > 1 else (2 if self.require_unique_max else 1)
