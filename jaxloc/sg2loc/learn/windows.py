"""Training windows: fixed particle sets, their renders and scores, stored once per window."""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.camera import Camera, RayGrid, stride_grid
from jaxloc.geometry import compose_yaw, wrap_angle
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._filter import Region
from jaxloc.sg2loc._rendering import render_batch
from jaxloc.sg2loc._scores import (
    ObservationConfig,
    Scores,
    match_patches,
    particle_log_likelihood,
)
from jaxloc.sg2loc._sequence import Frame, FrameSequence, frames_on_grid

#: Half-width (metres) of the box around a window's first true pose of its local particles.
LOCAL_HALF_WIDTH = 0.4
#: Yaw half-range (radians, 20 degrees) about a window's first true yaw of its local particles.
LOCAL_YAW_HALF_RANGE = float(np.deg2rad(20.0))


class Windows(NamedTuple):
    """Training samples: B windows of K frames, N particles each (leading B axis optional).

    Attributes:
        semantic, depth, color: (B, K, N) float32 the particles' scores at each frame.
        position_error: (B, K, N) float32 metres from each particle to the true pose at each
            frame of the window.
        yaw_error: (B, K, N) float32 absolute yaw error (radians) at each frame.
        valid: (B, N) bool, which particles count.
    """

    semantic: Array
    depth: Array
    color: Array
    position_error: Array
    yaw_error: Array
    valid: Array


def concat_windows(parts: list[Windows]) -> Windows:
    """Concatenate batches of windows along B (host side)."""
    return Windows(*(jnp.concatenate(xs, axis=0) for xs in zip(*parts, strict=True)))


def window_particles(
    key: Array,
    first_pose: Array,
    motions: Array,
    num_particles: int,
    region: Region,
    half_width: float = LOCAL_HALF_WIDTH,
    yaw_half_range: float = LOCAL_YAW_HALF_RANGE,
    heights: tuple[float, float] = (1.5, 1.8),
) -> Array:
    """The fixed particle set of a window: (K, N, 4) poses ``(x, y, z, yaw)`` at its K frames.

    The first ``N // 2`` particles are uniform in the box ``first_pose[:3] +- half_width``,
    yaw within ``+- yaw_half_range`` of ``first_pose[3]``; the rest uniform over ``region``'s
    floor at ``heights`` (metres above the floor) with uniform yaw. Every particle is carried
    through ``motions`` (K - 1, 4) body-frame ego-motions with :func:`jaxloc.geometry.compose_yaw`.

    Args:
        key: PRNG key.
        first_pose: (4,) true pose at the window's first frame (world frame).
        motions: (K - 1, 4) ego-motion between consecutive frames.
        num_particles: N (static).
        region: the room's floor region.
    """
    key_local, key_global = jax.random.split(key)
    num_local = num_particles // 2
    num_global = num_particles - num_local
    first_pose = jnp.asarray(first_pose, jnp.float32)
    offsets = jax.random.uniform(
        key_local,
        (num_local, 4),
        minval=-1.0,
        maxval=1.0,
    ) * jnp.array([half_width, half_width, half_width, yaw_half_range], jnp.float32)
    local = first_pose + offsets
    local = local.at[:, 3].set(wrap_angle(local[:, 3]))
    u = jax.random.uniform(key_global, (num_global, 4))
    lo, hi = region.lo, region.hi
    spread = jnp.stack(
        [
            lo[0] + u[:, 0] * (hi[0] - lo[0]),
            lo[1] + u[:, 1] * (hi[1] - lo[1]),
            region.floor_z + heights[0] + u[:, 2] * (heights[1] - heights[0]),
            -jnp.pi + 2.0 * jnp.pi * u[:, 3],
        ],
        axis=-1,
    )
    poses = jnp.concatenate([local, spread], axis=0)

    def advance(current, motion):
        moved = jax.vmap(compose_yaw, in_axes=(0, None))(current, motion)
        return moved, moved

    _, later = jax.lax.scan(advance, poses, jnp.asarray(motions, jnp.float32))
    return jnp.concatenate([poses[None], later], axis=0)


def score_particles(
    scene: SceneGraph,
    camera: Camera,
    grid: RayGrid,
    frame: Frame,
    poses: Array,
    observation: ObservationConfig,
    engine: str = "auto",
) -> Scores:
    """Render ``poses`` (N, 4) on ``grid`` and score them against ``frame`` (as the filter does).

    ``engine`` (static) is the nearest-hit engine of the rendering (:func:`jaxloc.raycast`).
    Returns :class:`~jaxloc.sg2loc._scores.Scores` with (N,) float32 fields.
    """
    views = render_batch(
        scene, poses, camera, grid, frame.tilt, engine=engine, differentiable=False
    )
    match = match_patches(frame.patch_embeddings, scene.embeddings, scene.object_valid)
    h, w = grid.shape
    return jax.vmap(
        lambda obj, depth, color: particle_log_likelihood(
            observation, match, obj, depth, frame.depth, color.reshape(h, w, 3), frame.rgb
        )
    )(views.patch_object, views.depth, views.color)


@eqx.filter_jit
def score_window(
    key: Array,
    scene: SceneGraph,
    camera: Camera,
    grid: RayGrid,
    frames: Frame,
    poses_gt: Array,
    region: Region,
    num_particles: int,
    observation: ObservationConfig,
    local_half_width: float | Array = LOCAL_HALF_WIDTH,
    local_yaw_half_range: float | Array = LOCAL_YAW_HALF_RANGE,
    engine: str = "auto",
) -> Windows:
    """One training window (no leading B axis): sample, render and score its particles.

    Args:
        key: PRNG key of the particle draw.
        scene: the map.
        camera: the query camera.
        grid: the ray grid the scores use.
        frames: the window's K frames (stacked :class:`~jaxloc.sg2loc.Frame`, sampled on
            ``grid``).
        poses_gt: (K, 4) true poses at those frames.
        region: the room's floor region.
        num_particles: N (static).
        observation: score variants (its sigma and lambdas do not matter here).
        local_half_width: half-width (metres) of the box of the local half of the particles
            (:func:`window_particles`).
        local_yaw_half_range: yaw half-range (radians) of that box.
        engine: nearest-hit engine of the rendering (static; :func:`jaxloc.raycast`).
    """
    poses = window_particles(
        key,
        poses_gt[0],
        frames.motion[1:],
        num_particles,
        region,
        local_half_width,
        local_yaw_half_range,
    )
    scores = jax.vmap(
        lambda frame, p: score_particles(scene, camera, grid, frame, p, observation, engine)
    )(frames, poses)
    return _window(scores, poses, poses_gt, jnp.ones(num_particles, bool))


def _window(scores: Scores, poses: Array, poses_gt: Array, valid: Array) -> Windows:
    """A window from the (K, N) scores of particles ``poses`` (K, N, 4) at truths (K, 4)."""
    truth = jnp.asarray(poses_gt, jnp.float32)[:, None, :]
    return Windows(
        semantic=scores.semantic,
        depth=scores.depth,
        color=scores.color,
        position_error=jnp.linalg.norm(poses[..., :3] - truth[..., :3], axis=-1),
        yaw_error=jnp.abs(wrap_angle(poses[..., 3] - truth[..., 3])),
        valid=valid,
    )


def sequence_windows(
    key: Array,
    scene: SceneGraph,
    sequence: FrameSequence,
    poses_gt: np.ndarray,
    grid: RayGrid,
    starts: tuple[int, ...],
    window_length: int,
    num_particles: int,
    observation: ObservationConfig | None = None,
    local_half_width: float = LOCAL_HALF_WIDTH,
    local_yaw_half_range: float = LOCAL_YAW_HALF_RANGE,
    engine: str = "auto",
) -> Windows:
    """Training windows of one sequence (host side): one per start frame, stacked on B.

    Args:
        key: PRNG key (window ``i`` uses ``fold_in(key, i)``).
        scene: the map; sequence: the query; poses_gt: (T, 4) its true poses.
        grid: the ray grid the scores use (its patch grid must be the sequence's).
        starts: first frame of each window; each needs ``start + window_length <= T``.
        window_length: K frames per window (static).
        num_particles: N particles per window (static).
        observation: score variants (default :class:`~jaxloc.sg2loc.ObservationConfig`).
        local_half_width: half-width (metres) of the box around the window's first true pose
            that the local half of the particles is drawn from (:func:`window_particles`).
        local_yaw_half_range: yaw half-range (radians) of that box.
        engine: nearest-hit engine of the rendering (:func:`jaxloc.raycast`).
    """
    observation = ObservationConfig() if observation is None else observation
    num_frames = sequence.num_frames
    if window_length < 1 or any(s < 0 or s + window_length > num_frames for s in starts):
        raise ValueError(
            f"every start + window_length ({window_length}) must fit the {num_frames} frames, "
            f"got starts {starts}"
        )
    if np.shape(poses_gt) != (num_frames, 4):
        raise ValueError(f"poses_gt must have shape ({num_frames}, 4), got {np.shape(poses_gt)}")
    frames = frames_on_grid(sequence, grid)
    region = Region.of_scene(scene)
    poses_gt = jnp.asarray(poses_gt, jnp.float32)
    parts = []
    for i, start in enumerate(starts):
        span = slice(start, start + window_length)
        window = score_window(
            jax.random.fold_in(key, i),
            scene,
            sequence.camera,
            grid,
            jax.tree.map(lambda a, span=span: a[span], frames),
            poses_gt[span],
            region,
            num_particles,
            observation,
            local_half_width,
            local_yaw_half_range,
            engine,
        )
        parts.append(jax.tree.map(lambda a: a[None], window))
    return concat_windows(parts)


@eqx.filter_jit
def score_particle_set(
    scene: SceneGraph,
    camera: Camera,
    grid: RayGrid,
    frame: Frame,
    poses: Array,
    valid: Array,
    pose_gt: Array,
    observation: ObservationConfig,
    engine: str = "auto",
) -> Windows:
    """A one-frame window (K = 1, no leading B axis) of a given particle set.

    Args:
        scene: the map; camera, grid: the query camera and the ray grid the scores use.
        frame: one :class:`~jaxloc.sg2loc.Frame` sampled on ``grid``.
        poses: (N, 4) particle poses ``(x, y, z, yaw)`` (world frame); rows that are not
            ``valid`` are ignored (they may be non-finite).
        valid: (N,) bool, which particles count.
        pose_gt: (4,) the frame's true pose.
        observation: score variants (its sigma and lambdas do not matter here).
        engine: nearest-hit engine of the rendering (static; :func:`jaxloc.raycast`).
    """
    valid = valid & jnp.all(jnp.isfinite(poses), axis=-1)
    poses = jnp.where(valid[:, None], poses, jnp.asarray(pose_gt, jnp.float32))
    scores = score_particles(scene, camera, grid, frame, poses, observation, engine)
    one_frame = jax.tree.map(lambda a: a[None], (scores, poses, pose_gt))
    return _window(*one_frame, valid)


def filter_windows(
    scene: SceneGraph,
    sequence: FrameSequence,
    poses_gt: Array,
    particles: Array,
    particle_weights: Array,
    strides: tuple[int, ...],
    observation: ObservationConfig | None = None,
    engine: str = "auto",
) -> Windows:
    """One-frame windows of the filter's own particle sets (host side), ``R * T`` on B.

    For round ``r`` and frame ``t`` of a :func:`jaxloc.sg2loc.localize` run, the window holds the
    particles the filter weighted at that frame (``SG2LocResult.particles[r, t]``), valid where
    their weight is positive (``particle_weights[r, t] > 0``: inactive slots, and the rare weight
    that underflowed to 0, are left out), scored on round ``r``'s ray grid against frame ``t``.
    The filter's prior over these particles is uniform (KLD resampling and injection leave equal
    weights), so a window's posterior is exactly the filter's update at that frame under any
    parameters (:mod:`jaxloc.sg2loc.learn`, "Filter windows").

    Args:
        scene: the map; sequence: the query; poses_gt: (T, 4) its true poses.
        particles: (R, T, N, 4) ``SG2LocResult.particles``.
        particle_weights: (R, T, N) ``SG2LocResult.particle_weights``.
        strides: the R ray strides of the run (``SG2LocConfig.strides``).
        observation: score variants (default
            :class:`~jaxloc.sg2loc.ObservationConfig`); use the run's (``use_depth`` /
            ``use_color`` as it used them).
        engine: nearest-hit engine of the rendering (:func:`jaxloc.raycast`).
    """
    observation = ObservationConfig() if observation is None else observation
    num_frames = sequence.num_frames
    particles = np.asarray(particles, np.float32)
    particle_weights = np.asarray(particle_weights, np.float32)
    rounds = len(strides)
    if (
        particles.ndim != 4
        or particles.shape[:2] != (rounds, num_frames)
        or particles.shape[3] != 4
    ):
        raise ValueError(
            f"particles must have shape (R, T, N, 4) = ({rounds}, {num_frames}, N, 4), "
            f"got {particles.shape}"
        )
    if particle_weights.shape != particles.shape[:3]:
        raise ValueError(
            f"particle_weights must have shape {particles.shape[:3]}, got {particle_weights.shape}"
        )
    if np.shape(poses_gt) != (num_frames, 4):
        raise ValueError(f"poses_gt must have shape ({num_frames}, 4), got {np.shape(poses_gt)}")
    poses_gt = jnp.asarray(poses_gt, jnp.float32)
    rows, cols = sequence.patch_shape
    parts = []
    for r, stride in enumerate(strides):
        grid = stride_grid(sequence.camera, stride, rows, cols)
        frames = frames_on_grid(sequence, grid)
        for t in range(num_frames):
            window = score_particle_set(
                scene,
                sequence.camera,
                grid,
                jax.tree.map(lambda a, t=t: a[t], frames),
                jnp.asarray(particles[r, t]),
                jnp.asarray(particle_weights[r, t] > 0),
                poses_gt[t],
                observation,
                engine,
            )
            parts.append(jax.tree.map(lambda a: a[None], window))
    return concat_windows(parts)
