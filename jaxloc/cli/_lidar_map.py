"""``jaxloc build-lidar-map``: instance and road-normal maps from a labelled sequence or bag."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from jaxloc.cli._errors import InputError, reading
from jaxloc.cli._lidar import add_triplet_options, check_save_path, describe_map, triplet_config
from jaxloc.cli._lidar_scans import BAG_OPTIONS, add_sequence_options, note_sequences
from jaxloc.cli._options import command, positive_int

DESCRIPTION = """\
Instance and road-normal maps from a labelled LiDAR sequence (SemanticKITTI, plain, HeLiPR) or
a ROS bag of labelled clouds (ROS 1 .bag, ROS 2 bag folder, .mcap).

TripletLoc's way (jaxloc.mapping.MapBuildConfig): trunk, pole and traffic-sign points of every
K-th scan clustered into instances fused across scans; a robust road plane per cell.

SEQ_DIR is a labelled sequence in one of three layouts (detected; --format forces one):
SemanticKITTI (the map frame: the velodyne frame of the first scan, T_map_scan = inv(Tr) P Tr)
  SEQ_DIR/velodyne/NNNNNN.bin   float32 x y z intensity (sensor frame)
  SEQ_DIR/labels/NNNNNN.label   uint32: semantic id in the low 16 bits (71 trunk, 80 pole,
                                81 traffic sign, 40 road), instance in the high 16 bits
  SEQ_DIR/poses.txt             one cam0 pose per scan, 12 numbers (KITTI 3x4, row-major)
  SEQ_DIR/calib.txt             "Tr: 12 numbers" (velodyne to cam0)
plain: NNN.bin with NNN.label beside them (or velodyne/ + labels/), poses.txt of T_map_scan rows
  (12 or 16 numbers; or TUM lines matched by time with times.txt), no calib.txt
HeLiPR / TripletLoc (the map frame: the GT's world frame; scans without a GT stamp left out)
  SEQ_DIR/LiDAR/<sensor>/<stamp>.bin   Ouster, Velodyne, Avia, Aeva or Ouster_filterd records
  SEQ_DIR/labels/<stamp>.label         uint16 class id (15 trunk, 17 pole, 18 sign) + instance
  SEQ_DIR/LiDAR_GT/<Sensor>_gt.txt     lines "stamp x y z qx qy qz qw"
a bag (the map frame: its poses' frame): labelled sensor_msgs/PointCloud2 as localize-lidar reads
  them, placed by --gt FILE or --gt-topic TOPIC, else by the bag's odometry (--odometry-topic)

OUT_DIR receives instances/15.txt, 17.txt, 18.txt (lines "id x y z") and RSN/road_normal.txt
(lines "x y nx ny nz std_deg"), the format localize-lidar reads; nothing unless all succeeds.
"""

EPILOG = """\
examples:
  jaxloc build-lidar-map dataset/sequences/00 maps/kitti00
  jaxloc build-lidar-map dataset/sequences/00 maps/kitti00 --every 10 --save-map kitti00.npz
  jaxloc localize-lidar maps/kitti00 dataset/sequences/00 --every 50
  jaxloc build-lidar-map HeLiPR/KAIST04 maps/KAIST04 --sensor Ouster --every 30
  jaxloc build-lidar-map drive.mcap maps/drive --gt slam.tum --every 10

--save-map FILE also describes the built map (m2loc_config's settings, or the localization
settings given) and saves it: localize-lidar then loads it in a second instead of describing it.
"""


def add_parser(commands) -> None:
    """Register ``build-lidar-map`` on the ``jaxloc`` subcommand parsers."""
    build = command(commands, "build-lidar-map", DESCRIPTION, EPILOG)
    build.add_argument("seq_dir", type=Path, metavar="SEQ_DIR", help="labelled sequence or bag")
    build.add_argument("out_dir", type=Path, metavar="OUT_DIR", help="map folder to write")
    build.add_argument(
        "--every", type=positive_int, help="use every K-th scan (default MapBuildConfig.every)"
    )
    build.add_argument("--save-map", type=Path, metavar="FILE", help="also save it described")
    build.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_sequence_options(build)
    build.add_argument("--gt", type=Path, metavar="FILE", help="a pose file of poses")
    BAG_OPTIONS.add(build, "a bag SEQ_DIR (defaults: the bag's)")
    add_triplet_options(build)


def check_build_lidar_map(args: argparse.Namespace) -> None:
    """Before any work: ``SEQ_DIR`` exists, ``--save-map`` names an ``.npz``, ``OUT_DIR`` is not a
    file."""
    check_save_path(args.save_map)
    if not args.seq_dir.exists():
        raise InputError(f"{args.seq_dir}: no such sequence folder or bag")
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise InputError(f"{args.out_dir}: exists and is not a folder")


def run_build_lidar_map(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from jaxloc import io
    from jaxloc.io import save_triplet_map, write_instance_maps
    from jaxloc.mapping import MapBuildConfig, build_lidar_maps

    start = time.perf_counter()
    with reading():
        scans = io.open_lidar_recording(args.seq_dir, layout=args.format, sensor=args.sensor,
                                        gt=args.gt, **BAG_OPTIONS.values(args))  # fmt: skip
    note_sequences(args, scans.sequences)
    config = MapBuildConfig() if args.every is None else MapBuildConfig(every=args.every)
    with reading(), tqdm(total=len(scans), unit="scan", disable=args.no_progress) as bar:
        maps = build_lidar_maps(scans, config, lambda n: bar.update(n * config.every))
    used = len(maps.scans_used)
    instances, normals = maps.instances, maps.road_normals
    triplet_map = None
    if args.save_map is not None:  # describe before writing anything: a bad map writes nothing
        config = triplet_config(args)
        triplet_map = describe_map(
            instances.points, instances.labels, config, normals, "built", args.command
        )
    write_instance_maps(args.out_dir, instances, normals)
    if triplet_map is not None:
        save_triplet_map(triplet_map, args.save_map)
    counts = ", ".join(
        f"{int(np.sum(instances.labels == c))} x {c}" for c in sorted(set(instances.labels))
    )
    placed = "ground truth" if scans.poses is not None else "odometry"
    seq = scans.sequences[0] if scans.sequences else None
    layout = f"{scans.bag.topic}, placed by its {placed}" if scans.bag else seq.layout
    print(
        f"{args.seq_dir} ({layout}{f', {seq.sensor}' if seq and seq.sensor else ''}): {used} of "
        f"{len(scans)} scans used -> "
        f"{len(instances.points)} instances ({counts}), {len(normals.xy)} road-normal cells, "
        f"in {time.perf_counter() - start:.1f} s; wrote {args.out_dir}/instances/*.txt and "
        f"{args.out_dir}/RSN/road_normal.txt" + (f" and {args.save_map}" if args.save_map else "")
    )
    return 0
