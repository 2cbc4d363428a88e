"""Choosing the uniqueness check's margin (``TripletConfig.ambiguity_margin``) on dev drives.

The drives of ``m2loc_drives.py`` (same generator, seeds and odometry noise), judged on each
drive's last scan: the single scan and the fused window of the last 3 scans, on every map, with
the robust default without the check and with it; the margins are compared on the same queries
from one run with margin 0 (a pose refused at margin 0 is refused at any larger margin, and a
larger margin refuses where ``rival >= fraction - margin``). Per row: successes (valid, RTE < 7.5
m, RRE < 10 deg), wrong valid poses, and false accepts (the next map's drives with a valid pose).

    JAX_PLATFORMS=cpu python experiments/m2loc_ambiguity.py --seeds 2000 3000 4000
"""

from __future__ import annotations

import sys

import m2loc_drives as drives
import numpy as np
from _atomic import write_text_atomic

from jaxloc.m2loc import build_map, localization_errors, m2loc_config, pad_scan
from jaxloc.m2loc._query import describe_query, register_query

MARGINS = (0.0, 0.05, 0.1, 0.15, 0.2)


def outcomes(triplet_map, queries, capacity) -> list[dict | None]:
    """valid, pose, own and rival verification of each query (None: fewer than 3 instances)."""
    config = triplet_map.config
    found = []
    for points, labels in queries:
        if len(points) < 3:
            found.append(None)
            continue
        scan = pad_scan(points, labels, config, capacity)
        d, v = describe_query(scan.points, scan.classes, scan.mask, config.descriptor)
        out = register_query(triplet_map, scan.points, scan.classes, d, v, scan.mask)
        found.append(
            {
                "valid": bool(out.valid),
                "pose": np.asarray(out.T_map_scan, np.float64),
                "fraction": float(out.inlier_fraction),
                "rival": float(out.rival_fraction),
            }
        )
    return found


def count(own, foreign, truths, keep) -> tuple[int, int, int]:
    """(successes, wrong valid poses, false accepts) of the queries ``keep`` accepts."""
    ok = wrong = 0
    for out, truth in zip(own, truths, strict=True):
        if out is None or not keep(out):
            continue
        rte, rre = localization_errors(out["pose"], truth)
        good = rte < drives.SUCCESS_RTE_M and rre < drives.SUCCESS_RRE_DEG
        ok, wrong = ok + good, wrong + (not good)
    return ok, wrong, sum(out is not None and keep(out) for out in foreign)


def rows_of(seed: int, name: str, all_maps: list, num_drives: int) -> list[tuple]:
    truths, by_window = drives.last_scan_queries(all_maps, name, seed, num_drives, (1, 3))
    _, points, labels, normals = next(m for m in all_maps if m[0] == name)
    rows = []
    for k, (own, foreign, capacity) in by_window.items():
        results = {}
        for margin in (None, 0.0):
            config = m2loc_config(3, query_capacity=capacity, ambiguity_margin=margin)
            triplet_map = build_map(points, labels, config, normals)
            results[margin] = (
                outcomes(triplet_map, own, capacity),
                outcomes(triplet_map, foreign, capacity),
            )
        row = [count(*results[None], truths, lambda o: o["valid"])]
        for margin in MARGINS:
            row.append(
                count(
                    *results[0.0],
                    truths,
                    lambda o, m=margin: o["valid"] and not o["rival"] >= o["fraction"] - m,
                )
            )
        rows.append((name, seed, k, row))
        print(rows[-1], file=sys.stderr, flush=True)
    return rows


def main() -> None:
    args = drives.development_parser(__doc__, "ambiguity.md").parse_args()
    rows = drives.rows_over_seeds_and_maps(args, rows_of)
    head = " | ".join(["without the check"] + [f"margin {m}" for m in MARGINS])
    lines = [
        "# The uniqueness check's margin on development drives",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_ambiguity.py --seeds "
        f"{' '.join(map(str, args.seeds))} --drives {args.drives}`",
        "",
        f"{args.drives} drives per map and seed; each cell: successes / wrong valid poses / false "
        "accepts (foreign drives), judged on the last scan (k = 1) or the fused window of the last "
        "3 scans (k = 3).",
        "",
        f"| map | seed | k | {head} |",
        "|---|---|---|" + "---|" * (1 + len(MARGINS)),
    ]
    for name, seed, k, cells in rows:
        text = " | ".join(f"{ok} / {wrong} / {false}" for ok, wrong, false in cells)
        lines.append(f"| {name} | {seed} | {k} | {text} |")
    totals = np.sum([cells for *_, cells in rows], axis=0)
    text = " | ".join(f"{ok} / {wrong} / {false}" for ok, wrong, false in totals)
    lines.append(f"| all | | | {text} |")
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
