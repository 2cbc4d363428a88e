"""Localizing a drive, not a scan (issue 26, first part): single scans vs the fused windows of the
last K scans (``jaxloc.m2loc.localize_window``), on simulated drives of small scans cut along the
roads of every shared real map and of the synthetic worlds.

Each drive is ``jaxloc.synthetic.outdoor.make_drive``: consecutive poses 5 m apart along the road
cells, each scan cut as ``make_query`` (vertices within 40-60 m, 50-80 % dropped, at most
``--max-kept`` kept, 0.2-0.5 m jitter, 10-30 % spurious, 1 degree tilt noise). The odometry
between scans is the ground truth with ``--odometry-noise`` (metres and degrees per scan, rms, on
each relative pose). A drive's last scan is localized alone (rows "single"; M2Loc as published,
TripletLoc and the robust default) and through the fused window of its last K scans (robust
default). Success: valid, RTE < 7.5 m, RRE < 10 deg; "wrong" counts valid poses off by more;
"false accepts": valid poses for drives cut from another map (the next one in the list).
Every setting runs at one query capacity (``--capacity``) per map, so it compiles once per map.

    JAX_PLATFORMS=cpu python experiments/m2loc_drives.py --drives 40 --seed 2000
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from jaxloc.io import load_instance_map, load_road_normals
from jaxloc.m2loc import (
    build_map,
    localization_errors,
    localize_scan,
    localize_window,
    m2loc_config,
    tripletloc_config,
)
from jaxloc.synthetic.outdoor import make_drive, make_outdoor_world

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "helipr_instance_maps"
OUT = ROOT / "experiments" / "results" / "m2loc"
SINGLE = {
    "TripletLoc": lambda capacity: tripletloc_config(query_capacity=capacity),
    "M2Loc (paper)": lambda capacity: m2loc_config(3, robust=False, query_capacity=capacity),
    "M2Loc robust": lambda capacity: m2loc_config(3, query_capacity=capacity),
}


def maps():
    for kind in ("sparse", "dense"):
        world = make_outdoor_world(kind, seed=0)
        yield f"Synth-{kind}", world.points, world.labels, world.road_normals
    if DATA.exists():
        for directory in sorted(DATA.iterdir()):
            m = load_instance_map(directory)
            yield directory.name, m.points, m.labels, load_road_normals(directory)


def noisy_odometry(drive, rng, sigma_m, sigma_deg) -> np.ndarray:
    """(K, 4, 4) T_newest_scan, newest first, each relative pose perturbed independently."""
    newest = np.linalg.inv(drive[-1].T_map_scan)
    poses = []
    for k, scan in enumerate(drive[::-1]):
        T = newest @ scan.T_map_scan
        if k > 0:
            angle = np.deg2rad(rng.normal(0.0, sigma_deg))
            c, s = np.cos(angle), np.sin(angle)
            noise = np.eye(4)
            noise[:2, :2] = [[c, -s], [s, c]]
            noise[:3, 3] = rng.normal(0.0, sigma_m / np.sqrt(3.0), 3) * k
            T = T @ noise
        poses.append(T)
    return np.stack(poses)


def localize_drive(triplet_map, window, rng, noise):
    """Localize the newest scan of ``window`` (oldest first) through the fused window; returns
    the result and the number of fused instances."""
    odometry = noisy_odometry(window, rng, *noise)
    newest_first = window[::-1]
    result, fused = localize_window(
        triplet_map, [s.points for s in newest_first], [s.labels for s in newest_first], odometry
    )
    return result, len(fused.points)


def score(results, truths) -> dict:
    ok = wrong = 0
    for result, truth in zip(results, truths, strict=True):
        if not result.valid:
            continue
        rte, rre = localization_errors(result.pose, truth)
        ok += rte < 7.5 and rre < 10
        wrong += not (rte < 7.5 and rre < 10)
    return {"success": ok / len(results), "wrong": wrong}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--drives", type=int, default=40)
    parser.add_argument("--seed", type=int, default=2000)
    parser.add_argument("--max-kept", type=int, default=11)
    parser.add_argument("--odometry-noise", type=float, nargs=2, default=(0.05, 0.5))
    parser.add_argument("--windows", type=int, nargs="+", default=[2, 3, 5])
    parser.add_argument("--capacity", type=int, default=128, help="query capacity (static)")
    parser.add_argument("--out", type=Path, default=OUT / "drives.md")
    args = parser.parse_args()
    all_maps = list(maps())
    drives = {}
    for name, points, labels, normals in all_maps:
        rng = np.random.default_rng(args.seed)
        drives[name] = [
            make_drive(points, labels, normals, rng, max(args.windows), max_kept=args.max_kept)
            for _ in range(args.drives)
        ]
    rows = []
    for index, (name, points, labels, normals) in enumerate(all_maps):
        foreign = drives[all_maps[(index + 1) % len(all_maps)][0]]
        own = drives[name]
        sizes = [len(d[-1].points) for d in own]
        truths = [d[-1].T_map_scan for d in own]
        built = {}
        for row, make_config in SINGLE.items():
            triplet_map = build_map(points, labels, make_config(args.capacity), normals)
            built[row] = triplet_map
            localize_scan(triplet_map, None, own[0][-1].points, own[0][-1].labels)  # compile
            start = time.perf_counter()
            results = [localize_scan(triplet_map, None, d[-1].points, d[-1].labels) for d in own]
            seconds = (time.perf_counter() - start) / len(own)
            stats = score(results, truths)
            stats["false"] = sum(
                localize_scan(triplet_map, None, d[-1].points, d[-1].labels).valid for d in foreign
            )
            rows.append((name, f"{row}, single scan", stats, seconds, np.median(sizes)))
            print(rows[-1], flush=True)
        robust = built["M2Loc robust"]  # the windows run on the single-scan robust map
        rng = np.random.default_rng(args.seed + 1)
        for k in args.windows:
            start = time.perf_counter()
            found = [localize_drive(robust, drive[-k:], rng, args.odometry_noise) for drive in own]
            seconds = (time.perf_counter() - start) / len(own)
            stats = score([result for result, _ in found], truths)
            stats["false"] = sum(
                localize_drive(robust, drive[-k:], rng, args.odometry_noise)[0].valid
                for drive in foreign
            )
            fused_size = np.median([size for _, size in found])
            rows.append((name, f"M2Loc robust, --accumulate {k}", stats, seconds, fused_size))
            print(rows[-1], flush=True)
    lines = [
        f"# Drives of small scans: single scans vs fused windows ({args.drives} drives per map, "
        f"seed {args.seed}, at most {args.max_kept} kept map vertices per scan, odometry noise "
        f"{args.odometry_noise[0]} m / {args.odometry_noise[1]} deg rms per scan)",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_drives.py --drives {args.drives} "
        f"--seed {args.seed} --max-kept {args.max_kept} --windows "
        f"{' '.join(map(str, args.windows))} --capacity {args.capacity}`",
        "",
        "| map | method | vertices (median) | success | wrong valid poses | false accepts "
        "(foreign drives) | s per scan |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, row, stats, seconds, size in rows:
        lines.append(
            f"| {name} | {row} | {size:.0f} | {stats['success']:.2f} | {stats['wrong']} | "
            f"{stats['false']}/{args.drives} | {seconds:.3f} |"
        )
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
