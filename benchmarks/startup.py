"""What a user waits for at the command line: fresh processes, first and second runs.

Times (wall, median of ``--repeats`` fresh processes; the first/second pairs once each, in order,
against an empty compilation cache of their own) beside ``python -c "import jax"`` in the same run:

* ``python -c "import jax"`` and ``python -c "import jaxloc"``;
* ``jaxloc --help`` and ``jaxloc localize-lidar --help``;
* ``jaxloc localize-lidar MAP SCAN``: one scan, first run (empty cache) and second run; MAP is a
  real HeLiPR map of ``../shared/data`` with the real SemanticKITTI scan when present (KAIST04,
  one scale), else the synthetic sparse world and one of its queries as a centroid file;
* ``jaxloc build-lidar-map SEQ OUT``: a synthetic 16-scan SemanticKITTI sequence (labelled
  scans and poses) into an instance map, first and second run;
* ``jaxloc localize-camera MAP.npz SEQ``: a 6-frame synthetic ScanNet export folder at 160x120,
  300 particles, with the command line's default progress bar (ticked from inside the rounds'
  program), first and second run;
* ``jaxloc demo`` (the paper's scale unless ``--demo-args`` says else): first and second run.

Each pair runs with ``JAXLOC_CACHE_DIR`` set to a fresh folder; ``--no-cache`` times the
second runs with the cache off instead (what a run costs without it). The pairs run through
``benchmarks/startup_probe.py``, which says where each run's time went (imports, tracing,
lowering, XLA compilation, cache loads, the rest: reading, computing, writing). Results as
Markdown tables on stdout (``--out FILE`` writes them too, with the machine's load before and
after).

    python benchmarks/startup.py                     # everything (a few minutes; the demo ~2 min)
    python benchmarks/startup.py --skip-demo --repeats 5
    python benchmarks/startup.py --baseline /tmp/jaxloc-base --repeats 5

``--baseline DIR`` (repeatable) times only the SG2Loc commands' first runs (``localize-camera``,
and the demo unless ``--skip-demo``), each against an empty cache, for this checkout and every
older checkout DIR in turn, ``--repeats`` rounds, so that a slow spell of the machine hits them
alike: the median and every run per checkout.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
JAXLOC = [sys.executable, "-m", "jaxloc.cli"]
PROBE = str(Path(__file__).resolve().parent / "startup_probe.py")
#: The columns of the breakdown table (startup_probe.py's keys).
PARTS = ("import", "trace", "lower", "compile", "cache_load", "rest")


def timed(argv: list[str], env: dict | None = None) -> float:
    """Wall seconds of one fresh process (output discarded; a failure stops the benchmark)."""
    start = time.perf_counter()
    done = subprocess.run(argv, env=env, capture_output=True, text=True, cwd=ROOT)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed:\n{done.stderr[-2000:]}")
    return seconds


def median_of(argv: list[str], repeats: int, env=None) -> float:
    return statistics.median(timed(argv, env) for _ in range(repeats))


def lidar_inputs(work: Path) -> list[str]:
    """MAP SCAN of the localize-lidar runs (real data when present)."""
    scan = SHARED / "semantickitti_scan" / "000000.bin"
    if scan.is_file() and (SHARED / "helipr_instance_maps" / "KAIST04").is_dir():
        return [str(SHARED / "helipr_instance_maps" / "KAIST04"), str(scan), "--scales", "1"]
    import numpy as np

    from jaxloc.io import write_instance_maps
    from jaxloc.m2loc import Instances
    from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

    world = make_outdoor_world("sparse", 1)
    sizes = np.ones(len(world.points))
    write_instance_maps(
        work / "map", Instances(world.points, world.labels, sizes), world.road_normals
    )
    rng = np.random.default_rng(0)
    query = make_query(world.points, world.labels, world.road_normals, rng, max_kept=25)
    rows = [f"{c} {x} {y} {z}" for c, (x, y, z) in zip(query.labels, query.points, strict=True)]
    (work / "scan.txt").write_text("\n".join(rows) + "\n")
    return [str(work / "map"), str(work / "scan.txt")]


def lidar_sequence_inputs(work: Path) -> list[str]:
    """SEQ OUT of the build-lidar-map runs: a synthetic labelled SemanticKITTI sequence."""
    from jaxloc.synthetic.lidar_scans import make_lidar_sequence, write_semantickitti_sequence
    from jaxloc.synthetic.outdoor import make_outdoor_world

    world = make_outdoor_world("dense", seed=2, blocks=1, bridge_length=0)
    scans = make_lidar_sequence(world, (10.0, 0.0), (190.0, 0.0), 16, seed=3, max_range=30.0)
    write_semantickitti_sequence(work / "kitti_seq", scans)
    return [str(work / "kitti_seq"), str(work / "built_map")]


def camera_inputs(work: Path) -> list[str]:
    """MAP.npz SEQ of the localize-camera runs: a small synthetic episode as an export folder."""
    from jaxloc.io import save_scene
    from jaxloc.synthetic import indoor

    config = indoor.EpisodeConfig(sensor=indoor.SensorConfig(width=160, height=120))
    episode = indoor.make_episode(1, 6, config)
    save_scene(episode.scene, work / "room.npz")
    indoor.write_scannet_export(episode, work / "seq")
    return [str(work / "room.npz"), str(work / "seq"), "--width", "160", "--particles", "300",
            "--strides", "10", "5"]  # fmt: skip


def pair(name: str, command: list[str], work: Path, cache: bool) -> tuple[float, float, list]:
    """(first, second, breakdowns) of ``jaxloc COMMAND`` against a fresh compilation cache (or
    none): wall seconds from outside, and each run's startup_probe.py report."""
    env = dict(os.environ)
    folder = work / f"cache_{name}"
    shutil.rmtree(folder, ignore_errors=True)
    env["JAXLOC_CACHE_DIR"] = str(folder)
    if not cache:
        env["JAXLOC_NO_CACHE"] = "1"
    walls, reports = [], []
    for run in ("first", "second"):
        report = work / f"{name}_{run}.json"
        walls.append(timed([sys.executable, PROBE, str(report), "--", *command], env))
        reports.append(json.loads(report.read_text()))
    return walls[0], walls[1], reports


def first_runs_beside(baselines: list[Path], repeats: int, skip_demo: bool) -> str:
    """The table of ``--baseline``: first runs (empty cache) per command and checkout."""
    trees = [ROOT, *(b.resolve() for b in baselines)]
    before = loadavg()
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        commands = {"localize-camera MAP.npz SEQ": ["localize-camera", *camera_inputs(work)]}
        if not skip_demo:
            commands["demo"] = ["demo", "--out", str(work / "demo.png")]
        runs = {(name, tree): [] for name in commands for tree in trees}
        for _ in range(repeats):
            for name, command in commands.items():
                for tree in trees:
                    env = dict(os.environ, JAXLOC_CACHE_DIR=str(work / "cache"))
                    shutil.rmtree(work / "cache", ignore_errors=True)
                    start = time.perf_counter()
                    done = subprocess.run(
                        [*JAXLOC, *command], env=env, capture_output=True, text=True, cwd=tree
                    )
                    if done.returncode != 0:
                        raise SystemExit(f"{tree}: {name} failed:\n{done.stderr[-2000:]}")
                    runs[name, tree].append(time.perf_counter() - start)
    lines = [
        f"First runs (empty cache), wall seconds, {repeats} rounds. Load average before: "
        f"{before}, after: {loadavg()}.",
        "",
        "| command | checkout | median (s) | runs (s) |",
        "|---|---|---|---|",
    ]
    for (name, tree), seconds in runs.items():
        label = "this one" if tree == ROOT else str(tree)
        values = " ".join(f"{v:.2f}" for v in seconds)
        lines.append(f"| `{name}` | {label} | {statistics.median(seconds):.2f} | {values} |")
    return "\n".join(lines)


def loadavg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--skip-demo", action="store_true")
    parser.add_argument("--demo-args", nargs="*", default=[])
    parser.add_argument("--no-cache", action="store_true", help="second runs without the cache")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--baseline", type=Path, action="append", default=[])
    args = parser.parse_args()
    if args.baseline:
        text = first_runs_beside(args.baseline, args.repeats, args.skip_demo)
        print(text)
        if args.out is not None:
            args.out.write_text(text + "\n")
        return
    before = loadavg()
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        jax_s = median_of([sys.executable, "-c", "import jax"], args.repeats)
        rows.append(("python -c 'import jax'", jax_s, None))
        rows.append(
            (
                "python -c 'import jaxloc'",
                median_of([sys.executable, "-c", "import jaxloc"], args.repeats),
                None,
            )
        )
        rows.append(("jaxloc --help", median_of([*JAXLOC, "--help"], args.repeats), None))
        rows.append(
            (
                "jaxloc localize-lidar --help",
                median_of([*JAXLOC, "localize-lidar", "--help"], args.repeats),
                None,
            )
        )
        cache = not args.no_cache
        lidar = ["localize-lidar", *lidar_inputs(work)]
        rows.append(("jaxloc localize-lidar MAP SCAN", *pair("lidar", lidar, work, cache)))
        build = ["build-lidar-map", *lidar_sequence_inputs(work)]
        rows.append(("jaxloc build-lidar-map SEQ OUT", *pair("build", build, work, cache)))
        camera = ["localize-camera", *camera_inputs(work)]
        rows.append(("jaxloc localize-camera MAP.npz SEQ", *pair("camera", camera, work, cache)))
        if not args.skip_demo:
            demo = ["demo", "--out", str(work / "demo.png"), *args.demo_args]
            rows.append(
                ("jaxloc demo " + " ".join(args.demo_args), *pair("demo", demo, work, cache))
            )
    lines = [
        f"Wall seconds, fresh processes; single runs: median of {args.repeats}. Load average "
        f"before: {before}, after: {loadavg()}. Second runs: "
        f"{'cache on' if not args.no_cache else 'cache off (JAXLOC_NO_CACHE=1)'}.",
        "",
        "| what | first run (s) | second run (s) | / import jax (first, second) |",
        "|---|---|---|---|",
    ]
    breakdown = [
        "",
        "Where the time went (startup_probe.py, wall seconds inside the process; `rest`: reading, "
        "computing, writing; programs: compilations requested / answered by the cache):",
        "",
        "| command | run | " + " | ".join(PARTS) + " | programs |",
        "|---|---|" + "---|" * (len(PARTS) + 1),
    ]
    for name, first, second, *reports in rows:
        if second is None:
            lines.append(f"| `{name}` | {first:.2f} | | {first / jax_s:.2f}x |")
        else:
            ratio = f"{first / jax_s:.1f}x, {second / jax_s:.1f}x"
            lines.append(f"| `{name}` | {first:.2f} | {second:.2f} | {ratio} |")
            for run, report in zip(("first", "second"), reports[0], strict=True):
                parts = " | ".join(f"{report[part]:.2f}" for part in PARTS)
                programs = f"{report['programs']} / {report['cache_hits']}"
                breakdown.append(f"| `{name}` | {run} | {parts} | {programs} |")
    text = "\n".join(lines + breakdown)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
