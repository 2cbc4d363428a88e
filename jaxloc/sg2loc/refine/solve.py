"""The refinement solve: alternate depth association and a robust Levenberg-Marquardt step
(:func:`refine_pose`), then check degeneracy and fit (see :mod:`jaxloc.sg2loc.refine`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jax import Array

from jaxloc.camera import Camera
from jaxloc.geometry import se3_to_yaw_pose
from jaxloc.lsq import RobustLoss, robust_block_scale, solve_pose
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc.refine.config import (
    SETTLED_ROTATION,
    SETTLED_TRANSLATION,
    STATUS_BAD_INPUT,
    STATUS_CONVERGED,
    STATUS_DEGENERATE,
    STATUS_DIVERGED,
    STATUS_POOR_FIT,
    STATUS_TOO_FEW_RESIDUALS,
    Observations,
    RefineConfig,
    RefineResult,
)
from jaxloc.sg2loc.refine.residuals import (
    DepthPlanes,
    associate_depth,
    point_to_plane,
    reprojection_residuals,
)


def _frame_poses(T_anchor: jaxlie.SE3, T_rel: jaxlie.SE3) -> jaxlie.SE3:
    """``T_anchor @ T_rel[t]`` for every frame: SE3 with a leading (F,) axis."""
    return jax.vmap(lambda rel: T_anchor @ jaxlie.SE3(rel))(T_rel.parameters())


def _associate_all(T_anchor, T_rel, scene, camera, obs: Observations, config) -> DepthPlanes:
    """Planes (F, N, ...) of every frame's depth pixels at the anchor pose ``T_anchor``."""
    poses = _frame_poses(T_anchor, T_rel)
    return jax.vmap(
        lambda p, d: associate_depth(
            jaxlie.SE3(p),
            scene,
            camera,
            obs.depth_uv,
            d,
            config.min_incidence,
            config.search_radius,
            config.search_spacing,
            engine=config.engine,
        )
    )(poses.parameters(), obs.depth)


def _blocks(T_anchor, T_rel, camera, obs: Observations, planes: DepthPlanes, config):
    """Normalised residual blocks (F * (N + M), 2), their validity (F * (N + M),) and the valid
    counts (depth, matches).

    Depth residuals are divided by ``depth_sigma_abs + depth_sigma_rel * depth`` and padded to
    blocks ``(r, 0)``; reprojection residuals are divided by ``pixel_sigma``.
    """

    def one(pose, depth, frame_planes, match_uv, match_points, match_valid):
        pose = jaxlie.SE3(pose)
        blocks, valid, num_depth, num_matches = [], [], jnp.int32(0), jnp.int32(0)
        if config.uses_depth:
            r, ok = point_to_plane(pose, camera, obs.depth_uv, depth, frame_planes)
            sigma = config.depth_sigma_abs + config.depth_sigma_rel * jnp.where(ok, depth, 0.0)
            r = r / jnp.where(ok, sigma, 1.0)
            blocks.append(jnp.stack([r, jnp.zeros_like(r)], axis=-1))
            valid.append(ok)
            num_depth = jnp.sum(ok, dtype=jnp.int32)
        if config.uses_matches:
            r, ok = reprojection_residuals(
                pose, camera, match_uv, match_points, match_valid, config.min_depth
            )
            blocks.append(r / config.pixel_sigma)
            valid.append(ok)
            num_matches = jnp.sum(ok, dtype=jnp.int32)
        return jnp.concatenate(blocks), jnp.concatenate(valid), num_depth, num_matches

    poses = _frame_poses(T_anchor, T_rel)
    blocks, valid, num_depth, num_matches = jax.vmap(one)(
        poses.parameters(), obs.depth, planes, obs.match_uv, obs.match_points, obs.match_valid
    )
    return blocks.reshape(-1, 2), valid.reshape(-1), jnp.sum(num_depth), jnp.sum(num_matches)


def _inlier_fraction(blocks_and_valid: tuple[Array, Array], threshold: Array) -> Array:
    """Fraction of the valid (K,) residual blocks (K, 2) with norm <= ``threshold`` (0 if none)."""
    blocks, valid = blocks_and_valid
    inside = valid & (jnp.sum(blocks**2, axis=-1) <= threshold**2)
    return jnp.sum(inside) / jnp.maximum(jnp.sum(valid), 1)


def _pose_std(blocks_fn, T: jaxlie.SE3, loss: RobustLoss) -> tuple[Array, Array]:
    """Worst-direction 1-sigma position (metres) and rotation (radians) uncertainty at ``T``.

    ``blocks_fn(T) -> (K, D)`` noise-normalised residual blocks (zero where masked). The
    information ``H = J^T W J`` uses the tangent Jacobian ``J`` of ``T @ exp(delta)`` at
    ``delta = 0`` (translation part in the camera frame: metres) and the robust loss's IRLS block
    weights ``W``; the marginal covariance blocks of ``H^-1`` give the two numbers (``inf`` where
    ``H`` is singular to float precision or non-finite).
    """
    T = jax.lax.stop_gradient(T)
    blocks = blocks_fn(T)
    jacobian = jax.jacfwd(lambda delta: blocks_fn(T @ jaxlie.SE3.exp(delta)))(
        jnp.zeros(6, blocks.dtype)
    )  # (K, D, 6)
    weight = robust_block_scale(jnp.sum(blocks * blocks, axis=-1), loss) ** 2
    jacobian = jnp.where(jnp.isfinite(jacobian), jacobian, 0.0).reshape(-1, blocks.shape[-1], 6)
    information = jnp.einsum("k,kdi,kdj->ij", weight, jacobian, jacobian, precision="highest")
    eigenvalues, vectors = jnp.linalg.eigh(information)
    # Eigenvalues below float32 rounding of the largest carry no information.
    floor = 1e-6 * jnp.maximum(eigenvalues[-1], 0.0)
    determined = (eigenvalues > floor) & (eigenvalues > 0)
    inverse = jnp.where(determined, 1.0 / jnp.where(determined, eigenvalues, 1.0), 0.0)
    finite = jnp.all(jnp.isfinite(information))

    def worst(rows: slice) -> Array:
        part = vectors[rows]  # (3, 6): this block's share of each eigenvector
        std = jnp.sqrt(
            jnp.maximum(
                jnp.linalg.eigvalsh(jnp.matmul(part * inverse, part.T, precision="highest"))[-1],
                0.0,
            )
        )
        free = jnp.any(~determined & (jnp.linalg.norm(part, axis=0) > 1e-3))
        return jnp.where(free | ~finite, jnp.inf, std)

    return worst(slice(0, 3)), worst(slice(3, 6))


def refine_pose(
    scene: SceneGraph,
    camera: Camera,
    T_init: jaxlie.SE3,
    T_rel: jaxlie.SE3,
    observations: Observations,
    config: RefineConfig,
) -> RefineResult:
    """Refine the anchor pose ``T_world_cam`` of the last frame; pure, jit/vmap-able.

    Depth residuals use projective data association, as projective ICP: each of
    ``config.rounds`` rounds raycasts the depth pixels from the current pose (fixing the hit
    planes), then runs :func:`~jaxloc.lsq.solve_pose` on the fixed-plane residuals (smooth in the
    pose, so the solver's linearisation is exact up to second order). Reprojection residuals need
    no association and take part in every round.

    Args:
        scene: the map.
        camera: intrinsics (static size).
        T_init: initial ``T_world_cam`` of the last frame.
        T_rel: (F,) fixed ``T_last^-1 T_t`` of each frame (identity for a single frame).
        observations: :class:`Observations` of the F frames.
        config: :class:`RefineConfig` (its ``mode`` is not used here: F is given by ``T_rel``).

    Returns:
        :class:`RefineResult`; on failure ``ok`` is False, ``status`` says why and the pose is
        ``T_init`` (or the identity if ``T_init`` is non-finite).
    """

    def associate(T: jaxlie.SE3) -> DepthPlanes:
        if config.uses_depth:
            return _associate_all(T, T_rel, scene, camera, observations, config)
        empty = jnp.zeros(observations.depth.shape + (3,), jnp.float32)
        return DepthPlanes(empty, empty, jnp.zeros(observations.depth.shape, bool))

    def residual_fn(T: jaxlie.SE3, planes: DepthPlanes) -> Array:
        return _blocks(T, T_rel, camera, observations, planes, config)[0]

    planes0 = associate(T_init)
    _, _, num_depth, num_matches = _blocks(T_init, T_rel, camera, observations, planes0, config)
    enough = jnp.bool_(False)
    if config.uses_depth:
        enough = enough | (num_depth >= config.min_depth_pixels)
    if config.uses_matches:
        enough = enough | (num_matches >= config.min_matches)

    def solve_round(T: jaxlie.SE3, planes: DepthPlanes):
        return solve_pose(
            residual_fn,
            T,
            planes,
            loss=config.loss,
            max_steps=steps_per_round,
            method=config.method,
        )

    def round_(carry, _):
        params, steps, input_ok, settled, last, last_planes = carry

        def run():
            T = jaxlie.SE3(params)
            planes = associate(T)
            solution = solve_round(T, planes)
            step = T.inverse() @ solution.pose
            # A pose that has stopped moving gets the same association and the same solve again:
            # the rounds after it are skipped (they would cost a raycast and a solve each).
            still = (jnp.linalg.norm(step.translation()) < SETTLED_TRANSLATION) & (
                jnp.linalg.norm(step.rotation().log()) < SETTLED_ROTATION
            )
            return (
                solution.pose.parameters(),
                steps + solution.steps,
                input_ok & (solution.status != STATUS_BAD_INPUT),
                solution.ok & still,
                solution,
                planes,
            )

        return jax.lax.cond(settled, lambda: carry, run), None

    rounds, steps_per_round = config.rounds, config.max_steps
    if not config.uses_depth:  # nothing to re-associate: one round, the same step budget
        rounds, steps_per_round = 1, config.rounds * config.max_steps
    placeholder = jax.tree.map(
        lambda a: jnp.zeros(a.shape, a.dtype), jax.eval_shape(solve_round, T_init, planes0)
    )
    start = (
        T_init.parameters(),
        jnp.int32(0),
        jnp.bool_(True),
        jnp.bool_(False),
        placeholder,
        planes0,
    )
    (params, steps, input_ok, _, last, last_planes), _ = jax.lax.scan(
        round_, start, None, length=rounds
    )
    T_final = jaxlie.SE3(params)
    position_std, rotation_std = _pose_std(
        lambda T: residual_fn(T, last_planes), T_final, config.loss
    )
    solved = last.ok & input_ok
    motion = T_init.inverse() @ T_final
    moved = jnp.linalg.norm(motion.translation())
    turned = jnp.linalg.norm(motion.rotation().log())
    diverged = solved & ~((moved <= config.max_translation) & (turned <= config.max_rotation))
    determined = (position_std <= config.max_position_std) & (
        rotation_std <= config.max_rotation_std
    )
    inlier_fraction = _inlier_fraction(
        _blocks(T_final, T_rel, camera, observations, associate(T_final), config)[:2],
        config.inlier_threshold,
    )
    fits = inlier_fraction >= config.min_inlier_fraction
    ok = solved & enough & ~diverged & determined & fits
    status = jnp.select(
        [~input_ok, ~last.ok, ~enough, diverged, ~determined, ~fits],
        [
            STATUS_BAD_INPUT,
            last.status,
            STATUS_TOO_FEW_RESIDUALS,
            STATUS_DIVERGED,
            STATUS_DEGENERATE,
            STATUS_POOR_FIT,
        ],
        STATUS_CONVERGED,
    ).astype(jnp.int32)
    identity = jnp.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], params.dtype)
    init_params = T_init.parameters()
    safe_init = jnp.where(jnp.all(jnp.isfinite(init_params)), init_params, identity)
    pose = jaxlie.SE3(jnp.where(ok, params, safe_init))
    return RefineResult(
        pose=pose,
        yaw_pose=se3_to_yaw_pose(pose),
        frame_poses=_frame_poses(pose, T_rel),
        ok=ok,
        status=status,
        steps=steps,
        cost=jnp.where(ok, last.cost, jnp.inf),
        num_depth=num_depth,
        num_matches=num_matches,
        position_std=position_std,
        rotation_std=rotation_std,
        inlier_fraction=inlier_fraction,
    )


#: The jitted solve the host-side entry points call.
refine_pose_jit = eqx.filter_jit(refine_pose)
