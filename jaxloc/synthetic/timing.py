"""Speed checks on synthetic data: the measurements ``jaxloc bench`` prints.

Each ``time_*`` function builds its inputs, compiles, then times the compiled work and returns
the numbers as a small frozen dataclass. Times are seconds: ``compile_s`` is the compilation (or
persistent-cache load), ``wall_s`` wall-clock time (``time.perf_counter``) and ``cpu_s`` the
process CPU time (``time.process_time``, all threads) of the timed run. The comparisons with peers
(Embree, networkx) are the scripts in ``benchmarks/`` of the repository.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "FilterTiming",
    "RaycastTiming",
    "TripletTiming",
    "time_filter",
    "time_raycast",
    "time_triplet",
]


def timed(fn: Callable[[], object], repeats: int = 1) -> tuple[float, float]:
    """(wall s, process CPU s) of the fastest (by wall time) of ``repeats`` calls of ``fn``."""
    best = (np.inf, np.inf)
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        best = min(best, (time.perf_counter() - wall, time.process_time() - cpu))
    return best


@dataclass(frozen=True)
class RaycastTiming:
    """What :func:`time_raycast` measured.

    Attributes:
        num_objects, num_triangles: the room's scene graph.
        poses: camera poses per batch; rays_per_pose: rays of the stride grid per pose.
        compile_s: compilation of ``jax.jit(render_batch)``, s.
        wall_s, cpu_s: the fastest timed batch, wall and process CPU s; repeats: batches timed.
    """

    num_objects: int
    num_triangles: int
    poses: int
    rays_per_pose: int
    compile_s: float
    wall_s: float
    cpu_s: float
    repeats: int

    @property
    def rays(self) -> int:
        """Rays cast per batch (poses x rays per pose)."""
        return self.poses * self.rays_per_pose

    @property
    def rays_per_s(self) -> float:
        """Rays per wall-clock second."""
        return self.rays / max(self.wall_s, 1e-9)

    @property
    def rays_per_cpu_s(self) -> float:
        """Rays per process CPU second (all threads)."""
        return self.rays / max(self.cpu_s, 1e-9)


def time_raycast(
    seed: int = 0,
    poses: int = 64,
    width: int = 480,
    height: int = 270,
    stride: int = 10,
    objects: int = 20,
    vertices: int = 600,
    repeats: int = 3,
) -> RaycastTiming:
    """Time :func:`jaxloc.sg2loc.render_batch` under ``jax.jit`` on ``poses`` random camera poses
    (0.3 m from the walls, 1.2-1.8 m high, any yaw) in a synthetic room of ``objects`` furniture
    objects of ``vertices`` mesh vertices each, casting the ``stride``-pixel grid of a 60 deg
    ``width`` x ``height`` px camera; the best of ``repeats`` batches."""
    import jax

    from jaxloc.camera import Camera, stride_grid
    from jaxloc.sg2loc import render_batch
    from jaxloc.synthetic.indoor import RoomConfig, make_room, scene_graph

    config = RoomConfig(num_objects=(objects, objects), vertex_range=(vertices, vertices))
    room = make_room(seed, config)
    scene = scene_graph(room)
    camera = Camera.from_fov(width, height, 60.0)
    grid = stride_grid(camera, stride)
    rng = np.random.default_rng(seed)
    (lx, ly, _), n = room.size, poses
    ranges = ((0.3, lx - 0.3), (0.3, ly - 0.3), (1.2, 1.8), (-np.pi, np.pi))  # x, y, z, yaw
    batch = np.column_stack([rng.uniform(lo, hi, n) for lo, hi in ranges]).astype(np.float32)
    start = time.perf_counter()
    compiled = jax.jit(render_batch).lower(scene, batch, camera, grid).compile()
    compile_s = time.perf_counter() - start
    wall, cpu = timed(lambda: jax.block_until_ready(compiled(scene, batch, camera, grid)), repeats)
    return RaycastTiming(
        scene.num_objects, scene.num_triangles, n, grid.uv.shape[0], compile_s, wall, cpu, repeats
    )


@dataclass(frozen=True)
class FilterTiming:
    """What :func:`time_filter` measured.

    Attributes:
        particles: the filter's capacity; rays_per_particle: rays of the stride grid per particle.
        num_objects, num_triangles: the room's scene graph; frames: frames localized.
        build_s: building the episode (room, trajectory, rendered frames), s.
        compile_s: the first run's time beyond the timed run's (compilation), s.
        wall_s, cpu_s: the timed run over all frames, wall and process CPU s.
    """

    particles: int
    rays_per_particle: int
    num_objects: int
    num_triangles: int
    frames: int
    build_s: float
    compile_s: float
    wall_s: float
    cpu_s: float

    @property
    def s_per_frame(self) -> float:
        """Wall seconds per frame."""
        return self.wall_s / self.frames

    @property
    def cpu_s_per_frame(self) -> float:
        """Process CPU seconds per frame."""
        return self.cpu_s / self.frames


def time_filter(
    episode_config, seed: int = 1, frames: int = 3, particles: int = 1000, stride: int = 8
) -> FilterTiming:
    """Time one round (render, score, resample per frame) of :func:`jaxloc.sg2loc.localize` with
    ``particles`` particles (KLD-sampling down to 300) at pixel stride ``stride`` on a ``frames``
    frame episode of :func:`jaxloc.synthetic.indoor.make_episode` (``episode_config``, an
    :class:`~jaxloc.synthetic.indoor.EpisodeConfig`), with a progress bar: a first run (seed
    ``seed``) compiles, a second (``seed + 1``) is timed."""
    import jax

    from jaxloc.camera import stride_grid
    from jaxloc.sg2loc import KLDConfig, SG2LocConfig, kld_for_capacity, localize
    from jaxloc.synthetic import indoor

    start = time.perf_counter()
    episode = indoor.make_episode(seed, frames, episode_config)
    build_s = time.perf_counter() - start
    scene, sequence = episode.scene, episode.sequence
    kld = kld_for_capacity(particles, KLDConfig(min_particles=300))
    config = SG2LocConfig(capacity=particles, strides=(stride,), kld=kld)

    def run(key: int) -> None:
        result = localize(jax.random.key(key), scene, sequence, config, progress=True)
        jax.block_until_ready(result.poses)

    first, _ = timed(lambda: run(seed))
    wall, cpu = timed(lambda: run(seed + 1))
    rays = stride_grid(sequence.camera, stride).uv.shape[0]
    n, t = scene.num_objects, scene.num_triangles
    return FilterTiming(particles, rays, n, t, frames, build_s, max(first - wall, 0.0), wall, cpu)


@dataclass(frozen=True)
class TripletTiming:
    """What :func:`time_triplet` measured.

    Attributes:
        queries: queries localized; query_instances: (fewest, most) instances of a query.
        compile_s: compilation (or cache load) of the query programs, s.
        descriptor_ms, match_ms: median per query of the descriptors and of match + clique +
            pose, ms.
        success_rate: fraction of queries localized (valid, RTE < 7.5 m, RRE < 10 deg).
    """

    queries: int
    query_instances: tuple[int, int]
    compile_s: float
    descriptor_ms: float
    match_ms: float
    success_rate: float


def time_triplet(
    triplet_map, points, labels, road_normals, queries: int = 20, max_kept: int = 24, seed: int = 0
) -> TripletTiming:
    """Time :func:`jaxloc.m2loc.localize_drive` (each query alone) on the described
    ``triplet_map`` of ``points`` (N, 3) m and ``labels`` (N,) with ``queries`` scan-like queries
    of :func:`jaxloc.synthetic.outdoor.make_query` (``max_kept`` map instances kept each, drawn
    with ``numpy.random.default_rng(seed)``) cut from them on ``road_normals``."""
    from jaxloc.m2loc import localize_drive
    from jaxloc.m2loc._evaluation import localization_success
    from jaxloc.synthetic.outdoor import make_query

    rng = np.random.default_rng(seed)
    cut = [make_query(points, labels, road_normals, rng, max_kept=max_kept) for _ in range(queries)]
    drive = localize_drive(triplet_map, cut)
    success = localization_success(drive.poses, np.stack([q.T_map_scan for q in cut]), drive.valid)
    times = np.array([(s.result.descriptor_time_ms, s.result.match_time_ms) for s in drive.steps])
    desc, match = np.median(times, axis=0)
    sizes = [len(q.points) for q in cut]
    compile_s = float(drive.compile_s.sum())
    return TripletTiming(
        queries,
        (min(sizes), max(sizes)),
        compile_s,
        float(desc),
        float(match),
        float(success.mean()),
    )
