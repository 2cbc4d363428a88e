"""``jaxloc bench``: quick in-package speed checks after compilation."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxloc.cli._demo import demo_episode_config
from jaxloc.cli._errors import InputError, reading
from jaxloc.cli._lidar import add_triplet_options, describe_map, triplet_config
from jaxloc.cli._options import Parser, at_least, command, positive_int, seed

_EPILOG = """\
examples:
  jaxloc bench raycast --poses 256 --width 320 --height 180   # rays/s of render_batch
  jaxloc bench filter --particles 2500           # s/frame of one SG2Loc filter step
  jaxloc bench triplet --queries 50 --scales 3   # ms/query of M2Loc
  jaxloc bench triplet --map maps/KAIST04

Times are after compilation (printed apart), wall and process CPU time. The comparisons with
peers (Embree, networkx) are the scripts in benchmarks/ of the repository.
"""


def add_parser(commands) -> None:
    """Register ``bench raycast|filter|triplet`` on the ``jaxloc`` subcommand parsers."""
    about = "Quick speed checks: raycast (rays/s), filter (s/frame), triplet (ms/query)\n"
    bench = command(commands, "bench", about + "\nOn synthetic data (no downloads).", _EPILOG)
    kinds = bench.add_subparsers(
        dest="bench", required=True, metavar="WHAT", help="what to time (WHAT --help: options)",
        parser_class=Parser,
    )  # fmt: skip

    def add(name: str, description: str, **options) -> argparse.ArgumentParser:
        """A bench whose ``options`` are ``NAME=(default, help[, type])``, positive integers
        unless a type is given."""
        parser = command(kinds, name, description)
        for option, (default, text, *kind) in options.items():
            name, kind = f"--{option.replace('_', '-')}", (kind or [positive_int])[0]
            parser.add_argument(name, type=kind, default=default, help=text)
        return parser

    width, height = (480, "image width, px"), (270, "image height, px")
    add("raycast", "rays/s of jax.jit(render_batch) on random poses in a synthetic room",
        poses=(64, "camera poses"), width=width, height=height,
        stride=(10, "pixel stride, at most 2 x min(width, height) - 1"),
        objects=(20, "furniture objects"), vertices=(600, "per object mesh", at_least(100)),
        repeats=(3, "timed runs, best of"), seed=(0, "room and pose seed", seed),
    )  # fmt: skip
    add("filter", "s/frame of the SG2Loc particle filter in the demo's room\n\nOne round: render, "
        "score, resample per frame.",
        particles=(1000, "capacity"), frames=(3, "frames timed"), width=(160, width[1]),
        height=(90, height[1]), stride=(8, "pixel stride, casting at least SSIM's 7 x 7 rays"),
        seed=(1, "episode seed", seed),
    )  # fmt: skip
    triplet = add(
        "triplet", "ms/query and success rate of M2Loc on a synthetic world or a map folder\n\n"
        "localize_scan on scan-like queries cut from it (jaxloc.synthetic.outdoor.make_query).",
        queries=(20, "queries"), blocks=(2, "synthetic world: blocks per side"),
        max_kept=(24, "map instances kept per query (with spurious ones <= 31: one compilation)"),
        seed=(0, "world and query seed", seed),
    )  # fmt: skip
    triplet.add_argument("--map", type=Path, help="instance map folder (default: synthetic)")
    triplet.add_argument("--world", choices=("sparse", "dense"), default="dense", help="kind")
    add_triplet_options(triplet, scales=1)


def _timed(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Best-of-``repeats`` wall seconds and the process CPU seconds of that run."""
    best = (np.inf, np.inf)
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        best = min(best, (time.perf_counter() - wall, time.process_time() - cpu))
    return best


def check_bench_raycast(args: argparse.Namespace) -> None:
    """``--stride`` must cast at least one ray per side of the ``--width x --height`` image."""
    from jaxloc.camera import stride_grid_shape

    if min(stride_grid_shape(args.stride, args.width, args.height)) < 1:
        largest = 2 * min(args.width, args.height) - 1
        raise InputError(f"--stride {args.stride} casts no ray on a {args.width} x {args.height} "
                         f"image; use --stride {largest} or less")  # fmt: skip


def check_bench_filter(args: argparse.Namespace) -> None:
    """The image must hold the demo's patch grid, and ``--stride`` cast at least SSIM's 7 x 7
    rays on it (:func:`jaxloc.sg2loc.check_ssim_strides`)."""
    from jaxloc.sg2loc import check_ssim_strides

    demo_episode_config(args)
    with reading():
        check_ssim_strides((args.stride,), args.width, args.height, "--stride")


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

    objects, vertices = (args.objects,) * 2, (args.vertices,) * 2
    room = make_room(args.seed, RoomConfig(num_objects=objects, vertex_range=vertices))
    scene = scene_graph(room)
    camera = Camera.from_fov(args.width, args.height, 60.0)
    grid = stride_grid(camera, args.stride)
    rng = np.random.default_rng(args.seed)
    (lx, ly, _), n = room.size, args.poses
    ranges = ((0.3, lx - 0.3), (0.3, ly - 0.3), (1.2, 1.8), (-np.pi, np.pi))  # x, y, z, yaw
    poses = np.column_stack([rng.uniform(lo, hi, n) for lo, hi in ranges]).astype(np.float32)
    start = time.perf_counter()
    compiled = jax.jit(render_batch).lower(scene, poses, camera, grid).compile()
    compile_s = time.perf_counter() - start
    wall, cpu = _timed(lambda: jax.block_until_ready(compiled(scene, poses, camera, grid)),
                       args.repeats)  # fmt: skip
    rays, per_cpu_s = n * grid.uv.shape[0], n * grid.uv.shape[0] / max(cpu, 1e-9) / 1e6
    print(f"raycast (render_batch): {scene.num_objects} objects, {scene.num_triangles} triangles; "
          f"{n} poses x {grid.uv.shape[0]} rays ({args.width}x{args.height}, stride "
          f"{args.stride}) = {rays} rays\n  engine: {describe_engine()}\n  compile "
          f"{compile_s:.2f} s; best of {args.repeats}: {wall * 1e3:.1f} ms\n  "
          f"{rays / wall / 1e6:.3f} M rays/s (wall), {per_cpu_s:.3f} M rays per "
          "CPU-second")  # fmt: skip
    return 0


def run_bench_filter(args: argparse.Namespace) -> int:
    import jax

    from jaxloc.camera import stride_grid
    from jaxloc.sg2loc import KLDConfig, SG2LocConfig, kld_for_capacity, localize
    from jaxloc.synthetic import indoor

    start = time.perf_counter()
    episode = indoor.make_episode(args.seed, args.frames, demo_episode_config(args))
    build_s = time.perf_counter() - start
    scene, sequence = episode.scene, episode.sequence
    kld = kld_for_capacity(args.particles, KLDConfig(min_particles=300))
    config = SG2LocConfig(capacity=args.particles, strides=(args.stride,), kld=kld)

    def run(seed: int) -> None:  # the demo's path: one scan per round, a progress bar
        result = localize(jax.random.key(seed), scene, sequence, config, progress=True)
        jax.block_until_ready(result.poses)

    start = time.perf_counter()
    run(args.seed)
    first_s = time.perf_counter() - start
    wall, cpu = _timed(lambda: run(args.seed + 1), 1)
    rays = stride_grid(sequence.camera, args.stride).uv.shape[0]
    print(f"filter (SG2Loc, one round): {args.particles} particles x {rays} rays "
          f"({args.width}x{args.height}, stride {args.stride}), {scene.num_objects} objects, "
          f"{scene.num_triangles} triangles (episode built in {build_s:.1f} s)\n  compile "
          f"{max(first_s - wall, 0.0):.2f} s\n  {wall / args.frames:.4f} s/frame wall, "
          f"{cpu / args.frames:.4f} s/frame CPU (mean over {args.frames} frames)")  # fmt: skip
    return 0


def run_bench_triplet(args: argparse.Namespace) -> int:
    from jaxloc.m2loc import localize_drive
    from jaxloc.m2loc._evaluation import localization_success
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
    rng = np.random.default_rng(args.seed + 1)
    queries = [make_query(points, labels, normals, rng, max_kept=args.max_kept)
               for _ in range(args.queries)]  # fmt: skip
    drive = localize_drive(triplet_map, queries)  # each query alone, compile timed apart
    truth = np.stack([q.T_map_scan for q in queries])
    success = localization_success(drive.poses, truth, drive.valid)
    times = np.array([(s.result.descriptor_time_ms, s.result.match_time_ms) for s in drive.steps])
    desc, match = np.median(times, axis=0)
    sizes = [len(q.points) for q in queries]
    scales = len(config.descriptor.scale_edges)
    print(f"triplet ({'TripletLoc' if args.tripletloc else f'M2Loc, {scales} scale(s)'}, "
          f"k={config.top_k}): {name}, {len(points)} map instances; {args.queries} queries of "
          f"{min(sizes)}-{max(sizes)} instances\n  compile {float(drive.compile_s.sum()):.2f} s"
          f"\n  descriptors {desc:.2f} ms/query, match + clique + pose {match:.2f} ms/query "
          f"(medians); success {success.mean():.0%}")  # fmt: skip
    return 0
