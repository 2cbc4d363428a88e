"""Labelled LiDAR sequences on disk: the SemanticKITTI layout, a plain one, and HeLiPR's.

SemanticKITTI (checked against the dataset's documentation and its API code, PRBonn's
``semantic-kitti-api``, ``generate_sequential.py``: ``parse_calibration`` / ``parse_poses``)::

    SEQ_DIR/velodyne/NNNNNN.bin   float32 x y z intensity per point (sensor frame, metres)
    SEQ_DIR/labels/NNNNNN.label   uint32 per point: semantic id (low 16 bits), instance (high 16)
    SEQ_DIR/poses.txt             one line per scan: 12 numbers, the 3x4 pose P of the left camera
                                  (cam0) in the frame of the first cam0, row-major
    SEQ_DIR/calib.txt             lines "KEY: 12 numbers" (P0..P3, Tr); Tr maps velodyne points to
                                  cam0 points
    SEQ_DIR/times.txt             optional: one time per scan, seconds (KITTI's)

    T_map_scan = inv(Tr) @ P @ Tr   (the map frame is the velodyne frame of the first scan)

Plain: ``NNN.bin`` with ``NNN.label`` in ``SEQ_DIR`` (or ``velodyne/`` + ``labels/``), a
``poses.txt`` of ``T_map_scan`` and no ``calib.txt``. Scans are ordered by their file names,
numerically when the names are numbers (``0, 11, 102``; two files of one number, ``1.bin`` and
``01.bin``, are an error). Labels of both are raw SemanticKITTI ids (converted with
:func:`jaxloc.io.semantickitti.semantickitti_class_ids`).

HeLiPR / TripletLoc (:mod:`jaxloc.io.helipr`): ``LiDAR/<sensor>/<stamp>.bin``,
``labels/<stamp>.label`` (SPVNAS class ids, used as they are), ``LiDAR_GT/<Sensor>_gt.txt``;
``T_map_scan`` is the GT's LiDAR -> world pose (the map frame is the GT's world frame).

``poses.txt`` may be KITTI (12 numbers a line), 4x4 (16) or TUM (8: ``t x y z qx qy qz qw``;
:mod:`jaxloc.io.poses`). A pose file with timestamps is matched to scans with timestamps (HeLiPR's
file names, or ``times.txt``) by time: HeLiPR's GT by the exact integer nanosecond stamp, a TUM
file in seconds within 1 ms. Then a scan without a pose is left out of the sequence (listed in
``LidarSequence.skipped``) and a pose without a scan is ignored (counted in ``unused_poses``).
Otherwise poses belong to scans by order: line i to the i-th scan, and the counts must agree.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc._lazy import renamed_names
from jaxloc.io import helipr
from jaxloc.io._numbering import check_distinct_numbers
from jaxloc.io._text import data_lines, parse_finite_floats
from jaxloc.io.poses import PoseFile, check_rigid, match_timestamps, read_pose_file, seconds_to_ns
from jaxloc.io.semantickitti import LabelledScan, read_semantickitti_scan

#: The layouts :func:`open_lidar_sequence` reads.
LAYOUTS = ("semantickitti", "plain", "helipr")


class LidarSequence(NamedTuple):
    """A labelled LiDAR sequence found on disk (nothing is read but the poses and calibration).

    Attributes:
        root: the sequence folder.
        bins: per scan the ``.bin`` path; labels: the matching ``.label`` paths.
        T_map_scan: (N, 4, 4) float64 scan-to-map poses, or None when the folder has no poses.
        layout: "semantickitti" (``calib.txt`` present, camera poses converted), "plain" or
            "helipr".
        timestamps: (N,) int64 nanoseconds of the scans (HeLiPR's file names, ``times.txt``), or
            None.
        point_format: the records of the ``.bin`` files: "kitti" (float32 x y z intensity) or a
            HeLiPR sensor's ("ouster", "velodyne", "avia", "aeva"; :mod:`jaxloc.io.helipr`).
        label_ids: "semantickitti" (raw SemanticKITTI ids, converted) or "spvnas" (jaxloc's
            class ids already, TripletLoc's labels).
        sensor: the HeLiPR scan folder read (e.g. "Ouster"), else None.
        sensors: the HeLiPR scan folders that hold scans (``sensor`` among them), else ().
        skipped: scans left out because the pose file has no pose at their time.
        unused_poses: lines of the pose file that match no scan.
    """

    root: Path
    bins: tuple[Path, ...]
    labels: tuple[Path, ...]
    T_map_scan: np.ndarray | None
    layout: str
    timestamps: np.ndarray | None = None
    point_format: str = "kitti"
    label_ids: str = "semantickitti"
    sensor: str | None = None
    sensors: tuple[str, ...] = ()
    skipped: tuple[Path, ...] = ()
    unused_poses: int = 0


def scan_order_key(path: Path) -> tuple:
    """Sort key of a scan file: numeric stems as numbers (``0 < 11 < 102``), then by name."""
    stem = path.stem
    return (0, int(stem), stem) if stem.isascii() and stem.isdigit() else (1, 0, stem)


def detect_layout(path: str | os.PathLike) -> str | None:
    """The layout of a sequence folder: "semantickitti" (``velodyne/*.bin`` and ``calib.txt``),
    "helipr" (``LiDAR/<sensor>/*.bin``), "plain" (``velodyne/*.bin`` or ``*.bin``), or None."""
    root = Path(path)
    if not root.is_dir():
        return None
    velodyne = (root / "velodyne").is_dir() and any((root / "velodyne").glob("*.bin"))
    if velodyne and (root / "calib.txt").is_file():
        return "semantickitti"
    if helipr.is_helipr_dir(root):
        return "helipr"
    if velodyne or any(root.glob("*.bin")):
        return "plain"
    return None


def is_sequence_dir(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder of scans in a sequence layout: ``velodyne/*.bin``
    (SemanticKITTI, plain) or ``LiDAR/<sensor>/*.bin`` (HeLiPR). A folder of loose ``*.bin``
    files is a plain sequence too, but is not recognised here (force it with
    ``open_lidar_sequence(..., layout="plain")``)."""
    layout = detect_layout(path)
    return layout in ("semantickitti", "helipr") or (
        layout == "plain" and (Path(path) / "velodyne").is_dir()
    )


def read_kitti_calibration(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A KITTI ``calib.txt``: lines ``KEY: 12 numbers`` as (4, 4) float64 matrices by key.

    Raises:
        ValueError: a line without ``KEY:``, not 12 numbers, NaN/inf, or a key given twice
            (which matrix holds would be a guess) (file:line).
    """
    calibration = {}
    for line_number, line in data_lines(path):
        where = f"{path}:{line_number}"
        key, colon, values = line.partition(":")
        fields = values.split()
        if not colon or not key.strip() or len(fields) != 12:
            raise ValueError(f"{where}: expected 'KEY: 12 numbers', got {line[:60]!r}")
        if key.strip() in calibration:
            raise ValueError(f"{where}: {key.strip()} is given twice")
        matrix = np.eye(4)
        matrix[:3] = np.reshape(parse_finite_floats(fields, where, key.strip()), (3, 4))
        calibration[key.strip()] = matrix
    return calibration


def velodyne_to_camera(path: str | os.PathLike) -> np.ndarray:
    """``Tr`` (4, 4) of a KITTI ``calib.txt`` (``Tr`` or ``Tr_velo_to_cam``), checked rigid."""
    calibration = read_kitti_calibration(path)
    for key in ("Tr", "Tr_velo_to_cam"):
        if key in calibration:
            check_rigid(calibration[key][None], f"{path} ({key})")
            return calibration[key]
    raise ValueError(f"{path}: no 'Tr:' line (the velodyne-to-camera transform)")


def read_times(path: str | os.PathLike, count: int) -> np.ndarray:
    """KITTI's ``times.txt``: one time in seconds per scan, in scan order, as (count,) int64
    nanoseconds. The times must increase strictly: a repeated time would give two scans one pose
    and leave a pose unused, a decreasing one would pair scans with poses out of order.

    Raises:
        ValueError: naming ``file:line``: not one number a line, NaN/inf, a time that is not
            after the previous line's; or another count.
    """
    stamps: list[int] = []
    previous = ("", 0)  # the previous time as written, and its line
    for line_number, line in data_lines(path, comments=True):
        fields = line.split()
        where = f"{path}:{line_number}"
        if len(fields) != 1:
            raise ValueError(f"{where}: expected one time (seconds), got {line[:60]!r}")
        stamp = seconds_to_ns(fields[0], where)
        if stamps and stamp <= stamps[-1]:
            raise ValueError(
                f"{where}: time {fields[0][:40]} s is not after line {previous[1]}'s "
                f"({previous[0][:40]} s); the times must increase, one per scan in scan order"
            )
        stamps.append(stamp)
        previous = (fields[0], line_number)
    if len(stamps) != count:
        raise ValueError(f"{path}: {len(stamps)} times for {count} scans")
    return np.asarray(stamps, np.int64)


def assign_poses(
    found: PoseFile, scan_stamps: np.ndarray | None, num_scans: int, path: str | os.PathLike
) -> tuple[np.ndarray, np.ndarray, int]:
    """Poses of a pose file for ``num_scans`` scans: by time when both have timestamps (exact for
    stamps in nanoseconds, within 1 ms for seconds; :meth:`PoseFile.match_tolerance_ns`), else
    by order (then the counts must agree).

    Returns:
        ``poses`` (num_scans, 4, 4) float64 (identity where unmatched), ``matched``
        (num_scans,) bool and the number of poses of the file that match no scan.

    Raises:
        ValueError: naming ``path``: another count by order, or no scan matched by time.
    """
    if found.timestamps is None or scan_stamps is None:
        if len(found.poses) != num_scans:
            raise ValueError(f"{path}: {len(found.poses)} poses for {num_scans} scans")
        return found.poses, np.ones(num_scans, bool), 0
    index = match_timestamps(scan_stamps, found.timestamps, found.match_tolerance_ns())
    matched = index >= 0
    if num_scans and not matched.any():
        raise ValueError(
            f"{path}: no pose has the time of a scan (scans from {scan_stamps.min()} to "
            f"{scan_stamps.max()} ns, poses from {found.timestamps.min()} to "
            f"{found.timestamps.max()} ns)"
        )
    poses = np.tile(np.eye(4), (num_scans, 1, 1))
    poses[matched] = found.poses[index[matched]]
    return poses, matched, len(found.poses) - len(np.unique(index[matched]))


def check_distinct_scan_numbers(bins: list[Path], what: str = "number") -> None:
    """Raise ``ValueError`` naming both files when two of the scans, sorted by
    :func:`scan_order_key`, are named by the same number (``1.bin`` and ``01.bin``): the scan of
    that number, its place in the order and its pose or stamp would be ambiguous. ``what`` names
    the number in the message ("number", or "stamp" for HeLiPR's nanosecond names)."""
    numbered = [(key[1], path) for path in bins if (key := scan_order_key(path))[0] == 0]
    check_distinct_numbers(numbered, f"scans named by the same {what}")


def _kitti_scan_files(root: Path) -> tuple[list[Path], list[Path]]:
    if (root / "velodyne").is_dir():
        bins = sorted((root / "velodyne").glob("*.bin"), key=scan_order_key)
        labels = [root / "labels" / path.with_suffix(".label").name for path in bins]
    else:
        bins = sorted(root.glob("*.bin"), key=scan_order_key)
        labels = [path.with_suffix(".label") for path in bins]
    if not bins:
        raise ValueError(f"{root}: no scans (expected velodyne/*.bin or *.bin)")
    check_distinct_scan_numbers(bins)
    return bins, labels


def _check_labels(labels: list[Path]) -> None:
    for label in labels:
        if not label.is_file():
            raise FileNotFoundError(f"{label}: missing label file")


def _select(
    sequence: LidarSequence, keep: np.ndarray, skipped: list[Path], unused: int
) -> LidarSequence:
    def pick(items):
        return tuple(item for item, k in zip(items, keep, strict=True) if k)

    return sequence._replace(
        bins=pick(sequence.bins),
        labels=pick(sequence.labels),
        T_map_scan=None if sequence.T_map_scan is None else sequence.T_map_scan[keep],
        timestamps=None if sequence.timestamps is None else sequence.timestamps[keep],
        skipped=tuple(skipped),
        unused_poses=unused,
    )


def _with_poses(sequence: LidarSequence, found: PoseFile, path: Path) -> LidarSequence:
    poses, matched, unused = assign_poses(found, sequence.timestamps, len(sequence.bins), path)
    sequence = sequence._replace(T_map_scan=poses, unused_poses=unused)
    if matched.all():
        return sequence
    skipped = [scan for scan, ok in zip(sequence.bins, matched, strict=True) if not ok]
    return _select(sequence, matched, skipped, unused)


def _kitti_sequence(root: Path, layout: str, require_poses: bool) -> LidarSequence:
    bins, labels = _kitti_scan_files(root)
    _check_labels(labels)
    times = root / "times.txt"
    stamps = read_times(times, len(bins)) if times.is_file() else None
    sequence = LidarSequence(root, tuple(bins), tuple(labels), None, layout, stamps)
    poses_path = root / "poses.txt"
    if not poses_path.is_file():
        if require_poses:
            raise FileNotFoundError(f"{poses_path}: missing poses (one per scan)")
        return sequence
    sequence = _with_poses(sequence, read_pose_file(poses_path), poses_path)
    if layout == "semantickitti":
        tr = velodyne_to_camera(root / "calib.txt")
        sequence = sequence._replace(T_map_scan=np.linalg.inv(tr) @ sequence.T_map_scan @ tr)
    return sequence


def _helipr_sequence(root: Path, sensor: str | None, require_poses: bool) -> LidarSequence:
    sensor = helipr.choose_sensor(root, sensor)
    folder = root / "LiDAR" / sensor
    # hidden files (macOS "._<stamp>.bin" resource forks in unpacked archives) are not scans
    bins = sorted(
        (p for p in folder.glob("*.bin") if not p.name.startswith(".")), key=scan_order_key
    )
    if not bins:
        raise ValueError(f"{folder}: no scans (<stamp>.bin)")
    check_distinct_scan_numbers(bins, "stamp")
    stamps = np.array([helipr.scan_stamp(path) for path in bins], np.int64)  # sorted, as bins
    labels_dir = helipr.label_folder(root)
    labels = [labels_dir / path.with_suffix(".label").name for path in bins]
    sequence = LidarSequence(
        root,
        tuple(bins),
        tuple(labels),
        None,
        "helipr",
        stamps,
        helipr.SENSOR_FORMATS[sensor],
        "spvnas",
        sensor,
        tuple(helipr.helipr_sensors(root)),
    )
    gt_path = root / "LiDAR_GT" / helipr.GT_FILES[sensor]
    if gt_path.is_file():
        gt = helipr.read_helipr_gt(gt_path)
        found = PoseFile(gt.T_world_lidar, gt.stamps, "tum", "ns")
        sequence = _with_poses(sequence, found, gt_path)
    elif require_poses:
        raise FileNotFoundError(
            f"{gt_path}: missing ground-truth poses ('stamp x y z qx qy qz qw')"
        )
    _check_labels(list(sequence.labels))
    return sequence


def open_lidar_sequence(
    seq_dir: str | os.PathLike,
    require_poses: bool = True,
    layout: str | None = None,
    sensor: str | None = None,
) -> LidarSequence:
    """Find the scans of a sequence folder and read its poses (see the module docstring).

    Args:
        seq_dir: the sequence folder.
        require_poses: raise when the folder has no pose file (else ``T_map_scan`` is None).
        layout: "semantickitti", "plain" or "helipr"; None detects it (:func:`detect_layout`).
        sensor: the HeLiPR scan folder (``LiDAR/<sensor>/``, case-insensitive); None takes the
            only one present, else Ouster (:func:`jaxloc.io.helipr.choose_sensor`).

    Raises:
        FileNotFoundError: no such folder, a scan without its label file, no pose file.
        ValueError: no scans, two scans named by one number or stamp, an unknown layout, a
            malformed pose, calibration or times file (times that do not increase, a TUM stamp
            on two lines), a pose count that differs from the scan count, poses whose times match
            no scan (each naming the file).
    """
    root = Path(seq_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such sequence folder")
    if layout is None:
        layout = detect_layout(root) or "plain"
    if layout == "helipr":
        return _helipr_sequence(root, sensor, require_poses)
    if layout not in LAYOUTS:
        raise ValueError(f"unknown sequence layout {layout!r}; expected one of {LAYOUTS}")
    if layout == "semantickitti" and not (root / "calib.txt").is_file():
        raise FileNotFoundError(f"{root / 'calib.txt'}: missing (the SemanticKITTI layout)")
    return _kitti_sequence(root, layout, require_poses)


def read_sequence_scan(sequence: LidarSequence, index: int) -> LabelledScan:
    """Scan ``index`` of ``sequence`` as a :class:`LabelledScan` (class ids), whatever the layout:
    SemanticKITTI records and raw ids, or a HeLiPR sensor's records and SPVNAS ids.

    Raises:
        FileNotFoundError: a missing file.
        ValueError: a malformed scan or label file (naming it).
    """
    if sequence.point_format == "kitti" and sequence.label_ids == "semantickitti":
        return read_semantickitti_scan(sequence.bins[index], sequence.labels[index])
    if sequence.label_ids != "spvnas" or sequence.point_format == "kitti":
        raise ValueError(
            f"{sequence.root}: unsupported scan format {sequence.point_format!r} with "
            f"{sequence.label_ids!r} labels"
        )
    stamp = None if sequence.timestamps is None else int(sequence.timestamps[index])
    return helipr.read_helipr_scan(
        sequence.bins[index], sequence.labels[index], sequence.point_format, stamp
    )


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_sequence_scan": "read_sequence_scan",
        "load_lidar_sequence": "open_lidar_sequence",
    },
)
