"""HeLiPR / TripletLoc sequences: timestamped scans of four LiDARs, SPVNAS labels, GT poses.

Layout (HeLiPR's download; TripletLoc's released query data)::

    SEQ/LiDAR/<sensor>/<stamp>.bin    one scan, packed little-endian point records (below);
                                      <sensor>: Ouster, Velodyne, Avia, Aeva, or TripletLoc's
                                      Ouster_filterd (Ouster records, points with
                                      sqrt(x^2 + y^2) > 150 m removed)
    SEQ/labels/<stamp>.label          per point a uint16 class id and a uint16 instance id
    SEQ/label/<stamp>.label           (TripletLoc's code reads labels/, its README shows label/;
                                      both are accepted, labels/ first)
    SEQ/LiDAR_GT/<Sensor>_gt.txt      one line per scan: ``stamp x y z qx qy qz qw``, the pose
                                      LiDAR -> world (Ouster_gt.txt for Ouster_filterd)

``<stamp>`` is the scan's time in integer nanoseconds since the epoch (~1.69e18). A scan is
matched to the GT line whose first field is the same integer (as TripletLoc does: it opens
``<stamp>.bin`` for each GT line), never to a nearby time.

Point records (one after another, no header; sensor from the folder name, since the sizes do not
tell the sensors apart)::

    Ouster    x y z intensity f32, t u32 (ns in the scan), reflectivity ring ambient u16  26 B
    Velodyne  x y z intensity f32, ring u16, time f32 (s in the scan)                     22 B
    Avia      x y z f32, reflectivity tag line u8, offset_time u32 (ns)                   19 B
    Aeva      x y z reflectivity velocity f32, time_offset_ns i32, line_index u8          25 B
              ... + intensity f32 when the stamp is > 1691936557946849179                 29 B

Checked against the readers of the dataset's authors and of TripletLoc: HeLiPR-File-Player
``src/ROSThread.h`` (point structs) and ``src/ROSThread.cpp`` (the field-by-field ``.bin``
readers and the Aeva stamp threshold; HeLiPR-File-Player@e8d95e3), HeLiPR-Pointcloud-Toolbox
``src/PointCloudProcessor.cpp`` (``readBinFile`` overloads, ``loadTrajectory``: stamps in ns),
HeLiMOS-PointCloud-Toolbox ``README.md`` (the ``LiDAR_GT/{Aeva,Avia,Ouster,Velodyne}_gt.txt``
names and the ``timestamp x y z qx qy qz qw`` columns), TripletLoc ``src/TripletLoc.cpp``
(``get_config``: the paths; ``get_pointcloud_with_semantic_helipr``: Ouster records and the
uint16 + uint16 labels; ``get_pose_gt_Helipr``: ``Quaterniond(w, x, y, z)`` from columns
7, 4, 5, 6, i.e. x y z w order) and ``src/preprocoss_filter_pc_heliper.cpp`` (the 150 m filter,
same records), all read through the repositories' public sources. The C++ readers loop
``while (!file.eof())`` and so append one garbage point; here a file that is not a whole number
of records is an error instead.

Labels are the class ids of TripletLoc's pretrained SPVNAS: 0-based SemanticKITTI learning ids
(8 road, 15 trunk, 17 pole, 18 traffic sign), which are jaxloc's class ids already, so no
learning map is applied (unlike SemanticKITTI's raw ids, :mod:`jaxloc.io.semantickitti`). Ids
above 18 (nothing SPVNAS's 19 classes produce) are read as unlabelled (-1).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc._lazy import renamed_names
from jaxloc.io.poses import read_pose_file
from jaxloc.io.semantickitti import LabelledScan, check_point_range

_F4, _U1, _U2, _U4, _I4 = "<f4", "<u1", "<u2", "<u4", "<i4"
_XYZ = [("x", _F4), ("y", _F4), ("z", _F4)]

#: Packed little-endian point records per sensor (numpy structured dtypes, no padding).
POINT_DTYPES: dict[str, np.dtype] = {
    "ouster": np.dtype(
        [
            *_XYZ,
            ("intensity", _F4),
            ("t", _U4),
            ("reflectivity", _U2),
            ("ring", _U2),
            ("ambient", _U2),
        ]
    ),
    "velodyne": np.dtype([*_XYZ, ("intensity", _F4), ("ring", _U2), ("time", _F4)]),
    "avia": np.dtype(
        [*_XYZ, ("reflectivity", _U1), ("tag", _U1), ("line", _U1), ("offset_time", _U4)]
    ),
    "aeva_v1": np.dtype(
        [
            *_XYZ,
            ("reflectivity", _F4),
            ("velocity", _F4),
            ("time_offset_ns", _I4),
            ("line_index", _U1),
        ]
    ),
}
POINT_DTYPES["aeva_v2"] = np.dtype([*POINT_DTYPES["aeva_v1"].descr, ("intensity", _F4)])

#: Aeva scans stamped after this (ns) carry the extra intensity field (HeLiPR's file player).
AEVA_INTENSITY_SINCE = 1691936557946849179

#: Scan folders under ``SEQ/LiDAR/`` -> point format (TripletLoc's Ouster_filterd keeps Ouster's).
SENSOR_FORMATS = {
    "Ouster": "ouster",
    "Ouster_filterd": "ouster",
    "Velodyne": "velodyne",
    "Avia": "avia",
    "Aeva": "aeva",
}
#: The GT file of each scan folder, under ``SEQ/LiDAR_GT/``.
GT_FILES = {sensor: f"{sensor.split('_')[0]}_gt.txt" for sensor in SENSOR_FORMATS}
#: Label folders, in the order they are looked for.
LABEL_FOLDERS = ("labels", "label")
#: SPVNAS (TripletLoc) labels are class ids 0..18; larger ids are unlabelled.
NUM_SPVNAS_CLASSES = 19


class HeliprGroundTruth(NamedTuple):
    """A ``LiDAR_GT/<Sensor>_gt.txt``: ``stamps`` (M,) int64 ns and ``T_world_lidar`` (M, 4, 4)
    float64."""

    stamps: np.ndarray
    T_world_lidar: np.ndarray


def point_dtype(point_format: str, stamp_ns: int | None = None) -> np.dtype:
    """The record dtype of ``point_format`` ("ouster", "velodyne", "avia", "aeva"; an Aeva scan
    needs its ``stamp_ns``: 29-byte records after :data:`AEVA_INTENSITY_SINCE`, else 25)."""
    if point_format == "aeva":
        if stamp_ns is None:
            raise ValueError("an Aeva scan's record size depends on its timestamp")
        return POINT_DTYPES["aeva_v2" if stamp_ns > AEVA_INTENSITY_SINCE else "aeva_v1"]
    if point_format not in POINT_DTYPES:
        raise ValueError(f"unknown point format {point_format!r}; known: {sorted(SENSOR_FORMATS)}")
    return POINT_DTYPES[point_format]


def scan_stamp(path: str | os.PathLike) -> int:
    """The integer nanosecond stamp a HeLiPR scan or label file is named by.

    Raises:
        ValueError: the file name (without suffix) is not a non-negative integer.
    """
    stem = Path(path).stem
    if not (stem.isascii() and stem.isdigit()):
        raise ValueError(f"{path}: a HeLiPR scan is named <stamp_ns>.bin, got {Path(path).name!r}")
    return int(stem)


def read_helipr_points(
    path: str | os.PathLike, point_format: str, stamp_ns: int | None = None
) -> np.ndarray:
    """The point records of one HeLiPR ``.bin`` as a structured array (fields as
    :data:`POINT_DTYPES`; ``stamp_ns`` defaults to the file name's, for Aeva).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file: a size that is not a whole number of records.
    """
    path = Path(path)
    if point_format == "aeva" and stamp_ns is None:
        stamp_ns = scan_stamp(path)
    dtype = point_dtype(point_format, stamp_ns)
    data = path.read_bytes()
    if len(data) % dtype.itemsize:
        raise ValueError(
            f"{path}: {len(data)} bytes is not a whole number of {dtype.itemsize}-byte "
            f"{point_format} point records"
        )
    return np.frombuffer(data, dtype)


def read_spvnas_labels(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """A TripletLoc ``.label``: per point a uint16 SPVNAS class id and a uint16 instance id
    (little-endian; the same bytes as a SemanticKITTI uint32 label word).

    Returns:
        ``labels`` (N,) int32 class ids (-1 for ids above 18) and ``instance_ids`` (N,) int32.

    Raises:
        ValueError: naming the file: a size that is not a multiple of 4 bytes.
    """
    data = Path(path).read_bytes()
    if len(data) % 4:
        raise ValueError(f"{path}: {len(data)} bytes is not a whole number of 4-byte labels")
    words = np.frombuffer(data, "<u2").reshape(-1, 2)
    classes = words[:, 0].astype(np.int32)
    classes[classes >= NUM_SPVNAS_CLASSES] = -1
    return classes, words[:, 1].astype(np.int32)


def read_helipr_scan(
    bin_path: str | os.PathLike,
    label_path: str | os.PathLike,
    point_format: str,
    stamp_ns: int | None = None,
) -> LabelledScan:
    """One labelled HeLiPR scan: points of ``bin_path`` (``point_format`` records, sensor frame,
    metres) with the SPVNAS labels of ``label_path``.

    Raises:
        FileNotFoundError: a missing file.
        ValueError: naming the file: partial records, a label count that differs from the point
            count, NaN/inf coordinates or points beyond
            :data:`~jaxloc.io.semantickitti.MAX_RANGE_M`.
    """
    records = read_helipr_points(bin_path, point_format, stamp_ns)
    points = np.column_stack([records["x"], records["y"], records["z"]]).astype(np.float32)
    labels, instances = read_spvnas_labels(label_path)
    if labels.size != points.shape[0]:
        raise ValueError(
            f"{label_path}: {labels.size} labels for {points.shape[0]} points in {bin_path}"
        )
    check_point_range(points, str(bin_path))
    return LabelledScan(points.reshape(-1, 3), labels, instances)


def read_helipr_gt(path: str | os.PathLike) -> HeliprGroundTruth:
    """A HeLiPR GT file (``stamp_ns x y z qx qy qz qw`` lines, LiDAR -> world).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming ``file:line``: not 8 fields, a stamp that is not an integer, NaN/inf,
            a quaternion that is not unit, a repeated stamp (as every TUM file,
            :func:`jaxloc.io.poses.read_pose_file`).
    """
    found = read_pose_file(path, time_unit="ns")
    if found.format != "tum":
        raise ValueError(f"{path}: expected 'stamp x y z qx qy qz qw' lines, got {found.format}")
    return HeliprGroundTruth(found.timestamps, found.poses)


def helipr_sensors(seq_dir: str | os.PathLike) -> list[str]:
    """The scan folders of ``SEQ/LiDAR/`` (names of :data:`SENSOR_FORMATS`) that hold ``.bin``
    files, in :data:`SENSOR_FORMATS` order."""
    lidar = Path(seq_dir) / "LiDAR"
    return [
        sensor
        for sensor in SENSOR_FORMATS
        if (lidar / sensor).is_dir() and any((lidar / sensor).glob("*.bin"))
    ]


def is_helipr_dir(seq_dir: str | os.PathLike) -> bool:
    """Whether ``seq_dir`` has ``LiDAR/<sensor>/*.bin`` scans (a HeLiPR / TripletLoc sequence)."""
    return bool(helipr_sensors(seq_dir))


def choose_sensor(seq_dir: str | os.PathLike, sensor: str | None = None) -> str:
    """The scan folder to read: ``sensor`` if given (matched case-insensitively), else the only
    one present, else Ouster (then Ouster_filterd).

    Raises:
        ValueError: the named sensor has no scans, or several sensors without Ouster.
    """
    present = helipr_sensors(seq_dir)
    if sensor is not None:
        for name in present:
            if name.lower() == sensor.lower():
                return name
        raise ValueError(
            f"{seq_dir}: no scans in LiDAR/{sensor}/ (sensors with scans: {present or 'none'})"
        )
    if not present:
        raise ValueError(f"{seq_dir}: no scans (expected LiDAR/<sensor>/<stamp>.bin)")
    if len(present) == 1:
        return present[0]
    for name in ("Ouster", "Ouster_filterd"):
        if name in present:
            return name
    raise ValueError(f"{seq_dir}: scans of several sensors {present}; choose one (sensor=...)")


def label_folder(seq_dir: str | os.PathLike) -> Path:
    """``SEQ/labels`` if it exists, else ``SEQ/label`` (which may not exist either)."""
    for name in LABEL_FOLDERS:
        if (Path(seq_dir) / name).is_dir():
            return Path(seq_dir) / name
    return Path(seq_dir) / LABEL_FOLDERS[0]


def helipr_scan_label(bin_path: str | os.PathLike) -> tuple[str, Path] | None:
    """For a ``SEQ/LiDAR/<sensor>/<stamp>.bin`` path, its point format and label path
    (``SEQ/labels/`` or ``SEQ/label/``); None for a path outside that layout."""
    path = Path(bin_path)
    if path.parent.name not in SENSOR_FORMATS or path.parent.parent.name != "LiDAR":
        return None
    seq = path.parent.parent.parent
    return SENSOR_FORMATS[path.parent.name], label_folder(seq) / path.with_suffix(".label").name


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_helipr_scan": "read_helipr_scan",
    },
)
