"""SG2Loc on a stream of frames: ``init`` once, then ``update`` with each frame as it arrives.

BlackJAX style, for a camera that delivers frames one at a time::

    state = online.init(jax.random.key(0), scene, camera)
    for patches, motion, depth, rgb in camera_stream:          # motion: zeros for the first frame
        state, est = online.update(state, patches, motion, depth=depth, rgb=rgb)
        if est.localized:
            act_on(est.pose)                                    # (x, y, z, yaw), world frame

The machinery is :func:`jaxloc.sg2loc.step`, the same step every round of
:func:`~jaxloc.sg2loc.localize` runs, with the same :class:`~jaxloc.sg2loc.SG2LocConfig`: the
stream runs round 0's settings on every frame (``strides[0]``, default 20). Without
coarse-to-fine rounds (which re-run past frames) the stream is one round: ``init(key, ...,
config)`` and ``update`` over frames 0..T-1 give the particles and estimates of ``localize(key,
..., config)`` with ``strides=(strides[0],)``, frame by frame, as long as no relocalization
happens (``tests/test_online.py``). Each frame costs one call of one compiled
program (``update`` is jitted; the state has fixed shapes); giving or leaving out depth or colour
selects one of at most four programs.

**Relocalization.** The verdict (:class:`~jaxloc.sg2loc.Verdict`) is computed every frame. When it
has been False for ``relocalize_after`` consecutive frames (default 5: the reference's injection
period), ``relocalize_count`` particles (default 2000, the reference's injection size, at most the
capacity) are replaced by random ones over the whole map's floor (the weakest first, as
:func:`~jaxloc.sg2loc._particles.inject_uniform` does) and the count starts again. This recovers
from a filter that converged on a wrong place or lost track (a kidnapped camera): the fresh
particles are scored on the next frame, and the old cloud keeps its weight where it still
explains the frames. ``relocalize_after = 0`` turns it off.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.camera import Camera
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._convert import as_float32, as_int32
from jaxloc.sg2loc._filter import Region, StepConfig, step
from jaxloc.sg2loc._localization import SG2LocConfig, step_config
from jaxloc.sg2loc._particles import PAPER_HEIGHTS, ParticleState, init_region, inject_uniform
from jaxloc.sg2loc._resampling import KLDConfig
from jaxloc.sg2loc._scores import ObservationConfig, check_ssim_strides
from jaxloc.sg2loc._sequence import Frame, FrameSequence, grid_pixels
from jaxloc.sg2loc._verdict import Verdict, VerdictConfig, default_verdict


class OnlineConfig(eqx.Module):
    """Deprecated (removed in jaxloc 0.4): the streaming filter takes an
    :class:`~jaxloc.sg2loc.SG2LocConfig` (``stride`` is its ``strides[0]``) and ``patch_shape``
    is an argument of :func:`init`. Built, it warns; :func:`init` converts it
    (:meth:`as_sg2loc`)."""

    capacity: int = eqx.field(static=True, default=2500)
    stride: int = eqx.field(static=True, default=20)
    patch_shape: tuple[int, int] = eqx.field(static=True, default=(9, 16))
    observation: ObservationConfig = ObservationConfig()
    kld: KLDConfig = KLDConfig()
    verdict: VerdictConfig | None = None
    sigma_trans: Array = eqx.field(default=0.05, converter=as_float32)
    sigma_rot: Array = eqx.field(default=0.05, converter=as_float32)
    region: Region | None = None
    heights: Array = eqx.field(default=PAPER_HEIGHTS, converter=as_float32)
    relocalize_after: Array = eqx.field(default=5, converter=as_int32)
    relocalize_count: Array = eqx.field(default=2000, converter=as_int32)
    engine: str = eqx.field(static=True, default="auto")
    particle_chunk: int | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        warnings.warn(
            "jaxloc.sg2loc.online.OnlineConfig is deprecated and will be removed in jaxloc 0.4; "
            "use jaxloc.sg2loc.SG2LocConfig(strides=(stride,), ...) and "
            "online.init(..., patch_shape=)",
            DeprecationWarning,
            stacklevel=3,
        )

    def as_sg2loc(self) -> tuple[SG2LocConfig, tuple[int, int]]:
        """The :class:`~jaxloc.sg2loc.SG2LocConfig` and patch shape it stands for."""
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        stride, patch_shape = fields.pop("stride"), tuple(fields.pop("patch_shape"))
        return SG2LocConfig(strides=(stride,), **fields), patch_shape


class OnlineState(eqx.Module):
    """Everything the stream carries from frame to frame (a pytree of fixed shapes).

    Attributes:
        particles: the particles after the last frame (resampled, relocalized).
        key: the PRNG key of the stream (frame t steps with ``fold_in(key, t)``).
        index: int32 number of frames seen.
        unlocalized: int32 consecutive frames without the verdict since the last relocalization.
        scene: the map.
        camera: the query camera.
        pixels: (2, R) int32 the image row and column of each ray of the grid.
        config: the step's configuration (grid, observation model); each frame's observation
            model and thresholds are set by :func:`update` from the inputs given.
        verdict: the verdict's thresholds of the configuration (None: each frame's preset).
        relocalize_after, relocalize_count: the relocalization policy (see the module docstring).
    """

    particles: ParticleState
    key: Array
    index: Array
    unlocalized: Array
    scene: SceneGraph
    camera: Camera
    pixels: Array
    config: StepConfig
    verdict: VerdictConfig | None
    relocalize_after: Array
    relocalize_count: Array


class Estimate(NamedTuple):
    """What :func:`update` tells about the frame it was given.

    Attributes:
        pose: (4,) float32 the MLE particle, (x, y, z, yaw), world frame, metres and radians.
        localized: bool, act on ``pose`` only when True.
        spread: (4,) float32 the particles' spread (``verdict.spread``).
        mean: (4,) float32 the weighted mean pose.
        verdict: the frame's :class:`~jaxloc.sg2loc.Verdict`.
        num_particles: int32 particles kept by KLD-sampling.
        relocalized: bool, random particles were injected over the map after this frame.
        motion_valid: bool, the ego-motion was finite (else the particles only diffused).
    """

    pose: Array
    localized: Array
    spread: Array
    mean: Array
    verdict: Verdict
    num_particles: Array
    relocalized: Array
    motion_valid: Array


def _round_keys(key: Array) -> tuple[Array, Array]:
    """``(key_init, key_run)`` of round 0 of :func:`~jaxloc.sg2loc.localize` with this key."""
    (round_key,) = jax.random.split(key, 1)
    key_init, key_run = jax.random.split(round_key)
    return key_init, key_run


def init(
    key: Array,
    scene: SceneGraph,
    camera: Camera,
    config: SG2LocConfig | OnlineConfig | None = None,
    *,
    patch_shape: tuple[int, int] = (9, 16),
) -> OnlineState:
    """The stream's first state: particles spread over the map's floor (or ``config.region``).

    Args:
        key: PRNG key; the same key and frames give the same estimates.
        scene: the map.
        camera: the query camera (its image size fixes the ray grid).
        config: :class:`~jaxloc.sg2loc.SG2LocConfig` (paper settings); the stream runs round
            0's settings: the ray grid of every ``strides[0]``-th pixel.
        patch_shape: (rows, cols) of the frames' patch embeddings (static; paper 9 x 16).

    Raises:
        TypeError: ``scene`` or ``camera`` of the wrong type.
        ValueError: a bad ``patch_shape``, or with the colour score on, a stride whose ray grid
            on the camera's image is smaller than SSIM's window
            (:func:`~jaxloc.sg2loc.check_ssim_strides`, naming ``SG2LocConfig(strides=)``).
    """
    if isinstance(config, OnlineConfig):
        config, patch_shape = config.as_sg2loc()
    config = SG2LocConfig() if config is None else config
    if not isinstance(scene, SceneGraph):
        raise TypeError(f"scene must be a jaxloc.SceneGraph, got {type(scene).__name__}")
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a jaxloc.Camera, got {type(camera).__name__}")
    patch_shape = tuple(patch_shape)
    if len(patch_shape) != 2 or any(not isinstance(n, int) or n < 1 for n in patch_shape):
        raise ValueError(f"patch_shape must be two positive ints, got {patch_shape!r}")
    if config.observation.use_color:
        setting, otherwise = "SG2LocConfig(strides=...)", "ObservationConfig(use_color=False)"
        check_ssim_strides(config.strides[:1], camera.width, camera.height, setting, otherwise)
    region = Region.of_scene(scene) if config.region is None else config.region
    round_config = step_config(config, camera, config.strides[0], patch_shape, region)
    pixels = jnp.asarray(np.stack(grid_pixels(camera, round_config.grid)), jnp.int32)
    key_init, key_run = _round_keys(key)
    particles = init_region(
        key_init, config.capacity, region.lo, region.hi, region.floor_z, heights=config.heights
    )
    state = OnlineState(
        particles=particles,
        key=key_run,
        index=jnp.int32(0),
        unlocalized=jnp.int32(0),
        scene=scene,
        camera=camera,
        pixels=pixels,
        config=round_config,
        verdict=config.verdict,
        relocalize_after=config.relocalize_after,
        relocalize_count=config.relocalize_count,
    )
    # Leaves as the compiled update returns them (NumPy scalars of the camera and the map become
    # JAX arrays), so the second frame finds the first frame's program.
    return jax.tree.map(jnp.asarray, state)


def _image(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    array = np.asarray(value, np.float32)
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} contains NaN/inf values")
    return array


def update(
    state: OnlineState,
    patch_embeddings,
    ego_motion,
    depth=None,
    rgb=None,
    tilt=None,
) -> tuple[OnlineState, Estimate]:
    """Filter one more frame: predict with ``ego_motion``, weigh, judge, resample, relocalize.

    Args:
        state: the stream's state (:func:`init`, or the last ``update``).
        patch_embeddings: (rows, cols, d) float patch embeddings of the frame.
        ego_motion: (4,) float (dx, dy, dz, dyaw) from the previous frame in its gravity-aligned
            body frame (metres, radians); zeros for the first frame (ignored there). A NaN motion
            (lost odometry) moves the particles by the motion noise only.
        depth: optional (H, W) sensor depth in metres (0 = invalid).
        rgb: optional (H, W, 3) colour in [0, 1].
        tilt: optional (2,) known (pitch, roll) in radians (default level).

    Returns:
        ``(state, estimate)``; see :class:`Estimate`.

    Raises:
        ValueError: an input of the wrong shape, or a NaN/inf in the images or embeddings.
    """
    if not isinstance(state, OnlineState):
        raise TypeError(f"state must be an OnlineState (online.init), got {type(state).__name__}")
    config, camera = state.config, state.camera
    rows, cols = config.grid.rows, config.grid.cols
    dim = state.scene.embeddings.shape[1]
    patches = _image("patch_embeddings", patch_embeddings, (rows, cols, dim))
    motion = np.asarray(ego_motion, np.float32)
    if motion.shape != (4,):
        raise ValueError(f"ego_motion must have shape (4,), got {motion.shape}")
    size = (camera.height, camera.width)
    depth = None if depth is None else _image("depth", depth, size)
    rgb = None if rgb is None else _image("rgb", rgb, (*size, 3))
    if depth is not None and np.any(depth < 0):
        raise ValueError("depth must be >= 0 (0 marks an invalid pixel)")
    tilt = np.zeros(2, np.float32) if tilt is None else _image("tilt", tilt, (2,))
    observation = dataclasses.replace(
        config.observation,
        use_depth=config.observation.use_depth and depth is not None,
        use_color=config.observation.use_color and rgb is not None,
    )
    return _update(
        state,
        observation,
        jnp.asarray(patches.reshape(rows * cols, dim)),
        jnp.asarray(motion),
        None if depth is None else jnp.asarray(depth),
        None if rgb is None else jnp.asarray(rgb),
        jnp.asarray(tilt),
    )


@eqx.filter_jit
def _update(state, observation, patches, motion, depth, rgb, tilt):
    verdict = default_verdict(observation.use_depth) if state.verdict is None else state.verdict
    config = dataclasses.replace(state.config, observation=observation, verdict=verdict)
    pixel_rows, pixel_cols = state.pixels
    h, w = config.grid.shape
    frame = Frame(
        index=state.index,
        motion=motion,
        patch_embeddings=patches,
        depth=(
            jnp.zeros(pixel_rows.shape, jnp.float32)
            if depth is None
            else depth[pixel_rows, pixel_cols]
        ),
        rgb=(
            jnp.zeros((h, w, 3), jnp.float32)
            if rgb is None
            else rgb[pixel_rows, pixel_cols].reshape(h, w, 3)
        ),
        tilt=tilt,
    )
    key = jax.random.fold_in(state.key, state.index)
    particles, info = step(key, state.particles, frame, state.scene, config)
    localized = info.verdict.localized
    unlocalized = jnp.where(localized, 0, state.unlocalized + 1)
    relocalize = (state.relocalize_after > 0) & (unlocalized >= state.relocalize_after)
    region = config.region
    particles = jax.lax.cond(
        relocalize,
        lambda p: inject_uniform(
            jax.random.fold_in(key, 1 << 30),
            p,
            state.relocalize_count,
            region.lo,
            region.hi,
            region.floor_z,
            config.heights,
        ),
        lambda p: p,
        particles,
    )
    state = dataclasses.replace(
        state,
        particles=particles,
        index=state.index + 1,
        unlocalized=jnp.where(relocalize, 0, unlocalized),
    )
    estimate = Estimate(
        pose=info.mle,
        localized=localized,
        spread=info.verdict.spread,
        mean=info.mean,
        verdict=info.verdict,
        num_particles=info.num_particles,
        relocalized=relocalize,
        motion_valid=info.motion_valid,
    )
    return state, estimate


def filter_sequence(
    key: Array,
    scene: SceneGraph,
    sequence: FrameSequence,
    config: SG2LocConfig | OnlineConfig | None = None,
    *,
    progress=None,
) -> Estimate:
    """A recorded sequence fed to the stream frame by frame (:func:`init`, then :func:`update`
    per frame): what a camera delivering these frames one at a time would have been told.

    Args:
        key: PRNG key (as for :func:`init`).
        scene: the map.
        sequence: the frames (:class:`~jaxloc.sg2loc.FrameSequence`; its depth and colour are
            used when present and ``config.observation`` uses them).
        config: as for :func:`init` (the patch shape is the sequence's).
        progress: optional callable ``progress(t)`` after each frame (e.g. a progress bar's
            ``update``).

    Returns:
        The :class:`Estimate` of every frame, stacked on a leading (T,) axis (host arrays).
    """
    if not isinstance(sequence, FrameSequence):
        raise TypeError(f"sequence must be a jaxloc.FrameSequence, got {type(sequence).__name__}")
    if isinstance(config, OnlineConfig):
        config, _ = config.as_sg2loc()
    config = SG2LocConfig() if config is None else config
    if sequence.rgb is None:  # no colour to score: the stride need not suit SSIM
        observation = dataclasses.replace(config.observation, use_color=False)
        config = dataclasses.replace(config, observation=observation)
    state = init(key, scene, sequence.camera, config, patch_shape=tuple(sequence.patch_shape))
    estimates = []
    for t in range(sequence.num_frames):
        motion = np.zeros(4, np.float32) if t == 0 else sequence.ego_motion[t - 1]
        state, estimate = update(
            state,
            sequence.patch_embeddings[t],
            motion,
            depth=None if sequence.depth is None else sequence.depth[t],
            rgb=None if sequence.rgb is None else sequence.rgb[t],
            tilt=sequence.tilt[t],
        )
        estimates.append(estimate)
        if progress is not None:
            progress(t)
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *estimates)
