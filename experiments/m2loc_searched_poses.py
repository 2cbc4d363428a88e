"""How well a pose found by the clique hypotheses verifies: right poses of true queries against
chance fits of foreign scans (development seeds only; the basis of ``hypothesis_min_fraction``).

The robust configuration runs with ``hypothesis_min_fraction`` 0.5 (the search keeps any pose that
verifies better than the maximum clique's and confirms ``hypothesis_min_support`` vertices) and
without the place check. A query counts as searched when its result differs from the same
configuration without hypotheses. True queries: DCC04 (the map where the search matters most),
Table I's generator, seeds 2000 and 3000. Foreign scans: those of ``m2loc_rejection.py --seed
2000`` and ``--seed 3000`` (scans of a similar dense world and of a sparse world, localized in a
dense map). The table counts the searched poses by verified fraction (a kept searched
pose verifies at least 0.5 here).

    JAX_PLATFORMS=cpu python experiments/m2loc_searched_poses.py
"""

from __future__ import annotations

import equinox as eqx
import numpy as np
from _atomic import write_text_atomic
from m2loc_losses import OUT, load_maps

from jaxloc.m2loc import build_map, localization_errors, localize_scan, m2loc_config
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

SEEDS = (2000, 3000)
BANDS = (0.5, 0.55, 0.6, 0.7, 1.01)


def maps(points, labels, normals):
    """The robust map without the place check, and the same map without hypotheses."""
    loose = dict(query_capacity=64, min_inlier_fraction=0.0, min_verified=0)
    searching = build_map(
        points, labels, m2loc_config(3, hypothesis_min_fraction=0.5, **loose), normals
    )
    plain = eqx.tree_at(lambda m: m.config, searching, m2loc_config(3, hypotheses=0, **loose))
    return searching, plain


def searched_fraction(searching, plain, query):
    """The verified fraction and pose of a searched query's result, or None if not searched."""
    result = localize_scan(searching, None, query.points, query.labels)
    before = localize_scan(plain, None, query.points, query.labels)
    if result.inlier_fraction == before.inlier_fraction:
        return None
    return result.inlier_fraction, result.pose


def true_queries() -> list[tuple[float, bool]]:
    _, points, labels, normals = next(load_maps(["DCC04"]))
    searching, plain = maps(points, labels, normals)
    found = []
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        for _ in range(200):
            q = make_query(points, labels, normals, rng, max_kept=25)
            if 3 <= len(q.points) <= 64 and (hit := searched_fraction(searching, plain, q)):
                rte, rre = localization_errors(hit[1], q.T_map_scan)
                found.append((hit[0], bool(rte < 7.5 and rre < 10.0)))
    return found


def foreign_scans() -> tuple[list[float], int]:
    """As ``m2loc_rejection.py --queries 120 --max-kept 25 --seed S``: the true queries are drawn
    (and skipped) so that the foreign scans are the same."""
    found, count = [], 0
    for seed in SEEDS:
        home = make_outdoor_world("dense", seed=seed + 1)
        searching, plain = maps(home.points, home.labels, home.road_normals)
        rng = np.random.default_rng(seed)
        for _ in range(120):
            make_query(home.points, home.labels, home.road_normals, rng, max_kept=25)
        for kind, world_seed in (("dense", seed + 2), ("sparse", seed + 3)):
            world = make_outdoor_world(kind, seed=world_seed)
            for _ in range(120):
                q = make_query(world.points, world.labels, world.road_normals, rng, max_kept=25)
                if not 3 <= len(q.points) <= 64:
                    continue
                count += 1
                if hit := searched_fraction(searching, plain, q):
                    found.append(hit[0])
    return found, count


def main() -> None:
    true = true_queries()
    foreign, scans = foreign_scans()
    lines = [
        "# Searched poses: right poses vs chance fits, by verified fraction",
        "",
        "Command: `JAX_PLATFORMS=cpu python experiments/m2loc_searched_poses.py` (development "
        f"seeds {SEEDS}; {2 * 200} DCC04 queries, {scans} foreign scans).",
        "",
        "| verified fraction | DCC04 searched, right | DCC04 searched, wrong | foreign searched |",
        "|---|---|---|---|",
    ]
    for low, high in zip(BANDS[:-1], BANDS[1:], strict=True):
        right = sum(low <= f < high and ok for f, ok in true)
        wrong = sum(low <= f < high and not ok for f, ok in true)
        chance = sum(low <= f < high for f in foreign)
        band = f"[{low:.2f}, 1.00]" if high > 1.0 else f"[{low:.2f}, {high:.2f})"
        lines.append(f"| {band} | {right} | {wrong} | {chance} |")
    write_text_atomic(OUT / "searched_poses.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
