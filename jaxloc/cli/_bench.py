"""``jaxloc bench``: quick in-package speed checks after compilation."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from jaxloc.cli._demo import (
    check_image_size,
    demo_episode_config,
    fits_ssim,
    largest_fitting_stride,
    ray_grid_shape,
)
from jaxloc.cli._errors import InputError
from jaxloc.cli._lidar import describe_map, triplet_config
from jaxloc.cli._lidar_scans import reading


def _timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Best-of-``repeats`` wall seconds and the process CPU seconds of that run."""
    best = (np.inf, np.inf)
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        elapsed = (time.perf_counter() - wall, time.process_time() - cpu)
        best = min(best, elapsed)
    return best


def check_bench_raycast(args: argparse.Namespace) -> None:
    """``--stride`` must cast at least one ray per side of the ``--width x --height`` image."""
    if min(ray_grid_shape(args.stride, args.width, args.height)) < 1:
        raise InputError(
            f"--stride {args.stride} casts no ray on a {args.width} x {args.height} image; use "
            f"--stride {2 * min(args.width, args.height) - 1} or less"
        )


def check_bench_filter(args: argparse.Namespace) -> None:
    """The image must hold the demo's patch grid, and ``--stride`` cast at least SSIM's 7 x 7
    rays on it (:class:`jaxloc.sg2loc.StepConfig` refuses a smaller ray grid)."""
    from jaxloc.sg2loc._scores import SSIM_WINDOW

    check_image_size(args)
    if not fits_ssim(args.stride, args.width, args.height):
        rows, cols = ray_grid_shape(args.stride, args.width, args.height)
        largest = largest_fitting_stride(args.width, args.height, args.stride)
        raise InputError(
            f"--stride: stride {args.stride} gives a {rows} x {cols} ray grid at {args.width} x "
            f"{args.height}, smaller than SSIM's {SSIM_WINDOW} x {SSIM_WINDOW} window; use "
            f"--stride {largest} or less"
        )


def describe_engine() -> str:
    """The engine ``"auto"`` picks here, in words (for Embree: which implementation, threads)."""
    from jaxloc.raycasting import embree, resolve_engine

    engine = resolve_engine("auto")
    return f"embree ({embree.describe()})" if engine == "embree" else engine


def run_bench_raycast(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.camera import Camera, stride_grid
    from jaxloc.sg2loc import render_batch
    from jaxloc.synthetic.indoor import RoomConfig, make_room, scene_graph

    room = make_room(
        args.seed,
        RoomConfig(num_objects=(args.objects, args.objects), vertex_range=(args.vertices,) * 2),
    )
    scene = scene_graph(room)
    camera = Camera.from_fov(args.width, args.height, 60.0)
    grid = stride_grid(camera, args.stride)
    rng = np.random.default_rng(args.seed)
    lx, ly, _ = room.size
    poses = np.column_stack(
        [
            rng.uniform(0.3, lx - 0.3, args.poses),
            rng.uniform(0.3, ly - 0.3, args.poses),
            rng.uniform(1.2, 1.8, args.poses),
            rng.uniform(-np.pi, np.pi, args.poses),
        ]
    ).astype(np.float32)
    start = time.perf_counter()
    compiled = jax.jit(render_batch).lower(scene, poses, camera, grid).compile()
    compile_s = time.perf_counter() - start
    wall, cpu = _timed(
        lambda: jax.block_until_ready(compiled(scene, poses, camera, grid)), args.repeats
    )
    rays = args.poses * grid.uv.shape[0]
    print(
        f"raycast (render_batch): {scene.num_objects} objects, {scene.num_triangles} triangles; "
        f"{args.poses} poses x {grid.uv.shape[0]} rays ({args.width}x{args.height}, "
        f"stride {args.stride}) = {rays} rays"
    )
    print(f"  engine: {describe_engine()}")
    print(f"  compile {compile_s:.2f} s; best of {args.repeats}: {wall * 1e3:.1f} ms")
    per_cpu_s = rays / max(cpu, 1e-9) / 1e6
    print(f"  {rays / wall / 1e6:.3f} M rays/s (wall), {per_cpu_s:.3f} M rays per CPU-second")
    return 0


def run_bench_filter(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.camera import stride_grid
    from jaxloc.sg2loc import KLDConfig, SG2LocConfig, localize
    from jaxloc.synthetic import indoor

    start = time.perf_counter()
    episode = indoor.make_episode(args.seed, args.frames, demo_episode_config(args))
    build_s = time.perf_counter() - start
    scene, sequence = episode.scene, episode.sequence
    config = SG2LocConfig(
        capacity=args.particles,
        strides=(args.stride,),
        kld=KLDConfig(min_particles=min(300, args.particles), max_particles=args.particles),
    )

    def run(seed: int) -> None:  # the demo's path: one scan per round, a progress bar
        result = localize(jax.random.key(seed), scene, sequence, config, progress=True)
        jax.block_until_ready(result.poses)

    start = time.perf_counter()
    run(args.seed)
    first_s = time.perf_counter() - start
    wall, cpu = _timed(lambda: run(args.seed + 1), 1)
    rays = stride_grid(sequence.camera, args.stride).uv.shape[0]
    print(
        f"filter (SG2Loc, one round): {args.particles} particles x {rays} rays "
        f"({args.width}x{args.height}, stride {args.stride}), {scene.num_objects} objects, "
        f"{scene.num_triangles} triangles (episode built in {build_s:.1f} s)"
    )
    print(f"  compile {max(first_s - wall, 0.0):.2f} s")
    print(
        f"  {wall / args.frames:.4f} s/frame wall, {cpu / args.frames:.4f} s/frame CPU "
        f"(mean over {args.frames} frames)"
    )
    return 0


def run_bench_triplet(args: argparse.Namespace) -> int:
    from jaxloc.m2loc import localization_errors, localize_drive
    from jaxloc.m2loc._evaluation import SUCCESS_RRE_DEG, SUCCESS_RTE_M
    from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

    config = triplet_config(args)
    if args.map is not None:
        from jaxloc.io.instance_maps import read_lidar_map

        with reading():
            instances, normals = read_lidar_map(args.map, config.descriptor.classes)
        if normals is None:
            raise InputError(f"{args.map}: queries are drawn on RSN/road_normal.txt, missing")
        points, labels, name = instances.points, instances.labels, str(args.map)
    else:
        world = make_outdoor_world(args.world, seed=args.seed, blocks=args.blocks, bridge_length=0)
        points, labels, normals = world.points, world.labels, world.road_normals
        name = f"synthetic {args.world} world ({args.blocks}x{args.blocks} blocks)"
    triplet_map = describe_map(points, labels, config, None if args.no_rsn else normals, name)
    num_vertices = len(points)
    rng = np.random.default_rng(args.seed + 1)
    queries = [
        make_query(points, labels, normals, rng, max_kept=args.max_kept)
        for _ in range(args.queries)
    ]
    drive = localize_drive(triplet_map, queries)  # each query alone, compile timed apart
    compile_s = float(drive.compile_s.sum())
    records = []
    for query, step in zip(queries, drive.steps, strict=True):
        result = step.result
        rte, rre = localization_errors(result.pose, query.T_map_scan)
        success = result.valid and rte < SUCCESS_RTE_M and rre < SUCCESS_RRE_DEG
        records.append((result.descriptor_time_ms, result.match_time_ms, success))
    desc, match, success = (np.array(column) for column in zip(*records, strict=True))
    sizes = [len(q.points) for q in queries]
    print(
        f"triplet ({'TripletLoc' if args.tripletloc else f'M2Loc, {args.scales} scale(s)'}, "
        f"k={args.k}): {name}, {num_vertices} map instances; {args.queries} queries of "
        f"{min(sizes)}-{max(sizes)} instances"
    )
    print(f"  compile {compile_s:.2f} s")
    print(
        f"  descriptors {np.median(desc):.2f} ms/query, match + clique + pose "
        f"{np.median(match):.2f} ms/query (medians); success {success.mean():.0%}"
    )
    return 0
