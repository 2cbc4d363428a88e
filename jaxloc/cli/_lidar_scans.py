"""The recording options of the LiDAR commands (``--format``, ``--sensor``, a bag's topics,
``--poses-out``, the drive's ``--accumulate`` family), their checks, and the notes of reading:
the reading itself is :func:`jaxloc.io.open_lidar_recording`."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from jaxloc.cli._errors import InputError, note, reading
from jaxloc.cli._options import OptionTable, count, given, positive_int

POSES_OUT_HELP = """\
--poses-out FILE writes the estimated T_map_scan: --pose-format tum, lines "t x y z qx qy qz qw"
of the VALID scans for evo (t the scan's timestamp in seconds, else its number), associated with
the reference by time; kitti, one 3x4 line per scan in order, a failed scan as the identity (then
evo_ape counts its error as jaxloc's RTE does); mcap (any FILE ending in .mcap), a
geometry_msgs/PoseStamped per valid scan on /jaxloc/pose and a std_msgs/Bool verdict per scan on
/jaxloc/valid, stamped as the scan, for Foxglove; rosbag2, the same as a new ROS 2 bag folder."""

#: A bag SCAN's topics and fields (open_lidar_recording's keywords): flag, metavar, help.
BAG_OPTIONS = OptionTable(
    (
        ("--topic", "TOPIC", "the labelled sensor_msgs/PointCloud2 topic (default: the only one)"),
        ("--odometry-topic", "TOPIC", "pose topic, /tf or none (default: sole Odometry, else /tf)"),
        ("--gt-topic", "TOPIC", "a pose topic of ground-truth T_map_scan (or --gt FILE)"),
        ("--label-field", "FIELD", "the clouds' class field (default label)"),
        ("--instance-field", "FIELD", "their instance field (default: a 32-bit label's high bits)"),
    )
)


def add_sequence_options(parser: argparse.ArgumentParser) -> None:
    """``--format`` and ``--sensor``: how a sequence folder is read."""
    layouts = ("semantickitti", "plain", "helipr")  # jaxloc.io.lidar_sequence.LAYOUTS
    parser.add_argument("--format", choices=layouts, help="sequence layout (default: detected)")
    parser.add_argument(
        "--sensor", help="HeLiPR scan folder LiDAR/<sensor>/ (default: the only one, else Ouster)"
    )


def add_drive_options(parser: argparse.ArgumentParser) -> None:
    """How the scans of a drive are localized (:func:`drive_options`), and ``--poses-out``."""
    add = parser.add_argument
    fuse = "localize each scan with the last K scans fused through odometry (more: few instances)"
    add("--accumulate", type=positive_int, default=1, metavar="K", help=fuse)
    grow = "with --accumulate K: grow the window while it holds fewer than N instances"
    add("--window-instances", type=count, metavar="N", help=f"{grow} (default DriveConfig's)")
    most = "with --accumulate K: the most scans a window grows to, M >= K (default 2K)"
    add("--accumulate-max", type=positive_int, metavar="M", help=most)
    odometry = "for --accumulate and --track, as --gt (default: a bag's odometry, else the poses)"
    add("--odometry", type=Path, metavar="FILE", help=odometry)
    track = "after a verified pose, localize the next scans near the odometry's prediction (ms)"
    add("--track", action="store_true", help=f"{track}, globally when that fails")
    add("--poses-out", type=Path, metavar="FILE", help="estimated poses (see below)")
    formats = ("tum", "kitti", "mcap", "rosbag2")
    add("--pose-format", choices=formats, default="tum", help="of --poses-out")


def note_sequences(args: argparse.Namespace, sequences: Sequence) -> None:
    """A note for each HeLiPR sequence whose sensor was chosen among several, and for each
    sequence whose scans without a pose were left out."""
    for seq in sequences:
        if seq.layout == "helipr" and args.sensor is None and len(seq.sensors) > 1:
            note(
                args.command,
                f"{seq.root}: scans of {list(seq.sensors)}; reading {seq.sensor} (--sensor)",
            )
        if seq.skipped:
            note(
                args.command,
                f"{seq.root}: {len(seq.skipped)} scan(s) without a pose at their "
                f"time left out (first: {seq.skipped[0].name})",
            )


def check_poses_out(args: argparse.Namespace) -> None:
    """Before any work: ``--poses-out`` must not be a folder, ``--pose-format`` must fit it."""
    from jaxloc.io.lidar_recording import pose_format_for

    if args.poses_out is None:
        return
    if args.poses_out.is_dir():
        raise InputError(f"--poses-out {args.poses_out}: is a folder")
    with reading("--poses-out/--pose-format"):
        pose_format_for(args.poses_out, args.pose_format)


def drive_options(args: argparse.Namespace):
    """``(K, jaxloc.m2loc.DriveConfig)`` of ``--accumulate K --accumulate-max M
    --window-instances N``, checked against each other and ``--odometry``."""
    from jaxloc.m2loc import DriveConfig

    least, most, instances = args.accumulate, args.accumulate_max, args.window_instances
    if args.odometry is not None and least == 1 and not args.track:
        raise InputError("--odometry is only used with --accumulate K > 1 or --track")
    if least == 1:
        for option, value in (("--window-instances", instances), ("--accumulate-max", most)):
            if value is not None:
                raise InputError(f"{option} is only used with --accumulate K > 1")
    elif most is not None and most < least:
        raise InputError(f"--accumulate-max must be >= --accumulate ({least}), got {most}")
    return least, DriveConfig(**given(most_scans=most, min_instances=instances))
