"""Configuration of M2Loc / TripletLoc localization: :class:`TripletConfig` and its presets."""

from __future__ import annotations

import equinox as eqx
import jax
from jax import Array

from jaxloc._traced import concrete, float32_leaf, int32_leaf, optional_float32_leaf
from jaxloc.lsq import RobustLoss
from jaxloc.m2loc._clique import check_clique_sizes
from jaxloc.m2loc._descriptors import DescriptorConfig


class TripletConfig(eqx.Module):
    """Localization parameters.

    Settings that fix shapes or the program (``descriptor``, ``top_k``, the switches, the
    attempt, hypothesis, clique and solver sizes, ``query_capacity``) are static; every threshold,
    fraction, radius, distance and loss scale is a traced array leaf: a sweep over them compiles
    once, and configurations that differ only in them stack (``jax.tree.map(lambda *x:
    jnp.stack(x), *configs)``) for ``jax.vmap`` (:func:`jaxloc.m2loc.query`). Concrete values
    are range-checked on construction.

    Attributes:
        descriptor: descriptor configuration (classes, scales, histograms).
        top_k: map matches per query vertex, class and scale.
        consistency_threshold: metres, ``| |q_i - q_j| - |m_i - m_j| |`` bound of an edge.
        one_to_one: no edge between associations that share a query or a map vertex, so a
            clique is a one-to-one matching (default False: TripletLoc's graph, where nearby map
            vertices of one query vertex can all join a clique).
        min_clique: M2Loc's T: add scales while the clique is smaller than this.
        min_inliers: fewer clique vertices than this gives ``valid = False``.
        min_inlier_fraction: place-not-in-the-map rejection: after registration, the fraction of
            the scan's vertices that land within ``verify_radius`` of a map vertex of their class
            must reach this (0 disables; see ``experiments/results/m2loc/rejection.md``).
        min_verified: fewer verified scan vertices than this (beyond those counted out by
            ``verify_beyond_minimal_set``) gives ``valid = False``, whatever the fraction: in a
            7-vertex scan 3 chance fits make 75 % (default 0; ``m2loc_config``: 4).
        verify_radius: metres, the verification radius (a map's cell grid for it is static:
            :func:`~jaxloc.m2loc.with_config` rebuilds it for a larger radius).
        verify_beyond_minimal_set: leave the 3 vertices a pose is determined by out of that
            fraction, ``(verified - 3) / (n - 3)``: they fit the pose by construction, and in a
            small scan they are a large share of it (a chance 3-clique in a 6-vertex scan from
            elsewhere verifies 50 % on its own). Default False (all vertices, as before).
        registration_attempts: cliques and poses tried at most (1: one, TripletLoc's and
            M2Loc's way). While the best pose so far verifies below ``retry_inlier_fraction``,
            another attempt drops the associations that agree with the poses tried (within
            ``verify_radius``) and solves the clique and the pose again; the attempt with the
            highest inlier fraction is kept.
        retry_inlier_fraction: the verification level below which an attempt is retried (and
            below which the hypotheses are searched).
        hypotheses: 0 (default) or the number of clique hypotheses verified when the best pose
            verifies below ``retry_inlier_fraction``: greedy cliques grown from every
            association of the final graph, the largest distinct ones, each with a closed-form
            pose; the best-verified one is refined and kept if it verifies better
            (``best_verified_clique``).
        hypothesis_min_support: a pose from the hypotheses is kept only if it verifies at least
            this many scan vertices beyond those counted out by ``verify_beyond_minimal_set``
            (the best of many poses fits a small scan by chance far more often than one pose).
        hypothesis_min_fraction: ... and only if it verifies at least this fraction (default
            0.55, above ``min_inlier_fraction``: on development seeds, 6 of the 8 searched poses
            of foreign scans that reached 0.5 stayed below 0.55, against 3 of 70 right poses of
            DCC04 queries; ``experiments/results/m2loc/searched_poses.md``).
        ambiguity_margin: None (default) or the uniqueness check: the ``hypotheses`` of the
            final graph are verified (``verified_hypotheses``, every query),
            and the pose is refused as ambiguous when one that moves the scan elsewhere (its
            vertices by more than ``ambiguity_distance`` on average) verifies at least the
            pose's own fraction minus this margin: a repetitive road explained equally well
            150 m further on is not a fix. Needs ``hypotheses`` > 0.
        ambiguity_distance: metres; see ``ambiguity_margin``.
        loss: robust loss of the pose refinement (GNC-TLS, 1 m, by default).
        use_rsn: use the road-surface-normal prior when the map has RSN cells.
        rot_delta_deg: added to an RSN cell's normal std (degrees) for the prior's sigma (>= 0).
        query_capacity: static padded query size (None: next power of two >= 32).
        clique_prefilter_size: :func:`max_clique`'s ``prefilter_size``.
        clique_greedy_tiers: :func:`max_clique`'s ``greedy_tiers``.
        clique_compact_size: :func:`max_clique`'s ``compact_size``.
        clique_max_nodes: :func:`max_clique`'s ``max_nodes``.
        clique_seeds: :func:`max_clique`'s ``num_seeds``.
        solver_steps: optimiser steps per solve.
    """

    descriptor: DescriptorConfig = DescriptorConfig()
    top_k: int = eqx.field(static=True, default=25)
    consistency_threshold: Array = eqx.field(default=1.0, converter=float32_leaf)
    one_to_one: bool = eqx.field(static=True, default=False)
    registration_attempts: int = eqx.field(static=True, default=1)
    retry_inlier_fraction: Array = eqx.field(default=0.5, converter=float32_leaf)
    hypotheses: int = eqx.field(static=True, default=0)
    hypothesis_min_support: Array = eqx.field(default=6, converter=int32_leaf)
    hypothesis_min_fraction: Array = eqx.field(default=0.55, converter=float32_leaf)
    ambiguity_margin: Array | None = eqx.field(default=None, converter=optional_float32_leaf)
    ambiguity_distance: Array = eqx.field(default=5.0, converter=float32_leaf)
    min_clique: Array = eqx.field(default=10, converter=int32_leaf)
    min_inliers: Array = eqx.field(default=3, converter=int32_leaf)
    min_inlier_fraction: Array = eqx.field(default=0.5, converter=float32_leaf)
    min_verified: Array = eqx.field(default=0, converter=int32_leaf)
    verify_radius: Array = eqx.field(default=1.5, converter=float32_leaf)
    verify_beyond_minimal_set: bool = eqx.field(static=True, default=False)
    loss: RobustLoss = RobustLoss("gnc_tls", 1.0)
    use_rsn: bool = eqx.field(static=True, default=True)
    rot_delta_deg: Array = eqx.field(default=1.0, converter=float32_leaf)
    query_capacity: int | None = eqx.field(static=True, default=None)
    clique_prefilter_size: int = eqx.field(static=True, default=256)
    clique_greedy_tiers: tuple[int, ...] = eqx.field(static=True, default=(256, 512))
    clique_compact_size: int = eqx.field(static=True, default=128)
    clique_max_nodes: int = eqx.field(static=True, default=4000)
    clique_seeds: int = eqx.field(static=True, default=64)
    solver_steps: int = eqx.field(static=True, default=30)

    def __check_init__(self) -> None:
        if self.top_k < 1:
            raise ValueError("top_k >= 1, min_inliers >= 3 and min_clique >= 1 are required")
        if self.registration_attempts < 1:
            raise ValueError("registration_attempts >= 1 and retry_inlier_fraction in [0, 1]")
        if self.hypotheses < 0:
            raise ValueError("hypotheses, hypothesis_min_support and min_verified must be >= 0")
        if self.ambiguity_margin is not None and self.hypotheses < 1:
            raise ValueError(
                "ambiguity_margin needs hypotheses > 0, a margin >= 0 and ambiguity_distance > 0"
            )
        check_clique_sizes(self.clique_compact_size, self.clique_greedy_tiers)
        if concrete(*jax.tree.leaves(self)):
            self._check_values()

    def _check_values(self) -> None:
        """Range checks of the traced settings (on construction, where they are concrete)."""
        if self.min_inliers < 3 or self.min_clique < 1:
            raise ValueError("top_k >= 1, min_inliers >= 3 and min_clique >= 1 are required")
        if not self.consistency_threshold > 0:
            raise ValueError("consistency_threshold must be > 0")
        if not 0.0 <= self.retry_inlier_fraction <= 1.0:
            raise ValueError("registration_attempts >= 1 and retry_inlier_fraction in [0, 1]")
        if min(self.hypothesis_min_support, self.min_verified) < 0:
            raise ValueError("hypotheses, hypothesis_min_support and min_verified must be >= 0")
        if not 0.0 <= self.min_inlier_fraction <= 1.0 or not self.verify_radius > 0:
            raise ValueError("min_inlier_fraction must be in [0, 1] and verify_radius > 0")
        if not 0.0 <= self.hypothesis_min_fraction <= 1.0:
            raise ValueError("hypothesis_min_fraction must be in [0, 1]")
        if self.ambiguity_margin is not None and not (
            self.ambiguity_margin >= 0 and self.ambiguity_distance > 0
        ):
            raise ValueError(
                "ambiguity_margin needs hypotheses > 0, a margin >= 0 and ambiguity_distance > 0"
            )
        if not self.rot_delta_deg >= 0:
            raise ValueError(f"rot_delta_deg must be >= 0, got {self.rot_delta_deg}")


#: M2Loc's settings as published, the ones ``m2loc_config(robust=True)`` changes: cliques may
#: join associations of one vertex, one registration attempt, no clique hypotheses, no uniqueness
#: check. ``dataclasses.replace(config, **PUBLISHED_SETTINGS)`` makes a robust configuration (a
#: saved map's) the paper's.
PUBLISHED_SETTINGS = {
    "one_to_one": False,
    "registration_attempts": 1,
    "hypotheses": 0,
    "ambiguity_margin": None,
}


def tripletloc_config(**overrides) -> TripletConfig:
    """TripletLoc: one scale [0, 20] m, angle + edge-length histograms (456 dims)."""
    return TripletConfig(**overrides)


def m2loc_config(
    num_scales: int = 3,
    scale_edges: tuple[float, ...] = (20.0, 30.0, 40.0),
    length_feature: str = "ratio",
    robust: bool = True,
    **overrides,
) -> TripletConfig:
    """M2Loc "Multi-n-En": the first ``num_scales`` intervals of ``scale_edges``, angle +
    length-ratio histograms, dynamic clique enhancement with T = 10, and the place-not-in-the-map
    check on the evidence beyond the pose's minimal set (``verify_beyond_minimal_set=True``).

    ``robust`` (default True) adds what helps small, noisy scans most in our measurements
    (``experiments/results/m2loc/losses*.md``, ``hypotheses.md``, ``table1.md``,
    ``ambiguity.md``): one-to-one cliques, 256 verified clique hypotheses searched when the
    maximum clique's pose verifies poorly, and the uniqueness check on them (``one_to_one=True,
    hypotheses=256, ambiguity_margin=0.0``: a pose is refused when a pose elsewhere verifies at
    least as well); ``robust=False`` is the paper's M2Loc. ``overrides`` win over both
    (``registration_attempts=3, hypotheses=0`` retries the registration instead of searching
    hypotheses; the uniqueness check needs hypotheses, so ``hypotheses=0`` turns it off unless
    ``ambiguity_margin`` is given)."""
    descriptor = DescriptorConfig(
        scale_edges=tuple(scale_edges[:num_scales]), length_feature=length_feature
    )
    defaults = {"verify_beyond_minimal_set": True, "min_verified": 4}
    if robust:
        defaults.update(one_to_one=True, hypotheses=256)
        if overrides.get("hypotheses", 256) > 0:
            defaults["ambiguity_margin"] = 0.0
    else:
        defaults.update(PUBLISHED_SETTINGS)
    return TripletConfig(descriptor=descriptor, **{**defaults, **overrides})
