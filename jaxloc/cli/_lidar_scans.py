"""The recording options of the LiDAR commands (``--format``, ``--sensor``, ``--poses-out``, the
drive's ``--accumulate`` family), their checks, and the notes and errors of reading: the reading
itself is :func:`jaxloc.io.open_lidar_recording` and
:func:`jaxloc.io.lidar_sequence.open_lidar_sequence`."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from jaxloc.cli._errors import InputError
from jaxloc.cli._options import count, positive_int

#: What ``--format`` accepts (:data:`jaxloc.io.lidar_sequence.LAYOUTS`).
SEQUENCE_FORMATS = ("semantickitti", "plain", "helipr")
#: What ``--pose-format`` accepts (:func:`jaxloc.io.write_lidar_poses`).
POSE_FORMATS = ("tum", "kitti")

POSES_OUT_HELP = """\
--poses-out FILE writes the estimated T_map_scan of the scans in a format evo reads
(evo_ape, evo_traj): --pose-format tum (default) gives lines "t x y z qx qy qz qw" (t the scan's
timestamp in seconds, exact to the nanosecond, or its scan number where it has none: its index in
its sequence folder, else its position among the scans), one per VALID scan: a scan that did not
localize is left out, and evo then associates the rest with the reference by time.
--pose-format kitti gives one line of 12 numbers (3x4 [R|t]) per scan, in the order of the scans,
invalid ones included with the pose jaxloc returns for them (the identity), since KITTI files are
matched line by line; evo_ape on it then counts a failed scan's error as jaxloc's RTE does."""


def note(command: str, message: str) -> None:
    """One line on stderr that is not an error: ``jaxloc COMMAND: note: message``."""
    print(f"jaxloc {command}: note: {message}", file=sys.stderr)


@contextlib.contextmanager
def reading() -> Iterator[None]:
    """The library's input errors as InputError (one line, exit 2): a ValueError, and a
    FileNotFoundError that names its file in its message (one with a ``filename`` goes on to
    :func:`jaxloc.cli._errors.run_guarded`: ``missing file: ...``)."""
    try:
        yield
    except FileNotFoundError as error:
        if error.filename is not None:
            raise
        raise InputError(str(error)) from error
    except ValueError as error:  # the readers name the file
        raise InputError(str(error)) from error


def add_sequence_options(parser: argparse.ArgumentParser) -> None:
    """``--format`` and ``--sensor``: how a sequence folder is read."""
    parser.add_argument(
        "--format",
        choices=SEQUENCE_FORMATS,
        help="sequence layout (default: detected: semantickitti = velodyne/ + calib.txt, helipr "
        "= LiDAR/<sensor>/, plain = the rest)",
    )
    parser.add_argument(
        "--sensor",
        help="HeLiPR scan folder LiDAR/<sensor>/: Ouster, Velodyne, Avia, Aeva or Ouster_filterd "
        "(default: the only one present, else Ouster)",
    )


def add_drive_options(parser: argparse.ArgumentParser) -> None:
    """``--accumulate``, ``--window-instances``, ``--accumulate-max``, ``--odometry`` and
    ``--track``: how the scans of a drive are localized (:func:`drive_options`)."""
    parser.add_argument(
        "--accumulate",
        type=positive_int,
        default=1,
        metavar="K",
        help="localize each scan with the instances of the last K >= 1 scans fused through "
        "odometry (default 1: each scan alone); the window grows with older scans while it holds "
        "few instances (--window-instances, --accumulate-max)",
    )
    parser.add_argument(
        "--window-instances",
        type=count,
        metavar="N",
        help="with --accumulate K: add older scans while the fused window holds fewer than N >= 0 "
        "instances (default: jaxloc.m2loc.WINDOW_MIN_INSTANCES; 0: exactly K scans)",
    )
    parser.add_argument(
        "--accumulate-max",
        type=positive_int,
        metavar="M",
        help="with --accumulate K: the most scans a window grows to, M >= K (default 2K)",
    )
    parser.add_argument(
        "--odometry",
        type=Path,
        metavar="FILE",
        help="odometry for --accumulate and --track: poses in any format --gt takes (default: "
        "the sequence's own poses)",
    )
    parser.add_argument(
        "--track",
        action="store_true",
        help="track the drive: after a verified pose, localize the next scans near the odometry "
        "prediction (milliseconds), global localization when that fails",
    )


def add_pose_output_options(parser: argparse.ArgumentParser) -> None:
    """``--poses-out`` and ``--pose-format`` (see :data:`POSES_OUT_HELP`)."""
    parser.add_argument(
        "--poses-out", type=Path, metavar="FILE", help="write the estimated poses (see below)"
    )
    parser.add_argument(
        "--pose-format",
        choices=POSE_FORMATS,
        default="tum",
        help="of --poses-out: tum (valid scans, timestamped) or kitti (every scan, in order)",
    )


def note_sequences(args: argparse.Namespace, sequences: Sequence) -> None:
    """A note on stderr for each HeLiPR sequence whose sensor was chosen among several and for
    each sequence whose scans without a pose were left out."""
    for sequence in sequences:
        if sequence.layout == "helipr" and args.sensor is None and len(sequence.sensors) > 1:
            note(
                args.command,
                f"{sequence.root}: scans of {list(sequence.sensors)}; reading {sequence.sensor} "
                "(--sensor)",
            )
        if sequence.skipped:
            note(
                args.command,
                f"{sequence.root}: {len(sequence.skipped)} scan(s) without a pose at their time "
                f"left out (first: {sequence.skipped[0].name})",
            )


def open_sequence(path: Path, args: argparse.Namespace):
    """:func:`jaxloc.io.lidar_sequence.open_lidar_sequence` with its poses, ``--format`` and
    ``--sensor``."""
    from jaxloc.io.lidar_sequence import open_lidar_sequence

    with reading():
        sequence = open_lidar_sequence(path, True, args.format, args.sensor)
    note_sequences(args, [sequence])
    return sequence


def check_poses_out(args: argparse.Namespace) -> None:
    """Before any work: ``--poses-out`` must not be a folder."""
    if args.poses_out is not None and args.poses_out.is_dir():
        raise InputError(f"--poses-out {args.poses_out}: is a folder")


def drive_options(args: argparse.Namespace):
    """``--accumulate K --accumulate-max M --window-instances N`` (and that ``--odometry`` is
    used), checked against each other, as ``(K, jaxloc.m2loc.DriveConfig)`` (M = 2K and N =
    ``WINDOW_MIN_INSTANCES`` by default; K, M >= 1 and N >= 0 are checked where
    they are parsed, :func:`add_drive_options`)."""
    from jaxloc.m2loc import DriveConfig

    least, most, instances = args.accumulate, args.accumulate_max, args.window_instances
    if args.odometry is not None and least == 1 and not args.track:
        raise InputError("--odometry is only used with --accumulate K > 1 or --track")
    if least == 1:
        for option, value in (("--window-instances", instances), ("--accumulate-max", most)):
            if value is not None:
                raise InputError(f"{option} is only used with --accumulate K > 1")
        return 1, DriveConfig()
    if most is not None and most < least:
        raise InputError(f"--accumulate-max must be >= --accumulate ({least}), got {most}")
    if instances is None:
        return least, DriveConfig(most_scans=most)
    return least, DriveConfig(most_scans=most, min_instances=instances)
