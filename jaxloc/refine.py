"""Visual 6-DoF pose refinement of SG2Loc's estimate (replaces SG2Loc's RoMa + PnP step).

Starting from the filter's 4-DoF estimate ``(x, y, z, yaw)`` plus the frame's known tilt, a robust
Levenberg-Marquardt solve (:func:`jaxloc.lsq.solve_pose`, tangent-space updates
``T = T_init @ SE3.exp(delta)``) refines ``T_world_cam`` with

(a) **depth-to-mesh residuals**: a strided subset of the depth image's pixels is back-projected with
    the intrinsics and the current pose, ``p_world = T_world_cam (depth * K^-1 [u, v, 1])``, and
    compared with the scene raycast along the pixel ray (point-to-plane): ``r = n . (p_world -
    p_hit)`` with ``p_hit`` the raycast hit and ``n`` the unit normal of the hit triangle. ``p_hit``
    lies on that triangle's plane, so this equals ``n . (p_world - v0)`` (``v0`` a corner of the
    triangle), which is how it is evaluated (no cancellation for long rays). The association
    (which triangle) is piecewise constant in the pose and carries no gradient; the residual is
    smooth for a fixed triangle. The solve alternates association and least squares (projective
    ICP, ``RefineConfig.rounds``), and associates within a small window of neighbouring rays
    (the hit nearest in 3-D to the back-projected point, :func:`associate_depth`), because pure
    projective association leaves points seen across an occlusion edge on the wrong surface, where
    their residual carries no information and the solve stalls (measured: 3 of 4 starts at 0.3 m /
    10 deg stalled 0.19 m off in height on a synthetic room frame; none with the window).
    Invalid pixels (depth 0 or non-finite), misses and grazing hits (``|n . d| < min_incidence``)
    get a zero residual. Residuals are divided by the depth noise
    ``depth_sigma_abs + depth_sigma_rel * depth``.
(b) **reprojection residuals** of user-given 2D-3D correspondences (pixel ``uv`` (M, 2), world
    points (M, 3), optional validity mask): ``(pi(T_world_cam^-1 X) - uv) / pixel_sigma``, one 2-D
    block per correspondence. Points closer than ``min_depth`` in front of the camera (or behind
    it), non-finite rows and masked rows get a zero residual (the division is guarded, so values and
    gradients stay finite).
(c) **both**: the blocks of (a) (as ``(r, 0)``) and (b) are stacked. The relative weighting is the
    noise model: each residual is divided by its standard deviation (metres for depth, pixels for
    reprojection), so the cost is the robustified negative log-likelihood of independent Gaussian
    noise, and the robust loss (``RefineConfig.loss``) acts on these normalised residuals (its scale
    is in units of sigma).

Sequences: with ``mode="sequence"`` every frame of a sequence contributes, through the known
ego-motion and tilts. The unknown is one SE(3) *anchor*, the last frame's ``T_world_cam``; frame t
is at ``T_anchor @ T_rel[t]``, where ``T_rel[t] = T_last^-1 T_t`` is fixed by the 4-DoF chain
(the last frame's estimate carried back through the ego-motion, :func:`frame_poses_from_last`) and
the frames' tilts. ``mode="last"`` uses the last frame alone.

Status codes of :class:`RefineResult` (failures are values; the pose is then the initial pose):
0 converged, 1 not converged (step budget or non-finite iterate), 2 non-finite or empty input
(from :func:`~jaxloc.lsq.solve_pose`), 3 too few valid residuals at the initial pose,
4 diverged (the solve moved farther than ``max_translation`` / ``max_rotation`` from the start),
5 degenerate (the data leave the pose undetermined along some direction, see below), 6 poor fit
(the solved pose explains too few of the observations, see below).

Degeneracy: a converged solve can still be wrong when the residuals do not constrain every degree
of freedom (a view of one wall leaves the translation along the wall and the rotation about its
normal free; a wall and the floor leave the translation along their intersection free), because
the solver then slides along the free direction while every residual stays zero. At the final
pose (and the last round's association) the Gauss-Newton information ``H = J^T W J`` of the
noise-normalised residuals in the pose tangent (``J`` (K, 6), ``W`` the robust loss's IRLS
weights) is the inverse covariance of the estimate under the configured noise model; the 1-sigma
standard deviations along the worst translation and rotation directions are
``sqrt(max eig [H^-1]_tt)`` (metres) and ``sqrt(max eig [H^-1]_rr)`` (radians) (marginal blocks,
so a free direction that mixes translation and rotation shows in both). They are reported as
``RefineResult.position_std`` / ``rotation_std``; above ``RefineConfig.max_position_std`` /
``max_rotation_std`` the result is status 5, not ok. This flags free directions only: a
well-constrained solve that converged to a wrong local minimum is not detected by it.

Fit check: at the solved pose the depth pixels are associated afresh and
``RefineResult.inlier_fraction`` is the fraction of the valid residual blocks within
``inlier_threshold`` sigma. A wrong local minimum leaves many observations unexplained; below
``RefineConfig.min_inlier_fraction`` the result is status 6, not ok. 0, the default, disables the
check, because the fraction at the true pose depends on how well the map's meshes model the sensed
surfaces and on the matcher's outlier rate, which only the user knows. Measured on synthetic
frames, whose depth is rendered from the map's own meshes: noise-free, 1.000 at every right answer
and 0.92 at the two wrong minima of depth-only refinement (``convergence.md`` in
``experiments/results/refine/``); with 2 % depth noise, holes and 10 % scene changes, 0.997-1.000
for depth alone at the refined pose, but 0.72-0.84 for matches with 20 % outliers (``table.md``).
Coarse meshes of real objects will sit lower; measure it on your own data before setting it.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jax import Array

from jaxloc._engines import check_engine_name
from jaxloc._refine_residuals import (
    DepthPlanes,
    associate_depth,
    depth_residuals,
    point_to_plane,
    reprojection_residuals,
)
from jaxloc.camera import Camera, stride_grid
from jaxloc.geometry import se3_to_yaw_pose, uncompose_yaw, yaw_pose_to_se3
from jaxloc.lsq import RobustLoss, robust_block_scale, solve_pose
from jaxloc.scene import SceneGraph
from jaxloc.sequence import Sequence

__all__ = [
    "STATUS_BAD_INPUT",
    "STATUS_CONVERGED",
    "STATUS_DEGENERATE",
    "STATUS_DIVERGED",
    "STATUS_NOT_CONVERGED",
    "STATUS_POOR_FIT",
    "STATUS_TOO_FEW_RESIDUALS",
    "DepthPlanes",
    "Observations",
    "RefineConfig",
    "RefineResult",
    "associate_depth",
    "correspondences",
    "depth_residuals",
    "depth_samples",
    "frame_poses_from_last",
    "point_to_plane",
    "refine",
    "refine_frame",
    "refine_pose",
    "reprojection_residuals",
]

ResidualKind = Literal["depth", "reprojection", "both"]
Mode = Literal["last", "sequence"]

STATUS_CONVERGED = 0
STATUS_NOT_CONVERGED = 1
STATUS_BAD_INPUT = 2
STATUS_TOO_FEW_RESIDUALS = 3
STATUS_DIVERGED = 4
STATUS_DEGENERATE = 5
STATUS_POOR_FIT = 6

#: A round that moves the pose less than this (metres, radians) ends the association rounds.
SETTLED_TRANSLATION = 1e-4
SETTLED_ROTATION = 1e-4


class RefineConfig(eqx.Module):
    """Settings of the refinement. Kinds, sizes and step budgets are static; the rest is traced.

    Attributes:
        residuals: "depth" (a), "reprojection" (b) or "both" (c) (static).
        mode: "last" (refine the last frame alone) or "sequence" (all frames jointly through the
            ego-motion, one SE(3) anchor) (static).
        depth_stride: every ``depth_stride``-th pixel of the depth image is used (static).
        depth_sigma_abs, depth_sigma_rel: depth noise ``abs + rel * depth`` (metres, fraction)
            that normalises the depth residuals.
        pixel_sigma: reprojection noise (pixels) that normalises the reprojection residuals.
        loss: robust loss on the normalised residual blocks (scale in units of sigma).
        min_incidence: depth pixels whose ray meets the hit plane with ``|cos| < min_incidence``
            (grazing) are dropped.
        search_radius, search_spacing: association window of the depth pixels in candidate rays
            (static) and pixels between them (:func:`associate_depth`; 0 = projective).
        min_depth: correspondences less than this far in front of the camera (metres) are dropped.
        min_depth_pixels, min_matches: fewest valid depth pixels / correspondences (over all frames,
            at the initial pose) for that residual type to count; with neither enough the result is
            status 3 (static).
        max_translation, max_rotation: a solve that moves the pose farther than this (metres,
            radians) is reported as diverged (status 4).
        max_position_std, max_rotation_std: a converged solve whose 1-sigma pose uncertainty
            along its worst direction exceeds this (metres, radians; module docstring) is reported
            as degenerate (status 5).
        inlier_threshold: a residual block is an inlier of the final pose when its norm is at
            most this (in units of sigma).
        min_inlier_fraction: a converged, determined solve whose final pose explains less than
            this fraction of the valid residuals (depth re-associated at the final pose) is
            reported as a poor fit (status 6); 0 disables the check (module docstring).
        rounds: the most data-association rounds of the depth residuals (projective ICP;
            static); each restarts the solver from the last iterate, and once a round moves the
            pose less than 0.1 mm and 0.1 mrad the remaining rounds are skipped. 16 by default: in
            the noise-free sweep (experiments/results/refine/convergence.md) joint depth
            refinement of a sequence was still moving after 8 rounds on 2 of 12 starts (0.31 m
            off) and converged with 16. Reprojection-only refinement needs no
            association and runs one round of ``rounds * max_steps`` steps (the same budget):
            restarting Levenberg-Marquardt every ``max_steps`` resets its damping, and with the
            Huber loss far outside its scale it needs more than 20 consecutive steps (measured:
            8 rounds x 20 steps left the same starts unconverged as 1 x 20;
            experiments/results/refine/convergence.md).
        max_steps: optimiser steps per round (static).
        method: "lm" (Levenberg-Marquardt) or "gn" (Gauss-Newton) (static).
        engine: nearest-hit engine of the depth association (static; see
            :func:`jaxloc.raycast`).
    """

    residuals: ResidualKind = eqx.field(static=True, default="depth")
    mode: Mode = eqx.field(static=True, default="last")
    depth_stride: int = eqx.field(static=True, default=4)
    depth_sigma_abs: float = 0.01
    depth_sigma_rel: float = 0.02
    pixel_sigma: float = 1.0
    loss: RobustLoss = RobustLoss("huber", 2.0)
    min_incidence: float = 0.1
    search_radius: int = eqx.field(static=True, default=2)
    search_spacing: float = 4.0
    min_depth: float = 0.05
    min_depth_pixels: int = eqx.field(static=True, default=12)
    min_matches: int = eqx.field(static=True, default=4)
    max_translation: float = 1.0
    max_rotation: float = 0.6
    max_position_std: float = 0.05
    max_rotation_std: float = 0.02
    inlier_threshold: float = 3.0
    min_inlier_fraction: float = 0.0
    rounds: int = eqx.field(static=True, default=16)
    max_steps: int = eqx.field(static=True, default=20)
    method: Literal["lm", "gn"] = eqx.field(static=True, default="lm")
    engine: str = eqx.field(static=True, default="auto")

    def __check_init__(self) -> None:
        check_engine_name(self.engine)
        if self.residuals not in ("depth", "reprojection", "both"):
            raise ValueError(
                f"residuals must be 'depth', 'reprojection' or 'both', got {self.residuals!r}"
            )
        if self.mode not in ("last", "sequence"):
            raise ValueError(f"mode must be 'last' or 'sequence', got {self.mode!r}")
        if not isinstance(self.rounds, int) or self.rounds < 1:
            raise ValueError(f"rounds must be a positive int, got {self.rounds!r}")
        if not isinstance(self.depth_stride, int) or self.depth_stride < 1:
            raise ValueError(f"depth_stride must be a positive int, got {self.depth_stride!r}")
        if self.method not in ("lm", "gn"):
            raise ValueError(f"method must be 'lm' or 'gn', got {self.method!r}")
        for name in (
            "pixel_sigma",
            "max_translation",
            "max_rotation",
            "max_position_std",
            "max_rotation_std",
            "inlier_threshold",
        ):
            value = getattr(self, name)
            if isinstance(value, float | int) and not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        for name in ("depth_sigma_abs", "depth_sigma_rel"):
            value = getattr(self, name)
            if isinstance(value, float | int) and not value >= 0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        abs_, rel = self.depth_sigma_abs, self.depth_sigma_rel
        if isinstance(abs_, float | int) and isinstance(rel, float | int) and abs_ + rel <= 0:
            raise ValueError("depth_sigma_abs + depth_sigma_rel must be > 0")
        fraction = self.min_inlier_fraction
        if isinstance(fraction, float | int) and not 0.0 <= fraction <= 1.0:
            raise ValueError(f"min_inlier_fraction must be in [0, 1], got {fraction}")

    @property
    def uses_depth(self) -> bool:
        return self.residuals in ("depth", "both")

    @property
    def uses_matches(self) -> bool:
        return self.residuals in ("reprojection", "both")


class Observations(eqx.Module):
    """What the refinement compares against, for F frames (F = 1 in ``mode="last"``).

    Attributes:
        depth_uv: (N, 2) float32 pixel coordinates of the depth samples (shared by all frames).
        depth: (F, N) float32 depth along the optical axis (metres); 0 or non-finite = invalid.
        match_uv: (F, M, 2) float32 pixel coordinates of the correspondences.
        match_points: (F, M, 3) float32 their world points (metres).
        match_valid: (F, M) bool, which correspondences count.
    """

    depth_uv: Array
    depth: Array
    match_uv: Array
    match_points: Array
    match_valid: Array


class RefineResult(eqx.Module):
    """Result of a refinement (a pytree; batch axes come from vmap).

    Attributes:
        pose: refined ``T_world_cam`` of the last frame (jaxlie.SE3); the initial pose when
            ``ok`` is False.
        yaw_pose: (4,) ``(x, y, z, yaw)`` of ``pose`` (pitch and roll dropped).
        frame_poses: ``T_world_cam`` of every frame (jaxlie.SE3 with a leading (F,) axis):
            ``pose @ T_rel[t]``, the frames placed through the ego-motion and tilts.
        ok: bool scalar, the solve converged, enough residuals were valid, it did not diverge and
            the pose is determined (not degenerate).
        status: int32 scalar: 0 converged, 1 not converged, 2 bad input, 3 too few residuals,
            4 diverged, 5 degenerate, 6 poor fit (module docstring).
        steps: int32 scalar, optimiser steps.
        cost: float32 scalar, final robustified cost (``inf`` when not ``ok``).
        num_depth: int32 scalar, valid depth residuals at the initial pose (all frames).
        num_matches: int32 scalar, valid correspondences at the initial pose (all frames).
        position_std: float32 scalar, 1-sigma position uncertainty (metres) of the solved pose
            along its worst direction, from the Gauss-Newton information (module docstring);
            ``inf`` where undetermined or non-finite.
        rotation_std: float32 scalar, the same for the rotation (radians).
        inlier_fraction: float32 scalar in [0, 1], the fraction of the valid residual blocks at
            the solved pose (depth re-associated there) whose norm is at most
            ``config.inlier_threshold`` sigma (0 when none is valid).
    """

    pose: jaxlie.SE3
    yaw_pose: Array
    frame_poses: jaxlie.SE3
    ok: Array
    status: Array
    steps: Array
    cost: Array
    num_depth: Array
    num_matches: Array
    position_std: Array
    rotation_std: Array
    inlier_fraction: Array


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


# ----------------------------------------------------------------------------- the solve


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
    information = jnp.einsum("k,kdi,kdj->ij", weight, jacobian, jacobian)
    eigenvalues, vectors = jnp.linalg.eigh(information)
    # Eigenvalues below float32 rounding of the largest carry no information.
    floor = 1e-6 * jnp.maximum(eigenvalues[-1], 0.0)
    determined = (eigenvalues > floor) & (eigenvalues > 0)
    inverse = jnp.where(determined, 1.0 / jnp.where(determined, eigenvalues, 1.0), 0.0)
    finite = jnp.all(jnp.isfinite(information))

    def worst(rows: slice) -> Array:
        part = vectors[rows]  # (3, 6): this block's share of each eigenvector
        std = jnp.sqrt(jnp.maximum(jnp.linalg.eigvalsh((part * inverse) @ part.T)[-1], 0.0))
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
            # A pose that no longer moves gets the same association and the same solve again:
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


_refine_pose_jit = eqx.filter_jit(refine_pose)


# ----------------------------------------------------------------------------- host-side helpers


def frame_poses_from_last(yaw_pose_last: Array, ego_motion: Array, tilt: Array) -> jaxlie.SE3:
    """``T_world_cam`` (F,) of every frame from the last frame's 4-DoF pose and the ego-motion.

    Args:
        yaw_pose_last: (4,) ``(x, y, z, yaw)`` of the last frame.
        ego_motion: (F-1, 4) motion from frame t to t+1 in frame t's body frame.
        tilt: (F, 2) known (pitch, roll) of every frame.
    """

    def back(current, motion):
        previous = uncompose_yaw(current, motion)
        return previous, previous

    _, earlier = jax.lax.scan(back, yaw_pose_last, ego_motion, reverse=True)
    yaw_poses = jnp.concatenate([earlier, yaw_pose_last[None]], axis=0)
    return jax.vmap(yaw_pose_to_se3)(yaw_poses, tilt)


def depth_samples(camera: Camera, depth_image, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ``stride``-th pixel of depth images: uv (N, 2) and depth (..., N) (host numpy).

    ``depth_image`` is (..., H, W) metres along the optical axis, 0 = invalid. Pixels are those
    of :func:`jaxloc.stride_grid` (centres at integer coordinates).
    """
    uv = np.asarray(stride_grid(camera, stride).uv)
    cols = uv[:, 0].astype(int)
    rows = uv[:, 1].astype(int)
    return uv, np.asarray(depth_image, np.float32)[..., rows, cols]


def _as_array(name: str, value, shape_tail: tuple[int, ...], ndim: int) -> np.ndarray:
    array = np.asarray(value)
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise TypeError(f"{name} must be a real numeric array, got dtype {array.dtype}")
    if array.ndim != ndim or array.shape[ndim - len(shape_tail) :] != shape_tail:
        tail = ", ".join(str(s) for s in shape_tail)
        lead = "(F, M, " if ndim == len(shape_tail) + 2 else "(M, "
        raise ValueError(f"{name} must have shape {lead}{tail}), got {array.shape}")
    array = array.astype(np.float32)
    if not np.all(np.isfinite(array)):
        bad = int(np.sum(~np.isfinite(array)))
        raise ValueError(
            f"{name} contains {bad} NaN/inf values (drop those correspondences or mask them)"
        )
    return array


def correspondences(uv, points_world, valid=None, *, num_frames: int | None = None):
    """Validated correspondence arrays for :func:`refine`: (F, M, 2), (F, M, 3), (F, M) bool.

    Args:
        uv: pixel coordinates (M, 2) of one frame, or (F, M, 2) for ``num_frames = F`` frames.
        points_world: the matching world points (M, 3) or (F, M, 3), metres.
        valid: optional mask (M,) or (F, M); rows whose mask is False are ignored.
        num_frames: F for per-frame arrays (``mode="sequence"``); None for one frame.

    Raises:
        ValueError naming the argument on a wrong shape or NaN/inf values.
    """
    ndim = 2 if num_frames is None else 3
    uv = _as_array("uv", uv, (2,), ndim)
    points = _as_array("points_world", points_world, (3,), ndim)
    if points.shape[:-1] != uv.shape[:-1]:
        raise ValueError(
            f"points_world {points.shape} must match uv {uv.shape} (one world point per pixel)"
        )
    if num_frames is not None and uv.shape[0] != num_frames:
        raise ValueError(f"uv has {uv.shape[0]} frames, expected {num_frames}")
    if valid is None:
        valid = np.ones(uv.shape[:-1], bool)
    valid = np.asarray(valid)
    if valid.shape != uv.shape[:-1] or valid.dtype != bool:
        raise ValueError(f"valid must be a bool array of shape {uv.shape[:-1]}, got {valid.shape}")
    if num_frames is None:
        uv, points, valid = uv[None], points[None], valid[None]
    return uv, points, valid


def refine_frame(
    scene: SceneGraph,
    camera: Camera,
    T_init: jaxlie.SE3,
    config: RefineConfig | None = None,
    *,
    depth=None,
    match_uv=None,
    match_points=None,
    match_valid=None,
    T_rel: jaxlie.SE3 | None = None,
) -> RefineResult:
    """Refine ``T_world_cam`` from a full SE(3) start (``config.mode`` is ignored).

    One frame by default. With ``T_rel`` (F,) (each frame's pose relative to the last one,
    ``T_last^-1 T_t``, e.g. from visual-inertial odometry) the F frames are refined jointly, as
    ``mode="sequence"`` does with the filter's 4-DoF ego-motion, and the observations are per
    frame.

    Args:
        scene: the map; camera: intrinsics.
        T_init: initial ``T_world_cam`` of the (last) frame (jaxlie.SE3, unbatched).
        config: :class:`RefineConfig`.
        depth: (H, W) depth image (metres along the optical axis, 0 = invalid), for depth residuals;
            (F, H, W) with ``T_rel``.
        match_uv, match_points, match_valid: (M, 2), (M, 3), optional (M,) correspondences;
            (F, M, 2), (F, M, 3), (F, M) with ``T_rel``.
        T_rel: optional jaxlie.SE3 with a leading (F,) axis, the last entry the identity.
    """
    config = RefineConfig() if config is None else config
    params = np.asarray(T_init.parameters())
    if params.shape != (7,) or not np.all(np.isfinite(params)):
        raise ValueError(f"T_init must be one finite jaxlie.SE3, got parameters {params!r}")
    if T_rel is None:
        rel = np.asarray(jaxlie.SE3.identity((1,)).parameters())
    else:
        rel = np.asarray(T_rel.parameters())
        if rel.ndim != 2 or rel.shape[0] < 1 or rel.shape[1] != 7 or not np.all(np.isfinite(rel)):
            raise ValueError(
                f"T_rel must be a finite jaxlie.SE3 with one leading (F,) axis, got parameters "
                f"of shape {rel.shape}"
            )
    frames = rel.shape[0]
    if config.uses_depth:
        if depth is None:
            raise ValueError(f"residuals={config.residuals!r} needs a depth image")
        depth = np.asarray(depth, np.float32)
        expected = (
            (camera.height, camera.width)
            if T_rel is None
            else (frames, camera.height, camera.width)
        )
        if depth.shape != expected:
            names = "(H, W)" if T_rel is None else "(F, H, W)"
            raise ValueError(f"depth must have shape {names} = {expected}, got {depth.shape}")
        if T_rel is None:
            depth = depth[None]
    observations = _observations(
        camera,
        config,
        frames,
        depth,
        match_uv,
        match_points,
        match_valid,
        per_frame=T_rel is not None,
    )
    return _refine_pose_jit(
        scene,
        camera,
        jaxlie.SE3(jnp.asarray(params)),
        jaxlie.SE3(jnp.asarray(rel)),
        observations,
        config,
    )


def _observations(
    camera, config, frames, depth_images, match_uv, match_points, match_valid, per_frame
) -> Observations:
    """Validated :class:`Observations` of ``frames`` frames (host side)."""
    if config.uses_matches:
        if match_uv is None or match_points is None:
            raise ValueError(
                f"residuals={config.residuals!r} needs match_uv and match_points correspondences"
            )
        uv, points, valid = correspondences(
            match_uv, match_points, match_valid, num_frames=frames if per_frame else None
        )
    else:
        uv = np.zeros((frames, 0, 2), np.float32)
        points = np.zeros((frames, 0, 3), np.float32)
        valid = np.zeros((frames, 0), bool)
    if config.uses_depth:
        depth_uv, depth = depth_samples(camera, depth_images, config.depth_stride)
    else:
        depth_uv, depth = np.zeros((0, 2), np.float32), np.zeros((frames, 0), np.float32)
    return Observations(
        depth_uv=jnp.asarray(depth_uv),
        depth=jnp.asarray(depth),
        match_uv=jnp.asarray(uv),
        match_points=jnp.asarray(points),
        match_valid=jnp.asarray(valid),
    )


def refine(
    scene: SceneGraph,
    sequence: Sequence,
    yaw_pose: Array,
    config: RefineConfig | None = None,
    *,
    match_uv=None,
    match_points=None,
    match_valid=None,
) -> RefineResult:
    """Refine the last frame of ``sequence`` from the filter's 4-DoF estimate ``yaw_pose``.

    Validates its inputs on the host, then runs the jitted :func:`refine_pose` (one compilation
    per shape and static configuration; frames of the same shape do not retrace).

    Args:
        scene: the map.
        sequence: the query (depth is needed for depth residuals; its tilt and ego-motion place
            the frames).
        yaw_pose: (4,) ``(x, y, z, yaw)`` estimate of the last frame, e.g.
            ``localize(...).poses[-1]``.
        config: :class:`RefineConfig`.
        match_uv, match_points, match_valid: correspondences for reprojection residuals:
            (M, 2), (M, 3), (M,) of the last frame in ``mode="last"``, (T, M, 2), (T, M, 3), (T, M)
            in ``mode="sequence"``.

    Returns:
        :class:`RefineResult` (``pose`` is the last frame's refined ``T_world_cam``).
    """
    config = RefineConfig() if config is None else config
    if not isinstance(scene, SceneGraph):
        raise TypeError(f"scene must be a jaxloc.SceneGraph, got {type(scene).__name__}")
    if not isinstance(sequence, Sequence):
        raise TypeError(f"sequence must be a jaxloc.Sequence, got {type(sequence).__name__}")
    yaw_pose = np.asarray(yaw_pose, np.float32)
    if yaw_pose.shape != (4,) or not np.all(np.isfinite(yaw_pose)):
        raise ValueError(f"yaw_pose must be a finite (4,) (x, y, z, yaw), got {yaw_pose!r}")
    if config.uses_depth and sequence.depth is None:
        raise ValueError(f"residuals={config.residuals!r} needs a sequence with depth")
    frames = sequence.num_frames if config.mode == "sequence" else 1
    camera = sequence.camera
    observations = _observations(
        camera,
        config,
        frames,
        None if sequence.depth is None else sequence.depth[-frames:],
        match_uv,
        match_points,
        match_valid,
        per_frame=config.mode == "sequence",
    )
    poses = frame_poses_from_last(
        jnp.asarray(yaw_pose), jnp.asarray(sequence.ego_motion), jnp.asarray(sequence.tilt)
    )
    poses = jaxlie.SE3(poses.parameters()[-frames:])
    T_init = jaxlie.SE3(poses.parameters()[-1])
    T_rel = jaxlie.SE3(
        jax.vmap(lambda p: (T_init.inverse() @ jaxlie.SE3(p)).parameters())(poses.parameters())
    )
    return _refine_pose_jit(scene, camera, T_init, T_rel, observations, config)
