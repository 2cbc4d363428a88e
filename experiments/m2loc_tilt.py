"""Would a bound on a pose's tilt refuse the wrong single-scan poses of the drives?

On the drives of ``m2loc_drives.py`` (same generator and odometry noise), judged on each drive's
last scan, this script localizes the single scan with the robust default and, for every valid
pose, measures the angle between the scan's up axis in the map (``T_map_scan[:3, 2]``) and the
normal of the map's nearest road-surface cell, beside the same angle of the true pose. A tilt
bound could refuse a wrong pose only if right poses stay well below it.

    JAX_PLATFORMS=cpu python experiments/m2loc_tilt.py --seeds 2000 3000 4000
"""

from __future__ import annotations

import m2loc_drives as drives
import numpy as np
from _atomic import write_text_atomic

from jaxloc.m2loc import build_map, localization_errors, localize_scan, m2loc_config


def tilt_deg(T_map_scan: np.ndarray, rsn_xy: np.ndarray, rsn_normals: np.ndarray) -> float:
    """Degrees between the scan's up axis and the normal of the road cell nearest the scan."""
    cell = np.argmin(np.sum((rsn_xy - T_map_scan[:2, 3]) ** 2, axis=1))
    normal = rsn_normals[cell] / np.linalg.norm(rsn_normals[cell])
    return float(np.degrees(np.arccos(min(abs(T_map_scan[:3, 2] @ normal), 1.0))))


def rows_of(seed: int, name: str, all_maps: list, num_drives: int) -> list[tuple]:
    """(map, seed, RTE, RRE, tilt, true tilt) of every valid single-scan pose."""
    truths, by_window = drives.last_scan_queries(all_maps, name, seed, num_drives, (1,))
    own, _, capacity = by_window[1]
    _, points, labels, normals = next(m for m in all_maps if m[0] == name)
    triplet_map = build_map(points, labels, m2loc_config(3, query_capacity=capacity), normals)
    cells = np.asarray(triplet_map.rsn_xy), np.asarray(triplet_map.rsn_normals)
    rows = []
    for query, truth in zip(own, truths, strict=True):
        result = localize_scan(triplet_map, None, *query)
        if result.valid:
            rte, rre = localization_errors(result.pose, truth)
            rows.append(
                (name, seed, float(rte), float(rre), tilt_deg(result.pose, *cells),
                 tilt_deg(truth, *cells))
            )  # fmt: skip
    return rows


def main() -> None:
    args = drives.development_parser(__doc__, "tilt.md").parse_args()
    rows = drives.rows_over_seeds_and_maps(args, rows_of)
    right = [r for r in rows if r[2] < drives.SUCCESS_RTE_M and r[3] < drives.SUCCESS_RRE_DEG]
    wrong = [r for r in rows if r not in right]
    tilts = np.array([r[4] for r in right])
    lines = [
        "# The tilt of single-scan poses on the drives",
        "",
        f"Command: `JAX_PLATFORMS=cpu python experiments/m2loc_tilt.py --seeds "
        f"{' '.join(map(str, args.seeds))} --drives {args.drives}`",
        "",
        f"Robust default, the last scan of {args.drives} drives per map and seed: {len(rows)} "
        f"valid poses, {len(right)} right (RTE < 7.5 m, RRE < 10 deg), {len(wrong)} wrong. Tilt: "
        "degrees between the scan's up axis and the nearest road cell's normal.",
        "",
        "Right poses' tilt, percentiles 50 / 90 / 99 / max: "
        + " / ".join(f"{v:.2f}" for v in np.percentile(tilts, [50, 90, 99, 100]))
        + f"; their true poses' tilt at most {max(r[5] for r in right):.2f}.",
        "",
        "| wrong pose: map | seed | RTE m | RRE deg | tilt deg | true tilt deg |",
        "|---|---|---|---|---|---|",
    ]
    lines += [f"| {r[0]} | {r[1]} | " + " | ".join(f"{v:.2f}" for v in r[2:]) + " |" for r in wrong]
    write_text_atomic(args.out, "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
