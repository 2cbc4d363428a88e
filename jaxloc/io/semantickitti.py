"""SemanticKITTI scans: ``.bin`` points and ``.label`` semantic / instance labels.

Class ids follow TripletLoc/Cylinder3D: SemanticKITTI learning ids minus one (13 fence,
14 vegetation, 15 trunk, 16 terrain, 17 pole, 18 traffic sign); unlabeled points get -1.

Every LiDAR reader (these files, HeLiPR's, centroid files, bags) refuses what no sensor records:
a point farther than :data:`MAX_RANGE_M` from the sensor (:func:`check_point_range`; such
coordinates come from records of another type, e.g. float64 read as float32) and, for raw
SemanticKITTI ids, an id the learning map does not know (:func:`checked_class_ids`).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc._lazy import renamed_names

# SemanticKITTI raw id -> learning id (semantic-kitti.yaml), 0 = unlabeled.
_LEARNING_MAP = {
    0: 0, 1: 0, 10: 1, 11: 2, 13: 5, 15: 3, 16: 5, 18: 4, 20: 5, 30: 6, 31: 7, 32: 8,
    40: 9, 44: 10, 48: 11, 49: 12, 50: 13, 51: 14, 52: 0, 60: 9, 70: 15, 71: 16, 72: 17,
    80: 18, 81: 19, 99: 0, 252: 1, 253: 7, 254: 6, 255: 8, 256: 5, 257: 5, 258: 4, 259: 5,
}  # fmt: skip


#: The raw SemanticKITTI ids (semantic-kitti.yaml), sorted.
SEMANTICKITTI_IDS = tuple(sorted(_LEARNING_MAP))
#: Metres: no point of a scan is farther from its sensor. Automotive and mapping LiDARs return
#: points up to 200-500 m (Ouster OS2 240 m, Livox Avia 450 m, Aeva Aeries II 500 m); twice the
#: longest leaves a margin, while points read from records of another type (float64 words read
#: as float32) reach 1e19 m and more.
MAX_RANGE_M = 1000.0


def check_point_range(points: np.ndarray, where: str) -> None:
    """Raise ``ValueError`` naming ``where`` unless every point of ``points`` (N, 3) (sensor
    frame, metres) is finite and at most :data:`MAX_RANGE_M` from the sensor."""
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{where}: non-finite point coordinates")
    ranges = np.linalg.norm(np.asarray(points, np.float64).reshape(-1, 3), axis=1)
    far = np.flatnonzero(ranges > MAX_RANGE_M)
    if far.size:
        raise ValueError(
            f"{where}: {far.size} point(s) beyond {MAX_RANGE_M:g} m of the sensor (point "
            f"{far[0]} at {ranges[far[0]]:.3g} m): not metres in the sensor frame, or records of "
            "another type"
        )


def checked_class_ids(raw_ids: np.ndarray, where: str) -> np.ndarray:
    """Raw SemanticKITTI semantic ids (N,) as class ids (:func:`semantickitti_class_ids`),
    refusing ids the learning map does not know.

    Raises:
        ValueError: naming ``where`` and the first unknown id.
    """
    raw = np.asarray(raw_ids, np.int64)
    unknown = np.setdiff1d(np.unique(raw), SEMANTICKITTI_IDS)
    if unknown.size:
        more = f" (and {unknown.size - 1} other id(s))" if unknown.size > 1 else ""
        raise ValueError(
            f"{where}: label id {unknown[0]}{more} is not in SemanticKITTI's learning map "
            f"(semantic-kitti.yaml: {len(SEMANTICKITTI_IDS)} ids from {SEMANTICKITTI_IDS[0]} to "
            f"{SEMANTICKITTI_IDS[-1]})"
        )
    return semantickitti_class_ids(raw)


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


def read_semantickitti_scan(bin_path: str | Path, label_path: str | Path) -> LabelledScan:
    """Read a SemanticKITTI scan: ``.bin`` float32 (x, y, z, intensity), ``.label`` uint32.

    Raises:
        ValueError: naming the file: sizes that are not whole records, mismatched counts,
            non-finite points or points beyond :data:`MAX_RANGE_M`, ids not in the learning map.
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
    check_point_range(points, str(bin_path))
    labels = checked_class_ids(label_words & 0xFFFF, str(label_path))
    return LabelledScan(points, labels, (label_words >> 16).astype(np.int32))


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_semantickitti_scan": "read_semantickitti_scan",
    },
)
