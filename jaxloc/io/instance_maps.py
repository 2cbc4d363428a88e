"""HeLiPR / TripletLoc instance maps (text): instance centroids per class and road normals.

Layout (TripletLoc's released maps, the HeLiPR instance maps among them)::

    MAP_DIR/instances/<class>.txt    one line per instance: ``id x y z`` (map frame, metres)
    MAP_DIR/RSN/road_normal.txt      one line per road cell: ``x y nx ny nz std_deg``
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc._lazy import renamed_names
from jaxloc.io._atomic import write_text_atomic
from jaxloc.io._text import read_float_table
from jaxloc.m2loc import Instances, RoadNormals
from jaxloc.m2loc._classes import GRAPH_CLASSES


class InstanceMap(NamedTuple):
    """Instance centroids of a map: ``points`` (N, 3) float64 metres (map frame), ``labels`` (N,)
    int32 class ids, ``ids`` (N,) int64 per-class instance ids from the files."""

    points: np.ndarray
    labels: np.ndarray
    ids: np.ndarray


def read_instance_map(map_dir: str | Path, classes: tuple[int, ...] = GRAPH_CLASSES) -> InstanceMap:
    """Read ``<map_dir>/instances/<class>.txt`` files (lines ``id x y z``) into one InstanceMap.

    Raises:
        FileNotFoundError: a class file is missing.
        ValueError: a malformed line (wrong field count, non-number, non-finite), with file:line,
            or an instance id that is not an integer (naming the file).
    """
    points, labels, ids = [], [], []
    for class_id in classes:
        table = read_float_table(Path(map_dir) / "instances" / f"{class_id}.txt", 4, "id x y z")
        if np.any(table[:, 0] != np.round(table[:, 0])) or np.any(np.abs(table[:, 0]) > 2**53):
            raise ValueError(f"{map_dir}/instances/{class_id}.txt: non-integer instance id")
        points.append(table[:, 1:4])
        labels.append(np.full(table.shape[0], class_id, np.int32))
        ids.append(table[:, 0].astype(np.int64))
    return InstanceMap(np.concatenate(points), np.concatenate(labels), np.concatenate(ids))


def read_lidar_map(
    map_dir: str | os.PathLike, classes: tuple[int, ...] = GRAPH_CLASSES, road_normals: bool = True
) -> tuple[InstanceMap, RoadNormals | None]:
    """An instance-map folder: its ``instances/<class>.txt`` of ``classes`` and, when the folder has
    one and ``road_normals`` is set, its ``RSN/road_normal.txt`` (else None).

    Raises:
        FileNotFoundError: no such folder, or a class file missing (naming them).
        ValueError: a malformed file (:func:`read_instance_map`, :func:`read_road_normals`).
    """
    root = Path(map_dir)
    if not root.is_dir():
        raise FileNotFoundError(f"map folder not found: {root}")
    for class_id in classes:
        if not (root / "instances" / f"{class_id}.txt").is_file():
            raise FileNotFoundError(f"{root}: missing instances/{class_id}.txt (lines: id x y z)")
    instances = read_instance_map(root, tuple(classes))
    normals = None
    if road_normals and (root / "RSN" / "road_normal.txt").is_file():
        normals = read_road_normals(root)
    return instances, normals


def read_road_normals(map_dir: str | Path) -> RoadNormals:
    """Read ``<map_dir>/RSN/road_normal.txt`` (lines ``x y nx ny nz std_deg``), normals unit-scaled.

    Raises:
        ValueError: a malformed line, a zero (or overflowing) normal, or a negative standard
            deviation.
    """
    path = Path(map_dir) / "RSN" / "road_normal.txt"
    table = read_float_table(path, 6, "x y nx ny nz std_deg")
    with np.errstate(over="ignore"):
        norms = np.linalg.norm(table[:, 2:5], axis=1)
    if np.any(norms < 1e-6) or not np.all(np.isfinite(norms)):
        raise ValueError(f"{path}: zero-length or overflowing road normal")
    if np.any(table[:, 5] < 0):
        raise ValueError(f"{path}: negative normal standard deviation")
    return RoadNormals(table[:, 0:2], table[:, 2:5] / norms[:, None], table[:, 5])


def write_instance_maps(
    out_dir: str | os.PathLike, instances: Instances, road_normals: RoadNormals
) -> None:
    """Write ``instances/<class>.txt`` (lines ``id x y z``, one file per graph class, ids from 0)
    and ``RSN/road_normal.txt`` (lines ``x y nx ny nz std_deg``) under ``out_dir``, each file
    atomically; the format :func:`read_instance_map` and :func:`read_road_normals` read."""
    out = Path(out_dir)
    texts = {}
    for class_id in sorted(set(instances.labels.tolist()) | set(GRAPH_CLASSES)):
        rows = instances.points[instances.labels == class_id]
        texts[out / "instances" / f"{class_id}.txt"] = "".join(
            f"{i} {x:.6f} {y:.6f} {z:.6f}\n" for i, (x, y, z) in enumerate(rows)
        )
    texts[out / "RSN" / "road_normal.txt"] = "".join(
        f"{x:.6f} {y:.6f} {nx:.9f} {ny:.9f} {nz:.9f} {s:.6f}\n"
        for (x, y), (nx, ny, nz), s in zip(
            road_normals.xy, road_normals.normals, road_normals.std_deg, strict=True
        )
    )
    for path, text in texts.items():
        write_text_atomic(path, text)


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_instance_map": "read_instance_map",
        "load_road_normals": "read_road_normals",
        "save_lidar_maps": "write_instance_maps",
        "load_lidar_map": "read_lidar_map",
    },
)
