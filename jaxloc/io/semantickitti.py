"""SemanticKITTI scans: ``.bin`` points and ``.label`` semantic / instance labels.

Class ids follow TripletLoc/Cylinder3D: SemanticKITTI learning ids minus one (13 fence,
14 vegetation, 15 trunk, 16 terrain, 17 pole, 18 traffic sign); unlabeled points get -1.
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


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_semantickitti_scan": "read_semantickitti_scan",
    },
)
