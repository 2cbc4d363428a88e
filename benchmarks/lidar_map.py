"""LiDAR map costs: describing the four real HeLiPR instance maps (M2Loc, 3 scales), saving and
loading the described maps, and building a map from a labelled sequence.

Wall time (what a user waits for) with process CPU time beside it, and the peak RSS of the
process. Describing is timed twice per map: the first call includes the compilations of the
descriptor kernel's neighbour-capacity buckets that earlier maps did not already need; the second
is warm. Loading a saved map is compared with describing the map again (the same process, the
same map), as a ratio.

    python benchmarks/lidar_map.py [--maps DCC04 KAIST04 ...] [--scans 90] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from jaxloc.io import load_triplet_map, read_instance_map, read_road_normals, save_triplet_map
from jaxloc.io.lidar_sequence import open_lidar_sequence
from jaxloc.m2loc import RoadNormals, build_map, m2loc_config
from jaxloc.mapping import MapBuildConfig, build_lidar_maps
from jaxloc.synthetic.lidar_scans import make_lidar_sequence, write_semantickitti_sequence
from jaxloc.synthetic.outdoor import make_outdoor_world

MAPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "helipr_instance_maps"


def timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    value = fn()
    return value, time.perf_counter() - wall, time.process_time() - cpu


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def read_map(name: str):
    """Instances and RSN cells of a shared map, or of several joined with "+" (each shifted 10 km
    east of the previous one): a stand-in for the 10-15k-instance maps of longer drives."""
    parts = name.split("+")
    points, labels, xy, normals, std = [], [], [], [], []
    for shift, part in enumerate(parts):
        instances, cells = read_instance_map(MAPS / part), read_road_normals(MAPS / part)
        offset = np.array([10_000.0 * shift, 0.0, 0.0])
        points.append(instances.points + offset)
        labels.append(instances.labels)
        xy.append(cells.xy + offset[:2])
        normals.append(cells.normals)
        std.append(cells.std_deg)
    cat = np.concatenate
    return (cat(points), cat(labels)), RoadNormals(cat(xy), cat(normals), cat(std))


def describe_rows(names: list[str], folder: Path) -> list[str]:
    rows = [
        "| map | instances | describe, first (s wall / CPU) | describe, warm (s wall / CPU) | "
        "save (s) | file (MB) | load (s wall) | describe / load |",
        "|---|---|---|---|---|---|---|---|",
    ]
    config = m2loc_config(3)
    for name in names:
        (points, labels), normals = read_map(name)

        def describe(points=points, labels=labels, normals=normals):
            return build_map(points, labels, config, normals)

        _, first_wall, first_cpu = timed(describe)
        described, warm_wall, warm_cpu = timed(describe)
        path = folder / f"{name.replace('+', '_')}.npz"
        _, save_wall, _ = timed(
            lambda described=described, path=path: save_triplet_map(described, path)
        )
        loaded, load_wall, _ = timed(lambda path=path: load_triplet_map(path))
        for a, b in zip(jax.tree.leaves(described), jax.tree.leaves(loaded), strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b)), name
        rows.append(
            f"| {name} | {len(points)} | {first_wall:.2f} / {first_cpu:.2f} | "
            f"{warm_wall:.2f} / {warm_cpu:.2f} | {save_wall:.2f} | "
            f"{path.stat().st_size / 1e6:.1f} | {load_wall:.2f} | {warm_wall / load_wall:.0f}x |"
        )
        print(rows[-1], flush=True)
    return rows


def sequence_rows(num_scans: int, folder: Path) -> list[str]:
    world = make_outdoor_world("dense", seed=0, blocks=3, bridge_length=0)
    scans = make_lidar_sequence(world, (10.0, 200.0), (590.0, 200.0), num_scans, max_range=80.0)
    write_semantickitti_sequence(folder / "sequence", scans)
    points = int(np.mean([len(p) for p in scans.points]))
    sequence = open_lidar_sequence(folder / "sequence")
    maps, wall, cpu = timed(lambda: build_lidar_maps(sequence, MapBuildConfig(every=1)))
    return [
        "",
        f"Map from a synthetic SemanticKITTI sequence: {num_scans} scans of ~{points} points "
        f"(80 m range), every scan used: {wall:.2f} s wall / {cpu:.2f} s CPU "
        f"({1e3 * wall / num_scans:.0f} ms per scan), {len(maps.instances.points)} instances, "
        f"{len(maps.road_normals.xy)} road-normal cells.",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--maps",
        nargs="+",
        default=["DCC04", "KAIST04", "Riverside04", "Town01", "DCC04+Town01"],
        help='shared maps; "A+B" joins maps (default: the four and DCC04+Town01, 14.4k)',
    )
    parser.add_argument("--scans", type=int, default=90, help="synthetic sequence length")
    parser.add_argument("--out", type=Path, help="also write the report to this file")
    args = parser.parse_args()
    if not MAPS.is_dir():
        sys.exit(f"no maps at {MAPS}")
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        rows = describe_rows(args.maps, Path(tmp))
        rows += sequence_rows(args.scans, Path(tmp))
    load_after = os.getloadavg()
    rows += [
        "",
        f"Peak RSS {peak_rss_mib():.0f} MiB; {os.cpu_count()} CPUs; load average (1 min) "
        f"{load_before[0]:.2f} before, {load_after[0]:.2f} after; jax {jax.__version__} on "
        f"{jax.default_backend()}.",
    ]
    report = "\n".join(rows)
    print(report)
    if args.out is not None:
        args.out.write_text(report + "\n")


if __name__ == "__main__":
    main()
