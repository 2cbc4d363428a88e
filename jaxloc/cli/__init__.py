"""The ``jaxloc`` command line: ``demo``, ``localize-lidar``, ``build-lidar-map``, ``bench
raycast|filter|triplet``, ``build-scene-graph``, ``localize-camera`` and ``cache``.

Every command has the same shape: parse the options, open the inputs with :mod:`jaxloc.io`, run
the method, write the outputs, print. Every rule (defaults, ranges that depend on each other,
errors, metrics) is the library's, so notebooks and the command line give the same checks.

Every command but ``cache`` turns on the persistent compilation cache
(:mod:`jaxloc.compilation_cache`) unless ``jaxloc --no-cache COMMAND`` or ``JAXLOC_NO_CACHE=1``.
Parsing and ``--help`` import neither JAX nor the pipelines. Input problems (missing or malformed
files, bad numbers, option values out of range) end with exit code 2 and a one-line message on
stderr, never a traceback. ``main(argv)`` returns the exit code (tests call it in-process).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from jaxloc.cli import _bench, _camera, _demo, _lidar, _lidar_map, _scene_graph
from jaxloc.cli._errors import InputError, run_guarded
from jaxloc.cli._options import Formatter, Parser, command
from jaxloc.compilation_cache import prefer_fast_compilation, quiet_xla_log

__all__ = ["InputError", "build_parser", "check_args", "main"]


_MAIN_EPILOG = """\
examples:
  jaxloc demo                                    # camera localization in a synthetic room
  jaxloc localize-lidar maps/KAIST04 scans/000000.bin
  jaxloc localize-lidar maps/KAIST04 scans/*.bin --gt poses.txt --json > result.json
  jaxloc build-lidar-map sequences/00 maps/kitti00 --every 30
  jaxloc bench triplet --queries 20
  jaxloc build-scene-graph scans/scene0000_00 scene0000_00.npz --format scannet
  jaxloc localize-camera scene0000_00.npz scans/scene0000_00/export --plot run.png
  jaxloc cache --clear                           # empty the compilation cache

Run `jaxloc COMMAND --help` for its options. List options take values separated by spaces or
commas (--strides 20 8 4 or --strides 20,8,4). Exit status: 0 on success, 2 on missing or
malformed files or bad options (one line on stderr; nothing written). Compiled programs are cached
(see `jaxloc cache`; `jaxloc --no-cache COMMAND` or JAXLOC_NO_CACHE=1 turns that off).
"""


_CACHE_DESCRIPTION = """\
Where the compilation cache is and how big; --clear empties it.

The programs commands compile are kept in $JAXLOC_CACHE_DIR, else jaxloc/xla in the user's cache
folder, up to 2 GiB (least recently used entries go first); clearing it costs compilations only.
"""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``jaxloc`` command and its subcommands."""
    parser = Parser(
        prog="jaxloc",
        description="Differentiable global localization against compact maps.",
        epilog=_MAIN_EPILOG,
        formatter_class=Formatter,
    )
    no_cache = "do not use JAX's persistent compilation cache (also: JAXLOC_NO_CACHE=1)"
    parser.add_argument("--no-cache", action="store_true", help=no_cache)
    commands = parser.add_subparsers(
        dest="command", required=True, metavar="COMMAND", help="COMMAND --help", parser_class=Parser
    )
    for module in (_demo, _lidar, _lidar_map, _bench, _scene_graph, _camera):
        module.add_parser(commands)
    cache = command(commands, "cache", _CACHE_DESCRIPTION)
    cache.add_argument("--clear", action="store_true", help="delete every cached program")
    return parser


def run_cache(args: argparse.Namespace) -> int:
    """``jaxloc cache``: print the folder and its size; ``--clear`` empties it."""
    from jaxloc.compilation_cache import cache_size, clear_compilation_cache, default_cache_dir

    folder = default_cache_dir()
    if args.clear:
        print(f"removed {clear_compilation_cache(folder)} files from {folder}")
    else:
        files, size = cache_size(folder)
        print(f"{folder}: {files} files, {size / 1e6:.1f} MB")
    return 0


def _enable_cache() -> None:
    """Turn the persistent compilation cache on (a folder that cannot be created is a note: the
    command then compiles as without a cache)."""
    from jaxloc.compilation_cache import enable_compilation_cache

    try:
        enable_compilation_cache()
    except OSError as error:
        print(f"jaxloc: note: no compilation cache ({error})", file=sys.stderr)


#: The checks of options that depend on each other (or on the file system) per command, run
#: after parsing and before the command does any work: an InputError, one line, exit status 2.
#: A single option's range is checked where it is parsed (:mod:`jaxloc.cli._options`).
_CHECKS: dict[str, Callable[[argparse.Namespace], object]] = {
    "demo": _demo.fitting_strides,
    "localize-lidar": _lidar.check_localize_lidar,
    "build-lidar-map": _lidar_map.check_build_lidar_map,
    "bench raycast": _bench.check_bench_raycast,
    "bench filter": _bench.check_bench_filter,
}

_COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "demo": _demo.run_demo,
    "localize-lidar": _lidar.run_localize_lidar,
    "build-lidar-map": _lidar_map.run_build_lidar_map,
    "bench raycast": _bench.run_bench_raycast,
    "bench filter": _bench.run_bench_filter,
    "bench triplet": _bench.run_bench_triplet,
    "build-scene-graph": _scene_graph.run_build_scene_graph,
    "localize-camera": _camera.run_localize_camera,
    "cache": run_cache,
}


#: The commands compiled with XLA:CPU's legacy fusion emitters (:func:`prefer_fast_compilation`):
#: the SG2Loc ones, whose rounds compile 20 % faster with them and run as fast (the M2Loc query's
#: three scales run ~20 % slower with them; ``_localization.LEGACY_EMITTERS_MAX_ASSOCIATIONS``).
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
    if getattr(args, "rerun", None) is not None:  # rerun-sdk is there before any compiling
        from jaxloc.io.rerun_log import require_rerun

        try:
            require_rerun()
        except ModuleNotFoundError as error:
            raise InputError(f"--rerun {args.rerun}: {error}") from None


def main(argv: list[str] | None = None) -> int:
    """Run the ``jaxloc`` command with ``argv`` (default ``sys.argv[1:]``); returns the exit code:
    2 after one line on stderr for usage errors, options that do not fit each other
    (:func:`check_args`) and bad input files. ``--help`` exits through argparse (``SystemExit``).
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
        caching = not args.no_cache and args.command != "cache"
        if name in FAST_COMPILATION_COMMANDS:
            prefer_fast_compilation()
        if caching:
            quiet_xla_log()
        check_args(args)
        if caching:
            _enable_cache()
        return _COMMANDS[name](args)

    return run_guarded(name, checked_run)
