"""Tracking vs one-shot global localization of the same scans: wall time per scan.

For each map: drives of scan-sized queries (``jaxloc.synthetic.outdoor.make_drive``), the tracker
(``jaxloc.m2loc.Tracker``, jitted ``track_step``) run over each drive with the true relative
poses as odometry, and, on the same scans, ``localize_scan`` (the robust default, the peer). The
tracker's steps are timed per mode (tracked, i.e. the local association verified; or the global
fallback); the ratio is the median tracked step over the median global query. Wall time (the
tracker's including ``pad_scan``, the validation and padding a user's call does) after
compilation (both programs compiled before timing), ``jax.block_until_ready`` on every step;
peak RSS of the process. Run nothing else meanwhile.

    JAX_PLATFORMS=cpu python benchmarks/m2loc_tracking.py [--drives 5] [--length 20]
        [--max-kept 13] [--maps KAIST04 ...] [--out benchmarks/results/m2loc_tracking_cpu.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import time
from pathlib import Path

import jax
import numpy as np

from jaxloc.io import read_instance_map, read_road_normals
from jaxloc.m2loc import Tracker, build_map, localize_scan, m2loc_config, pad_scan
from jaxloc.m2loc._tracking import TRACKED, track_step
from jaxloc.synthetic.outdoor import make_drive, make_outdoor_world

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "helipr_instance_maps"
CAPACITY = 32


def maps(names):
    world = make_outdoor_world("dense", seed=0)
    candidates = [("Synth-dense", lambda: (world.points, world.labels, world.road_normals))]
    if DATA.exists():
        for directory in sorted(DATA.iterdir()):

            def load(directory=directory):
                m = read_instance_map(directory)
                return m.points, m.labels, read_road_normals(directory)

            candidates.append((directory.name, load))
    for name, load in candidates:
        if not names or name in names:
            yield name, *load()


def timed(fn, *args):
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--drives", type=int, default=5)
    parser.add_argument("--length", type=int, default=20)
    parser.add_argument("--max-kept", type=int, default=13)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--maps", nargs="+")
    parser.add_argument(
        "--out", type=Path, default=ROOT / "benchmarks" / "results" / "m2loc_tracking_cpu.md"
    )
    args = parser.parse_args()
    load_start = os.getloadavg()[0]
    rows = []
    for name, points, labels, normals in maps(args.maps):
        triplet_map = build_map(points, labels, m2loc_config(3, query_capacity=CAPACITY), normals)
        tracker = Tracker(triplet_map)
        rng = np.random.default_rng(args.seed)
        drives = [
            make_drive(points, labels, normals, rng, args.length, max_kept=args.max_kept)
            for _ in range(args.drives)
        ]
        scans = [s for d in drives for s in d]

        def step(state, scan, odometry, tracker=tracker):  # as a user calls it: pad, then step
            padded = pad_scan(scan.points, scan.labels, tracker.triplet_map.config, CAPACITY)
            return track_step(tracker, state, padded, odometry)

        # Compile both programs (or load them from the cache) before timing.
        first = scans[0]
        _, compile_track = timed(step, tracker.init(), first, np.eye(4))
        _, compile_global = timed(localize_scan, triplet_map, None, first.points, first.labels)
        tracked, fallback = [], []
        for drive in drives:
            state = tracker.init()
            for i, scan in enumerate(drive):
                odometry = np.linalg.inv(drive[i - 1].T_map_scan) @ scan.T_map_scan if i else None
                odometry = np.eye(4) if odometry is None else odometry
                (state, out), seconds = timed(step, state, scan, odometry)
                (tracked if int(out.mode) == TRACKED else fallback).append(seconds)
        one_shot = [timed(localize_scan, triplet_map, None, s.points, s.labels)[1] for s in scans]
        rows.append(
            {
                "map": name,
                "instances": int(np.median([len(s.points) for s in scans])),
                "tracked": tracked,
                "fallback": fallback,
                "global": one_shot,
                "compile": (compile_track, compile_global),
            }
        )
        print(name, f"tracked {1e3 * np.median(tracked):.2f} ms", flush=True)
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    lines = [
        "# Tracking vs one-shot global localization (wall time per scan, CPU)",
        "",
        f"Command: `JAX_PLATFORMS=cpu python benchmarks/m2loc_tracking.py --drives {args.drives} "
        f"--length {args.length} --max-kept {args.max_kept} --seed {args.seed}"
        + (f" --maps {' '.join(args.maps)}" if args.maps else "")
        + "`",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, jax "
        f"{jax.__version__}; load average {load_start:.1f} at the start, "
        f"{os.getloadavg()[0]:.1f} at the end; peak RSS of the process {peak_mib:.0f} MiB. "
        f"Robust M2Loc configuration (3 scales), scans padded to {CAPACITY}; odometry: the true "
        "relative poses.",
        "",
        "| map | instances per scan (median) | tracked steps | tracked ms median (p90) | "
        "global fallback steps, ms median | one-shot global ms median (p90) | tracked / global "
        "| compile s (step, global) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        t, g = 1e3 * np.array(row["tracked"]), 1e3 * np.array(row["global"])
        f = 1e3 * np.array(row["fallback"])
        fallback = f"{len(f)}, {np.median(f):.1f}" if len(f) else "0"
        lines.append(
            f"| {row['map']} | {row['instances']} | {len(t)} | {np.median(t):.2f} "
            f"({np.percentile(t, 90):.2f}) | {fallback} | {np.median(g):.1f} "
            f"({np.percentile(g, 90):.1f}) | {np.median(t) / np.median(g):.3f} | "
            f"{row['compile'][0]:.1f}, {row['compile'][1]:.1f} |"
        )
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
