"""Every LiDAR recording jaxloc reads, as one :class:`LidarRecording`: its scans in order, their
stamps and poses, each scan read on demand.

:func:`open_lidar_recording` takes a path or a list of paths, each one of:

* a sequence folder in any layout of :func:`~jaxloc.io.lidar_sequence.open_lidar_sequence`
  (SemanticKITTI, plain, HeLiPR / TripletLoc; ``layout``, ``sensor``): every ``every``-th of
  its scans, with their timestamps and poses when the folder has them;
* ``NAME.bin``, a SemanticKITTI scan with ``NAME.label`` beside it or in ``../labels/`` (the
  dataset's layout), or a HeLiPR ``SEQ/LiDAR/<sensor>/<stamp>.bin`` with ``SEQ/labels/`` (its
  stamp kept);
* ``NAME.txt``, instance centroids already extracted: lines ``class_id x y z`` (scan frame, metres;
  ``#`` starts a comment; :func:`read_centroid_scan`);
* a folder with ``instances/<class>.txt``, a scan in the map's own format
  (:func:`~jaxloc.io.read_instance_map`);
* a bag, given alone: a ROS 1 ``.bag``, a ROS 2 bag folder or a bare ``.mcap``, its labelled
  ``sensor_msgs/PointCloud2`` clouds with their header stamps, the bag's odometry and ground
  truth (:mod:`jaxloc.io.rosbag_lidar`; ``topic``, ``odometry_topic``, ``gt_topic``,
  ``label_field``, ``instance_field``).

``gt=FILE`` replaces the poses by a pose file's (KITTI, 4x4 or TUM / HeLiPR lines,
:func:`~jaxloc.io.read_pose_file`): by time when the file and every scan have timestamps (exact
for nanoseconds, within 1 ms for seconds; a scan without a pose at its time gets none), else line
i for the i-th scan (the counts must agree); :meth:`LidarRecording.with_poses` does the same for
an odometry file. Labelled scans become instance centroids with TripletLoc's recipe
(:func:`jaxloc.m2loc.cluster_instances`). Cheap checks (files present, formats known, labels
found, every option applying to the input) run when the recording is opened, so a bad argument
fails before any work.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from jaxloc._lazy import renamed_names
from jaxloc.io import _rosbag, helipr
from jaxloc.io._text import data_lines
from jaxloc.io.instance_maps import read_instance_map
from jaxloc.io.lidar_sequence import (
    LidarSequence,
    assign_poses,
    is_sequence_dir,
    open_lidar_sequence,
    read_sequence_scan,
)
from jaxloc.io.poses import read_pose_file, write_kitti, write_tum
from jaxloc.io.rosbag_lidar import RosbagScans, open_rosbag_scans
from jaxloc.io.rosbag_poses import write_pose_bag
from jaxloc.io.semantickitti import LabelledScan, check_point_range, read_semantickitti_scan
from jaxloc.m2loc import cluster_instances
from jaxloc.m2loc._classes import GRAPH_CLASSES
from jaxloc.m2loc._drive import ScanInstances

#: Suffix of an instance-centroid scan file (lines ``class_id x y z``).
CENTROID_SUFFIX = ".txt"


@dataclasses.dataclass(frozen=True, eq=False)
class LidarRecording:
    """A LiDAR recording: N scans in order, read one at a time (a
    ``ScanSource``, what :func:`jaxloc.m2loc.localize_drive` reads).

    Attributes:
        paths: per scan its file (``.bin``, centroid ``.txt``), instance-map folder or bag.
        numbers: per scan its number: its index in its sequence folder or among its bag topic's
            clouds, else its position among the scans.
        stamps: per scan its time in integer nanoseconds (HeLiPR names, ``times.txt``, a cloud's
            header), or None.
        poses: (N, 4, 4) float64 ``T_map_scan`` of the LiDAR (identity where a scan has none), or
            None when no scan has one.
        has_pose: (N,) bool, the scans ``poses`` holds a pose for.
        sequences: the sequence folders the scans come from
            (:class:`~jaxloc.io.LidarSequence`: layout, sensor, scans left out without a pose).
        sources: per scan the index of its sequence in ``sequences``, or -1 for a scan given alone
            or read from a bag.
        odometry: (N, 4, 4) float64 ``T_odom_scan`` from the recording's own odometry (a bag's,
            interpolated to the scans' stamps), or None; pass it as ``localize_drive``'s
            ``odometry`` (``poses`` is the ground truth).
        bag: the bag the scans are read from (:class:`~jaxloc.io.rosbag_lidar.RosbagScans`), or
            None.
    """

    paths: tuple[Path, ...]
    numbers: tuple[int, ...]
    stamps: tuple[int | None, ...]
    poses: np.ndarray | None
    has_pose: np.ndarray
    sequences: tuple[LidarSequence, ...] = ()
    sources: tuple[int, ...] = ()
    odometry: np.ndarray | None = None
    bag: RosbagScans | None = None

    def __len__(self) -> int:
        return len(self.paths)

    @property
    def timestamps(self) -> np.ndarray | None:
        """(N,) int64 nanoseconds, or None unless every scan has a stamp."""
        if None in self.stamps:
            return None
        return np.asarray(self.stamps, np.int64)

    def name(self, index: int) -> str:
        """The scan's path (a bag's scan: ``BAG:TOPIC[number]``), as errors name it."""
        return str(self.paths[index]) if self.bag is None else self.bag.name(index)

    def scan(self, index: int) -> LabelledScan:
        """Scan ``index``'s labelled points (class ids, sensor frame).

        Raises:
            FileNotFoundError, ValueError: naming the file (a missing or malformed scan or label
                file; a scan given as instance centroids, which has no points).
        """
        path, source = self.paths[index], self.sources[index]
        if self.bag is not None:
            return self.bag.scan(index)
        if source >= 0:
            return read_sequence_scan(self.sequences[source], self.numbers[index])
        _check_scan_file(path)
        if path.is_dir() or path.suffix != ".bin":
            raise ValueError(f"{path}: instance centroids, not a labelled point scan")
        found = helipr.helipr_scan_label(path)
        if found is not None:
            return helipr.read_helipr_scan(path, found[1], found[0])
        return read_semantickitti_scan(path, _label_path(path))

    def instances(self, index: int, classes: Sequence[int] = GRAPH_CLASSES) -> ScanInstances:
        """Scan ``index``'s instance centroids of ``classes``: clustered from its labelled points
        (TripletLoc's recipe), or read from its centroid file or instance-map folder.

        Raises:
            FileNotFoundError, ValueError: naming the file (as :meth:`scan`; a centroid file's
                malformed lines or class ids outside ``classes``).
        """
        path = self.paths[index]
        if (
            self.bag is None
            and self.sources[index] < 0
            and (path.is_dir() or path.suffix != ".bin")
        ):
            _check_scan_file(path)
            if path.is_dir():
                found = read_instance_map(path, tuple(classes))
                return ScanInstances(found.points, found.labels)
            return ScanInstances(*read_centroid_scan(path, classes))
        scan = self.scan(index)
        found = cluster_instances(scan.points, scan.labels)
        return ScanInstances(found.points, found.labels)

    def with_poses(self, path: str | os.PathLike) -> LidarRecording:
        """The recording with the poses of a pose file instead of its own (matched as ``gt=``;
        see the module docstring).

        Raises:
            FileNotFoundError: no such file.
            ValueError: naming the file: malformed or non-rigid poses, another pose count (by
                order), or no scan matched by time.
        """
        timed = self.timestamps
        found = read_pose_file(path)
        if (found.timestamps is None or timed is None) and len(found.poses) != len(self):
            raise ValueError(f"{path}: {len(found.poses)} poses for {len(self)} scan(s)")
        poses, matched, _ = assign_poses(found, timed, len(self), path)
        return dataclasses.replace(self, poses=poses, has_pose=matched)


def _label_path(bin_path: Path) -> Path:
    """The ``.label`` of a SemanticKITTI ``.bin``: beside it, or in ``../labels/`` (the dataset's
    ``velodyne/`` + ``labels/`` layout)."""
    beside = bin_path.with_suffix(".label")
    if beside.exists():
        return beside
    dataset_layout = bin_path.parent.parent / "labels" / beside.name
    if dataset_layout.exists():
        return dataset_layout
    raise FileNotFoundError(f"{bin_path}: no label file (looked for {beside} and {dataset_layout})")


def _check_scan_file(path: Path) -> None:
    """The cheap checks of a scan given alone: it exists, its format is known, a ``.bin`` has
    labels."""
    if not path.exists():
        raise FileNotFoundError(f"missing scan: {path}")
    if path.is_dir():
        return
    if path.suffix == ".bin":
        found = helipr.helipr_scan_label(path)
        if found is None:
            _label_path(path)
        elif not found[1].is_file():
            raise FileNotFoundError(f"{path}: no label file (looked for {found[1]})")
    elif path.suffix != CENTROID_SUFFIX:
        raise ValueError(
            f"{path}: unknown scan format (expected .bin + .label, a {CENTROID_SUFFIX} "
            "centroid file, or a folder with instances/<class>.txt)"
        )


def read_centroid_scan(
    path: str | os.PathLike, classes: Sequence[int] = GRAPH_CLASSES
) -> tuple[np.ndarray, np.ndarray]:
    """Read an instance-centroid scan file: lines ``class_id x y z`` (scan frame, metres; ``#``
    starts a comment).

    Returns (N, 3) float64 points and (N,) int64 class ids.

    Raises:
        ValueError: naming the file (and line): not UTF-8 text, a wrong field count, a
            non-number or NaN/inf, non-integer or unknown class ids, a centroid beyond
            :data:`~jaxloc.io.semantickitti.MAX_RANGE_M` of the sensor.
    """
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
    check_point_range(table[:, 1:4], str(path))
    return table[:, 1:4], labels.astype(np.int64)


def _is_sequence(path: Path, layout: str | None) -> bool:
    if not path.is_dir() or (path / "instances").is_dir():
        return False
    return layout is not None or is_sequence_dir(path)


def _check_options(paths: list[Path], sequences, options: dict, bag_options: dict) -> None:
    """Every option given applies to the input: ``layout`` and ``every`` to sequence folders,
    ``sensor`` to HeLiPR sequences, the bag options to a bag."""
    what = f"{paths[0]}{' ...' if len(paths) > 1 else ''}"
    given = {name: value for name, value in options.items() if value not in (None, 1)}
    if not sequences and given:
        name, value = next(iter(given.items()))
        raise ValueError(f"{what}: {name}={value!r} applies to sequence folders; none is given")
    if options["sensor"] is not None and not any(s.layout == "helipr" for s in sequences):
        raise ValueError(
            f"{what}: sensor={options['sensor']!r} applies to HeLiPR sequence folders "
            "(LiDAR/<sensor>/); none is given"
        )
    for name, value in bag_options.items():
        if value is not None:
            raise ValueError(f"{what}: {name}={value!r} applies to bags; none is given")


def _open_bag(path: Path, every: int, gt, bag_options: dict) -> LidarRecording:
    if bag_options["gt_topic"] is not None and gt is not None:
        raise ValueError(f"{path}: give gt= or gt_topic=, not both")
    scans = open_rosbag_scans(path, every=every, **bag_options)
    recording = LidarRecording(
        (path,) * len(scans),
        scans.numbers,
        tuple(int(t) for t in scans.stamps),
        scans.ground_truth,
        scans.has_ground_truth,
        sources=(-1,) * len(scans),
        odometry=scans.odometry,
        bag=scans,
    )
    return recording if gt is None else recording.with_poses(gt)


def open_lidar_recording(
    path: str | os.PathLike | Sequence[str | os.PathLike],
    *,
    layout: str | None = None,
    sensor: str | None = None,
    every: int = 1,
    gt: str | os.PathLike | None = None,
    topic: str | None = None,
    odometry_topic: str | None = None,
    gt_topic: str | None = None,
    label_field: str | None = None,
    instance_field: str | None = None,
) -> LidarRecording:
    """Open a LiDAR recording: a sequence folder, a scan file, a list of them, or a bag (see the
    module docstring). Nothing is read but the file lists, stamps, poses and calibration (of a
    bag: its topics, the clouds' headers, odometry and ground truth).

    Args:
        path: a path or a list of paths (sequence folders, scans), in order; or one bag.
        layout: the layout of sequence folders ("semantickitti", "plain", "helipr"; default
            detected); given, any folder without ``instances/`` is read as a sequence.
        sensor: the HeLiPR scan folder (``LiDAR/<sensor>/``; default the only one, else Ouster).
        every: of a sequence folder or a bag, every ``every``-th scan.
        gt: a pose file that replaces the poses (:meth:`LidarRecording.with_poses`).
        topic: a bag's PointCloud2 topic (default: the only one).
        odometry_topic: a bag's odometry topic (default: the only ``nav_msgs/Odometry``, else
            ``/tf``; ``"none"``: none): ``LidarRecording.odometry``.
        gt_topic: a bag's pose topic of ground truth ``T_map_scan``: the poses.
        label_field: a bag's label field (:mod:`jaxloc.io.rosbag_lidar`).
        instance_field: a bag's instance field.

    Returns:
        A :class:`LidarRecording`.

    Raises:
        FileNotFoundError, ValueError: naming the file: a missing scan, folder or label file, an
            unknown scan format, a HeLiPR scan not named by its stamp, any error of
            :func:`~jaxloc.io.lidar_sequence.open_lidar_sequence`, of
            :func:`~jaxloc.io.rosbag_lidar.open_rosbag_scans` or of the pose file; an option
            that does not apply to the input (``sensor`` without a HeLiPR sequence, a bag
            option without a bag, ``layout`` with a bag).
    """
    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    paths = [Path(path)] if isinstance(path, str | os.PathLike) else list(map(Path, path))
    bag_options = dict(
        topic=topic,
        odometry_topic=odometry_topic,
        gt_topic=gt_topic,
        label_field=label_field,
        instance_field=instance_field,
    )
    options = dict(layout=layout, sensor=sensor, every=every)
    bags = [item for item in paths if _rosbag.is_bag(item)]
    if bags:
        if len(paths) > 1:
            raise ValueError(f"{bags[0]}: a bag is read alone, not in a list of {len(paths)} paths")
        for name in ("layout", "sensor"):
            if options[name] is not None:
                raise ValueError(
                    f"{bags[0]}: {name}={options[name]!r} applies to sequence folders, not a bag"
                )
        return _open_bag(paths[0], every, gt, bag_options)
    scans, numbers, stamps, poses, sources = [], [], [], [], []
    sequences: list[LidarSequence] = []
    for item in paths:
        if not _is_sequence(item, layout):
            _check_scan_file(item)
            found = helipr.helipr_scan_label(item)
            scans.append(item)
            numbers.append(len(numbers))
            stamps.append(None if found is None else helipr.scan_stamp(item))
            poses.append(None)
            sources.append(-1)
            continue
        sequence = open_lidar_sequence(item, False, layout, sensor)
        for index in range(0, len(sequence.bins), every):
            scans.append(sequence.bins[index])
            numbers.append(index)
            stamps.append(None if sequence.timestamps is None else int(sequence.timestamps[index]))
            poses.append(None if sequence.T_map_scan is None else sequence.T_map_scan[index])
            sources.append(len(sequences))
        sequences.append(sequence)
    _check_options(paths, sequences, options, bag_options)
    has_pose = np.array([pose is not None for pose in poses], bool)
    stacked = None
    if has_pose.any():
        stacked = np.stack([np.eye(4) if pose is None else pose for pose in poses])
    recording = LidarRecording(
        tuple(scans),
        tuple(numbers),
        tuple(stamps),
        stacked,
        has_pose,
        tuple(sequences),
        tuple(sources),
    )
    return recording if gt is None else recording.with_poses(gt)


#: What :func:`write_lidar_poses` writes: text for evo, or a bag for ROS tools.
POSE_FORMATS = ("tum", "kitti", "mcap", "rosbag2")


def pose_format_for(path: str | os.PathLike, format: str) -> str:
    """The format :func:`write_lidar_poses` writes ``path`` in: an ``.mcap`` path is MCAP
    (``format`` "tum", the default, or "mcap"), any other path the format given.

    Raises:
        ValueError: an unknown format, or one that does not fit the name (naming the path).
    """
    path = Path(path)
    if format not in POSE_FORMATS:
        raise ValueError(f"format must be one of {POSE_FORMATS}, got {format!r}")
    mcap = path.suffix == ".mcap"
    if mcap and format not in ("tum", "mcap") or format == "mcap" and not mcap:
        raise ValueError(
            f"{path}: format {format!r} does not fit the name (an .mcap path is written as "
            "MCAP, format 'mcap' needs one)"
        )
    return "mcap" if mcap else format


def write_lidar_poses(
    path: str | os.PathLike,
    recording: LidarRecording,
    poses: np.ndarray,
    valid: np.ndarray,
    format: str = "tum",
) -> int:
    """Write estimated ``T_map_scan`` of a recording's scans for evo or for ROS tools
    (atomically).

    ``format="tum"``: lines ``t x y z qx qy qz qw`` of the VALID scans only (``t`` the scan's
    stamp in seconds, exact to the nanosecond, or its number where it has none), which evo then
    associates with a reference by time; ``"kitti"``: 12 numbers (3x4) per scan, every scan in
    order, invalid ones with the pose given for them, since KITTI files are matched line by line;
    ``"mcap"`` (any ``.mcap`` path, whatever text format is asked) or ``"rosbag2"`` (a new ROS 2
    bag folder): a
    ``geometry_msgs/PoseStamped`` per valid scan on ``/jaxloc/pose`` and a ``std_msgs/Bool``
    verdict per scan on ``/jaxloc/valid``, stamped as the scan (or its number in seconds;
    :func:`~jaxloc.io.rosbag_poses.write_pose_bag`).

    Args:
        path: the file (or bag folder) to write.
        recording: the scans (their stamps and numbers).
        poses: (N, 4, 4) poses, one per scan; valid: (N,) bool.
        format: one of :data:`POSE_FORMATS` ("tum" and "mcap" write an ``.mcap`` path as MCAP;
            "kitti" and "rosbag2" refuse one).

    Returns:
        The number of scans left out (TUM, bags: the invalid ones; KITTI: 0).

    Raises:
        ValueError: another count of poses or flags, an unknown format or one that does not fit
            the path's name, or an error of the writer (naming the path).
    """
    path = Path(path)
    format = pose_format_for(path, format)
    poses = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    valid = np.asarray(valid, bool)
    if len(poses) != len(recording) or valid.shape != (len(recording),):
        raise ValueError(f"need one pose and flag per scan ({len(recording)}), got {len(poses)}")
    if format == "kitti":
        write_kitti(path, poses)
        return 0
    stamps = np.array(
        [
            n * 10**9 if t is None else t
            for n, t in zip(recording.numbers, recording.stamps, strict=True)
        ],
        np.int64,
    )
    if format == "tum":
        write_tum(path, poses[valid], stamps[valid])
    else:
        write_pose_bag(path, stamps, poses, valid)
    return int((~valid).sum())


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_centroid_scan": "read_centroid_scan",
    },
)
