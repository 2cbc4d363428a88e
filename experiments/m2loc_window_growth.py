"""Choosing how a fused window grows on sparse stretches, on development drives.

``--accumulate K`` fuses the last K scans. Where those scans hold few instances (a stretch of road
with 3-5 objects per scan) the fused window of 3 scans can hold 8-10 instances, too few to
localize. A window that grows beyond K scans, up to ``M`` scans, until its fused submap holds at
least ``N`` instances costs nothing where scans are rich and adds scans where they are poor.

On the drives of ``m2loc_drives.py`` (same generator, seeds and odometry noise), this script
localizes the fused window of the last k scans of every drive (own and foreign drives, each query
at the capacity band of its size, as the command line runs it) for k from 2 up, stopping past the
largest K once a window holds the largest N, and records size, validity, clique size and
rightness of each. Every rule (K, N, M) is then judged from that one run: the window is the
shortest of K..M scans holding N fused instances, else the M scans. Poses of windows on a clique
below ``WINDOW_MIN_CLIQUE`` are refused, as ``localize_window`` does.

    JAX_PLATFORMS=cpu python experiments/m2loc_window_growth.py --seeds 2000 3000 4000
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import m2loc_drives as drives
import numpy as np
from _atomic import write_text_atomic

from jaxloc.m2loc import build_map, localization_errors, localize_scan, m2loc_config
from jaxloc.m2loc._accumulation import WINDOW_MIN_CLIQUE

LENGTH = 10  # scans per drive, as m2loc_drives.py's default
LEAST_SCANS = (2, 3, 5)
LEAST_INSTANCES = (0, 12, 15, 18, 21, 24)


def outcome(triplet_map, points, labels, truth) -> dict:
    """Size, validity (a window's clique rule applied), clique size and rightness of one query
    (``truth`` None: a foreign drive, never right)."""
    found = {"size": len(points), "valid": False, "clique": 0, "right": False}
    if len(points) < 3:
        return found
    result = localize_scan(triplet_map, None, points, labels)
    found["clique"] = int(result.clique_size)
    found["valid"] = bool(result.valid)
    if truth is not None and result.valid:
        rte, rre = localization_errors(result.pose, truth)
        found["right"] = bool(rte < drives.SUCCESS_RTE_M and rre < drives.SUCCESS_RRE_DEG)
    return found


def rows_of(seed: int, name: str, all_maps: list, num_drives: int) -> list[dict]:
    """Per drive (own and foreign) of map ``name``: the outcome of the last-k-scan window for
    every k from 1 to the drive's length."""
    other, by_map, chains = drives.own_and_foreign_drives(
        all_maps, name, seed, num_drives, LENGTH, 11, (0.05, 0.5)
    )
    _, points, labels, normals = next(m for m in all_maps if m[0] == name)
    triplet_map = build_map(points, labels, m2loc_config(3), normals)
    rows = []
    for which, own in ((other, False), (name, True)):
        for drive, chain in zip(by_map[which], chains[which], strict=True):
            truth = drive[-1].T_map_scan if own else None
            windows = [None]  # k = 1, which no rule takes
            for k in range(2, len(drive) + 1):
                if k > max(LEAST_SCANS) and windows[-1]["size"] >= max(LEAST_INSTANCES):
                    break  # no rule takes a longer window
                query = drives.fused_query(drive, chain, len(drive) - 1, k)
                windows.append(outcome(triplet_map, *query[:2], truth))
            rows.append({"map": name, "seed": seed, "own": own, "windows": windows})
        print(name, seed, "own" if own else "foreign", file=sys.stderr, flush=True)
    return rows


def chosen(windows: list[dict], least: int, instances: int, most: int) -> dict:
    """The window the rule (K = ``least``, N = ``instances``, M = ``most``) takes, its clique
    rule applied."""
    most = min(most, LENGTH)
    k = next((k for k in range(least, most + 1) if windows[k - 1]["size"] >= instances), most)
    window = dict(windows[k - 1], scans=k)
    if k > 1 and window["clique"] < WINDOW_MIN_CLIQUE:
        window["valid"] = window["right"] = False
    return window


def tally(rows: list[dict], least: int, instances: int, most: int) -> tuple:
    """(successes, wrong valid, false accepts, mean scans fused, worst map's success count)."""
    picks = [(row, chosen(row["windows"], least, instances, most)) for row in rows]
    own = [(row, p) for row, p in picks if row["own"]]
    per_map: dict = {}
    for row, p in own:
        key = (row["map"], row["seed"])
        per_map[key] = per_map.get(key, 0) + p["right"]
    return (
        sum(p["right"] for _, p in own),
        sum(p["valid"] and not p["right"] for _, p in own),
        sum(p["valid"] for row, p in picks if not row["own"]),
        float(np.mean([p["scans"] for _, p in own])),
        min(per_map.values()),
    )


def main() -> None:
    parser = drives.development_parser(__doc__, "window_growth.md")
    parser.add_argument("--raw", type=Path, help="JSON of every window's outcome")
    parser.add_argument("--from-raw", type=Path, help="tabulate a --raw file instead of running")
    args = parser.parse_args()
    if args.from_raw is not None:
        rows = json.loads(args.from_raw.read_text())
    else:
        rows = drives.rows_over_seeds_and_maps(args, rows_of)
    if args.raw is not None:
        write_text_atomic(args.raw, json.dumps(rows))
    seeds = sorted({row["seed"] for row in rows})
    lines = [
        "# How a fused window grows on sparse stretches, on development drives",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_window_growth.py --seeds "
        f"{' '.join(map(str, seeds))} --drives {args.drives}`",
        "",
        f"{args.drives} drives of {LENGTH} scans per map and seed, robust default "
        f"(`m2loc_config(3)`), judged on the window of each drive's last scan: the shortest of K "
        f"to M scans whose fused submap holds at least N instances (else M scans); N = 0 is the "
        f"fixed window of K scans. Cells: successes / wrong valid poses / false accepts (foreign "
        f"drives) / mean scans fused / the worst map and seed's successes (of {args.drives}).",
        "",
    ]
    for least in LEAST_SCANS:
        mosts = sorted({least, least + 2, 2 * least} & set(range(1, LENGTH + 1)))
        head = " | ".join(f"M = {m}" for m in mosts)
        lines += [f"## K = {least}", "", f"| N | {head} |", "|---|" + "---|" * len(mosts)]
        for instances in LEAST_INSTANCES:
            cells = []
            for most in mosts:
                ok, wrong, false, scans, worst = tally(rows, least, instances, most)
                cells.append(f"{ok} / {wrong} / {false} / {scans:.2f} / {worst}")
            lines.append(f"| {instances} | {' | '.join(cells)} |")
        lines.append("")
    write_text_atomic(args.out, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
