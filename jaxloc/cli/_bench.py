"""``jaxloc bench``: quick in-package speed checks after compilation."""

from __future__ import annotations

import argparse
from pathlib import Path

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
        dest="bench",
        required=True,
        metavar="WHAT",
        help="what to time (WHAT --help: options)",
        parser_class=Parser,
    )

    def add(name: str, description: str, **options) -> argparse.ArgumentParser:
        """A bench whose ``options`` are ``NAME=(default, help[, type])``, positive integers
        unless a type is given."""
        parser = command(kinds, name, description)
        for option, (default, text, *kind) in options.items():
            name, kind = f"--{option.replace('_', '-')}", (kind or [positive_int])[0]
            parser.add_argument(name, type=kind, default=default, help=text)
        return parser

    width, height = (480, "image width, px"), (270, "image height, px")
    add(
        "raycast",
        "rays/s of jax.jit(render_batch) on random poses in a synthetic room",
        poses=(64, "camera poses"),
        width=width,
        height=height,
        stride=(10, "pixel stride, at most 2 x min(width, height) - 1"),
        objects=(20, "furniture objects"),
        vertices=(600, "per object mesh", at_least(100)),
        repeats=(3, "timed runs, best of"),
        seed=(0, "room and pose seed", seed),
    )
    add(
        "filter",
        "s/frame of the SG2Loc particle filter in the demo's room\n\nOne round: render, "
        "score, resample per frame.",
        particles=(1000, "capacity"),
        frames=(3, "frames timed"),
        width=(160, width[1]),
        height=(90, height[1]),
        stride=(8, "pixel stride, casting at least SSIM's 7 x 7 rays"),
        seed=(1, "episode seed", seed),
    )
    triplet = add(
        "triplet",
        "ms/query and success rate of M2Loc on a synthetic world or a map folder\n\n"
        "localize_scan on scan-like queries cut from it (jaxloc.synthetic.outdoor.make_query).",
        queries=(20, "queries"),
        blocks=(2, "synthetic world: blocks per side"),
        max_kept=(24, "map instances kept per query (with spurious ones <= 31: one compilation)"),
        seed=(0, "world and query seed", seed),
    )
    triplet.add_argument("--map", type=Path, help="instance map folder (default: synthetic)")
    triplet.add_argument("--world", choices=("sparse", "dense"), default="dense", help="kind")
    add_triplet_options(triplet, scales=1)


def check_bench_raycast(args: argparse.Namespace) -> None:
    """``--stride`` must cast at least one ray per side of the ``--width x --height`` image."""
    from jaxloc.camera import stride_grid_shape

    if min(stride_grid_shape(args.stride, args.width, args.height)) < 1:
        largest = 2 * min(args.width, args.height) - 1
        raise InputError(
            f"--stride {args.stride} casts no ray on a {args.width} x {args.height} "
            f"image; use --stride {largest} or less"
        )


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
    from jaxloc.synthetic.timing import time_raycast

    sizes = ("seed", "poses", "width", "height", "stride", "objects", "vertices", "repeats")
    t = time_raycast(**{name: getattr(args, name) for name in sizes})
    print(
        f"raycast (render_batch): {t.num_objects} objects, {t.num_triangles} triangles; "
        f"{t.poses} poses x {t.rays_per_pose} rays ({args.width}x{args.height}, stride "
        f"{args.stride}) = {t.rays} rays\n  engine: {describe_engine()}\n  compile "
        f"{t.compile_s:.2f} s; best of {t.repeats}: {t.wall_s * 1e3:.1f} ms\n  "
        f"{t.rays_per_s / 1e6:.3f} M rays/s (wall), {t.rays_per_cpu_s / 1e6:.3f} M rays per "
        "CPU-second"
    )
    return 0


def run_bench_filter(args: argparse.Namespace) -> int:
    from jaxloc.synthetic.timing import time_filter

    config = demo_episode_config(args)  # the demo's room: its compilations are shared
    t = time_filter(config, args.seed, args.frames, args.particles, args.stride)
    print(
        f"filter (SG2Loc, one round): {t.particles} particles x {t.rays_per_particle} rays "
        f"({args.width}x{args.height}, stride {args.stride}), {t.num_objects} objects, "
        f"{t.num_triangles} triangles (episode built in {t.build_s:.1f} s)\n  compile "
        f"{t.compile_s:.2f} s\n  {t.s_per_frame:.4f} s/frame wall, {t.cpu_s_per_frame:.4f} "
        f"s/frame CPU (mean over {t.frames} frames)"
    )
    return 0


def run_bench_triplet(args: argparse.Namespace) -> int:
    from jaxloc.synthetic.outdoor import make_outdoor_world
    from jaxloc.synthetic.timing import time_triplet

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
    sizes = dict(queries=args.queries, max_kept=args.max_kept, seed=args.seed + 1)
    t = time_triplet(triplet_map, points, labels, normals, **sizes)
    scales = len(config.descriptor.scale_edges)
    print(
        f"triplet ({'TripletLoc' if args.tripletloc else f'M2Loc, {scales} scale(s)'}, "
        f"k={config.top_k}): {name}, {len(points)} map instances; {t.queries} queries of "
        f"{t.query_instances[0]}-{t.query_instances[1]} instances\n  compile {t.compile_s:.2f} s"
        f"\n  descriptors {t.descriptor_ms:.2f} ms/query, match + clique + pose {t.match_ms:.2f} "
        f"ms/query (medians); success {t.success_rate:.0%}"
    )
    return 0
