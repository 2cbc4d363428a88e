"""Choosing the smallest clique a fused window may rest on, on development drives.

A pose from a clique of 3 rests on the minimal set: three associations always fit some rigid
motion, so only the verification of the other vertices speaks for it. On the drives of
``m2loc_drives.py`` (same generator, seeds and odometry noise), judged on each drive's last scan,
this script localizes the single scan and the fused windows of the last 2, 3 and 5 scans on every
map with the robust default, and counts, for a smallest clique of 3 (minimal), 4 and 5: successes
(valid, RTE < 7.5 m, RRE < 10 deg), wrong valid poses and false accepts (the next map's drives with
a valid pose). A larger smallest clique only refuses poses, so one run judges every rule.

    JAX_PLATFORMS=cpu python experiments/m2loc_window_clique.py --seeds 2000 3000 4000
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import m2loc_drives as drives
import numpy as np
from _atomic import write_text_atomic

from jaxloc.m2loc import build_map, localization_errors, localize_scan, m2loc_config

WINDOWS = (1, 2, 3, 5)
SMALLEST = (3, 4, 5)


def outcomes(triplet_map, queries, truths) -> list[tuple[int, int, bool]]:
    """(query size, clique size, right) of every valid pose; right is False for foreign drives
    (``truths`` None)."""
    found = []
    for i, (points, labels) in enumerate(queries):
        if len(points) < 3:
            continue
        result = localize_scan(triplet_map, None, points, labels)
        if not result.valid:
            continue
        right = False
        if truths is not None:
            rte, rre = localization_errors(result.pose, truths[i])
            right = bool(rte < drives.SUCCESS_RTE_M and rre < drives.SUCCESS_RRE_DEG)
        found.append((len(points), result.clique_size, right))
    return found


def rows_of(seed: int, name: str, all_maps: list, num_drives: int) -> list[tuple]:
    truths, by_window = drives.last_scan_queries(all_maps, name, seed, num_drives, WINDOWS)
    _, points, labels, normals = next(m for m in all_maps if m[0] == name)
    rows = []
    for k, (own, foreign, capacity) in by_window.items():
        triplet_map = build_map(points, labels, m2loc_config(3, query_capacity=capacity), normals)
        found = outcomes(triplet_map, own, truths), outcomes(triplet_map, foreign, None)
        rows.append((name, seed, k, *found))
        print(rows[-1][:3], [len(r) for r in rows[-1][3:]], file=sys.stderr, flush=True)
    return rows


def cells(own: list, foreign: list) -> list[tuple[int, int, int]]:
    """(successes, wrong valid, false accepts) for every smallest clique of :data:`SMALLEST`."""
    return [
        (
            sum(right for _, size, right in own if size >= smallest),
            sum(not right for _, size, right in own if size >= smallest),
            sum(size >= smallest for _, size, _ in foreign),
        )
        for smallest in SMALLEST
    ]


def main() -> None:
    parser = drives.development_parser(__doc__, "window_clique.md")
    parser.add_argument("--raw", type=Path, help="JSON of every valid pose: (size, clique, right)")
    args = parser.parse_args()
    rows = drives.rows_over_seeds_and_maps(args, rows_of)
    head = " | ".join(f"smallest clique {c}" for c in SMALLEST)
    lines = [
        "# The smallest clique of a fused window, on development drives",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_window_clique.py --seeds "
        f"{' '.join(map(str, args.seeds))} --drives {args.drives}`",
        "",
        f"{args.drives} drives per map and seed, robust default (`m2loc_config(3)`); each cell: "
        "successes / wrong valid poses / false accepts (foreign drives), judged on the last scan "
        "(k = 1) or the fused window of the last k scans.",
        "",
        "## Totals over maps and seeds",
        "",
        f"| k | {head} |",
        "|---|" + "---|" * len(SMALLEST),
    ]
    for k in WINDOWS:
        totals = np.sum([cells(own, foreign) for *_, kk, own, foreign in rows if kk == k], axis=0)
        text = " | ".join(f"{ok} / {wrong} / {false}" for ok, wrong, false in totals)
        lines.append(f"| {k} | {text} |")
    lines += [
        "",
        "## Per map and seed",
        "",
        f"| map | seed | k | {head} |",
        "|---|---|---|" + "---|" * len(SMALLEST),
    ]
    for name, seed, k, own, foreign in rows:
        text = " | ".join(f"{ok} / {wrong} / {false}" for ok, wrong, false in cells(own, foreign))
        lines.append(f"| {name} | {seed} | {k} | {text} |")
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    if args.raw is not None:
        write_text_atomic(args.raw, json.dumps(rows))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
