"""Parameter sweeps: configurations per second, compilations, peak memory and memory mappings of
a sweep over traced settings, for M2Loc and SG2Loc, each way a user can run one, beside a baseline
checkout of jaxloc (an older commit: ``git worktree add /tmp/jaxloc-base <commit>``) in the same
run.

    python benchmarks/sweeps.py [--baseline /tmp/jaxloc-base] [--method m2loc sg2loc]
        [--m2loc-configs 24] [--m2loc-queries 5] [--sg2loc-configs 6] [--modes config lax.map]

Each row runs in a fresh process (``JAXLOC_NO_CACHE=1``, nothing in JAX's persistent cache:
``JAX_COMPILATION_CACHE_DIR`` unset), so compilations and memory are the row's own:

* M2Loc on the HeLiPR map KAIST04 (``../shared/data``; the synthetic dense world without it):
  ``consistency_threshold`` x ``min_inlier_fraction`` grids, the same scan-like queries for each.
  ``rebuild``: the map described again per configuration and every query localized
  (``build_map`` + ``localize_scan``: the only way before query settings were traced; runs in
  both checkouts); ``config=``: one map, ``localize_scan(..., config=c)``; ``lax.map``: one jitted
  ``jax.lax.map`` of :func:`jaxloc.m2loc.query` over the stacked configurations and the scans;
  ``vmap``: ``jax.vmap`` over the stacked configurations (and the scans).
* SG2Loc on a synthetic episode (160x90, 500 particles, strides 10 and 8, 5 frames):
  configurations differing in sigma, lambda_depth, the heights' values and the verdict's bounds.
  ``loop``: ``localize`` per configuration; ``jit``: one ``jax.jit`` of ``localize`` called per
  configuration; ``vmap``: ``jax.vmap`` of it over the stacked configurations.

Columns: wall time of the whole sweep and its first configuration (compilation included), the
time per configuration after the first, XLA compilations (``jax.monitoring``), peak RSS, and the
process's memory mappings before and after the sweep.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "helipr_instance_maps"


def _mappings() -> int:
    with open("/proc/self/maps", "rb") as maps:
        return maps.read().count(b"\n")


def _peak_rss_gib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2


# ---------------------------------------------------------------------------------------- M2Loc


def _m2loc_inputs(count: int, queries: int):
    import numpy as np

    from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

    if (DATA / "KAIST04").is_dir():
        from jaxloc.io import read_instance_map, read_road_normals

        instances = read_instance_map(DATA / "KAIST04")
        points, labels = instances.points, instances.labels
        normals = read_road_normals(DATA / "KAIST04")
        source = "KAIST04"
    else:
        world = make_outdoor_world("dense", seed=1000, blocks=3)
        points, labels, normals, source = (
            world.points,
            world.labels,
            world.road_normals,
            "synthetic",
        )
    rng = np.random.default_rng(1000)
    found = []
    while len(found) < queries:
        q = make_query(points, labels, normals, rng, max_kept=48)
        if len(q.points) <= 64:
            found.append(q)
    fractions = np.linspace(0.3, 0.9, 4) if count >= 4 else np.array([0.5])
    thresholds = np.linspace(0.5, 2.0, -(-count // len(fractions)))
    grid = [(float(t), float(f)) for t in thresholds for f in fractions][:count]
    return points, labels, normals, found, grid, source


def _m2loc_worker(mode: str, count: int, queries: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxloc.m2loc import build_map, localize_scan, m2loc_config

    points, labels, normals, found, grid, source = _m2loc_inputs(count, queries)

    def config(threshold, fraction):
        return m2loc_config(
            3, consistency_threshold=threshold, min_inlier_fraction=fraction, query_capacity=64
        )

    configs = [config(t, f) for t, f in grid]
    times, valid = [], []
    maps_before = _mappings()
    start = time.perf_counter()
    if mode == "rebuild":
        for c in configs:
            t = time.perf_counter()
            triplet_map = build_map(points, labels, c, normals)
            valid.append([bool(localize_scan(triplet_map, None, q.points, q.labels).valid)
                          for q in found])  # fmt: skip
            times.append(time.perf_counter() - t)
    elif mode == "config":
        triplet_map = build_map(points, labels, configs[0], normals)
        for c in configs:
            t = time.perf_counter()
            valid.append([bool(localize_scan(triplet_map, None, q.points, q.labels, config=c).valid)
                          for q in found])  # fmt: skip
            times.append(time.perf_counter() - t)
    else:
        from jaxloc.m2loc import pad_scan, query

        triplet_map = build_map(points, labels, configs[0], normals)
        scans = [pad_scan(q.points, q.labels, configs[0], 64) for q in found]
        scans = jax.tree.map(lambda *x: np.stack(x), *scans)
        stacked = jax.tree.map(lambda *x: jnp.stack(x), *configs)
        if mode == "lax.map":

            def sweep(m, s, c):
                return jax.lax.map(lambda cc: jax.lax.map(lambda ss: query(m, ss, cc), s), c)
        else:

            def sweep(m, s, c):
                over_scans = jax.vmap(query, in_axes=(None, 0, None))
                return jax.vmap(over_scans, in_axes=(None, None, 0))(m, s, c)

        out, times = _first_and_again(jax.jit(sweep), (triplet_map, scans, stacked), len(configs))
        valid = np.asarray(out.valid).tolist()
    return dict(
        _timing(times, start, maps_before),
        source=source,
        configs=len(configs),
        queries=len(found),
        valid=valid,
    )


# --------------------------------------------------------------------------------------- SG2Loc


def _sg2loc_inputs(count: int):
    """A 5-frame synthetic episode (160x90) and ``count`` configurations of 500 particles, strides
    10 and 8, that differ in traced settings only (the baseline's heights were static)."""
    import numpy as np

    from jaxloc.sg2loc import ObservationConfig, SG2LocConfig, VerdictConfig
    from jaxloc.synthetic.indoor import EpisodeConfig, SensorConfig, make_episode

    episode = make_episode(1000, 5, EpisodeConfig(sensor=SensorConfig(width=160, height=90)))
    configs = [
        SG2LocConfig(
            capacity=500,
            strides=(10, 8),
            box_half_widths=(0.8,),
            observation=ObservationConfig(sigma=sigma, lambda_depth=1.5 + 0.25 * (i % 3)),
            heights=tuple(h + 0.05 * (i % 2) for h in (1.5, 1.6, 1.7, 1.8)),
            verdict=VerdictConfig(max_spread_z=0.05 + 0.01 * i),
        )
        for i, sigma in enumerate(np.linspace(0.4, 0.8, count))
    ]
    return episode, configs


def _sg2loc_worker(mode: str, count: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxloc.sg2loc import localize

    episode, configs = _sg2loc_inputs(count)
    scene, sequence = episode.scene, episode.sequence
    key = jax.random.key(0)
    times, poses = [], []
    maps_before = _mappings()
    start = time.perf_counter()
    if mode in ("loop", "jit"):
        run = localize if mode == "loop" else jax.jit(lambda k, c: localize(k, scene, sequence, c))
        for c in configs:
            t = time.perf_counter()
            result = run(key, scene, sequence, c) if mode == "loop" else run(key, c)
            poses.append(np.asarray(jax.block_until_ready(result.poses)).tolist())
            times.append(time.perf_counter() - t)
    else:
        stacked = jax.tree.map(lambda *x: jnp.stack(x), *configs)
        run = jax.jit(jax.vmap(lambda c: localize(key, scene, sequence, c).poses))
        out, times = _first_and_again(run, (stacked,), len(configs))
        poses = np.asarray(out).tolist()
    return dict(_timing(times, start, maps_before), configs=len(configs), poses=poses)


def _first_and_again(run, args: tuple, count: int):
    """A batched sweep run twice: its output and per-configuration times (the first call's,
    compilation included, then the second call's divided over the ``count`` configurations)."""
    import jax

    t = time.perf_counter()
    jax.block_until_ready(run(*args))
    first = time.perf_counter() - t
    t = time.perf_counter()
    out = jax.block_until_ready(run(*args))
    return out, [first] + [(time.perf_counter() - t) / count] * (count - 1)


def _timing(times: list[float], start: float, maps_before: int) -> dict:
    import numpy as np

    return {
        "wall_s": time.perf_counter() - start,
        "first_s": times[0],
        "per_config_s": float(np.median(times[1:])) if len(times) > 1 else float("nan"),
        "maps_before": maps_before,
    }


# ------------------------------------------------------------------------------------- the runs


def _worker(args) -> None:
    import jax

    compiled = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **_: (
            compiled.append(seconds)
            if event == "/jax/core/compile/backend_compile_duration"
            else None
        )
    )
    method, mode = args.worker
    if method == "m2loc":
        row = _m2loc_worker(mode, args.m2loc_configs, args.m2loc_queries)
    else:
        row = _sg2loc_worker(mode, args.sg2loc_configs)
    import jaxloc

    row.update(
        jaxloc=str(Path(jaxloc.__file__).parent),
        compilations=len(compiled),
        compile_s=sum(compiled),
        peak_rss_gib=_peak_rss_gib(),
        maps_after=_mappings(),
    )
    print("RESULT " + json.dumps(row))


def _run(method: str, mode: str, args, tree: Path) -> dict | None:
    env = dict(os.environ, JAXLOC_NO_CACHE="1", PYTHONPATH=str(tree))
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--worker",
        method,
        mode,
        "--m2loc-configs",
        str(args.m2loc_configs),
        "--m2loc-queries",
        str(args.m2loc_queries),
        "--sg2loc-configs",
        str(args.sg2loc_configs),
    ]
    done = subprocess.run(command, env=env, capture_output=True, text=True, cwd=tree)
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if done.returncode != 0 or not lines:
        print(f"  {method} {mode} ({tree}) failed:\n{done.stderr[-2000:]}", file=sys.stderr)
        return None
    return json.loads(lines[-1][len("RESULT ") :])


def _print(label: str, row: dict | None) -> None:
    if row is None:
        print(f"| {label} | failed | | | | | |")
        return
    print(
        f"| {label} | {row['wall_s']:.1f} | {row['first_s']:.1f} | {row['per_config_s']:.3f} | "
        f"{row['compilations']} ({row['compile_s']:.1f} s) | {row['peak_rss_gib']:.2f} | "
        f"{row['maps_before']} -> {row['maps_after']} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, help="an older jaxloc checkout to run beside")
    parser.add_argument("--method", nargs="+", default=["m2loc", "sg2loc"])
    parser.add_argument("--m2loc-configs", type=int, default=24)
    parser.add_argument("--m2loc-queries", type=int, default=5)
    parser.add_argument("--sg2loc-configs", type=int, default=6)
    parser.add_argument(
        "--modes",
        nargs="+",
        default=["rebuild", "config", "lax.map", "vmap", "loop", "jit"],
        help="the rows to run (M2Loc: rebuild config lax.map vmap; SG2Loc: loop jit vmap)",
    )
    parser.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        _worker(args)
        return
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {os.getloadavg()}")
    rows = {}
    tables = {
        "m2loc": (f"M2Loc: {args.m2loc_configs} configurations x {args.m2loc_queries} queries",
                  ["rebuild", "config", "lax.map", "vmap"]),
        "sg2loc": (f"SG2Loc: {args.sg2loc_configs} configurations", ["loop", "jit", "vmap"]),
    }  # fmt: skip
    for method in args.method:
        title, modes = tables[method]
        print(f"\n{title}\n")
        print(
            "| run | sweep s | first config s | s / config after | compilations | peak RSS GiB "
            "| mappings |\n|---|---|---|---|---|---|---|"
        )
        runs = [(modes[0], args.baseline)] if args.baseline else []
        for mode, tree in runs + [(mode, ROOT) for mode in modes]:
            if mode in args.modes:
                label = f"{mode} ({'baseline' if tree != ROOT else 'this checkout'})"
                rows[(method, label)] = row = _run(method, mode, args, tree)
                _print(label, row)
    _agreement(rows)
    print(f"\nload after: {os.getloadavg()}")


def _agreement(rows: dict) -> None:
    """Whether the ways of running a sweep gave the same flags (M2Loc) and poses (SG2Loc)."""
    import numpy as np

    m2 = [r["valid"] for (method, _), r in rows.items() if method == "m2loc" and r]
    if len(m2) > 1:
        same = all(np.array_equal(np.asarray(m2[0]), np.asarray(v)) for v in m2[1:])
        print(f"\nM2Loc valid flags equal across the runs: {same}")
    sg = [np.asarray(r["poses"]) for (method, _), r in rows.items() if method == "sg2loc" and r]
    if len(sg) > 1:
        gap = max(float(np.max(np.abs(sg[0] - p))) for p in sg[1:])
        print(f"SG2Loc poses: largest difference across the runs {gap:.2e}")


if __name__ == "__main__":
    main()
