"""``jaxloc build-lidar-map``: instance and road-normal maps from a labelled LiDAR sequence."""

from __future__ import annotations

import argparse
import time

import numpy as np

from jaxloc.cli._errors import InputError
from jaxloc.cli._lidar import check_save_path, describe_map, triplet_config

DESCRIPTION = """\
Builds a TripletLoc/HeLiPR-format instance map and road-surface-normal map from a labelled
LiDAR sequence, TripletLoc's way: every K-th scan, trunk/pole/traffic-sign points clustered
into instance centroids (0.1 m voxels, 0.5 m clusters of >= 20 voxels), moved to the map frame
and fused across scans within 0.5 m; road points binned into 10 m cells (within 80 m of the
sensor), a robust plane per cell, cells fused within 3.5 m.

SEQ_DIR is a SemanticKITTI sequence:
  SEQ_DIR/velodyne/NNNNNN.bin   float32 x y z intensity (sensor frame)
  SEQ_DIR/labels/NNNNNN.label   uint32: semantic id in the low 16 bits (71 trunk, 80 pole,
                                81 traffic sign, 40 road), instance in the high 16 bits
  SEQ_DIR/poses.txt             one cam0 pose per scan, 12 numbers (KITTI 3x4, row-major)
  SEQ_DIR/calib.txt             "Tr: 12 numbers" (velodyne to cam0; P0-P3 lines are ignored)
The map frame is then the velodyne frame of the first scan: T_map_scan = inv(Tr) P Tr.
Or a plain folder: NNN.bin with NNN.label beside them (or velodyne/ + labels/) and a poses.txt of
T_map_scan rows (12 or 16 numbers), no calib.txt. Scans sort by number (0, 11, 102); line i of
poses.txt belongs to the i-th scan.

OUT_DIR receives instances/15.txt, 17.txt, 18.txt (lines "id x y z") and RSN/road_normal.txt
(lines "x y nx ny nz std_deg"), the format localize-lidar reads. Nothing is written unless the
whole build succeeds.
"""

EPILOG = """\
examples:
  jaxloc build-lidar-map dataset/sequences/00 maps/kitti00
  jaxloc build-lidar-map dataset/sequences/00 maps/kitti00 --every 10 --save-map kitti00.npz
  jaxloc localize-lidar maps/kitti00 dataset/sequences/00 --every 50

--save-map FILE also describes the built map (M2Loc, 3 scales, or the localization settings
given) and saves it, so that localize-lidar loads it in a second instead of describing it again.

exit status: 0 on success, 2 on missing or malformed files or bad options (one-line message).
"""


def run_build_lidar_map(args: argparse.Namespace) -> int:
    from tqdm.auto import tqdm

    from jaxloc.io import load_lidar_sequence, save_lidar_maps, save_triplet_map
    from jaxloc.mapping import MapBuildConfig, build_lidar_maps

    if args.every < 1:
        raise InputError(f"--every must be >= 1, got {args.every}")
    check_save_path(args.save_map)
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise InputError(f"{args.out_dir}: exists and is not a folder")
    start = time.perf_counter()
    try:
        sequence = load_lidar_sequence(args.seq_dir)
        used = len(sequence.bins[:: args.every])
        with tqdm(total=used, unit="scan", disable=args.no_progress) as bar:
            maps = build_lidar_maps(sequence, MapBuildConfig(every=args.every), bar.update)
    except (ValueError, FileNotFoundError) as error:  # the loaders name the file
        raise InputError(str(error)) from error
    instances, normals = maps.instances, maps.road_normals
    triplet_map = None
    if args.save_map is not None:  # describe before writing anything: a bad map writes nothing
        config = triplet_config(args)
        triplet_map = describe_map(instances.points, instances.labels, config, normals, "built")
    save_lidar_maps(args.out_dir, instances, normals)
    if triplet_map is not None:
        save_triplet_map(triplet_map, args.save_map)
    counts = ", ".join(
        f"{int(np.sum(instances.labels == c))} x {c}" for c in sorted(set(instances.labels))
    )
    print(
        f"{args.seq_dir} ({sequence.layout}): {used} of {len(sequence.bins)} scans used -> "
        f"{len(instances.points)} instances ({counts}), {len(normals.xy)} road-normal cells, "
        f"in {time.perf_counter() - start:.1f} s; wrote {args.out_dir}/instances/*.txt and "
        f"{args.out_dir}/RSN/road_normal.txt" + (f" and {args.save_map}" if args.save_map else "")
    )
    return 0
