"""One jitted SG2Loc filter step, and a whole pass over a sequence with ``lax.scan``.

``step(key, state, frame, scene, config) -> (state, info)`` composes, for every particle of a
padded :class:`~jaxloc.sg2loc.ParticleState`: prediction through the ego-motion (eq. 1),
rendering of the scene graph on the configured ray grid, the semantic / depth / SSIM scores and
the combined likelihood (eq. 2) in log space, the Bayes update, the estimates (MLE, weighted mean),
KLD-sampling resampling into the padded buffer and optional random-particle injection. Its parts
are public too: :func:`predict_step`, :func:`score_active` (the only part that reads the ray grid)
and :func:`update_step` (with :class:`UpdateConfig`, the grid-free part of :class:`StepConfig`).

Everything that varies per frame is a traced :class:`~jaxloc.sg2loc.Frame`; the map, the particle
capacity, the ray grid and the score variants fix the compiled shapes, so a new frame, a new map of
the same capacity or a new value of sigma / lambda / epsilon never recompiles. :func:`run_pass`
can tick a progress bar after each frame (a host call inside its scan). The frames come from a
:class:`~jaxloc.FrameSequence` through :func:`~jaxloc.sg2loc.frames_on_grid`. The host-side
helpers (:meth:`Region.of_scene`, ``frames_on_grid``) use NumPy on concrete inputs (no program
compiled) and ``jax.numpy`` on traced ones (inside a caller's ``jit``).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.sharding import Mesh, PartitionSpec

from jaxloc._traced import concrete
from jaxloc.camera import Camera, RayGrid
from jaxloc.raycasting.engines import check_engine_name
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._convert import as_float32, as_int32
from jaxloc.sg2loc._particles import (
    PAPER_HEIGHTS,
    ParticleState,
    inject_uniform,
    mle,
    predict,
    update_weights,
    weighted_mean,
)
from jaxloc.sg2loc._progress import tick_after
from jaxloc.sg2loc._rendering import render_batch
from jaxloc.sg2loc._resampling import KLDConfig, kld_resample
from jaxloc.sg2loc._scores import (
    ObservationConfig,
    PatchMatch,
    Scores,
    match_patches,
    particle_log_likelihood,
)
from jaxloc.sg2loc._sequence import Frame
from jaxloc.sg2loc._verdict import Verdict, VerdictConfig, judge


class Region(eqx.Module):
    """A floor region for particle initialisation and injection (world frame, metres).

    Attributes:
        lo, hi: (2,) float32 x-y corners.
        floor_z: float32 floor height; camera heights are measured from it.
    """

    lo: Array = eqx.field(converter=as_float32)
    hi: Array = eqx.field(converter=as_float32)
    floor_z: Array = eqx.field(converter=as_float32)

    @staticmethod
    def of_scene(scene: SceneGraph) -> Region:
        """The map's floor bounds: the x-y extent of its meshes, floor at their lowest point."""
        bounds = np.asarray(scene.bounds) if concrete(scene.bounds) else scene.bounds
        return Region(bounds[0, :2], bounds[1, :2], bounds[0, 2])


#: Rays rendered at once by default (``StepConfig.particle_chunk``) on a GPU: 2^20 rays keep the
#: step's working set near 1 GiB at any stride (benchmarks/results/filter_profile_cpu.md).
CHUNK_RAYS = 2**20

#: The same on XLA:CPU: at 960 x 540, 2500 particles, the paper's strides took 1.59-1.68 s per
#: frame against 1.79-2.01 s with 2^20, paired; 2^19 and 2^17 were slower (filter_step_cpu.md).
CPU_CHUNK_RAYS = 2**18


def default_chunk_rays(platform: str) -> int:
    """Rays rendered at once by default on devices of ``platform`` ("cpu", "gpu", "cuda", ...)."""
    return CPU_CHUNK_RAYS if platform == "cpu" else CHUNK_RAYS


def check_particle_chunk(chunk: int | None) -> None:
    """Raise a ValueError unless ``chunk`` is a positive int or None (for configs)."""
    if chunk is not None and (not isinstance(chunk, int) or chunk < 1):
        raise ValueError(f"particle_chunk must be a positive int or None, got {chunk!r}")


class StepConfig(eqx.Module):
    """Everything one filter step needs besides the state, the frame and the map.

    Attributes:
        camera: the query camera.
        grid: the ray grid of this pass (a stride grid or a patch grid).
        observation: score variants and likelihood parameters (eq. 2).
        kld: KLD-sampling parameters.
        region: where injected random particles go.
        sigma_trans, sigma_rot: motion-model noise (metres, radians), traced.
        inject_count: particles replaced by random ones on injection frames (traced; 0 = off).
        inject_every: inject on frames whose index is a positive multiple of this (static).
        heights: (H,) float32 camera heights above ``region.floor_z`` (metres) of the particles
            spread over the region and of injected ones (default the paper's 1.5-1.8 m).
        engine: nearest-hit engine of the rendering (static; see :func:`jaxloc.raycast`).
        particle_chunk: particles rendered and scored together (static). Only the chunks that
            hold active particles are rendered (a loop over them), so the step's time follows the
            active count and its peak memory ``particle_chunk`` x rays per particle. ``None``
            picks about 2^18 rays a chunk on a CPU and 2^20 on other devices
            (:func:`default_chunk_rays`; at least 1 particle); a value >= the particle capacity
            renders every slot at once (no loop).
        verdict: the thresholds of the per-frame verdict (:mod:`jaxloc.sg2loc._verdict`).
        mesh: a 1-D device mesh the particle buffer is split over (static; set by
            :mod:`jaxloc.sharding` and ``localize(..., mesh=)``). Each device then renders and
            scores its own shard (``jax.shard_map``), calling the engine on its own rays, with its
            own chunk loop; the weights and resampling stay global. ``None``: one device.
    """

    camera: Camera
    grid: RayGrid
    observation: ObservationConfig
    kld: KLDConfig
    region: Region
    sigma_trans: Array = eqx.field(default=0.05, converter=as_float32)
    sigma_rot: Array = eqx.field(default=0.05, converter=as_float32)
    inject_count: Array = eqx.field(default=0, converter=as_int32)
    inject_every: int = eqx.field(static=True, default=5)
    heights: Array = eqx.field(default=PAPER_HEIGHTS, converter=as_float32)
    engine: str = eqx.field(static=True, default="auto")
    particle_chunk: int | None = eqx.field(static=True, default=None)
    verdict: VerdictConfig = VerdictConfig()
    mesh: Mesh | None = eqx.field(static=True, default=None)

    def __check_init__(self) -> None:
        check_engine_name(self.engine)
        check_particle_chunk(self.particle_chunk)

    @property
    def update(self) -> UpdateConfig:
        """The fields :func:`update_step` reads."""
        return UpdateConfig(
            self.observation,
            self.kld,
            self.region,
            self.inject_count,
            self.inject_every,
            self.heights,
            self.verdict,
            int(self.grid.uv.shape[0]),
        )

    def chunk_size(self, capacity: int) -> int:
        """Particles per chunk for a buffer of ``capacity`` slots (static), by default about
        :func:`default_chunk_rays` rays for the platform of ``mesh`` or else JAX's default
        backend."""
        if self.particle_chunk is not None:
            return min(self.particle_chunk, capacity)
        mesh = self.mesh
        platform = jax.default_backend() if mesh is None else mesh.devices.flat[0].platform
        return max(1, min(default_chunk_rays(platform) // self.grid.uv.shape[0], capacity))


class StepInfo(NamedTuple):
    """Diagnostics of one step (scalars unless noted).

    Attributes:
        mle: (4,) the maximum-likelihood particle after the update.
        mean: (4,) the weighted mean pose after the update.
        num_particles: int32 particles after KLD resampling.
        num_bins: int32 occupied KLD bins.
        degenerate: bool, every likelihood underflowed (weights reset to uniform).
        motion_valid: bool, the frame's ego-motion was finite. A non-finite one is replaced by
            zero motion (the particles move by the motion noise only), so it cannot poison them.
        semantic, depth, color, log_likelihood: the MLE particle's scores.
        particles: (N, 4) particle poses after the update (before resampling).
        particle_weights: (N,) their normalised weights (0 for inactive slots).
        verdict: the frame's :class:`~jaxloc.sg2loc.Verdict` (``verdict.localized``:
            act on ``mle``), from the weighted particles and the MLE's scores.
    """

    mle: Array
    mean: Array
    num_particles: Array
    num_bins: Array
    degenerate: Array
    motion_valid: Array
    semantic: Array
    depth: Array
    color: Array
    log_likelihood: Array
    particles: Array
    particle_weights: Array
    verdict: Verdict


def _score_poses(
    poses: Array, frame: Frame, scene: SceneGraph, config: StepConfig, match: PatchMatch
) -> Scores:
    """Render ``poses`` (M, 4) (NaN rows: skipped, their rays miss) and score them: (M,) each."""
    # The filter never differentiates: the engine's own hit values (raycast's values-only path).
    views = render_batch(
        scene,
        poses,
        config.camera,
        config.grid,
        frame.tilt,
        engine=config.engine,
        differentiable=False,
    )
    h, w = config.grid.shape
    return jax.vmap(
        lambda obj, depth, color: particle_log_likelihood(
            config.observation,
            match,
            obj,
            depth,
            frame.depth,
            color.reshape(h, w, 3),
            frame.rgb,
        )
    )(views.patch_object, views.depth, views.color)


def score_active(
    state: ParticleState,
    frame: Frame,
    scene: SceneGraph,
    config: StepConfig,
    match: PatchMatch | None = None,
) -> Scores:
    """Scores (N,) of the active particles of ``state`` against ``frame``; the scores of inactive
    slots are meaningless (the caller masks them). ``match``: the frame's
    :func:`~jaxloc.sg2loc._scores.match_patches` (computed here when None).

    The active particles are gathered to the front and rendered ``config.chunk_size(N)`` at a
    time in a ``lax.while_loop`` that stops after the last chunk holding one (a chunk size >= N
    renders every slot in one call instead). With ``config.mesh`` every device does this for its
    own shard of the buffer.
    """
    if match is None:
        match = match_patches(frame.patch_embeddings, scene.embeddings, scene.object_valid)
    if config.mesh is None:
        return _score_shard(state.poses, state.active, frame, scene, config, match)
    split, whole = PartitionSpec(config.mesh.axis_names[0]), PartitionSpec()
    per_device = jax.shard_map(
        _score_shard,
        mesh=config.mesh,
        in_specs=(split, split, whole, whole, whole, whole),
        out_specs=split,
        check_vma=False,
    )
    return per_device(state.poses, state.active, frame, scene, config, match)


def _score_shard(
    poses: Array,
    active: Array,
    frame: Frame,
    scene: SceneGraph,
    config: StepConfig,
    match: PatchMatch,
) -> Scores:
    """:func:`score_active` of particles ``poses`` (M, 4) with mask ``active`` (M,)."""
    capacity = active.shape[0]
    chunk = config.chunk_size(capacity)
    if chunk >= capacity:
        # Inactive slots cast invalid (NaN) rays, which every engine retires at once.
        return _score_poses(jnp.where(active[:, None], poses, jnp.nan), frame, scene, config, match)
    num_chunks = -(-capacity // chunk)
    order = jnp.argsort(~active, stable=True)  # active slots first, in slot order
    order = jnp.pad(order, (0, num_chunks * chunk - capacity))
    num_active = jnp.sum(active)
    scored = jnp.zeros((num_chunks * chunk,), jnp.float32)
    init = (jnp.int32(0), Scores(scored, scored, scored, scored))

    def body(carry):
        i, scores = carry
        rank = i * chunk + jnp.arange(chunk)
        slots = jax.lax.dynamic_slice(order, (i * chunk,), (chunk,))
        chosen = jnp.where((rank < num_active)[:, None], poses[slots], jnp.nan)
        found = _score_poses(chosen, frame, scene, config, match)
        scores = jax.tree.map(
            lambda all_, part: jax.lax.dynamic_update_slice(all_, part, (i * chunk,)),
            scores,
            found,
        )
        return i + 1, scores

    _, scores = jax.lax.while_loop(lambda c: c[0] * chunk < num_active, body, init)
    # Back to slot order (slots past the active ones keep the zeros of ``init``).
    return jax.tree.map(
        lambda a: jnp.zeros((capacity,), a.dtype).at[order[:capacity]].set(a[:capacity]), scores
    )


def predict_step(
    key: Array,
    state: ParticleState,
    frame_index: Array,
    motion: Array,
    sigma_trans: Array,
    sigma_rot: Array,
) -> tuple[ParticleState, Array]:
    """The prediction of :func:`step`: ``(particles moved by the ego-motion, motion_valid)``.

    Frame 0 (``frame_index == 0``) is not moved: its particles are the initial set. A non-finite
    ``motion`` (4,) counts as zero motion (``motion_valid`` False). ``key`` is the step's key.
    """
    key_motion, _, _ = jax.random.split(key, 3)
    motion_valid = jnp.all(jnp.isfinite(motion))
    motion = jnp.where(motion_valid, motion, 0.0)
    moved = predict(key_motion, state, motion, sigma_trans, sigma_rot)
    state = jax.tree.map(lambda a, b: jnp.where(frame_index > 0, a, b), moved, state)
    return state, motion_valid


class UpdateConfig(eqx.Module):
    """The part of :class:`StepConfig` that :func:`update_step` reads (no camera, no ray grid);
    fields as in :class:`StepConfig`, and ``num_rays``, the int32 rays per particle of its grid
    (traced, for :attr:`~jaxloc.sg2loc.Verdict.confidence`: rounds of several strides share one
    update)."""

    observation: ObservationConfig
    kld: KLDConfig
    region: Region
    inject_count: Array
    inject_every: int = eqx.field(static=True)
    heights: Array
    verdict: VerdictConfig
    num_rays: Array = eqx.field(converter=as_int32)


def update_step(
    key: Array,
    state: ParticleState,
    scores: Scores,
    match: PatchMatch,
    frame_index: Array,
    motion_valid: Array,
    config: UpdateConfig,
) -> tuple[ParticleState, StepInfo]:
    """The rest of :func:`step` after scoring: Bayes update, estimates, verdict, KLD resampling,
    injection. ``key`` is the step's key; ``scores`` (N,) those of ``state``'s particles
    (:func:`score_active`); ``match`` the frame's patch match."""
    _, key_resample, key_inject = jax.random.split(key, 3)
    log_likelihood = jnp.where(state.active, scores.log_likelihood, -jnp.inf)
    state, degenerate = update_weights(state, log_likelihood)
    best_pose, best = mle(state)
    mean_pose = weighted_mean(state)
    best_scores = jax.tree.map(lambda a: a[best], scores)
    judged = (config.observation, config.verdict, degenerate, config.num_rays)
    verdict = judge(state, best_pose, best_scores, match, *judged)

    weighted = state
    state, kld_info = kld_resample(key_resample, state, config.kld)
    inject_now = (frame_index > 0) & (frame_index % config.inject_every == 0)
    count = jnp.where(inject_now, config.inject_count, 0)
    region = config.region
    state = inject_uniform(
        key_inject, state, count, region.lo, region.hi, region.floor_z, config.heights
    )
    info = StepInfo(
        mle=best_pose,
        mean=mean_pose,
        num_particles=kld_info.num_particles,
        num_bins=kld_info.num_bins,
        degenerate=degenerate,
        motion_valid=motion_valid,
        semantic=best_scores.semantic,
        depth=best_scores.depth,
        color=best_scores.color,
        log_likelihood=best_scores.log_likelihood,
        particles=weighted.poses,
        particle_weights=jnp.where(weighted.active, jnp.exp(weighted.log_weights), 0.0),
        verdict=verdict,
    )
    return state, info


def step(
    key: Array, state: ParticleState, frame: Frame, scene: SceneGraph, config: StepConfig
) -> tuple[ParticleState, StepInfo]:
    """One SG2Loc filter step: predict, render, score, weight, estimate, resample, inject.

    It is :func:`predict_step`, :func:`~jaxloc.sg2loc._scores.match_patches`,
    :func:`score_active` and :func:`update_step` in turn. The first frame (``frame.index == 0``)
    is not moved: its particles are the initial set. A non-finite ego-motion counts as zero
    motion and is flagged in ``info.motion_valid``.
    """

    def score(moved: ParticleState, match: PatchMatch) -> Scores:
        return score_active(moved, frame, scene, config, match)

    return step_scored_by(key, state, frame, scene, config, config.update, score)


def step_scored_by(
    key: Array,
    state: ParticleState,
    frame: Frame,
    scene: SceneGraph,
    config: StepConfig,
    update: UpdateConfig,
    score,
) -> tuple[ParticleState, StepInfo]:
    """:func:`step` with its scoring given: ``score(state, match) -> Scores`` of the moved
    particles (:func:`score_active` on some ray grid); ``frame`` supplies the index, the
    ego-motion and the patch embeddings, ``config`` the motion noise. The rounds of
    :func:`~jaxloc.sg2loc.localize` share everything but the scoring this way."""
    with jax.named_scope("predict"):
        state, motion_valid = predict_step(
            key, state, frame.index, frame.motion, config.sigma_trans, config.sigma_rot
        )
    with jax.named_scope("match"):
        match = match_patches(frame.patch_embeddings, scene.embeddings, scene.object_valid)
    with jax.named_scope("score"):
        scores = score(state, match)
    with jax.named_scope("update"):
        return update_step(key, state, scores, match, frame.index, motion_valid, update)


def run_pass(
    key: Array,
    state: ParticleState,
    frames: Frame,
    scene: SceneGraph,
    config: StepConfig,
    progress: Array | None = None,
) -> tuple[ParticleState, StepInfo]:
    """Filter a whole sequence (``frames`` stacked on a leading T axis) with ``lax.scan``.

    Frame ``t`` steps with the key ``jax.random.fold_in(key, frames.index[t])``, as a stream of
    frames does (:mod:`jaxloc.sg2loc.online`). Returns the final state and the per-frame
    :class:`StepInfo` stacked on a leading T axis.

    ``progress``: None, or the int32 id of an open progress bar of ``localize(...,
    progress=True)``, ticked by a host call after each frame (once per frame under ``jax.vmap``
    too); it changes the compiled program, not the results.
    """

    def step_frame(key_t, carry, frame):
        return step(key_t, carry, frame, scene, config)

    return scan_frames(key, state, frames, frames.index, step_frame, progress, config.mesh)


def scan_frames(key, state, frames, index, step_frame, progress, mesh) -> tuple:
    """``lax.scan`` of ``step_frame(key_t, state, frame) -> (state, info)`` over ``frames``
    (any pytree stacked on T), frame ``t`` with ``key_t = jax.random.fold_in(key, index[t])``
    ((T,) int32 frame numbers), ticking the progress bar ``progress`` (None: none) after each;
    ``mesh``: the particles' mesh, or None. The one frame loop of :func:`run_pass` and of
    :func:`~jaxloc.sg2loc.localize`'s rounds."""

    def body(carry, x):
        i, frame = x
        carry, info = step_frame(jax.random.fold_in(key, i), carry, frame)
        if progress is not None:
            tick_after(progress, info.num_particles, mesh is not None)
        return carry, info

    return jax.lax.scan(body, state, (index, frames))
