"""Pose from associations: weighted Kabsch/Umeyama, then robust refinement (jaxloc.lsq)."""

from __future__ import annotations

import jax.numpy as jnp
import jaxlie
from jax import Array

from jaxloc.geometry import transform_points
from jaxloc.lsq import PoseSolution, RobustLoss, solve_pose


def weighted_kabsch(source: Array, target: Array, weights: Array) -> tuple[jaxlie.SE3, Array]:
    """Closed-form rigid transform ``T`` minimising ``sum w_i |T source_i - target_i|^2``.

    Args:
        source: (M, 3) points (e.g. scan frame); target: (M, 3) points (map frame); weights: (M,)
            non-negative (0 for padding).

    Returns:
        ``(T_target_source, ok)``: ``ok`` False (and T the identity) when fewer than 3 points carry
        weight, the weights are non-finite, or the result is non-finite. Reflections are corrected.
    """
    weights = jnp.where(jnp.isfinite(weights), jnp.maximum(weights, 0.0), 0.0)
    source = jnp.where(weights[:, None] > 0, source, 0.0)
    target = jnp.where(weights[:, None] > 0, target, 0.0)
    total = jnp.sum(weights)
    safe_total = jnp.where(total > 0, total, 1.0)
    mean_source = jnp.sum(weights[:, None] * source, axis=0) / safe_total
    mean_target = jnp.sum(weights[:, None] * target, axis=0) / safe_total
    covariance = jnp.matmul(
        ((target - mean_target) * weights[:, None]).T, source - mean_source, precision="highest"
    )
    u, _, vt = jnp.linalg.svd(covariance)
    sign = jnp.sign(jnp.linalg.det(jnp.matmul(u, vt, precision="highest")))
    sign = jnp.where(sign == 0, 1.0, sign)
    flip = jnp.array([1.0, 1.0, 1.0], source.dtype).at[2].set(sign)
    rotation = jnp.matmul(u * flip, vt, precision="highest")
    translation = mean_target - jnp.matmul(rotation, mean_source, precision="highest")
    ok = (
        (jnp.sum(weights > 0) >= 3)
        & jnp.all(jnp.isfinite(rotation))
        & jnp.all(jnp.isfinite(translation))
    )
    rotation = jnp.where(ok, rotation, jnp.eye(3, dtype=source.dtype))
    translation = jnp.where(ok, translation, 0.0)
    T = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_matrix(rotation), translation)
    return T, ok


def point_residuals(T: jaxlie.SE3, args: tuple[Array, Array, Array]) -> Array:
    """(M, 3) residuals ``T source_i - target_i`` (zeroed where the mask is False)."""
    source, target, mask = args
    return jnp.where(mask[:, None], transform_points(T, source) - target, 0.0)


def up_axis_prior(T: jaxlie.SE3, normal: Array, sigma: Array) -> Array:
    """(3,) residual ``(R e_z) x n / sigma``: the scan's up axis (in the map) along a road normal.

    Constrains roll and pitch only (rotations about ``n`` leave it unchanged); ``sigma`` radians.
    """
    up = T.rotation().as_matrix()[:, 2]
    return jnp.cross(up, normal) / sigma


def register(
    source: Array,
    target: Array,
    mask: Array,
    *,
    loss: RobustLoss,
    normal: Array | None = None,
    normal_sigma: Array | None = None,
    max_steps: int = 30,
) -> tuple[PoseSolution, Array]:
    """Kabsch initialisation on the masked pairs then robust refinement with an optional prior.

    Args:
        source: (M, 3) scan points; target: (M, 3) map points; mask: (M,) bool pairs to use.
        loss: robust loss for the refinement (e.g. GNC-TLS with a 1 m threshold).
        normal: optional (3,) unit road normal (map frame) for the roll/pitch prior.
        normal_sigma: prior standard deviation (radians) when ``normal`` is given.
        max_steps: optimiser steps per solve.

    Returns:
        ``(solution, kabsch_ok)``; ``solution.ok`` also requires ``kabsch_ok``.
    """
    T0, kabsch_ok = weighted_kabsch(source, target, mask.astype(source.dtype))
    prior_fn = None
    if normal is not None:
        prior_fn = lambda T, args: up_axis_prior(T, normal, normal_sigma)  # noqa: E731
    solution = solve_pose(
        point_residuals,
        T0,
        (source, target, mask),
        loss=loss,
        prior_fn=prior_fn,
        max_steps=max_steps,
    )
    ok = solution.ok & kabsch_ok
    return solution.__class__(
        pose=solution.pose,
        ok=ok,
        status=solution.status,
        steps=solution.steps,
        cost=solution.cost,
        weights=solution.weights,
    ), kabsch_ok
