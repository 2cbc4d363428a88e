"""Reading LiDAR scans from a ROS bag against localizing them: time per scan and peak memory.

Writes a ROS 2 MCAP bag (``rosbags``' writer, as the tests write theirs) of ``--scans`` labelled
``sensor_msgs/PointCloud2`` clouds of ``--points`` points each (x, y, z, intensity float32 and a
uint32 ``label``: 20 bytes a point; the defaults, 800 x 130,000 points, make a 2.1 GB bag) with
``nav_msgs/Odometry``. The clouds cycle through ``--distinct`` scans simulated on a synthetic
city block (``jaxloc.synthetic.lidar_scans``), padded with road points to ``--points``. Then, in
this one process:

* **read**: ``jaxloc.io.open_lidar_recording(bag)`` and every scan's points and labels
  (``recording.scan(i)``), the whole bag, scan by scan;
* **localize**: ``jaxloc.m2loc.localize_drive(map, recording, accumulate=3,
  odometry=recording.odometry)`` over the first ``--drive`` scans (reading, clustering, the
  fused queries) over every k-th scan, about ``--drive`` of them, timed on a second run (the
  first compiles the query programs).

Prints the read time per scan, the drive's time per scan, their ratio, and the process's peak
resident memory (``VmHWM``) after reading the whole bag and after the drive.

    python benchmarks/rosbag_read.py [--scans 800] [--points 130000] [--drive 40] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import jax  # noqa: E402
from _rosbag_fixtures import BagWriter, bag_path, packed_records  # noqa: E402

from jaxloc.io import open_lidar_recording  # noqa: E402
from jaxloc.m2loc import build_map, localize_drive, m2loc_config  # noqa: E402
from jaxloc.synthetic.lidar_scans import make_lidar_sequence  # noqa: E402
from jaxloc.synthetic.outdoor import make_outdoor_world  # noqa: E402

FIRST_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000  # 10 Hz


def peak_rss_gib() -> float:
    """The process's peak resident memory so far (VmHWM), GiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 2**20
    return float("nan")


def write_bag(folder: Path, args) -> tuple[Path, object]:
    """The bag (see the module docstring) and the synthetic world its scans see."""
    world = make_outdoor_world("dense", seed=4, blocks=1, bridge_length=0)
    scans = make_lidar_sequence(world, (20.0, 0.0), (180.0, 0.0), args.distinct, seed=5)
    rng = np.random.default_rng(0)
    clouds = []
    for points, raw in zip(scans.points, scans.raw_labels, strict=True):
        extra = max(args.points - len(points), 0)
        road = np.column_stack(
            [rng.uniform(-40, 40, (extra, 2)), rng.normal(-1.8, 0.02, extra)]
        ).astype(np.float32)
        road_raw = np.full(extra, 40, np.uint32)  # SemanticKITTI "road"
        cloud = np.concatenate([points, road]), np.concatenate([raw, road_raw])
        clouds.append(packed_records(*cloud))
    path = bag_path(folder, "mcap")
    with BagWriter(path, "mcap") as bag:
        for i in range(args.scans):
            k = i % args.distinct
            stamp = FIRST_NS + i * PERIOD_NS
            bag.cloud("/points", stamp, clouds[k])
            bag.odometry("/odom", stamp, scans.T_map_scan[k])
    return path, world


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", type=int, default=800, help="clouds in the bag")
    parser.add_argument("--points", type=int, default=130_000, help="points per cloud")
    parser.add_argument("--distinct", type=int, default=8, help="distinct simulated scans")
    parser.add_argument("--drive", type=int, default=40, help="scans localized")
    parser.add_argument("--keep", type=Path, help="write the bag here (default: a temp folder)")
    args = parser.parse_args(argv)
    folder = Path(tempfile.mkdtemp()) if args.keep is None else args.keep
    folder.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    path, world = write_bag(folder, args)
    files = list(path.rglob("*")) if path.is_dir() else [path]
    size = sum(f.stat().st_size for f in files)
    print(f"bag: {path}, {size / 1e9:.2f} GB, {args.scans} clouds of {args.points} points, "
          f"written in {time.perf_counter() - start:.1f} s")  # fmt: skip

    start = time.perf_counter()
    recording = open_lidar_recording(path)
    open_s = time.perf_counter() - start
    start = time.perf_counter()
    for i in range(len(recording)):
        recording.scan(i)
    read_s = time.perf_counter() - start
    read_peak = peak_rss_gib()
    per_read = (open_s + read_s) / len(recording)

    config = m2loc_config(3)
    triplet_map = build_map(world.points, world.labels, config, world.road_normals)
    drive_rec = open_lidar_recording(path, every=max(1, len(recording) // args.drive))
    odometry = drive_rec.odometry
    localize_drive(triplet_map, drive_rec, accumulate=3, odometry=odometry)  # compiles
    start = time.perf_counter()
    result = localize_drive(triplet_map, drive_rec, accumulate=3, odometry=odometry)
    drive_s = time.perf_counter() - start
    per_drive = drive_s / len(drive_rec)
    print(f"read: open {open_s:.2f} s + {read_s:.1f} s for {len(recording)} scans = "
          f"{per_read * 1e3:.1f} ms/scan; peak RSS after reading {read_peak:.2f} GiB")  # fmt: skip
    print(f"localize_drive (accumulate 3, bag odometry), {len(drive_rec)} scans: "
          f"{per_drive * 1e3:.1f} ms/scan, {int(np.sum(result.valid))} valid")  # fmt: skip
    print(
        f"read / localize per scan: {per_read / per_drive:.1%}; peak RSS {peak_rss_gib():.2f} GiB"
    )
    print(f"jax {jax.__version__}, {jax.devices()[0]}, {os.cpu_count()} CPUs, load average "
          f"{os.getloadavg()[0]:.1f}, python {platform.python_version()}")  # fmt: skip


if __name__ == "__main__":
    main()
