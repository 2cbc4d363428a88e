"""Whether SG2Loc is localized: a per-frame verdict computed inside the jitted filter step.

A particle filter always returns a pose; the verdict says whether to act on it. It rests on two
kinds of evidence, because either alone fails:

* **Convergence**: the particles' weighted spread (per axis: x, y, z in metres, yaw in radians,
  around the weighted mean) and the effective sample size. A spread-out cloud has not decided.
* **Explanation**: how well the estimate (the MLE particle) explains the frame, against the best
  the map could explain. The semantic fraction is the MLE's semantic score over the score of a
  view that would show every patch's best-matching map object (:func:`best_semantic_score`); the
  depth deficit is the MLE's depth score below the variant's best (for the default ``"l1"``
  variant: the mean absolute depth error in metres, a rendered miss counting 1 m); the colour
  score is the MLE's SSIM score. Particles also converge on a place that only looks like the
  map (the same furniture classes in another arrangement): there the cloud is tight, but no pose
  renders the right objects at the right depths, which the explanation terms see.

``localized = spread_xy <= max_spread_xy & spread_z <= max_spread_z & spread_yaw <= max_spread_yaw
& ess_fraction <= max_ess_fraction & semantic_fraction >= min_semantic_fraction & depth_deficit <=
max_depth_deficit & color >= min_color`` (a term whose score the filter does not use is left out),
and never on a degenerate update. A high effective sample size after the update means the
likelihood hardly tells the particles apart: nothing explains the frame much better than anything
else. The thresholds
(:class:`VerdictConfig`) are traced, so a sweep does not recompile; the presets
(:data:`VERDICT_WITH_DEPTH`, :data:`VERDICT_WITHOUT_DEPTH`) were chosen on development rooms and
look-alike wrong places (``experiments/sg2loc_verdict.py``) for the paper's observation model and
image size, and their precision and recall on rooms not used for the choice are in
docs/pages/sg2loc.md.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.geometry import wrap_angle
from jaxloc.sg2loc._convert import as_float32, finite_scalar
from jaxloc.sg2loc._particles import ParticleState, effective_sample_size, normalized_weights
from jaxloc.sg2loc._scores import (
    COLOR_MAX,
    DEPTH_MAX,
    ObservationConfig,
    PatchMatch,
    Scores,
)

#: The posterior mass is clipped to [MASS_CLIP, 1 - MASS_CLIP] before its logit.
MASS_CLIP = 0.01
_EVIDENCE_WEIGHTS = ("mass_weight", "semantic_weight", "depth_weight")
_CONFIDENCE_FIELDS = ("bias", "sigma_weight", "rays_weight", "particles_weight")
_CONFIDENCE_FIELDS += _EVIDENCE_WEIGHTS


class ConfidenceModel(eqx.Module):
    """The weights of :attr:`Verdict.confidence`, a logistic model of the estimate being within
    0.5 m and 10 degrees of the truth (traced float32 scalars).

    ``confidence = sigmoid(bias + sigma_weight * log(sigma) + rays_weight * log(rays) +
    particles_weight * log(capacity) + mass_weight * logit(mass) + semantic_weight *
    semantic_fraction - depth_weight * depth_deficit)`` (the depth term only where the filter
    scores depth; 0 on a degenerate update): the evidence (:attr:`Verdict.mass` clipped to
    [:data:`MASS_CLIP`, 1 - :data:`MASS_CLIP`], the semantic fraction, the depth deficit) with
    weights >= 0, so that the confidence rises with each kind, shifted by what the step knows of
    how sharp that evidence is: the likelihood width ``sigma``, the rays per particle of its grid
    and the particle capacity. ``ConfidenceModel()`` has every weight 0 (a constant 0.5); the
    fitted presets are :data:`CONFIDENCE_WITH_DEPTH` and :data:`CONFIDENCE_WITHOUT_DEPTH`, which
    :data:`VERDICT_WITH_DEPTH` and :data:`VERDICT_WITHOUT_DEPTH` carry.
    """

    bias: Array = eqx.field(default=0.0, converter=as_float32)
    sigma_weight: Array = eqx.field(default=0.0, converter=as_float32)
    rays_weight: Array = eqx.field(default=0.0, converter=as_float32)
    particles_weight: Array = eqx.field(default=0.0, converter=as_float32)
    mass_weight: Array = eqx.field(default=0.0, converter=as_float32)
    semantic_weight: Array = eqx.field(default=0.0, converter=as_float32)
    depth_weight: Array = eqx.field(default=0.0, converter=as_float32)

    def __check_init__(self):
        for name in _CONFIDENCE_FIELDS:
            value = finite_scalar("ConfidenceModel", name, getattr(self, name))
            if value is not None and name in _EVIDENCE_WEIGHTS and not value >= 0:
                raise ValueError(
                    f"ConfidenceModel.{name} must be >= 0 (the confidence rises with the "
                    f"evidence), got {value}"
                )


#: The confidence's weights for sequences with depth, fitted by logistic regression on 60
#: synthetic development conditions (image sizes 160x90 to 960x540, strides, 1000 or 2500
#: particles, sigma 0.2-1.0, camera heights within and beyond the configured ones, depth noise and
#: holes, patch confusion, colour noise, mesh coarseness) with a look-alike wrong place each,
#: offline and streaming (``experiments/sg2loc_verdict_conditions.py --fit dev``).
CONFIDENCE_WITH_DEPTH = ConfidenceModel(
    bias=-1.454,
    sigma_weight=2.439,
    rays_weight=0.162,
    particles_weight=-0.424,
    mass_weight=0.644,
    semantic_weight=8.036,
    depth_weight=6.834,
)
#: The weights for sequences without depth, fitted the same way on the runs without depth.
CONFIDENCE_WITHOUT_DEPTH = ConfidenceModel(
    bias=-5.026,
    sigma_weight=0.691,
    rays_weight=0.356,
    particles_weight=-0.461,
    mass_weight=0.257,
    semantic_weight=8.259,
)


class VerdictConfig(eqx.Module):
    """Thresholds of the per-frame verdict (traced float32 scalars; see the module docstring).

    The defaults are :data:`VERDICT_WITH_DEPTH`'s; :func:`default_verdict` picks the preset for
    a sequence with or without depth.

    Attributes:
        max_spread_xy: largest horizontal spread ``hypot(spread_x, spread_y)`` (metres).
        max_spread_z: largest vertical spread (metres).
        max_spread_yaw: largest yaw spread (radians).
        max_ess_fraction: largest effective sample size over the active count (0-1).
        min_semantic_fraction: smallest semantic score of the MLE over the frame's best (0-1).
        max_depth_deficit: largest depth deficit of the MLE (the depth variant's best minus its
            score; metres of mean absolute error for ``"l1"``).
        min_color: smallest colour score of the MLE (mean SSIM for the ``"paper"`` variant).
        mass_radius, mass_yaw: the posterior mass (:attr:`Verdict.mass`, not part of the rule)
            counts the particles within this distance (metres, 3-D) and yaw (radians) of the
            estimate.
        confidence: the weights of :attr:`Verdict.confidence` (not part of the rule).
    """

    max_spread_xy: Array = eqx.field(default=np.inf, converter=as_float32)
    max_spread_z: Array = eqx.field(default=0.05, converter=as_float32)
    max_spread_yaw: Array = eqx.field(default=0.08, converter=as_float32)
    max_ess_fraction: Array = eqx.field(default=0.4, converter=as_float32)
    min_semantic_fraction: Array = eqx.field(default=0.65, converter=as_float32)
    max_depth_deficit: Array = eqx.field(default=0.15, converter=as_float32)
    min_color: Array = eqx.field(default=0.0, converter=as_float32)
    mass_radius: Array = eqx.field(default=0.25, converter=as_float32)
    mass_yaw: Array = eqx.field(default=float(np.deg2rad(5.0)), converter=as_float32)
    confidence: ConfidenceModel = CONFIDENCE_WITH_DEPTH


#: The verdict's thresholds for sequences with depth, chosen on 20 development rooms and their
#: look-alike wrong places at the paper's settings, offline and streaming
#: (``experiments/sg2loc_verdict.py --choose dev``): the most frames within 0.25 m and 5 degrees
#: flagged while >= 99 % of the flagged frames are within 0.5 m and 10 degrees and <= 2 % of the
#: wrong places' frames are flagged. The colour score is not required: SSIM against a coarse
#: mesh's colours is the score least likely to carry over from synthetic rooms to real images.
VERDICT_WITH_DEPTH = VerdictConfig()
#: The thresholds for sequences without depth (stricter on the spread and the semantics), chosen
#: the same way on a proxy: the development runs with the depth term left out of the verdict.
VERDICT_WITHOUT_DEPTH = VerdictConfig(
    max_spread_xy=0.2,
    max_spread_z=0.1,
    max_spread_yaw=0.05,
    max_ess_fraction=0.2,
    min_semantic_fraction=0.72,
    max_depth_deficit=np.inf,
    confidence=CONFIDENCE_WITHOUT_DEPTH,
)


def default_verdict(use_depth: bool) -> VerdictConfig:
    """:data:`VERDICT_WITH_DEPTH` or :data:`VERDICT_WITHOUT_DEPTH`."""
    return VERDICT_WITH_DEPTH if use_depth else VERDICT_WITHOUT_DEPTH


class Verdict(NamedTuple):
    """One frame's verdict and what it is made of (scalars unless noted).

    Attributes:
        localized: bool, the estimate can be acted on.
        spread: (4,) float32 weighted standard deviation of the particles around their weighted
            mean: x, y, z (metres) and yaw (radians, of the wrapped differences).
        ess_fraction: float32 effective sample size over the active particle count, in (0, 1].
        semantic_fraction: float32 the MLE's semantic score over the frame's best attainable one
            (0 when no patch matches any map object).
        depth_deficit: float32 the MLE's depth score below its variant's best (0: no depth used
            or no valid sensor depth).
        color: float32 the MLE's colour score (the variant's best when colour is not used).
        mass: float32 the posterior mass (the normalized weight of the active particles) within
            ``mass_radius`` and ``mass_yaw`` of the estimate, in [0, 1]: how much of the filter's
            belief agrees with its estimate (reported, not part of the rule).
        confidence: float32 in [0, 1], the probability that the estimate is within 0.5 m and 10
            degrees of the truth (:class:`ConfidenceModel`; reported, not part of the rule).
    """

    localized: Array
    spread: Array
    ess_fraction: Array
    semantic_fraction: Array
    depth_deficit: Array
    color: Array
    mass: Array
    confidence: Array


def particle_spread(state: ParticleState) -> Array:
    """(4,) float32 weighted standard deviation of the active particles around their weighted
    mean: x, y, z in metres and yaw in radians (of the differences wrapped to [-pi, pi) around
    the circular mean). Zeros with no active particle."""
    weights, _ = normalized_weights(state.log_weights, state.active)
    poses = jnp.where(state.active[:, None], state.poses, 0.0)
    mean_xyz = jnp.sum(weights[:, None] * poses[:, :3], axis=0)
    mean_yaw = jnp.arctan2(
        jnp.sum(weights * jnp.sin(poses[:, 3])), jnp.sum(weights * jnp.cos(poses[:, 3]))
    )
    deviation = jnp.concatenate(
        [poses[:, :3] - mean_xyz, wrap_angle(poses[:, 3] - mean_yaw)[:, None]], axis=1
    )
    variance = jnp.sum(weights[:, None] * deviation**2, axis=0)
    return jnp.sqrt(jnp.maximum(variance, 0.0))


def best_semantic_score(match: PatchMatch) -> Array:
    """The semantic score of a view that shows every patch's best-matching object (float32): the
    most a pose in this map could score on this frame, in either variant (``"soft"`` also counts
    other objects, but a patch's own best object is its largest term)."""
    num_patches = match.cosines.shape[0]
    found = match.predicted >= 0
    safe = jnp.where(found, match.predicted, 0)
    cosine = jnp.take_along_axis(match.cosines, safe[:, None], axis=1)[:, 0]
    return jnp.sum(jnp.where(found, cosine + 1.0, 0.0)) / num_patches


def posterior_mass(state: ParticleState, estimate: Array, radius: Array, yaw: Array) -> Array:
    """The normalized weight (float32, in [0, 1]) of the active particles within ``radius``
    metres (3-D) and ``yaw`` radians (wrapped) of ``estimate`` (4,) = (x, y, z, yaw)."""
    weights, _ = normalized_weights(state.log_weights, state.active)
    offset = state.poses[:, :3] - estimate[:3]
    near = (jnp.sum(offset**2, axis=1) <= radius**2) & (
        jnp.abs(wrap_angle(state.poses[:, 3] - estimate[3])) <= yaw
    )
    return jnp.clip(jnp.sum(jnp.where(near & state.active, weights, 0.0)), 0.0, 1.0)


def confidence_logit(
    evidence: tuple[Array, Array, Array],
    known: tuple[Array, Array, Array],
    model: ConfidenceModel,
    use_depth: bool,
) -> Array:
    """The logit of :attr:`Verdict.confidence` (float32; see :class:`ConfidenceModel`).

    Args:
        evidence: ``(mass, semantic_fraction, depth_deficit)``.
        known: ``(sigma, rays, capacity)``: the likelihood width, the rays per particle and the
            particle capacity (positive).
        model: the weights.
        use_depth: whether the depth term enters.

    Works on arrays of any shape (the terms broadcast).
    """
    mass, semantic_fraction, depth_deficit = evidence
    sigma, rays, capacity = (jnp.asarray(v, jnp.float32) for v in known)
    clipped = jnp.clip(mass, MASS_CLIP, 1.0 - MASS_CLIP)
    logit = (
        model.bias
        + model.sigma_weight * jnp.log(sigma)
        + model.rays_weight * jnp.log(rays)
        + model.particles_weight * jnp.log(capacity)
        + model.mass_weight * (jnp.log(clipped) - jnp.log1p(-clipped))
        + model.semantic_weight * semantic_fraction
    )
    return logit - model.depth_weight * depth_deficit if use_depth else logit


def judge(
    state: ParticleState,
    estimate: Array,
    best: Scores,
    match: PatchMatch,
    observation: ObservationConfig,
    config: VerdictConfig,
    degenerate: Array,
    num_rays: Array,
) -> Verdict:
    """The verdict of one frame from the weighted particles after the update.

    Args:
        state: the particles after the Bayes update (before resampling).
        estimate: (4,) float32 the frame's estimate (the MLE particle's pose).
        best: the MLE particle's :class:`~jaxloc.sg2loc._scores.Scores`.
        match: the frame's :class:`~jaxloc.sg2loc._scores.PatchMatch`.
        observation: the observation model the scores came from (which terms, which variants).
        config: the thresholds.
        degenerate: bool, the update's weights fell back to uniform (never localized).
        num_rays: int32 rays per particle of the step's grid.
    """
    spread = particle_spread(state)
    active = jnp.maximum(jnp.sum(state.active), 1).astype(jnp.float32)
    ess_fraction = effective_sample_size(state) / active
    attainable = best_semantic_score(match)
    semantic_fraction = jnp.where(
        attainable > 0.0, best.semantic / jnp.where(attainable > 0.0, attainable, 1.0), 0.0
    )
    depth_deficit = (
        DEPTH_MAX[observation.depth_variant] - best.depth
        if observation.use_depth
        else jnp.zeros((), jnp.float32)
    )
    color = (
        best.color if observation.use_color else jnp.float32(COLOR_MAX[observation.color_variant])
    )
    localized = (
        (jnp.hypot(spread[0], spread[1]) <= config.max_spread_xy)
        & (spread[2] <= config.max_spread_z)
        & (spread[3] <= config.max_spread_yaw)
        & (ess_fraction <= config.max_ess_fraction)
        & (semantic_fraction >= config.min_semantic_fraction)
        & ~degenerate
    )
    if observation.use_depth:
        localized = localized & (depth_deficit <= config.max_depth_deficit)
    if observation.use_color:
        localized = localized & (color >= config.min_color)
    mass = posterior_mass(state, estimate, config.mass_radius, config.mass_yaw)
    known = (observation.sigma, num_rays, state.active.shape[0])
    logit = confidence_logit(
        (mass, semantic_fraction, depth_deficit), known, config.confidence, observation.use_depth
    )
    confidence = jnp.where(degenerate, 0.0, jax.nn.sigmoid(logit))
    return Verdict(
        localized,
        spread,
        ess_fraction,
        semantic_fraction,
        depth_deficit,
        color,
        mass,
        confidence,
    )
