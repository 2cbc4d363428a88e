"""Localizing a drive, not a scan: single scans, the fused windows of the last K scans
(``jaxloc.m2loc.localize_window``) and tracking (``jaxloc.m2loc.Tracker``), on simulated drives of
small scans cut along the roads of every shared real map and of the synthetic worlds.

Each drive is ``jaxloc.synthetic.outdoor.make_drive``: ``--length`` consecutive poses 5 m apart
along the road cells, each scan cut as ``make_query`` (vertices within 40-60 m, 50-80 % dropped,
at most ``--max-kept`` kept, 0.2-0.5 m jitter, 10-30 % spurious, 1 degree tilt noise). The
odometry is a chain of the true relative poses, each perturbed by ``--odometry-noise`` (metres
and degrees rms per scan), so a window's relative poses and the tracker's predictions carry the
same drift. Every row is judged on the drive's last scan: localized alone (M2Loc as published,
TripletLoc, the robust default), through the fused window of its last K scans (a pose on a clique
below ``WINDOW_MIN_CLIQUE`` refused, as ``localize_window`` does), or by the tracker that ran over
the whole drive (on single scans, or on fused windows of 3).

Success: valid, RTE < 7.5 m, RRE < 10 deg; RTE / RRE: medians over the successes; "wrong": valid
poses off by more (the tracker's over every scan of every drive); "false accepts": drives cut from
another map (the next one in the list) with a valid last-scan pose (the tracker's: a valid pose at
any scan of the drive). Time: mean wall seconds per scan; the tracker's also the median step of
the scans it tracked. Each setting runs at one query capacity per map (the band of its largest
query), so it compiles once per map.

    JAX_PLATFORMS=cpu python experiments/m2loc_drives.py --drives 20 --seed 2000
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import subprocess
import sys
import time
from pathlib import Path

import equinox as eqx
import numpy as np
from _atomic import write_text_atomic

from jaxloc.io import read_instance_map, read_road_normals
from jaxloc.m2loc import (
    DriveConfig,
    TrackConfig,
    TripletConfig,
    build_map,
    localization_errors,
    localize_drive,
    localize_scan,
    m2loc_config,
    tripletloc_config,
)
from jaxloc.m2loc._accumulation import WINDOW_MIN_CLIQUE, WINDOW_MIN_INSTANCES, require_clique
from jaxloc.m2loc._drive import drive_window
from jaxloc.m2loc._evaluation import SUCCESS_RRE_DEG, SUCCESS_RTE_M
from jaxloc.m2loc._localization import query_capacity
from jaxloc.m2loc._tracking import TRACKED
from jaxloc.synthetic.outdoor import make_drive, make_outdoor_world

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "helipr_instance_maps"
OUT = ROOT / "experiments" / "results" / "m2loc"
SINGLE = {
    "TripletLoc": lambda capacity: tripletloc_config(query_capacity=capacity),
    "M2Loc (paper)": lambda capacity: m2loc_config(3, robust=False, query_capacity=capacity),
    "M2Loc robust": lambda capacity: m2loc_config(3, query_capacity=capacity),
}
COUNTS = ("wrong", "false")  # integer statistics


def maps():
    for kind in ("sparse", "dense"):
        world = make_outdoor_world(kind, seed=0)
        yield f"Synth-{kind}", world.points, world.labels, world.road_normals
    if DATA.exists():
        for directory in sorted(DATA.iterdir()):
            m = read_instance_map(directory)
            yield directory.name, m.points, m.labels, read_road_normals(directory)


def band(size: int) -> int:
    """The query capacity band of a query of ``size`` vertices (``query_capacity``)."""
    return query_capacity(max(size, 1), TripletConfig())


def odometry_chain(drive, rng, sigma_m, sigma_deg) -> np.ndarray:
    """(S, 4, 4) odometry poses of a drive (oldest first): the true relative poses, each
    perturbed by a yaw and a translation error, composed from the first scan's true pose."""
    chain = [drive[0].T_map_scan]
    for previous, scan in zip(drive, drive[1:], strict=False):
        angle = np.deg2rad(rng.normal(0.0, sigma_deg))
        noise = np.eye(4)
        noise[:2, :2] = [[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]]
        noise[:3, 3] = rng.normal(0.0, sigma_m / np.sqrt(3.0), 3)
        chain.append(chain[-1] @ np.linalg.inv(previous.T_map_scan) @ scan.T_map_scan @ noise)
    return np.stack(chain)


def fused_query(drive, chain, end: int, k: int, most: int | None = None, min_instances: int = 0):
    """Points, labels and scans fused of the window of scan ``end``: its last ``k`` scans, grown
    with older ones up to ``most`` (default ``k``) while it holds fewer than ``min_instances``
    fused instances (``drive_window``, as ``localize_drive`` and ``localize-lidar
    --accumulate k`` do)."""
    points, labels = [s.points for s in drive], [s.labels for s in drive]
    fused = drive_window(points, labels, chain, end, k, most, min_instances)
    return fused.points, fused.labels, fused.members.shape[1]


def judge(pose, valid, truth) -> tuple[bool, bool, float, float]:
    """(success, wrong, RTE, RRE)."""
    rte, rre = localization_errors(pose, truth)
    good = rte < SUCCESS_RTE_M and rre < SUCCESS_RRE_DEG
    return valid and good, valid and not good, float(rte), float(rre)


def stats_of(judged, drives: int) -> dict:
    hits = [(rte, rre) for ok, _, rte, rre in judged if ok]
    return {
        "success": sum(ok for ok, *_ in judged) / drives,
        "wrong": int(sum(wrong for _, wrong, *_ in judged)),
        "rte": np.median([h[0] for h in hits]) if hits else np.nan,
        "rre": np.median([h[1] for h in hits]) if hits else np.nan,
    }


def run_one_shot(
    triplet_map, queries, truths, foreign_queries, min_clique: int = 3
) -> tuple[dict, float]:
    """Localize each (points, labels) query, refusing poses on a clique below ``min_clique``
    (``WINDOW_MIN_CLIQUE`` for windows, as ``localize_window`` and the command line); returns
    stats and mean seconds per query."""

    def localize(query):
        return require_clique(localize_scan(triplet_map, None, *query), min_clique)

    localize(max(queries, key=lambda q: len(q[0])))  # compile
    start = time.perf_counter()
    results = [localize(q) for q in queries]
    seconds = (time.perf_counter() - start) / len(queries)
    judged = [judge(r.pose, r.valid, t) for r, t in zip(results, truths, strict=True)]
    stats = stats_of(judged, len(queries))
    stats["false"] = int(sum(localize(q).valid for q in foreign_queries))
    return stats, seconds


def run_tracker(triplet_map, drives, chains, k: int, config: DriveConfig) -> tuple[list, list]:
    """``localize_drive`` tracking each drive with windows of ``k`` scans (``config``: their
    growth and the tracker): per drive its ``DriveResult``; every step's (seconds, mode)."""
    runs = [
        localize_drive(triplet_map, d, odometry=c, accumulate=k, track=True, config=config)
        for d, c in zip(drives, chains, strict=True)
    ]
    seconds = [
        (1e-3 * ms, int(mode))
        for run in runs
        for ms, mode in zip(run.localize_ms, run.status, strict=True)
    ]
    return runs, seconds


def own_and_foreign_drives(all_maps, only, seed, count, length, max_kept, noise):
    """The drives of map ``only`` and of its foreign map (the next one in ``all_maps``), with
    their odometry chains: ``(foreign name, {name: drives}, {name: chains})``. Each map's drives
    come from a generator of their own (``seed``), its chains from another (``seed + 1``)."""
    names = [m[0] for m in all_maps]
    other = names[(names.index(only) + 1) % len(names)]
    drives, chains = {}, {}
    for name, points, labels, normals in all_maps:
        if name not in (only, other):
            continue
        rng = np.random.default_rng(seed)
        drives[name] = [
            make_drive(points, labels, normals, rng, length, max_kept=max_kept)
            for _ in range(count)
        ]
        rng = np.random.default_rng(seed + 1)
        chains[name] = [odometry_chain(d, rng, *noise) for d in drives[name]]
    return other, drives, chains


def development_parser(doc: str, out_name: str) -> argparse.ArgumentParser:
    """The command line of the development scripts: ``--seeds``, ``--drives``, ``--maps`` and
    ``--out`` (default ``OUT / out_name``)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[2000, 3000, 4000])
    parser.add_argument("--drives", type=int, default=20)
    parser.add_argument("--maps", nargs="+", help="only these maps (default: all)")
    parser.add_argument("--out", type=Path, default=OUT / out_name)
    return parser


def rows_over_seeds_and_maps(args: argparse.Namespace, rows_of) -> list:
    """``rows_of(seed, name, all_maps, drives)`` for every seed and (selected) map, in order."""
    all_maps = list(maps())
    rows = []
    for seed in args.seeds:
        for name, *_ in all_maps:
            if args.maps is None or name in args.maps:
                rows.extend(rows_of(seed, name, all_maps, args.drives))
    return rows


def last_scan_queries(all_maps, name: str, seed: int, count: int, windows) -> tuple:
    """The queries the development scripts judge: on ``count`` drives of map ``name`` (and of its
    foreign map) with this script's default drive settings, the fused window of the last k scans
    of each drive for every k of ``windows`` (k = 1: the last scan).

    Returns ``(truths, {k: (own queries, foreign queries, capacity)})``: the last scans' true
    ``T_map_scan`` and per k the (points, labels) queries and the capacity band of the largest.
    """
    other, drives, chains = own_and_foreign_drives(all_maps, name, seed, count, 10, 11, (0.05, 0.5))
    by_window = {}
    for k in windows:
        own, foreign = (
            [
                fused_query(d, c, len(d) - 1, k)[:2]
                for d, c in zip(drives[w], chains[w], strict=True)
            ]
            for w in (name, other)
        )
        by_window[k] = own, foreign, band(max(len(q[0]) for q in own + foreign))
    return [d[-1].T_map_scan for d in drives[name]], by_window


def rows_of_map(args, only: str) -> list:
    """The rows of one map (run in a process of its own: a process that compiles every map's
    programs ran out of memory mappings on this machine)."""
    all_maps = list(maps())
    other, drives, chains = own_and_foreign_drives(
        all_maps, only, args.seed, args.drives, args.length, args.max_kept, args.odometry_noise
    )
    rows = []
    for name, points, labels, normals in all_maps:
        if name != only:
            continue
        own, foreign = drives[name], drives[other]
        truths = [d[-1].T_map_scan for d in own]

        def windows_of(window, which, chain_set):
            k, most, instances = window
            return [
                fused_query(d, c, len(d) - 1, k, most, instances)
                for d, c in zip(which, chain_set, strict=True)
            ]

        # (K, M, N): the last K scans, grown up to M while fewer than N fused instances
        single = (1, 1, 0)
        windows = [(k, k, 0) for k in args.windows]
        if args.window_instances > 0:
            windows += [(k, 2 * k, args.window_instances) for k in args.windows]
        queries = {single: [(d[-1].points, d[-1].labels, 1) for d in own]}
        foreign_queries = {single: [(d[-1].points, d[-1].labels, 1) for d in foreign]}
        for window in windows:
            queries[window] = windows_of(window, own, chains[name])
            foreign_queries[window] = windows_of(window, foreign, chains[other])
        capacity = {
            w: band(max(len(q[0]) for q in queries[w] + foreign_queries[w])) for w in queries
        }
        robust = {}
        for row, make_config in SINGLE.items():
            triplet_map = build_map(points, labels, make_config(capacity[single]), normals)
            if row == "M2Loc robust":
                robust[capacity[single]] = triplet_map
            stats, seconds = run_one_shot(
                triplet_map, queries[single], truths, foreign_queries[single]
            )
            size = np.median([len(q[0]) for q in queries[single]])
            rows.append((name, f"{row}, single scan", stats, seconds, float(size), None))
            print(rows[-1], file=sys.stderr, flush=True)
        for window in windows:
            k, most, instances = window
            if capacity[window] not in robust:
                config = m2loc_config(3, query_capacity=capacity[window])
                robust[capacity[window]] = build_map(points, labels, config, normals)
            stats, seconds = run_one_shot(
                robust[capacity[window]],
                queries[window],
                truths,
                foreign_queries[window],
                WINDOW_MIN_CLIQUE,
            )
            size = float(np.median([len(q[0]) for q in queries[window]]))
            how = (
                f"{k} to {most} scans for {instances} instances, mean "
                f"{np.mean([q[2] for q in queries[window]]):.2f}"
                if instances
                else f"{k} scans"
            )
            label = f"M2Loc robust, --accumulate {k} ({how})"
            rows.append((name, label, stats, seconds, size, None))
            print(rows[-1], file=sys.stderr, flush=True)
        track_configs = [("", TrackConfig())]
        if args.compare_confirm:
            track_configs.append((", no confirmation", TrackConfig(confirm=False)))
        for k, (suffix, track_config) in itertools.product(args.track_windows, track_configs):
            most, instances = (2 * k, args.window_instances) if k > 1 else (1, 0)
            config = DriveConfig(most_scans=most, min_instances=instances, track=track_config)
            sizes = {
                which: [
                    len(d[i].points) if k == 1 else len(fused_query(d, c, i, k, most, instances)[0])
                    for d, c in zip(drives[which], chains[which], strict=True)
                    for i in range(len(d))
                ]
                for which in (name, other)
            }
            # every step at the band of the largest query (one compilation per map)
            size = band(max(sizes[name] + sizes[other]))
            tracker_map = robust[capacity[single]]
            tracker_map = eqx.tree_at(
                lambda m: m.config,
                tracker_map,
                dataclasses.replace(tracker_map.config, query_capacity=size),
            )
            runs, seconds = run_tracker(tracker_map, own, chains[name], k, config)
            judged_last = [
                judge(run.poses[-1], bool(run.valid[-1]), t)
                for run, t in zip(runs, truths, strict=True)
            ]
            stats = stats_of(judged_last, len(runs))
            every_scan = [
                judge(pose, bool(valid), scan.T_map_scan)
                for run, d in zip(runs, own, strict=True)
                for pose, valid, scan in zip(run.poses, run.valid, d, strict=True)
            ]
            stats["wrong"] = int(sum(wrong for _, wrong, *_ in every_scan))
            stats["right_share"] = sum(ok for ok, *_ in every_scan) / len(every_scan)
            foreign_runs, _ = run_tracker(tracker_map, foreign, chains[other], k, config)
            stats["false"] = int(sum(bool(run.valid.any()) for run in foreign_runs))
            tracked = [s for s, mode in seconds if mode == TRACKED]
            stats["tracked_ms"] = 1e3 * np.median(tracked) if tracked else np.nan
            stats["tracked_share"] = len(tracked) / len(seconds)
            mean = float(np.mean([s for s, _ in seconds]))
            label = "--track" + (f" --accumulate {k}" if k > 1 else "") + suffix
            median_size = np.median(sizes[name])
            rows.append((name, f"M2Loc robust, {label}", stats, mean, float(median_size), size))
            print(rows[-1], file=sys.stderr, flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--drives", type=int, default=20)
    parser.add_argument("--seed", type=int, default=2000)
    parser.add_argument("--length", type=int, default=10, help="scans per drive")
    parser.add_argument("--max-kept", type=int, default=11)
    parser.add_argument("--odometry-noise", type=float, nargs=2, default=(0.05, 0.5))
    parser.add_argument("--windows", type=int, nargs="+", default=[2, 3, 5])
    parser.add_argument("--track-windows", type=int, nargs="+", default=[1, 3])
    parser.add_argument(
        "--window-instances",
        type=int,
        default=WINDOW_MIN_INSTANCES,
        help="windows of K scans grow up to 2K scans while their fused submap holds fewer "
        "instances than this (0: fixed windows only; also the tracker's windows)",
    )
    parser.add_argument("--maps", nargs="+", help="only these maps (default: all)")
    parser.add_argument(
        "--compare-confirm", action="store_true", help="add tracking rows without confirmation"
    )
    parser.add_argument("--out", type=Path, default=OUT / "drives.md")
    parser.add_argument("--one-map", help=argparse.SUPPRESS)  # the child process of one map
    args = parser.parse_args()
    if args.one_map is not None:
        rows = rows_of_map(args, args.one_map)
        print(
            json.dumps(
                [
                    [a, b, {k: v if k in COUNTS else float(v) for k, v in c.items()}, d, e, f]
                    for a, b, c, d, e, f in rows
                ]
            )
        )
        return
    rows = []
    for name in [m[0] for m in maps()]:
        if args.maps and name not in args.maps:
            continue
        child = [sys.executable, __file__, *sys.argv[1:], "--one-map", name]
        done = subprocess.run(child, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise SystemExit(f"{name} failed:\n{done.stderr[-3000:]}")
        rows += [
            (r[0], r[1], r[2], r[3], r[4], r[5]) for r in json.loads(done.stdout.splitlines()[-1])
        ]
        print(f"{name}: done", flush=True)
    lines = [
        f"# Drives of small scans: single scans, fused windows and tracking ({args.drives} drives "
        f"of {args.length} scans per map, seed {args.seed}, at most {args.max_kept} kept map "
        f"vertices per scan, odometry noise {args.odometry_noise[0]} m / "
        f"{args.odometry_noise[1]} deg rms per scan)",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_drives.py --drives {args.drives} "
        f"--seed {args.seed} --length {args.length} --max-kept {args.max_kept} --windows "
        f"{' '.join(map(str, args.windows))} --track-windows "
        f"{' '.join(map(str, args.track_windows))} --window-instances {args.window_instances}"
        + (f" --maps {' '.join(args.maps)}" if args.maps else "")
        + (" --compare-confirm" if args.compare_confirm else "")
        + "`",
        "",
        "Judged on each drive's last scan. `--accumulate K (K to 2K scans for N instances)`: the "
        "window grows beyond its last K scans, up to 2K, while its fused submap holds fewer than "
        "N instances (`grow_window`, the command line's default); `(K scans)`: the fixed window. "
        "The tracker's windows grow the same way. Tracking rows: the tracker ran over the whole "
        "drive; 'wrong' counts valid poses off by more than 7.5 m / 10 deg at any scan, a false "
        "accept is a foreign drive with a valid pose at any scan; 'tracked' is the share of all "
        "steps the local association verified and their median wall time; then the share of all "
        "scans of the drives with a right valid pose.",
        "",
        "| map | method | vertices (median) | success | RTE m (median) | RRE deg (median) | "
        "wrong valid poses | false accepts (foreign drives) | s per scan | tracked: share, "
        "median ms; right / all scans |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row, stats, seconds, size, _ in rows:
        tracked = ""
        if "tracked_ms" in stats:
            tracked = (
                f"{stats['tracked_share']:.2f}, {stats['tracked_ms']:.1f}; "
                f"{stats['right_share']:.2f}"
            )
        lines.append(
            f"| {name} | {row} | {size:.0f} | {stats['success']:.2f} | {stats['rte']:.2f} | "
            f"{stats['rre']:.2f} | {stats['wrong']} | {stats['false']}/{args.drives} | "
            f"{seconds:.3f} | {tracked} |"
        )
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
