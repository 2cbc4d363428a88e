"""The ``jaxloc`` command line.

* ``jaxloc demo``: localize a camera in an embedded synthetic room (SG2Loc, no downloads).
* ``jaxloc localize-lidar MAP_DIR SCAN...``: one-shot LiDAR localization (M2Loc) of scans in a
  HeLiPR/TripletLoc instance map; prints ``T_map_scan`` per scan, optionally RTE/RRE.
* ``jaxloc build-lidar-map SEQ_DIR OUT_DIR``: instance and road-normal maps from a labelled LiDAR
  sequence (SemanticKITTI, plain or HeLiPR layout), in the format ``localize-lidar`` reads.
* ``jaxloc bench raycast|filter|triplet``: quick in-package speed checks after compilation.
* ``jaxloc build-scene-graph SCAN OUT.npz``: a map from a ScanNet / 3RScan / labelled scan.
* ``jaxloc localize-camera MAP.npz SEQ``: SG2Loc on a ScanNet export folder, ``.sens`` or 3RScan
  scan.
* ``jaxloc cache [--clear]``: where JAX's persistent compilation cache is, its size; clear it.

Every command but ``cache`` turns on the persistent compilation cache
(:mod:`jaxloc.compilation_cache`) unless ``jaxloc --no-cache COMMAND`` or ``JAXLOC_NO_CACHE=1``:
a program compiled once on a machine is loaded, not compiled, by later runs. Parsing and ``--help``
import neither JAX nor the pipelines (each command imports what it needs).

Input problems (missing or malformed files, bad numbers, option values out of their range) end
with exit code 2 and a one-line message on stderr, never a traceback. ``main(argv)`` returns the
exit code, so the command can be called in-process (tests do).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

from jaxloc.cli import _camera, _scene_graph
from jaxloc.cli._bench import (
    check_bench_filter,
    check_bench_raycast,
    run_bench_filter,
    run_bench_raycast,
    run_bench_triplet,
)
from jaxloc.cli._demo import check_demo, run_demo
from jaxloc.cli._errors import InputError, run_guarded
from jaxloc.cli._lidar import (
    DEFAULT_K,
    DEFAULT_MIN_CLIQUE,
    DEFAULT_SCALES,
    DEFAULT_THRESHOLD,
    check_localize_lidar,
    run_localize_lidar,
)
from jaxloc.cli._lidar import DESCRIPTION as _LIDAR_DESCRIPTION
from jaxloc.cli._lidar import EPILOG as _LIDAR_EPILOG
from jaxloc.cli._lidar_map import DESCRIPTION as _BUILD_LIDAR_MAP_DESCRIPTION
from jaxloc.cli._lidar_map import EPILOG as _BUILD_LIDAR_MAP_EPILOG
from jaxloc.cli._lidar_map import check_build_lidar_map, run_build_lidar_map
from jaxloc.cli._lidar_scans import add_drive_options, add_pose_output_options, add_sequence_options
from jaxloc.cli._options import (
    Parser,
    at_least,
    positive_float,
    positive_int,
    seed,
    stride_list,
)
from jaxloc.compilation_cache import prefer_fast_compilation, quiet_xla_log

__all__ = ["InputError", "build_parser", "check_args", "main"]


_MAIN_EPILOG = """\
examples:
  jaxloc demo                                    # camera localization in a synthetic room
  jaxloc localize-lidar maps/KAIST04 scans/000000.bin
  jaxloc localize-lidar maps/KAIST04 scans/*.bin --gt poses.txt --json > result.json
  jaxloc build-lidar-map sequences/00 maps/kitti00 --every 30
  jaxloc localize-lidar maps/kitti00 sequences/00 --every 50
  jaxloc bench raycast --poses 64
  jaxloc bench triplet --queries 20
  jaxloc build-scene-graph scans/scene0000_00 scene0000_00.npz --format scannet
  jaxloc localize-camera scene0000_00.npz scans/scene0000_00/export --plot run.png
  jaxloc cache --clear                           # empty the compilation cache

Run `jaxloc COMMAND --help` for the options of a command. Compiled programs are cached in
$JAXLOC_CACHE_DIR (default: the user's cache folder, see `jaxloc cache`); `jaxloc --no-cache
COMMAND` or JAXLOC_NO_CACHE=1 turns that off.
"""

_BENCH_EPILOG = """\
examples:
  jaxloc bench raycast                           # rays/s of render_batch
  jaxloc bench raycast --poses 256 --width 320 --height 180
  jaxloc bench filter --particles 2500           # s/frame of one SG2Loc filter step
  jaxloc bench triplet --queries 50 --scales 3   # ms/query of M2Loc
  jaxloc bench triplet --map ../shared/data/helipr_instance_maps/KAIST04

Times are after compilation (compile time is printed separately); wall and process CPU time
are both given where the machine may be shared. The full comparisons with peers (Embree,
networkx) are the scripts in benchmarks/ of the repository.
"""


def _add_triplet_options(
    parser: argparse.ArgumentParser, scales: int | None, k: int | None
) -> None:
    """Localization options; a None default means "the default, unless a saved map says else"."""
    group = parser.add_argument_group("localization settings")
    group.add_argument(
        "--scales",
        type=int,
        choices=(1, 2, 3),
        default=scales,
        help="M2Loc descriptor scales: [0,20], (20,30], (30,40] m "
        f"(default {scales or DEFAULT_SCALES})",
    )
    group.add_argument(
        "--tripletloc",
        action="store_true",
        help="use TripletLoc's one-scale descriptor (edge lengths) instead of M2Loc's",
    )
    group.add_argument(
        "-k",
        type=positive_int,
        default=k,
        help=f"map matches per scan instance and scale, >= 1 (default {k or DEFAULT_K})",
    )
    group.add_argument(
        "--threshold",
        type=positive_float,
        help=f"consistency threshold of the match graph, metres, > 0 (default {DEFAULT_THRESHOLD})",
    )
    group.add_argument(
        "--min-clique",
        type=positive_int,
        help="add scales while the clique is smaller than this, >= 1 (M2Loc's T, default "
        f"{DEFAULT_MIN_CLIQUE})",
    )
    group.add_argument("--no-rsn", action="store_true", help="ignore the road-normal prior")
    group.add_argument(
        "--no-robust",
        action="store_true",
        help="M2Loc as published: cliques may join associations of one vertex, no clique "
        "hypotheses (default: one-to-one cliques, 256 verified hypotheses when the pose verifies "
        "poorly)",
    )


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``jaxloc`` command (demo, localize-lidar, build-lidar-map,
    bench)."""
    parser = Parser(
        prog="jaxloc",
        description="Differentiable global localization against compact maps.",
        epilog=_MAIN_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--no-cache",
        action="store_true",
        help="do not use JAX's persistent compilation cache (also: JAXLOC_NO_CACHE=1)",
    )
    commands = parser.add_subparsers(
        dest="command",
        required=True,
        metavar="COMMAND",
        help="what to run (COMMAND --help)",
        parser_class=Parser,
    )
    demo = commands.add_parser(
        "demo",
        help="localize a camera in an embedded synthetic room (no downloads)",
        description="Builds a synthetic room and a query sequence, renders a few views, runs the "
        "coarse-to-fine SG2Loc particle filter with a progress bar, prints per-frame errors and "
        "writes a figure of the particles per round and frame.",
        epilog="examples:\n  jaxloc demo\n  jaxloc demo --seed 3 --frames 10 --out demo.png\n"
        "  jaxloc demo --width 160 --height 120   # strides lowered to fit: 18,8,4",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument("--seed", type=seed, default=1, help="room and sequence seed (default 1)")
    demo.add_argument(
        "--frames", type=positive_int, default=6, help="frames in the sequence (default 6)"
    )
    demo.add_argument(
        "--particles",
        type=positive_int,
        default=2500,
        help="particle capacity (default 2500, the paper's)",
    )
    demo.add_argument(
        "--width", type=positive_int, default=960, help="image width, pixels, >= 16 (default 960)"
    )
    demo.add_argument(
        "--height", type=positive_int, default=540, help="image height, pixels, >= 9 (default 540)"
    )
    demo.add_argument(
        "--strides",
        type=stride_list,
        help="pixel stride of each coarse-to-fine round, each casting at least 7 x 7 rays "
        "(default the paper's 20,8,4, each lowered to fit a small image)",
    )
    demo.add_argument("--out", type=Path, default=Path("jaxloc_demo.png"), help="figure path (PNG)")

    lidar = commands.add_parser(
        "localize-lidar",
        help="localize LiDAR scans in an instance map (M2Loc): pose and metrics per scan",
        description=_LIDAR_DESCRIPTION,
        epilog=_LIDAR_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    lidar.add_argument("map", type=Path, metavar="MAP", help="instance map folder or saved .npz")
    lidar.add_argument("scans", type=Path, nargs="+", metavar="SCAN", help="scan file(s)")
    lidar.add_argument("--gt", type=Path, help="ground-truth poses: KITTI, 4x4 or TUM (see below)")
    lidar.add_argument(
        "--every",
        type=positive_int,
        default=1,
        help="of a sequence folder, every N-th scan (default 1)",
    )
    add_drive_options(lidar)
    lidar.add_argument("--save-map", type=Path, metavar="FILE", help="save the described map")
    lidar.add_argument("--json", action="store_true", help="print one JSON document instead")
    lidar.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_sequence_options(lidar)
    add_pose_output_options(lidar)
    _add_triplet_options(lidar, scales=None, k=None)

    build = commands.add_parser(
        "build-lidar-map",
        help="instance + road-normal maps from a labelled LiDAR sequence (SemanticKITTI, HeLiPR)",
        description=_BUILD_LIDAR_MAP_DESCRIPTION,
        epilog=_BUILD_LIDAR_MAP_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    build.add_argument("seq_dir", type=Path, metavar="SEQ_DIR", help="labelled sequence folder")
    build.add_argument("out_dir", type=Path, metavar="OUT_DIR", help="map folder to write")
    build.add_argument(
        "--every",
        type=positive_int,
        default=30,
        help="use every K-th scan (default 30, as TripletLoc)",
    )
    build.add_argument("--save-map", type=Path, metavar="FILE", help="also save it described")
    build.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_sequence_options(build)
    _add_triplet_options(build, scales=None, k=None)

    bench = commands.add_parser(
        "bench",
        help="quick speed checks: raycast (rays/s), filter (s/frame), triplet (ms/query)",
        description="Quick in-package benchmarks on synthetic data (no Embree, no downloads).",
        epilog=_BENCH_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    kinds = bench.add_subparsers(
        dest="bench",
        required=True,
        metavar="WHAT",
        help="what to time (WHAT --help: options)",
        parser_class=Parser,
    )
    raycast = kinds.add_parser(
        "raycast",
        help="rays/s of render_batch in a synthetic room",
        description="Times jax.jit(render_batch) on random poses in a synthetic room.",
    )
    raycast.add_argument("--poses", type=positive_int, default=64, help="camera poses (default 64)")
    raycast.add_argument(
        "--width", type=positive_int, default=480, help="image width (default 480)"
    )
    raycast.add_argument(
        "--height", type=positive_int, default=270, help="image height (default 270)"
    )
    raycast.add_argument(
        "--stride",
        type=positive_int,
        default=10,
        help="pixel stride, at most 2 x min(width, height) - 1 (default 10)",
    )
    raycast.add_argument(
        "--objects", type=positive_int, default=20, help="furniture objects (default 20)"
    )
    raycast.add_argument(
        "--vertices",
        type=at_least(100),
        default=600,
        help="vertices per object mesh, >= 100 (default 600)",
    )
    raycast.add_argument(
        "--repeats", type=positive_int, default=3, help="timed runs, best of (default 3)"
    )
    raycast.add_argument("--seed", type=seed, default=0, help="room and pose seed (default 0)")

    filter_ = kinds.add_parser(
        "filter",
        help="s/frame of the SG2Loc particle filter",
        description="Times SG2Loc (one round: render, score, resample per frame) on the demo's "
        "synthetic room, after compilation.",
    )
    filter_.add_argument(
        "--particles", type=positive_int, default=1000, help="capacity (default 1000)"
    )
    filter_.add_argument("--frames", type=positive_int, default=3, help="frames timed (default 3)")
    filter_.add_argument(
        "--width", type=positive_int, default=160, help="image width, >= 16 (default 160)"
    )
    filter_.add_argument(
        "--height", type=positive_int, default=90, help="image height, >= 9 (default 90)"
    )
    filter_.add_argument(
        "--stride",
        type=positive_int,
        default=8,
        help="pixel stride, casting at least 7 x 7 rays (default 8)",
    )
    filter_.add_argument("--seed", type=seed, default=1, help="episode seed (default 1)")

    triplet = kinds.add_parser(
        "triplet",
        help="ms/query of M2Loc on a synthetic world or a map folder",
        description="Times localize_scan on seeded scan-like queries cut from the map "
        "(jaxloc.synthetic.outdoor.make_query), and reports the success rate.",
    )
    triplet.add_argument("--queries", type=positive_int, default=20, help="queries (default 20)")
    triplet.add_argument(
        "--max-kept",
        type=positive_int,
        default=24,
        help="map instances kept per query (default 24: with the spurious ones at most 31, "
        "so all queries share one compilation)",
    )
    triplet.add_argument("--map", type=Path, help="instance map folder (default: synthetic world)")
    triplet.add_argument(
        "--world", choices=("sparse", "dense"), default="dense", help="synthetic world kind"
    )
    triplet.add_argument(
        "--blocks", type=positive_int, default=2, help="synthetic world: blocks per side"
    )
    triplet.add_argument("--seed", type=seed, default=0, help="world and query seed (default 0)")
    _add_triplet_options(triplet, scales=1, k=25)
    _scene_graph.add_parser(commands)
    _camera.add_parser(commands)
    cache = commands.add_parser(
        "cache",
        help="where the compilation cache is and how big; --clear empties it",
        description="JAX's persistent compilation cache of jaxloc: every command stores the "
        "programs it compiles there and loads them on later runs. The folder is "
        "$JAXLOC_CACHE_DIR, else jaxloc/xla in the user's cache folder; it is bounded to 2 GiB "
        "(least recently used entries go first) and can be cleared at any time.",
    )
    cache.add_argument("--clear", action="store_true", help="delete every cached program")
    return parser


def run_cache(args: argparse.Namespace) -> int:
    """``jaxloc cache``: print the folder and its size; ``--clear`` empties it."""
    from jaxloc.compilation_cache import cache_size, clear_compilation_cache, default_cache_dir

    folder = default_cache_dir()
    if args.clear:
        print(f"removed {clear_compilation_cache(folder)} files from {folder}")
        return 0
    files, size = cache_size(folder)
    print(f"{folder}: {files} files, {size / 1e6:.1f} MB")
    return 0


def _enable_cache(args: argparse.Namespace) -> None:
    """Turn the persistent compilation cache on for a command (a folder that cannot be created
    is a note, not an error: the command then compiles as without a cache)."""
    if args.no_cache or args.command == "cache":
        return
    from jaxloc.compilation_cache import enable_compilation_cache

    try:
        enable_compilation_cache()
    except OSError as error:
        print(f"jaxloc: note: no compilation cache ({error})", file=sys.stderr)


#: The checks of options that depend on each other (or on the file system) per command, run
#: after parsing and before the command does any work: an InputError, one line, exit status 2.
#: A single option's range is checked where it is parsed (:mod:`jaxloc.cli._options`).
_CHECKS: dict[str, Callable[[argparse.Namespace], None]] = {
    "demo": check_demo,
    "localize-lidar": check_localize_lidar,
    "build-lidar-map": check_build_lidar_map,
    "bench raycast": check_bench_raycast,
    "bench filter": check_bench_filter,
}

_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "demo": run_demo,
    "localize-lidar": run_localize_lidar,
    "build-lidar-map": run_build_lidar_map,
    "bench raycast": run_bench_raycast,
    "bench filter": run_bench_filter,
    "bench triplet": run_bench_triplet,
    "build-scene-graph": _scene_graph.run_build_scene_graph,
    "localize-camera": _camera.run_localize_camera,
    "cache": run_cache,
}


#: The commands compiled with XLA:CPU's legacy fusion emitters (:func:`prefer_fast_compilation`):
#: the SG2Loc ones, whose filter rounds compile 20 % faster with them and run as fast. The M2Loc
#: query with its default three scales runs ~20 % slower with them, so the LiDAR commands keep
#: XLA's defaults; only their query program of small graphs (one scale) uses them, per program
#: (``jaxloc.m2loc._localization.LEGACY_EMITTERS_MAX_ASSOCIATIONS``).
FAST_COMPILATION_COMMANDS = frozenset({"localize-camera", "demo"})


def _command_name(args: argparse.Namespace) -> str:
    return args.command if args.command != "bench" else f"bench {args.bench}"


def check_args(args: argparse.Namespace) -> None:
    """The checks of parsed ``args`` that span several options (the demo's strides against its
    image size, ``--accumulate-max`` against ``--accumulate``, ...): an InputError naming the
    option if they do not fit. Cheap: reads no input file, compiles nothing."""
    check = _CHECKS.get(_command_name(args))
    if check is not None:
        check(args)


def main(argv: list[str] | None = None) -> int:
    """Run the ``jaxloc`` command with ``argv`` (default ``sys.argv[1:]``); returns the exit code.

    Usage errors (an unknown command or option, an option value out of its range), options that
    do not fit each other (:func:`check_args`) and bad input files return 2 after one line on
    stderr; ``--help`` prints the help and exits through argparse (``SystemExit(0)``).
    """
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exit_info:
        if not exit_info.code:  # --help
            raise
        return exit_info.code  # Parser.error: its one line is on stderr
    name = _command_name(args)

    def checked_run() -> int:
        # before any check imports JAX (the demo's strides need SSIM's window, in a module that
        # imports JAX): once JAX is in, its C++ log level and XLA's flags are fixed
        if name in FAST_COMPILATION_COMMANDS:
            prefer_fast_compilation()
        if not args.no_cache and args.command != "cache":
            quiet_xla_log()
        check_args(args)
        _enable_cache(args)
        return _COMMANDS[name](args)

    return run_guarded(name, checked_run)


if __name__ == "__main__":
    sys.exit(main())
