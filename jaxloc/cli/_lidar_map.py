"""``jaxloc build-lidar-map``: instance and road-normal maps from a labelled LiDAR sequence."""

from __future__ import annotations

import argparse
import time

import numpy as np

from jaxloc.cli._errors import InputError
from jaxloc.cli._lidar import check_save_path, describe_map, triplet_config
from jaxloc.cli._lidar_scans import open_sequence, reading

DESCRIPTION = """\
Builds a TripletLoc/HeLiPR-format instance map and road-surface-normal map from a labelled
LiDAR sequence, TripletLoc's way: every K-th scan, trunk/pole/traffic-sign points clustered
into instance centroids (0.1 m voxels, 0.5 m clusters of >= 20 voxels), moved to the map frame
and fused across scans within 0.5 m; road points binned into 10 m cells (within 80 m of the
sensor), a robust plane per cell, cells fused within 3.5 m.

SEQ_DIR is a labelled sequence in one of three layouts (detected; --format forces one).
A SemanticKITTI sequence:
  SEQ_DIR/velodyne/NNNNNN.bin   float32 x y z intensity (sensor frame)
  SEQ_DIR/labels/NNNNNN.label   uint32: semantic id in the low 16 bits (71 trunk, 80 pole,
                                81 traffic sign, 40 road), instance in the high 16 bits
  SEQ_DIR/poses.txt             one cam0 pose per scan, 12 numbers (KITTI 3x4, row-major)
  SEQ_DIR/calib.txt             "Tr: 12 numbers" (velodyne to cam0; P0-P3 lines are ignored)
The map frame is then the velodyne frame of the first scan: T_map_scan = inv(Tr) P Tr.
Or a plain folder: NNN.bin with NNN.label beside them (or velodyne/ + labels/) and a poses.txt of
T_map_scan rows (12 or 16 numbers), no calib.txt. Scans sort by number (0, 11, 102); line i of
poses.txt belongs to the i-th scan. Either may have times.txt (seconds per scan, KITTI's) and a
TUM poses.txt ("t x y z qx qy qz qw"), matched to the scans by time.
Or a HeLiPR / TripletLoc sequence:
  SEQ_DIR/LiDAR/<sensor>/<stamp>.bin   Ouster (26-byte points), Velodyne (22), Avia (19), Aeva
                                       (25 or 29) or TripletLoc's Ouster_filterd; <stamp> in ns
  SEQ_DIR/labels/<stamp>.label         uint16 SPVNAS class id (8 road, 15 trunk, 17 pole,
                                       18 traffic sign) + uint16 instance per point (or label/)
  SEQ_DIR/LiDAR_GT/<Sensor>_gt.txt     lines "stamp x y z qx qy qz qw" (LiDAR to world)
--sensor picks the scan folder (default: the only one present, else Ouster). A scan is matched
to the GT line with its exact stamp; scans without one are left out (a note on stderr), GT lines
without a scan are ignored. The map frame is the GT's world frame.

OUT_DIR receives instances/15.txt, 17.txt, 18.txt (lines "id x y z") and RSN/road_normal.txt
(lines "x y nx ny nz std_deg"), the format localize-lidar reads. Nothing is written unless the
whole build succeeds.
"""

EPILOG = """\
examples:
  jaxloc build-lidar-map dataset/sequences/00 maps/kitti00
  jaxloc build-lidar-map dataset/sequences/00 maps/kitti00 --every 10 --save-map kitti00.npz
  jaxloc localize-lidar maps/kitti00 dataset/sequences/00 --every 50
  jaxloc build-lidar-map HeLiPR/KAIST04 maps/KAIST04 --sensor Ouster --every 30

--save-map FILE also describes the built map (M2Loc, 3 scales, or the localization settings
given) and saves it, so that localize-lidar loads it in a second instead of describing it again.

exit status: 0 on success, 2 on missing or malformed files or bad options (one-line message).
"""


def check_build_lidar_map(args: argparse.Namespace) -> None:
    """Before any work: ``--save-map`` names an ``.npz``, ``OUT_DIR`` is not a file."""
    check_save_path(args.save_map)
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise InputError(f"{args.out_dir}: exists and is not a folder")


def run_build_lidar_map(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from jaxloc.io import save_triplet_map, write_instance_maps
    from jaxloc.mapping import MapBuildConfig, build_lidar_maps

    start = time.perf_counter()
    sequence = open_sequence(args.seq_dir, args)
    used = len(sequence.bins[:: args.every])
    with reading(), tqdm(total=used, unit="scan", disable=args.no_progress) as bar:
        maps = build_lidar_maps(sequence, MapBuildConfig(every=args.every), bar.update)
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
    layout = sequence.layout + (f", {sequence.sensor}" if sequence.sensor else "")
    print(
        f"{args.seq_dir} ({layout}): {used} of {len(sequence.bins)} scans used -> "
        f"{len(instances.points)} instances ({counts}), {len(normals.xy)} road-normal cells, "
        f"in {time.perf_counter() - start:.1f} s; wrote {args.out_dir}/instances/*.txt and "
        f"{args.out_dir}/RSN/road_normal.txt" + (f" and {args.save_map}" if args.save_map else "")
    )
    return 0
