"""HeLiPR / TripletLoc sequences written byte by byte for the tests, independently of
:mod:`jaxloc.io.helipr`.

The point records are packed field by field in the order of the C++ readers that define the
format (HeLiPR-File-Player ``src/ROSThread.cpp``: ``file.read(&point.x, sizeof(float))`` ...;
HeLiPR-Pointcloud-Toolbox ``src/PointCloudProcessor.cpp`` ``readBinFile``; TripletLoc
``src/TripletLoc.cpp`` ``get_pointcloud_with_semantic_helipr``), little-endian, without padding:
each field is turned into its bytes on its own and the columns are concatenated, so no numpy
structured dtype (what the reader under test uses) is involved. Labels are a uint16 class id
then a uint16 instance id per point; GT lines are ``stamp_ns x y z qx qy qz qw``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

#: SemanticKITTI raw id -> SPVNAS (TripletLoc) class id: the learning map of
#: semantic-kitti-api's config/semantic-kitti.yaml minus one, for the ids the synthetic scans use
#: (71 trunk, 80 pole, 81 traffic sign, 40 road, 50 building).
RAW_TO_SPVNAS = {71: 15, 80: 17, 81: 18, 40: 8, 50: 12}
#: A HeLiPR-like first stamp (ns) and scan period (100 ms, 10 Hz).
FIRST_STAMP, PERIOD_NS = 1_691_900_000_123_456_789, 100_000_000
#: Aeva scans after this stamp have the 29-byte records (HeLiPR-File-Player ``ROSThread.cpp``).
AEVA_THRESHOLD = 1691936557946849179

#: Per sensor folder: the record's fields in file order, as (name, little-endian numpy type).
FIELDS = {
    "Ouster": [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("intensity", "<f4"),
        ("t", "<u4"),
        ("reflectivity", "<u2"),
        ("ring", "<u2"),
        ("ambient", "<u2"),
    ],
    "Velodyne": [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("intensity", "<f4"),
        ("ring", "<u2"),
        ("time", "<f4"),
    ],
    "Avia": [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("reflectivity", "<u1"),
        ("tag", "<u1"),
        ("line", "<u1"),
        ("offset_time", "<u4"),
    ],
    "Aeva": [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("reflectivity", "<f4"),
        ("velocity", "<f4"),
        ("time_offset_ns", "<i4"),
        ("line_index", "<u1"),
    ],
}
FIELDS["Ouster_filterd"] = FIELDS["Ouster"]
AEVA_INTENSITY = ("intensity", "<f4")


def record_fields(sensor: str, stamp: int) -> list[tuple[str, str]]:
    """The fields of ``sensor``'s records in a scan stamped ``stamp`` (Aeva grows one field)."""
    fields = list(FIELDS[sensor])
    if sensor == "Aeva" and stamp > AEVA_THRESHOLD:
        fields.append(AEVA_INTENSITY)
    return fields


def pack_records(points: np.ndarray, sensor: str, stamp: int) -> bytes:
    """Points (N, 3) float32 as ``sensor`` records; the other fields get deterministic values
    derived from the point index (so a reader that slips a byte would move x, y, z)."""
    n = len(points)
    index = np.arange(n)
    columns = []
    for name, dtype in record_fields(sensor, stamp):
        if name in ("x", "y", "z"):
            values = points[:, "xyz".index(name)]
        elif np.dtype(dtype).kind == "f":
            values = 0.5 + (index % 97) * 0.25
        else:
            values = (index * 7 + len(name)) % np.iinfo(np.dtype(dtype)).max
        column = np.ascontiguousarray(np.asarray(values).astype(dtype))
        columns.append(column.view(np.uint8).reshape(n, np.dtype(dtype).itemsize))
    return np.concatenate(columns, axis=1).tobytes() if n else b""


def pack_labels(raw_labels: np.ndarray) -> bytes:
    """SemanticKITTI words (semantic | instance << 16) as SPVNAS labels: uint16 class, uint16
    instance."""
    raw = np.asarray(raw_labels, np.uint32)
    classes = np.array([RAW_TO_SPVNAS[int(r)] for r in raw & 0xFFFF], "<u2")
    instances = (raw >> 16).astype("<u2")
    return np.column_stack([classes, instances]).astype("<u2").tobytes()


def tum_line(stamp: str, pose: np.ndarray) -> str:
    """``stamp x y z qx qy qz qw`` with repr floats (scipy's quaternion, x y z w order)."""
    q = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return " ".join([stamp, *(repr(float(v)) for v in pose[:3, 3]), *(repr(float(v)) for v in q)])


def ns_to_seconds(ns: int) -> str:
    """Exact decimal seconds of a positive ns stamp."""
    seconds, rest = divmod(int(ns), 10**9)
    return f"{seconds}.{rest:09d}"


def write_helipr_sequence(
    root: Path,
    scans,
    sensor: str = "Ouster",
    label_folder: str = "labels",
    stamps: list[int] | None = None,
    gt_poses: np.ndarray | None = None,
    gt_stamps: list[int] | None = None,
) -> list[int]:
    """Write ``scans`` (a :class:`jaxloc.synthetic.lidar_scans.LabelledScans`) as
    ``root/LiDAR/<sensor>/<stamp>.bin``, ``root/<label_folder>/<stamp>.label`` and
    ``root/LiDAR_GT/<Sensor>_gt.txt`` (``gt_poses``/``gt_stamps`` default to the scans' own).
    Returns the scan stamps."""
    stamps = (
        [FIRST_STAMP + i * PERIOD_NS for i in range(len(scans.points))]
        if stamps is None
        else stamps
    )
    (root / "LiDAR" / sensor).mkdir(parents=True, exist_ok=True)
    (root / label_folder).mkdir(exist_ok=True)
    for stamp, points, raw in zip(stamps, scans.points, scans.raw_labels, strict=True):
        (root / "LiDAR" / sensor / f"{stamp}.bin").write_bytes(pack_records(points, sensor, stamp))
        (root / label_folder / f"{stamp}.label").write_bytes(pack_labels(raw))
    poses = scans.T_map_scan if gt_poses is None else gt_poses
    gt_stamps = stamps if gt_stamps is None else gt_stamps
    (root / "LiDAR_GT").mkdir(exist_ok=True)
    lines = [tum_line(str(stamp), pose) for stamp, pose in zip(gt_stamps, poses, strict=True)]
    gt_name = sensor.split("_")[0] + "_gt.txt"
    (root / "LiDAR_GT" / gt_name).write_text("\n".join(lines) + "\n")
    return stamps


def write_kitti_twin(root: Path, scans, poses: np.ndarray) -> None:
    """The same scans in the SemanticKITTI layout, with ``calib.txt`` Tr = identity and
    ``poses.txt`` the given ``T_map_scan`` as repr floats (so the reader's
    ``inv(Tr) @ P @ Tr`` is exactly ``P``)."""
    (root / "velodyne").mkdir(parents=True, exist_ok=True)
    (root / "labels").mkdir(exist_ok=True)
    for index, (points, raw) in enumerate(zip(scans.points, scans.raw_labels, strict=True)):
        xyzi = np.column_stack([points, np.zeros(len(points), np.float32)]).astype("<f4")
        xyzi.tofile(root / "velodyne" / f"{index:06d}.bin")
        np.asarray(raw, "<u4").tofile(root / "labels" / f"{index:06d}.label")
    rows = [" ".join(repr(float(v)) for v in pose[:3].ravel()) for pose in poses]
    (root / "poses.txt").write_text("\n".join(rows) + "\n")
    (root / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
