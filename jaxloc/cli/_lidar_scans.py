"""The scans and poses of the LiDAR commands: scan arguments (files and sequence folders in any
layout), ground truth matched by time or by order, and the ``--poses-out`` trajectory."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc.cli._errors import InputError

#: Suffix of an instance-centroid scan file (lines ``class_id x y z``).
CENTROID_SUFFIX = ".txt"
#: What ``--format`` accepts (:data:`jaxloc.io.lidar_sequence.LAYOUTS`).
SEQUENCE_FORMATS = ("semantickitti", "plain", "helipr")
#: What ``--pose-format`` accepts.
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


class ScanRef(NamedTuple):
    """One scan to localize: ``path``, its ``number`` (index in its sequence folder, else its
    position among the scans), ``timestamp`` (int ns or None), the ``sequence`` it comes from
    (or None) and its ``index`` there, and its ground truth ``T_gt`` (4, 4) or None."""

    path: Path
    number: int
    timestamp: int | None = None
    sequence: object | None = None
    index: int = 0
    T_gt: np.ndarray | None = None


class ScanInstances(NamedTuple):
    """Instance centroids of one scan: ``points`` (N, 3) float64 metres in the scan frame,
    ``labels`` (N,) int class ids, ``load_ms`` time to read (and cluster) the scan."""

    points: np.ndarray
    labels: np.ndarray
    load_ms: float


def note(command: str, message: str) -> None:
    """One line on stderr that is not an error: ``jaxloc COMMAND: note: message``."""
    print(f"jaxloc {command}: note: {message}", file=sys.stderr)


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


def open_sequence(path: Path, args: argparse.Namespace, require_poses: bool):
    """:func:`jaxloc.io.load_lidar_sequence` with ``--format`` / ``--sensor``; errors as
    InputError, a note on stderr for the sensor chosen among several and for scans left out."""
    from jaxloc.io import load_lidar_sequence
    from jaxloc.io.helipr import helipr_sensors

    try:
        sequence = load_lidar_sequence(path, require_poses, args.format, args.sensor)
    except (ValueError, FileNotFoundError) as error:  # the loaders name the file
        raise InputError(str(error)) from error
    if sequence.layout == "helipr" and args.sensor is None:
        present = helipr_sensors(path)
        if len(present) > 1:
            note(args.command, f"{path}: scans of {present}; reading {sequence.sensor} (--sensor)")
    if sequence.skipped:
        note(
            args.command,
            f"{path}: {len(sequence.skipped)} scan(s) without a pose at their time left out "
            f"(first: {sequence.skipped[0].name})",
        )
    return sequence


def _label_path(bin_path: Path) -> Path:
    """The ``.label`` of a SemanticKITTI ``.bin``: beside it, or in ``../labels/`` (the dataset's
    ``velodyne/`` + ``labels/`` layout)."""
    beside = bin_path.with_suffix(".label")
    if beside.exists():
        return beside
    dataset_layout = bin_path.parent.parent / "labels" / beside.name
    if dataset_layout.exists():
        return dataset_layout
    raise InputError(f"{bin_path}: no label file (looked for {beside} and {dataset_layout})")


def check_scan_path(path: Path) -> None:
    """Cheap checks before any work: the scan exists, its format is known, a ``.bin`` has labels."""
    from jaxloc.io.helipr import helipr_scan_label

    if not path.exists():
        raise InputError(f"missing scan: {path}")
    if path.is_dir():
        return
    if path.suffix == ".bin":
        found = helipr_scan_label(path)
        if found is None:
            _label_path(path)
        elif not found[1].is_file():
            raise InputError(f"{path}: no label file (looked for {found[1]})")
    elif path.suffix != CENTROID_SUFFIX:
        raise InputError(
            f"{path}: unknown scan format (expected .bin + .label, a {CENTROID_SUFFIX} "
            "centroid file, or a folder with instances/<class>.txt)"
        )


def load_centroid_scan(path: Path, classes: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """Read an instance-centroid scan file: lines ``class_id x y z`` (scan frame, metres; ``#``
    starts a comment).

    Returns (N, 3) float64 points and (N,) int64 class ids.

    Raises:
        ValueError: naming the file (and line): not UTF-8 text, a wrong field count, a
            non-number or NaN/inf, non-integer or unknown class ids.
    """
    from jaxloc.io._text import data_lines

    rows = []
    for line_number, line in data_lines(path, comments=True):
        fields = line.split()
        if len(fields) != 4:
            raise ValueError(
                f"{path}:{line_number}: expected 4 numbers (class_id x y z), got {len(fields)}"
            )
        try:
            values = np.array([float(field) for field in fields])
        except ValueError:
            raise ValueError(f"{path}:{line_number}: not a number in {line[:60]!r}") from None
        if not np.all(np.isfinite(values)):
            raise ValueError(f"{path}:{line_number}: non-finite value in {line[:60]!r}")
        rows.append(values)
    table = np.asarray(rows, np.float64).reshape(-1, 4)
    labels = table[:, 0]
    if np.any(labels != np.round(labels)):
        raise ValueError(f"{path}: class ids (first column) must be integers")
    unknown = sorted(set(labels.astype(int).tolist()) - set(classes))
    if unknown:
        raise ValueError(f"{path}: unknown class ids {unknown}; expected some of {list(classes)}")
    return table[:, 1:4], labels.astype(np.int64)


def _labelled_scan(ref: ScanRef):
    from jaxloc.io import load_helipr_scan, load_semantickitti_scan, load_sequence_scan
    from jaxloc.io.helipr import helipr_scan_label

    if ref.sequence is not None:
        return load_sequence_scan(ref.sequence, ref.index)
    found = helipr_scan_label(ref.path)
    if found is not None:
        return load_helipr_scan(ref.path, found[1], found[0])
    return load_semantickitti_scan(ref.path, _label_path(ref.path))


def load_scan(ref: ScanRef, classes: Sequence[int]) -> ScanInstances:
    """Instance centroids of a scan: a labelled point scan (SemanticKITTI or HeLiPR ``.bin`` +
    ``.label``, alone or from a sequence) clustered with TripletLoc's recipe, a centroid
    ``.txt`` (``class_id x y z``), or a folder in the map's format (``instances/<class>.txt``)."""
    from jaxloc.io import load_instance_map
    from jaxloc.m2loc import cluster_instances

    path = ref.path
    if ref.sequence is None:
        check_scan_path(path)
    start = time.perf_counter()
    try:
        if ref.sequence is None and path.is_dir():
            instances = load_instance_map(path, tuple(classes))
            points, labels = instances.points, instances.labels
        elif ref.sequence is not None or path.suffix == ".bin":
            scan = _labelled_scan(ref)
            instances = cluster_instances(scan.points, scan.labels)
            points, labels = instances.points, instances.labels
        else:
            points, labels = load_centroid_scan(path, classes)
    except (ValueError, FileNotFoundError) as error:  # the loaders name the file
        raise InputError(str(error)) from error
    return ScanInstances(points, labels, 1e3 * (time.perf_counter() - start))


def _is_sequence(path: Path, args: argparse.Namespace) -> bool:
    from jaxloc.io import is_sequence_dir

    if not path.is_dir() or (path / "instances").is_dir():
        return False
    return args.format is not None or is_sequence_dir(path)


def expand_scans(paths: Sequence[Path], args: argparse.Namespace) -> list[ScanRef]:
    """SCAN arguments as scans: a sequence folder (any layout, ``--format`` / ``--sensor``)
    gives every ``--every``-th of its scans with their timestamps and ground truth (when the
    folder has poses); other arguments are single scans (a HeLiPR ``LiDAR/<sensor>/<stamp>.bin``
    keeps its stamp)."""
    from jaxloc.io.helipr import helipr_scan_label, scan_stamp

    refs: list[ScanRef] = []
    for path in paths:
        if not _is_sequence(path, args):
            check_scan_path(path)
            try:
                stamp = scan_stamp(path) if helipr_scan_label(path) is not None else None
            except ValueError as error:  # a HeLiPR scan not named by its stamp
                raise InputError(str(error)) from error
            refs.append(ScanRef(path, len(refs), stamp))
            continue
        sequence = open_sequence(path, args, require_poses=False)
        for index in range(0, len(sequence.bins), args.every):
            stamps, truth = sequence.timestamps, sequence.T_map_scan
            refs.append(
                ScanRef(
                    sequence.bins[index],
                    index,
                    None if stamps is None else int(stamps[index]),
                    sequence,
                    index,
                    None if truth is None else truth[index],
                )
            )
    return refs


def attach_ground_truth(refs: list[ScanRef], path: Path) -> list[ScanRef]:
    """``--gt FILE`` (KITTI, 4x4 or TUM/HeLiPR lines, :func:`jaxloc.io.read_pose_file`): by time
    when the file and every scan have timestamps (scans without a pose at their time get none),
    else line i for the i-th scan (the counts must agree)."""
    from jaxloc.io import read_pose_file
    from jaxloc.io.lidar_sequence import assign_poses

    stamps = [ref.timestamp for ref in refs]
    timed = None if None in stamps else np.asarray(stamps, np.int64)
    try:
        found = read_pose_file(path)
        if (found.timestamps is None or timed is None) and len(found.poses) != len(refs):
            raise ValueError(f"{path}: {len(found.poses)} poses for {len(refs)} scan(s)")
        poses, matched, _ = assign_poses(found, timed, len(refs), path)
    except ValueError as error:
        raise InputError(str(error)) from error
    return [
        ref._replace(T_gt=pose if ok else None)
        for ref, pose, ok in zip(refs, poses, matched, strict=True)
    ]


def check_poses_out(args: argparse.Namespace) -> None:
    """Before any work: ``--poses-out`` must not be a folder."""
    if args.poses_out is not None and args.poses_out.is_dir():
        raise InputError(f"--poses-out {args.poses_out}: is a folder")


def write_poses_out(args: argparse.Namespace, refs: list[ScanRef], results: list) -> None:
    """Write ``--poses-out`` (:data:`POSES_OUT_HELP`)."""
    from jaxloc.io import write_kitti, write_tum

    poses = np.asarray([result.pose for result in results], np.float64).reshape(-1, 4, 4)
    if args.pose_format == "kitti":
        write_kitti(args.poses_out, poses)
        return
    valid = np.array([bool(result.valid) for result in results], bool)
    stamps = np.array(
        [ref.number * 10**9 if ref.timestamp is None else ref.timestamp for ref in refs], np.int64
    )
    write_tum(args.poses_out, poses[valid], stamps[valid])
    if not valid.all():
        note(
            args.command,
            f"{args.poses_out}: {int((~valid).sum())} scan(s) that did not localize left out (TUM)",
        )
