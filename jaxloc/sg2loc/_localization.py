"""SG2Loc: sequential localization of a camera in a scene graph, coarse-to-fine (paper section 3.5).

:func:`localize` runs the particle filter over the whole sequence once per round. Round 0 spreads
particles over the map's floor (or a given region) and casts every ``strides[0]``-th pixel; each
later round carries the previous round's last-frame MLE back to the first frame through the
ego-motion, re-initialises the particles in a box around it (half-widths ``box_half_widths``) and
casts a denser ray grid. The paper's defaults are strides 20, 8, 4 and boxes of 1.6^3 then 0.8^3 m.

All rounds are one compiled program: a ``lax.scan`` over the rounds of a ``lax.scan`` of the
filter step over the frames (:func:`~jaxloc.sg2loc.step`, as in
:func:`~jaxloc.sg2loc.run_pass`). The rounds share the prediction, the update and the
re-initialisation, and choose their stride's scoring with ``lax.switch``, so the first call
traces and compiles each part once. With ``progress=True`` a host call inside the frames' scan
ticks a progress bar after every frame.

:func:`localize` composes with the caller's transformations: it runs inside ``jax.jit`` (key,
scene, sequence and configuration may all be traced) and ``jax.vmap`` (over keys, over the array
leaves of configurations stacked with ``jax.tree.map(lambda *c: jnp.stack(c), *configs)``, over
sequences of one shape stacked the same way). Every continuous setting of :class:`SG2LocConfig`
is a traced array leaf, so a sweep over its values compiles once; only sizes, strides, schedules,
engines and variants are static.

:func:`warm_up` compiles the programs of a later :func:`localize` call in background threads,
from arguments that need only have the right shapes, so that compilation overlaps the caller's
own work (reading the recording).
"""

from __future__ import annotations

import dataclasses
import threading
from concurrent.futures import Future
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.sharding import Mesh

from jaxloc._traced import concrete
from jaxloc.camera import Camera, stride_grid
from jaxloc.raycasting.engines import check_engine_name
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._convert import as_float32, as_int32, finite_nonnegative, shown
from jaxloc.sg2loc._filter import (
    Region,
    StepConfig,
    StepInfo,
    check_particle_chunk,
)
from jaxloc.sg2loc._particles import (
    DEFAULT_BOX_YAW_HALF_RANGE,
    PAPER_HEIGHTS,
)
from jaxloc.sg2loc._progress import FrameBar
from jaxloc.sg2loc._resampling import KLDConfig
from jaxloc.sg2loc._rounds import all_rounds
from jaxloc.sg2loc._scores import ObservationConfig, check_ssim_strides
from jaxloc.sg2loc._sequence import FrameSequence, frames_on_grid
from jaxloc.sg2loc._verdict import VerdictConfig, default_verdict
from jaxloc.sharding import check_divisible


class SG2LocConfig(eqx.Module):
    """Settings of :func:`localize`. Sizes, schedules and switches are static; every continuous
    setting is a traced array leaf (a new value never recompiles; stacked configurations vmap).

    Attributes:
        capacity: particle buffer size (static); KLD-sampling chooses how many are active.
        strides: pixel stride of each round's ray grid (static; paper 20, 8, 4).
        box_half_widths: (B,) float32 half-widths (metres) of the re-initialisation boxes of
            rounds 1, 2, ... (round r uses ``box_half_widths[r - 1]``; B >= R - 1 for R rounds;
            paper 0.8 and 0.4, i.e. 1.6^3 and 0.8^3 m boxes).
        yaw_half_range: float32 yaw half-range (radians) of the re-initialisation boxes.
        observation: score variants and likelihood parameters.
        kld: KLD-sampling parameters.
        sigma_trans, sigma_rot: float32 motion noise (metres, radians; paper 0.05 and 0.05).
        inject_count: int32 random particles injected on injection frames (reference: 2000;
            default 0, off).
        inject_every: inject on frames whose index is a positive multiple of this (static;
            reference 5).
        region: initialisation region (default: the map's floor bounds).
        heights: (H,) float32 camera heights above the region's floor (metres) of round 0's
            particles and of injected ones (H static; default the paper's 1.5, 1.6, 1.7, 1.8 m).
            Set them near the query camera's real height (e.g. 1.2-1.5 m for a hand-held ScanNet
            camera).
        engine: nearest-hit engine of the rendering (static; "auto", "jax", "embree" or "warp",
            see :func:`jaxloc.raycast`).
        particle_chunk: particles rendered together (static; ``StepConfig.particle_chunk``:
            None sizes chunks to :func:`jaxloc.sg2loc._filter.default_chunk_rays` rays).
        verdict: thresholds of the per-frame verdict
            (:class:`~jaxloc.sg2loc.VerdictConfig`; None: the preset for whether the
            sequence's depth is used, :func:`~jaxloc.sg2loc.default_verdict`).
        relocalize_after: the streaming filter (:mod:`~jaxloc.sg2loc.online`) relocalizes after
            this many consecutive frames without the verdict (int32, traced; 0: never).
            :func:`localize` does not use it (its later rounds re-initialise instead).
        relocalize_count: particles the streaming filter then replaces by random ones over the
            region (int32, traced, clamped to ``capacity``; the reference's 2000).

    The streaming filter (:func:`jaxloc.sg2loc.online.init`) takes the same configuration and
    runs round 0's settings (``strides[0]``, ``heights``, the region) on every frame.

    Concrete values are validated on construction; traced ones (a configuration built inside a
    caller's ``jax.jit`` or ``jax.vmap``) only by shape.
    """

    capacity: int = eqx.field(static=True, default=2500)
    strides: tuple[int, ...] = eqx.field(static=True, default=(20, 8, 4))
    box_half_widths: Array = eqx.field(default=(0.8, 0.4), converter=as_float32)
    yaw_half_range: Array = eqx.field(default=DEFAULT_BOX_YAW_HALF_RANGE, converter=as_float32)
    observation: ObservationConfig = ObservationConfig()
    kld: KLDConfig = KLDConfig()
    sigma_trans: Array = eqx.field(default=0.05, converter=as_float32)
    sigma_rot: Array = eqx.field(default=0.05, converter=as_float32)
    inject_count: Array = eqx.field(default=0, converter=as_int32)
    inject_every: int = eqx.field(static=True, default=5)
    region: Region | None = None
    heights: Array = eqx.field(default=PAPER_HEIGHTS, converter=as_float32)
    engine: str = eqx.field(static=True, default="auto")
    particle_chunk: int | None = eqx.field(static=True, default=None)
    verdict: VerdictConfig | None = None
    relocalize_after: Array = eqx.field(default=5, converter=as_int32)
    relocalize_count: Array = eqx.field(default=2000, converter=as_int32)

    def __check_init__(self):
        check_engine_name(self.engine)
        check_particle_chunk(self.particle_chunk)
        if not isinstance(self.capacity, int) or self.capacity < 1:
            raise ValueError(f"capacity must be a positive int, got {self.capacity!r}")
        if len(self.strides) < 1 or any(int(s) < 1 for s in self.strides):
            raise ValueError(f"strides must be positive ints, got {self.strides}")
        boxes, heights = self.box_half_widths, self.heights
        if boxes.ndim != 1 or boxes.shape[0] < len(self.strides) - 1:
            raise ValueError(
                f"{len(self.strides)} rounds need {len(self.strides) - 1} box_half_widths, "
                f"got {shown(boxes)}"
            )
        if concrete(boxes) and not np.all(np.asarray(boxes) > 0):
            raise ValueError(f"box_half_widths must be positive, got {shown(boxes)}")
        if heights.ndim != 1 or heights.shape[0] < 1 or not finite_nonnegative(heights):
            raise ValueError(
                f"heights must be a non-empty tuple of finite heights >= 0 m, got {shown(heights)}"
            )
        for name in ("inject_count", "relocalize_after", "relocalize_count"):
            count = getattr(self, name)
            if count.ndim != 0 or (concrete(count) and np.asarray(count) < 0):
                raise ValueError(f"{name} must be an int >= 0, got {shown(count)}")


class SG2LocResult(NamedTuple):
    """Output of :func:`localize` (T frames, R rounds, N particle capacity).

    Attributes:
        poses: (T, 4) the final round's MLE at every frame, (x, y, z, yaw).
        localized: (T,) bool, the final round's verdict at every frame: act on ``poses[t]`` only
            where it is True (:mod:`jaxloc.sg2loc._verdict`; what it is made of:
            ``info.verdict``). It is shy where the data differ from its calibration; with the
            recording's depth, :func:`~jaxloc.sg2loc.depth_blind_check` is a verdict that
            carried over to held-out conditions, at the cost of a second, depth-blind filter.
        round_mle: (R, T, 4) every round's per-frame MLE.
        round_start: (R, 4) the centre each round was initialised around (round 0: NaN).
        num_particles: (R, T) int32 particles after KLD resampling.
        info: the final round's per-frame :class:`~jaxloc.sg2loc.StepInfo` (scores, flags).
        particles: (R, T, N, 4) particle poses after each frame's update (before resampling).
        particle_weights: (R, T, N) their normalised weights (0 for inactive slots).
        used_depth, used_color: whether the depth / colour scores were used.
    """

    poses: Array
    localized: Array
    round_mle: Array
    round_start: Array
    num_particles: Array
    info: StepInfo
    particles: Array
    particle_weights: Array
    used_depth: bool
    used_color: bool


def _call(program, *args):
    return program(*args)


class _Lowering:
    """Runs no program: lowers each jitted ``program`` for ``args`` in the calling thread, starts
    its compilation at once in a thread of its own (so that a :func:`localize` started meanwhile
    finds every program compiling, never queued: JAX makes a call wait for a program that is
    being compiled), and returns zeros shaped like its output, for :func:`warm_up`.
    ``compiled``: the compilations' futures, in call order."""

    def __init__(self):
        self.compiled: list[Future] = []

    def __call__(self, program, *args):
        lowered = program.lower(*args)
        compiled: Future = Future()
        name = f"jaxloc-warm-up_{len(self.compiled)}"
        threading.Thread(target=_compile, args=(lowered, compiled), name=name, daemon=True).start()
        self.compiled.append(compiled)
        if isinstance(lowered, jax.stages.Lowered):
            shapes = lowered.out_info
        else:  # equinox's: its output's arrays, then the rest of its output put back
            shapes = lowered.postprocess(lowered.lowered.out_info)
        return jax.tree.map(_zeros, shapes)


def _zeros(shape: jax.ShapeDtypeStruct) -> Array:
    if jax.dtypes.issubdtype(shape.dtype, jax.dtypes.prng_key):
        return jnp.zeros(shape.shape, shape.dtype)
    return jax.device_put(np.zeros(shape.shape, shape.dtype))  # compiles nothing


def localize(
    key: Array,
    scene: SceneGraph,
    sequence: FrameSequence,
    config: SG2LocConfig | None = None,
    *,
    progress: bool = False,
    mesh: Mesh | None = None,
) -> SG2LocResult:
    """Localize every frame of ``sequence`` in ``scene`` with the coarse-to-fine particle filter.

    Depth and colour scores are used when the sequence carries depth / RGB and the configuration
    enables them; a sequence without depth (or RGB) runs without that score.

    Runs inside a caller's ``jax.jit`` and ``jax.vmap`` (see the module docstring); the result
    is the same as an eager call's up to float32 rounding.

    Args:
        key: PRNG key; the same key and inputs give the same result.
        scene: the map.
        sequence: the query (its patch grid fixes the semantic patches).
        config: :class:`SG2LocConfig` (paper defaults).
        progress: show a progress bar over rounds x frames, ticked by a host call from inside
            the rounds' compiled scan (the same result as without). Not shown when ``key`` is
            traced (inside a caller's ``jax.jit``, or a ``jax.vmap`` over keys). On a GPU or with
            ``mesh`` the host call is a Python callback, and JAX keeps such programs out of its
            persistent compilation cache.
        mesh: a 1-D device mesh (:func:`jaxloc.sharding.device_mesh`) to split the particle
            buffer over; ``config.capacity`` must be a multiple of its device count. Same keys,
            same result as one device up to the float32 reduction order (see
            :mod:`jaxloc.sharding`).

    Raises:
        TypeError: ``scene`` or ``sequence`` of the wrong type.
        ValueError: embeddings of another length than the map's, a capacity that does not
            split evenly over ``mesh``, or with colour a stride whose ray grid is smaller than
            SSIM's window (:func:`~jaxloc.sg2loc.check_ssim_strides`).
    """
    config = SG2LocConfig() if config is None else config
    step_configs = _checked(scene, sequence, config, mesh)
    keys = jax.random.split(key, len(config.strides))
    if not progress or isinstance(keys, jax.core.Tracer):
        return _run_rounds(keys, scene, sequence, config, step_configs, None, mesh, _call)
    with FrameBar(config.strides, sequence.num_frames) as bar:
        result = _run_rounds(keys, scene, sequence, config, step_configs, bar.id, mesh, _call)
        return jax.block_until_ready(result)  # every frame's tick reaches the open bar


def warm_up(
    key: Array,
    scene: SceneGraph,
    sequence: FrameSequence,
    config: SG2LocConfig | None = None,
    *,
    progress: bool = False,
    mesh: Mesh | None = None,
) -> Future:
    """Compile the programs that :func:`localize` runs for these arguments in background
    threads, without running the filter; returns a :class:`concurrent.futures.Future` that is
    done when they are compiled (its result is None; a failure is its exception).

    Only the arguments' shapes, dtypes and static settings matter, not their values: while a
    recording is still being read, pass a placeholder of its sizes (:meth:`FrameSequence.zeros`).
    :func:`localize` with arguments of the same shapes then compiles nothing, even while the
    warm-up is still compiling: it can start at once, and each of its programs waits for the
    warm-up's compilation of it (all of them compile side by side, one thread each).

    The programs are traced and lowered here, in the calling thread, and compiled in the
    background (XLA releases the GIL). Tracing holds the GIL: work of the caller's that runs
    without it (numpy, XLA, file reads) overlaps the tracing too when started in a thread of its
    own before this call, as ``jaxloc demo`` renders its query frames. The programs also go to
    the persistent compilation cache, where it is enabled (with a progress bar, on one CPU device
    only: see ``progress``).

    Args:
        key: a PRNG key of the kind :func:`localize` will get (its value is not used).
        scene: as for :func:`localize`.
        sequence: as for :func:`localize` (or :meth:`FrameSequence.zeros` of its sizes).
        config: as for :func:`localize`.
        progress: as for :func:`localize` (the rounds' programs with the progress bar's host
            call, or without).
        mesh: as for :func:`localize`.

    Raises:
        TypeError: ``scene`` or ``sequence`` of the wrong type (as :func:`localize`, here
            rather than in the future).
        ValueError: embeddings of another length than the map's, or a capacity that does not
            split evenly over ``mesh`` (as :func:`localize`).
    """
    config = SG2LocConfig() if config is None else config
    step_configs = _checked(scene, sequence, config, mesh)
    keys = jax.random.split(key, len(config.strides))
    bar_id = np.int32(0) if progress else None  # a placeholder: only its type matters
    lowering = _Lowering()
    _run_rounds(keys, scene, sequence, config, step_configs, bar_id, mesh, lowering)
    return _all_done(lowering.compiled)


def _compile(lowered, done: Future) -> None:
    """Compiles ``lowered`` into JAX's caches (keeping neither it nor the result: memory) and
    settles ``done``."""
    try:
        lowered.compile()
    except BaseException as error:  # handed to the caller through the future
        done.set_exception(error)
    else:
        done.set_result(None)


def _all_done(futures: list[Future]) -> Future:
    """A future that is done when every one of ``futures`` is, with the first failure."""
    done: Future = Future()
    remaining = [len(futures)]
    lock = threading.Lock()

    def settle(_):
        with lock:
            remaining[0] -= 1
            if remaining[0]:
                return
        failures = [f.exception() for f in futures if f.exception() is not None]
        if failures:
            done.set_exception(failures[0])
        else:
            done.set_result(None)

    if not futures:
        done.set_result(None)
    for future in futures:
        future.add_done_callback(settle)
    return done


def step_config(
    config: SG2LocConfig,
    camera: Camera,
    stride: int,
    patch_shape: tuple[int, int],
    region: Region,
    observation: ObservationConfig | None = None,
    verdict: VerdictConfig | None = None,
    mesh: Mesh | None = None,
) -> StepConfig:
    """The :class:`~jaxloc.sg2loc.StepConfig` of one round of ``config`` (offline, or the
    streaming filter's one round): ``camera`` cast on a grid of every ``stride``-th pixel with
    ``patch_shape`` patches, particles started and injected over ``region``; ``observation`` and
    ``verdict`` replace the configuration's (the scores a sequence can have, the verdict's preset
    for them)."""
    return StepConfig(
        camera=camera,
        grid=stride_grid(camera, stride, *patch_shape),
        observation=config.observation if observation is None else observation,
        kld=config.kld,
        region=region,
        sigma_trans=config.sigma_trans,
        sigma_rot=config.sigma_rot,
        inject_count=config.inject_count,
        inject_every=config.inject_every,
        heights=config.heights,
        engine=config.engine,
        particle_chunk=config.particle_chunk,
        verdict=VerdictConfig() if verdict is None else verdict,
        mesh=mesh,
    )


def _checked(scene, sequence, config: SG2LocConfig, mesh) -> tuple[StepConfig, ...]:
    """:func:`localize`'s argument checks; returns the step configuration of each round."""
    if not isinstance(scene, SceneGraph):
        raise TypeError(f"scene must be a jaxloc.SceneGraph, got {type(scene).__name__}")
    if not isinstance(sequence, FrameSequence):
        raise TypeError(f"sequence must be a jaxloc.FrameSequence, got {type(sequence).__name__}")
    d_seq, d_map = sequence.patch_embeddings.shape[-1], scene.embeddings.shape[1]
    if d_seq != d_map:
        raise ValueError(f"patch embeddings have {d_seq} dims but the map's objects have {d_map}")
    if mesh is not None:
        check_divisible(config.capacity, mesh, "SG2LocConfig.capacity")
    observation = config.observation
    used_depth = observation.use_depth and sequence.depth is not None
    used_color = observation.use_color and sequence.rgb is not None
    observation = dataclasses.replace(observation, use_depth=used_depth, use_color=used_color)
    if used_color:
        width, height = sequence.camera.width, sequence.camera.height
        setting, otherwise = "SG2LocConfig(strides=...)", "ObservationConfig(use_color=False)"
        check_ssim_strides(config.strides, width, height, setting, otherwise)
    region = Region.of_scene(scene) if config.region is None else config.region
    verdict = default_verdict(used_depth) if config.verdict is None else config.verdict
    return tuple(
        step_config(
            config,
            sequence.camera,
            stride,
            sequence.patch_shape,
            region,
            observation=observation,
            verdict=verdict,
            mesh=mesh,
        )
        for stride in config.strides
    )


def _run_rounds(keys, scene, sequence, config, step_configs, bar_id, mesh, run) -> SG2LocResult:
    """The rounds of :func:`localize` (one key of ``keys`` each; ``step_configs`` from
    :func:`_checked`; ``bar_id`` a progress bar's id or None), their one program run by ``run``
    (:func:`_call`; a :class:`_Lowering` lowers it instead)."""
    distinct = list(dict.fromkeys(config.strides))
    branches = tuple(distinct.index(stride) for stride in config.strides)
    configs = tuple(step_configs[config.strides.index(stride)] for stride in distinct)
    frames = tuple(frames_on_grid(sequence, c.grid) for c in configs)
    boxes = (config.box_half_widths, config.yaw_half_range)
    program_args = (keys, frames, scene, configs, branches, boxes, sequence.ego_motion)
    info, infos, starts = run(all_rounds, *program_args, config.capacity, mesh, bar_id)
    return SG2LocResult(
        poses=info.mle,
        localized=info.verdict.localized,
        round_mle=infos.mle,
        round_start=starts,
        num_particles=infos.num_particles,
        info=info,
        particles=infos.particles,
        particle_weights=infos.particle_weights,
        used_depth=step_configs[0].observation.use_depth,
        used_color=step_configs[0].observation.use_color,
    )
