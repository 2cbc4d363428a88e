"""Learning the SG2Loc likelihood parameters (sigma, lambda_depth, lambda_color) by gradient.

Parameters. :class:`LikelihoodParams` holds ``log sigma``, ``log lambda_depth`` and
``log lambda_color`` (unconstrained floats; the values are their exponentials, so they stay
positive). :meth:`LikelihoodParams.to_config` maps them into an
:class:`~jaxloc.scores.ObservationConfig`, clipping the logs to ``[-LOG_BOUND, LOG_BOUND]`` so that
eq. (2) stays finite in float32 (``(S_max - S)^2 / (2 sigma^2)`` cannot overflow). The motion noise
(``sigma_trans``, ``sigma_rot``) is not learned: the loss below holds the particles fixed, so it
does not depend on the motion noise (see "Why not through resampling").

Loss. One training sample is a *window* of ``K`` consecutive frames of a synthetic episode and a
fixed set of ``N`` particles (:func:`window_particles`): half drawn uniformly in a box around the
true pose of the window's first frame (``LOCAL_HALF_WIDTH`` 0.4 m, ``LOCAL_YAW_HALF_RANGE`` 20 deg),
half uniformly over the room's floor at camera heights (round 0's spread). The particles are carried
through the window by the measured (noisy) ego-motion without noise, which is the filter's
prediction step with the noise switched off. Their weights after the window are the product of the
``K`` frames' likelihoods, i.e. ``log w = log_softmax(sum_k log L_k)`` with ``log L_k`` eq. (2) of
the scores the filter computes (:func:`jaxloc.scores.particle_log_likelihood` on the particles'
rendered views). That is the filter's posterior over this particle set: sequential importance
sampling without resampling. The default loss (``"nll"``) is the negative log density of the true
last-frame pose under the weighted particle mixture with a Gaussian kernel of
``position_scale`` metres and ``yaw_scale`` radians::

    loss = -log sum_i w_i exp(-(e_pos_i / position_scale)^2 / 2 - (e_yaw_i / yaw_scale)^2 / 2)

The defaults (kernel 0.1 m / 5 deg, local box +-0.4 m / +-20 deg, the whole window's posterior)
were chosen by measurement on held-out scenes against the filter's hand-set parameters: a
0.25 m / 10 deg kernel with the fine round's box (+-0.8 m / +-45 deg), the per-frame loss and the
filter windows below all did worse than these (``experiments/results/learn/NOTE.md``).

Per-frame loss (``LossConfig(frames="every")``). The filter resamples after every frame, so it acts
on the posterior after frames 1..k for every k, not only on the one after the whole window; a
likelihood that is confident on a wrong mode after the first frame collapses the particle set there
even when the window as a whole points to the truth. With ``frames="every"`` the loss is the mean
over k = 1..K of the loss of the posterior after frames 1..k (``log w_k = log_softmax(sum_{j<=k}
log L_j)``) at frame k's true pose, so that over-confidence is paid for. Measured, it does the
opposite: the learned likelihood gets sharper (lambda_depth 12.3 vs 5.7 with the default loss) and
the filter's R@(0.25 m, 10 deg) on 50 held-out scenes drops from 0.72 (hand-set) to 0.51; it is
kept for comparison.

Filter windows (:func:`filter_windows`). The windows above draw half of their particles close to the
truth, far denser there than the filter's early rounds, which spread a few hundred particles over
the whole room; a sharp likelihood is rewarded on such sets and punished by the filter. One-frame
windows of the particles a filter run actually weighted (every round and frame of
:func:`jaxloc.sg2loc.localize`) have the filter's own density: the loss of such a window is the
loss of the filter's update at that frame. The particle sets depend on the parameters that ran the
filter, so training alternates runs and fits (``experiments/learn_params.py --windows filter``).
Measured on 50 held-out scenes, the parameters learned this way beat the hand-set ones on the
median errors and recalls over all frames but not on the last frame, and are no better than those
learned on the default windows.

A proper scoring rule: it rewards weight near the truth and punishes confident weight on a wrong
mode, which is what the filter needs (an over-confident likelihood collapses the particle set onto
a wrong mode at resampling, an under-confident one never concentrates). The alternative
``"expected_error"`` is the weighted mean of ``e_pos / position_scale + e_yaw / yaw_scale``; it is
minimised by putting all weight on the best-scoring particle, so it tends to drive sigma to zero
(over-confidence), and is offered for comparison.

The renders and the scores ``s``, ``s_d``, ``s_i`` do not depend on the parameters, only their
combination in eq. (2) does; they are computed once per window (:func:`score_window`, jitted) and
the training loop differentiates eq. (2) and the loss on the stored scores. The gradient is the
same as differentiating through rendering and scoring (whose derivative with respect to the
parameters is zero).

Why not through resampling. Resampling draws discrete ancestor indices: its output is piecewise
constant in the weights, so its derivative is zero almost everywhere and the true gradient of the
filter's estimate is carried by the jumps. Differentiable relaxations (soft resampling, optimal
transport resampling) are biased, much costlier, and would make the gradient depend on the
particle noise of a whole sequence. Between two resamplings, however, the filter's posterior over
a fixed particle set is exactly the product of the likelihoods above, so holding the set fixed
differentiates the part of the filter that the parameters control, without these problems.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import Array

from jaxloc._render import render_batch
from jaxloc.camera import Camera, RayGrid, stride_grid
from jaxloc.filter import Frame, Region, frames_on_grid
from jaxloc.geometry import compose_yaw, wrap_angle
from jaxloc.scene import SceneGraph
from jaxloc.scores import (
    ObservationConfig,
    Scores,
    log_likelihood,
    match_patches,
    particle_log_likelihood,
)
from jaxloc.sequence import Sequence

#: The logs of the parameters are clipped to +-LOG_BOUND in :meth:`LikelihoodParams.to_config`.
LOG_BOUND = 15.0

LOSS_KINDS = ("nll", "expected_error")
LOSS_FRAMES = ("last", "every")


#: Half-width (metres) and yaw half-range (radians) of the box around a window's first true pose
#: that the local half of its particles is drawn from (module docstring).
LOCAL_HALF_WIDTH = 0.4
LOCAL_YAW_HALF_RANGE = float(np.deg2rad(20.0))


class LikelihoodParams(eqx.Module):
    """The learned likelihood parameters, in log space (float32 scalars, unconstrained).

    Attributes:
        log_sigma: log of ``sigma`` (width of eq. (2)'s Gaussian).
        log_lambda_depth: log of ``lambda_depth``.
        log_lambda_color: log of ``lambda_color``.
    """

    log_sigma: Array
    log_lambda_depth: Array
    log_lambda_color: Array

    @staticmethod
    def from_config(config: ObservationConfig) -> LikelihoodParams:
        """The parameters of an observation config (sigma, lambdas must be positive)."""
        values = {}
        for name in ("sigma", "lambda_depth", "lambda_color"):
            value = float(np.asarray(getattr(config, name)))
            if not (np.isfinite(value) and value > 0):
                raise ValueError(
                    f"config.{name} must be positive and finite to be learned in log space, "
                    f"got {value}"
                )
            values[name] = jnp.asarray(np.log(value), jnp.float32)
        return LikelihoodParams(values["sigma"], values["lambda_depth"], values["lambda_color"])

    def values(self) -> tuple[Array, Array, Array]:
        """``(sigma, lambda_depth, lambda_color)`` float32 scalars (logs clipped to +-LOG_BOUND)."""
        return tuple(
            jnp.exp(jnp.clip(jnp.asarray(v, jnp.float32), -LOG_BOUND, LOG_BOUND))
            for v in (self.log_sigma, self.log_lambda_depth, self.log_lambda_color)
        )

    def to_config(self, base: ObservationConfig) -> ObservationConfig:
        """``base`` with sigma and the lambdas replaced by these parameters (jit-able)."""
        sigma, lambda_depth, lambda_color = self.values()
        return dataclasses.replace(
            base, sigma=sigma, lambda_depth=lambda_depth, lambda_color=lambda_color
        )


class LossConfig(eqx.Module):
    """Which loss and its scales.

    Attributes:
        kind: ``"nll"`` (default) or ``"expected_error"`` (static); see the module docstring.
        frames: ``"last"`` (default): the loss of the posterior after the whole window at its
            last frame; ``"every"``: the mean over k of the loss of the posterior after frames
            1..k at frame k (static; module docstring, "Per-frame loss").
        position_scale: kernel width / error unit in metres (default 0.1 m).
        yaw_scale: kernel width / error unit in radians (default 5 degrees).
    """

    kind: str = eqx.field(static=True, default="nll")
    frames: str = eqx.field(static=True, default="last")
    position_scale: Array = eqx.field(default=0.1, converter=lambda x: jnp.asarray(x, jnp.float32))
    yaw_scale: Array = eqx.field(
        default=float(np.deg2rad(5.0)), converter=lambda x: jnp.asarray(x, jnp.float32)
    )

    def __check_init__(self):
        if self.kind not in LOSS_KINDS:
            raise ValueError(f"LossConfig.kind must be one of {LOSS_KINDS}, got {self.kind!r}")
        if self.frames not in LOSS_FRAMES:
            raise ValueError(f"LossConfig.frames must be one of {LOSS_FRAMES}, got {self.frames!r}")


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
    Returns :class:`~jaxloc.scores.Scores` with (N,) float32 fields.
    """
    views = render_batch(scene, poses, camera, grid, frame.tilt, engine=engine)
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
        camera, grid: the query camera and the ray grid the scores use.
        frames: the window's K frames (stacked :class:`~jaxloc.filter.Frame`, sampled on ``grid``).
        poses_gt: (K, 4) true poses at those frames.
        region: the room's floor region.
        num_particles: N (static).
        observation: score variants (its sigma and lambdas do not matter here).
        local_half_width, local_yaw_half_range: the box of the local half of the particles
            (metres, radians; :func:`window_particles`).
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
    sequence: Sequence,
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
        observation: score variants (default :class:`~jaxloc.scores.ObservationConfig`).
        local_half_width, local_yaw_half_range: the box (metres, radians) around the window's first
            true pose that the local half of the particles is drawn from
            (:func:`window_particles`).
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
        frame: one :class:`~jaxloc.filter.Frame` sampled on ``grid``.
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
    sequence: Sequence,
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
    parameters (module docstring, "Filter windows").

    Args:
        scene: the map; sequence: the query; poses_gt: (T, 4) its true poses.
        particles: (R, T, N, 4) ``SG2LocResult.particles``.
        particle_weights: (R, T, N) ``SG2LocResult.particle_weights``.
        strides: the R ray strides of the run (``SG2LocConfig.strides``).
        observation: score variants (default :class:`~jaxloc.scores.ObservationConfig`); use the
            run's (``use_depth`` / ``use_color`` as it used them).
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


def window_log_weights(params: LikelihoodParams, base: ObservationConfig, window: Windows) -> Array:
    """(N,) float32 normalised log-weights of one window's particles after all K frames.

    The log-softmax of the summed eq. (2) log-likelihoods over the valid particles, ``-inf`` for
    invalid ones (:func:`prefix_log_weights`' last row).
    """
    return _normalised(config_log_likelihood(params.to_config(base), window), window.valid)


def prefix_log_weights(params: LikelihoodParams, base: ObservationConfig, window: Windows) -> Array:
    """(K, N) float32 normalised log-weights after frames 1..k, for every k of the window.

    Row k is the log-softmax of the eq. (2) log-likelihoods summed over the first k + 1 frames,
    over the valid particles (``-inf`` for invalid ones). When no valid particle has a finite
    log-likelihood the weights are uniform over the valid particles (as
    :func:`jaxloc.particles.update_weights` does), and over all N when none is valid (such a
    window carries no information; its loss is constant). Values and gradients stay finite.
    """
    config = params.to_config(base)
    per_frame = log_likelihood(config, window.semantic, window.depth, window.color)
    return jax.vmap(lambda row: _normalised(row, window.valid))(jnp.cumsum(per_frame, axis=0))


def _normalised(log_likelihood: Array, valid: Array) -> Array:
    """(N,) log-softmax of ``log_likelihood`` (N,) over ``valid`` (docstring above)."""
    usable = valid & jnp.isfinite(log_likelihood)
    any_usable = jnp.any(usable)
    safe = jnp.where(usable, log_likelihood, 0.0)
    top = jax.lax.stop_gradient(jnp.max(jnp.where(usable, safe, -jnp.inf)))
    top = jnp.where(any_usable, top, 0.0)
    shifted = jnp.where(any_usable, jnp.where(usable, safe - top, -jnp.inf), 0.0)
    shifted = jnp.where(valid | ~jnp.any(valid), shifted, -jnp.inf)
    return shifted - jax.nn.logsumexp(shifted)


def config_log_likelihood(config: ObservationConfig, window: Windows) -> Array:
    """(N,) eq. (2) log-likelihood of each particle summed over the window's K frames."""
    return jnp.sum(log_likelihood(config, window.semantic, window.depth, window.color), axis=0)


def window_loss(
    params: LikelihoodParams, base: ObservationConfig, window: Windows, loss: LossConfig
) -> Array:
    """Float32 loss of one window (see the module docstring and :class:`LossConfig`)."""
    if loss.frames == "last":
        log_weights = window_log_weights(params, base, window)
        return _posterior_loss(
            log_weights, window.position_error[-1], window.yaw_error[-1], window.valid, loss
        )
    per_prefix = jax.vmap(lambda lw, pos, yaw: _posterior_loss(lw, pos, yaw, window.valid, loss))(
        prefix_log_weights(params, base, window), window.position_error, window.yaw_error
    )
    return jnp.mean(per_prefix)


def _posterior_loss(
    log_weights: Array, position_error: Array, yaw_error: Array, valid: Array, loss: LossConfig
) -> Array:
    """The loss of one weighted particle set (N,) against the truth at one frame."""
    position = position_error / loss.position_scale
    yaw = yaw_error / loss.yaw_scale
    if loss.kind == "nll":
        log_kernel = -0.5 * (position**2 + yaw**2)
        terms = jnp.where(jnp.isfinite(log_weights), log_weights + log_kernel, -jnp.inf)
        return -jax.nn.logsumexp(terms)
    weights = jnp.exp(log_weights)
    return jnp.sum(jnp.where(valid, weights * (position + yaw), 0.0))


def batch_loss(
    params: LikelihoodParams, base: ObservationConfig, windows: Windows, loss: LossConfig
) -> Array:
    """Mean :func:`window_loss` over a batch of windows (leading B axis)."""
    return jnp.mean(jax.vmap(lambda w: window_loss(params, base, w, loss))(windows))


def expected_position_error(
    params: LikelihoodParams, base: ObservationConfig, windows: Windows
) -> Array:
    """Mean over windows of the weighted mean position error (metres) of the particles at the
    window's last frame."""

    def one(window):
        weights = jnp.exp(window_log_weights(params, base, window))
        return jnp.sum(jnp.where(window.valid, weights * window.position_error[-1], 0.0))

    return jnp.mean(jax.vmap(one)(windows))


class TrainState(NamedTuple):
    """Parameters and optimizer state of the training loop."""

    params: LikelihoodParams
    opt_state: optax.OptState


@functools.lru_cache(maxsize=16)
def adam(learning_rate: float) -> optax.GradientTransformation:
    """``optax.adam(learning_rate)``, one object per rate (so compiled steps are reused)."""
    return optax.adam(learning_rate)


@eqx.filter_jit
def _train_step(
    optimizer: optax.GradientTransformation,
    base: ObservationConfig,
    loss: LossConfig,
    state: TrainState,
    key: Array,
    windows: Windows,
    batch_size: int,
) -> tuple[TrainState, Array]:
    count = windows.valid.shape[0]
    picks = jax.random.randint(key, (batch_size,), 0, count)
    batch = jax.tree.map(lambda a: a[picks], windows)
    value, grads = jax.value_and_grad(batch_loss)(state.params, base, batch, loss)
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    return TrainState(optax.apply_updates(state.params, updates), opt_state), value


def make_train_step(
    optimizer: optax.GradientTransformation, base: ObservationConfig, loss: LossConfig
) -> Callable[[TrainState, Array, Windows, int], tuple[TrainState, Array]]:
    """A jitted ``step(state, key, windows, batch_size) -> (state, loss)``.

    Each step draws ``batch_size`` (static int) windows of ``windows`` uniformly with replacement
    using ``key`` and takes one optimizer step on their mean loss. It compiles once per
    (optimizer object, score variants, loss kind, number of windows, batch size); new window
    values, parameters or keys never recompile.
    """
    return functools.partial(_train_step, optimizer, base, loss)


@eqx.filter_jit
def _evaluate(params, base, loss, train_windows, heldout_windows):
    return (
        batch_loss(params, base, train_windows, loss),
        batch_loss(params, base, heldout_windows, loss),
        expected_position_error(params, base, heldout_windows),
        jnp.stack(params.values()),
    )


class History(NamedTuple):
    """The learning curve (host numpy arrays, one entry per evaluation).

    Attributes:
        step: (E,) int step index of each evaluation (0 = before training).
        train_loss: (E,) mean loss over all training windows.
        heldout_loss: (E,) mean loss over the held-out windows.
        heldout_position_error: (E,) held-out mean weighted position error (metres).
        sigma, lambda_depth, lambda_color: (E,) the parameters.
    """

    step: np.ndarray
    train_loss: np.ndarray
    heldout_loss: np.ndarray
    heldout_position_error: np.ndarray
    sigma: np.ndarray
    lambda_depth: np.ndarray
    lambda_color: np.ndarray


def train(
    key: Array,
    params: LikelihoodParams,
    base: ObservationConfig,
    train_windows: Windows,
    heldout_windows: Windows,
    num_steps: int,
    learning_rate: float = 0.05,
    batch_size: int = 16,
    eval_every: int = 10,
    loss: LossConfig | None = None,
) -> tuple[LikelihoodParams, History]:
    """Adam on the window loss; returns the final parameters and the learning curve.

    Deterministic for a given ``key`` and inputs.
    """
    loss = LossConfig() if loss is None else loss
    if num_steps < 0 or batch_size < 1 or eval_every < 1:
        raise ValueError(
            f"need num_steps >= 0, batch_size >= 1, eval_every >= 1; got {num_steps}, "
            f"{batch_size}, {eval_every}"
        )
    optimizer = adam(float(learning_rate))
    step = make_train_step(optimizer, base, loss)
    state = TrainState(params, optimizer.init(params))
    rows = []
    keys = jax.random.split(key, max(num_steps, 1))
    for i in range(num_steps + 1):
        if i % eval_every == 0 or i == num_steps:
            metrics = _evaluate(state.params, base, loss, train_windows, heldout_windows)
            rows.append((i, *(np.asarray(v) for v in metrics)))
        if i < num_steps:
            state, _ = step(state, keys[i], train_windows, batch_size)
    steps, train_l, held_l, held_e, values = zip(*rows, strict=True)
    values = np.stack(values)
    history = History(
        np.asarray(steps),
        np.asarray(train_l),
        np.asarray(held_l),
        np.asarray(held_e),
        values[:, 0],
        values[:, 1],
        values[:, 2],
    )
    return state.params, history
