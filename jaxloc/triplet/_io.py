"""Loaders: SemanticKITTI scans (.bin/.label) and TripletLoc/HeLiPR instance maps (text).

Class ids follow TripletLoc/Cylinder3D: SemanticKITTI learning ids minus one (13 fence,
14 vegetation, 15 trunk, 16 terrain, 17 pole, 18 traffic sign); unlabeled points get -1.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc._textio import read_float_table

TRUNK, POLE, TRAFFIC_SIGN = 15, 17, 18
#: The classes TripletLoc/M2Loc build graphs from.
GRAPH_CLASSES: tuple[int, ...] = (TRUNK, POLE, TRAFFIC_SIGN)

# SemanticKITTI raw id -> learning id (semantic-kitti.yaml), 0 = unlabeled.
_LEARNING_MAP = {
    0: 0, 1: 0, 10: 1, 11: 2, 13: 5, 15: 3, 16: 5, 18: 4, 20: 5, 30: 6, 31: 7, 32: 8,
    40: 9, 44: 10, 48: 11, 49: 12, 50: 13, 51: 14, 52: 0, 60: 9, 70: 15, 71: 16, 72: 17,
    80: 18, 81: 19, 99: 0, 252: 1, 253: 7, 254: 6, 255: 8, 256: 5, 257: 5, 258: 4, 259: 5,
}  # fmt: skip


def semantickitti_class_ids(raw_labels: np.ndarray) -> np.ndarray:
    """Map raw SemanticKITTI semantic ids (N,) to class ids (learning id - 1; -1 unlabeled)."""
    lut = np.full(65536, -1, np.int32)
    for raw, learning in _LEARNING_MAP.items():
        lut[raw] = learning - 1
    return lut[np.asarray(raw_labels, np.int64) & 0xFFFF]


class LabelledScan(NamedTuple):
    """A labelled LiDAR scan: ``points`` (N, 3) float32 metres in the sensor frame, ``labels`` (N,)
    int32 class ids, ``instance_ids`` (N,) int32 (the label file's high 16 bits)."""

    points: np.ndarray
    labels: np.ndarray
    instance_ids: np.ndarray


def load_semantickitti_scan(bin_path: str | Path, label_path: str | Path) -> LabelledScan:
    """Read a SemanticKITTI scan: ``.bin`` float32 (x, y, z, intensity), ``.label`` uint32.

    Raises:
        ValueError: on sizes that are not whole records, mismatched counts or non-finite points.
    """
    raw = np.fromfile(bin_path, dtype="<f4")
    if raw.size % 4:
        raise ValueError(f"{bin_path}: {raw.size} floats is not a multiple of 4 (x, y, z, i)")
    points = raw.reshape(-1, 4)[:, :3].copy()
    label_words = np.fromfile(label_path, dtype="<u4")
    if label_words.size != points.shape[0]:
        raise ValueError(
            f"{label_path}: {label_words.size} labels for {points.shape[0]} points in {bin_path}"
        )
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{bin_path}: non-finite point coordinates")
    labels = semantickitti_class_ids(label_words & 0xFFFF)
    return LabelledScan(points, labels, (label_words >> 16).astype(np.int32))


class InstanceMap(NamedTuple):
    """Instance centroids of a map: ``points`` (N, 3) float64 metres (map frame), ``labels`` (N,)
    int32 class ids, ``ids`` (N,) int64 per-class instance ids from the files."""

    points: np.ndarray
    labels: np.ndarray
    ids: np.ndarray


class RoadNormals(NamedTuple):
    """Road-surface-normal (RSN) cells: ``xy`` (M, 2) cell centres (map frame, metres),
    ``normals`` (M, 3) unit normals, ``std_deg`` (M,) normal standard deviation in degrees."""

    xy: np.ndarray
    normals: np.ndarray
    std_deg: np.ndarray


def load_instance_map(map_dir: str | Path, classes: tuple[int, ...] = GRAPH_CLASSES) -> InstanceMap:
    """Read ``<map_dir>/instances/<class>.txt`` files (lines ``id x y z``) into one InstanceMap.

    Raises:
        FileNotFoundError: a class file is missing.
        ValueError: a malformed line (wrong field count, non-number, non-finite), with file:line.
    """
    points, labels, ids = [], [], []
    for class_id in classes:
        table = read_float_table(Path(map_dir) / "instances" / f"{class_id}.txt", 4, "id x y z")
        if np.any(table[:, 0] != np.round(table[:, 0])):
            raise ValueError(f"{map_dir}/instances/{class_id}.txt: non-integer instance id")
        points.append(table[:, 1:4])
        labels.append(np.full(table.shape[0], class_id, np.int32))
        ids.append(table[:, 0].astype(np.int64))
    return InstanceMap(np.concatenate(points), np.concatenate(labels), np.concatenate(ids))


def load_road_normals(map_dir: str | Path) -> RoadNormals:
    """Read ``<map_dir>/RSN/road_normal.txt`` (lines ``x y nx ny nz std_deg``), normals unit-scaled.

    Raises:
        ValueError: a malformed line, a zero normal, or a negative standard deviation.
    """
    path = Path(map_dir) / "RSN" / "road_normal.txt"
    table = read_float_table(path, 6, "x y nx ny nz std_deg")
    norms = np.linalg.norm(table[:, 2:5], axis=1)
    if np.any(norms < 1e-6):
        raise ValueError(f"{path}: zero-length road normal")
    if np.any(table[:, 5] < 0):
        raise ValueError(f"{path}: negative normal standard deviation")
    return RoadNormals(table[:, 0:2], table[:, 2:5] / norms[:, None], table[:, 5])
