"""Labelled indoor reconstructions: the type every reconstruction reader returns.

A :class:`LabelledReconstruction` holds the reconstruction's vertices (and faces, for a mesh),
their colours, and an object id per vertex with each object's class id and label.
:func:`jaxloc.mapping.scene_graph_from_reconstruction` turns it into a map. The readers:
:func:`jaxloc.io.scannet.read_scannet` (ScanNet v2), :func:`jaxloc.io.rscan.read_3rscan` (3RScan)
and :func:`jaxloc.io.ply.read_labelled_ply` (any labelled PLY). The world frame is the
reconstruction's (metres, z up, as in both datasets). Every problem raises ``FileNotFoundError`` or
``ValueError`` naming the file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxloc.io._faces import check_face_indices

#: A file path: ``str`` or ``os.PathLike``.
PathLike = str | os.PathLike


class ReconstructionObject(NamedTuple):
    """One labelled object: its id in the source files, class id (>= 0) and label name."""

    object_id: int
    class_id: int
    label: str


class LabelledReconstruction(NamedTuple):
    """A reconstruction with an object id per vertex (host arrays).

    Attributes:
        vertices: (V, 3) float64 positions, world frame, metres, z up.
        colors: (V, 3) float64 RGB in [0, 1], or None when the file has no vertex colours.
        faces: (F, 3) int64 vertex indices of a mesh, or None for a point cloud.
        vertex_object: (V,) int64 index into ``objects`` of each vertex, -1 for none.
        objects: the objects, in file order.
        source: the file the object assignment comes from (for error messages).
    """

    vertices: np.ndarray
    colors: np.ndarray | None
    faces: np.ndarray | None
    vertex_object: np.ndarray
    objects: tuple[ReconstructionObject, ...]
    source: Path


def require_file(path: Path) -> Path:
    if not path.is_file():
        raise FileNotFoundError(2, "No such file", str(path))
    return path


def read_json(path: Path) -> dict:
    try:
        data = json.loads(require_file(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable JSON file ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    return data


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, dict]:
    """Vertices (V, 3), faces (F, 3) or None, colours (V, 3) or None and the raw per-vertex
    properties (name -> (V,) array) of a PLY file, loaded unprocessed."""
    import trimesh  # here: a camera recording's reader needs no trimesh (~0.4 s of imports)

    require_file(path)
    try:
        geometry = trimesh.load(path, process=False)
    except Exception as err:  # noqa: BLE001 - any parser failure is a bad file
        raise ValueError(f"{path}: not a readable PLY file ({type(err).__name__}: {err})") from err
    if not isinstance(geometry, trimesh.Trimesh | trimesh.PointCloud):
        raise ValueError(f"{path}: expected one mesh or point cloud, got {type(geometry).__name__}")
    vertices = np.asarray(geometry.vertices, np.float64)
    if vertices.shape[0] == 0:
        raise ValueError(f"{path}: no vertices")
    if not np.all(np.isfinite(vertices)):
        raise ValueError(f"{path}: vertices contain NaN or inf")
    faces = None
    if isinstance(geometry, trimesh.Trimesh) and len(geometry.faces):
        faces = np.asarray(geometry.faces, np.int64)
        check_face_indices(faces, vertices.shape[0], str(path))
    raw = geometry.metadata.get("_ply_raw", {}).get("vertex", {}).get("data", {})
    if isinstance(raw, np.ndarray):  # binary PLY: one structured array
        raw = {name: raw[name] for name in raw.dtype.names or ()}
    properties = {name: np.asarray(values).reshape(-1) for name, values in raw.items()}
    colors = None
    if all(c in properties for c in ("red", "green", "blue")):
        colors = np.stack([properties[c] for c in ("red", "green", "blue")], -1) / 255.0
    return vertices, faces, colors, properties


def seg_groups(path: Path, data: dict) -> list[dict]:
    groups = data.get("segGroups")
    if not isinstance(groups, list):
        raise ValueError(f"{path}: no 'segGroups' list")
    for i, group in enumerate(groups):
        if not isinstance(group, dict) or "label" not in group:
            raise ValueError(f"{path}: segGroups[{i}] has no 'label'")
        if "objectId" not in group and "id" not in group:
            raise ValueError(f"{path}: segGroups[{i}] has neither 'objectId' nor 'id'")
    return groups


def check_every_object_has_vertices(path: Path, vertex_object: np.ndarray, objects) -> None:
    if not objects:
        raise ValueError(f"{path}: no objects")
    counts = np.bincount(vertex_object[vertex_object >= 0], minlength=len(objects))
    for index in np.flatnonzero(counts == 0):
        obj = objects[index]
        raise ValueError(f"{path}: object {obj.object_id} ({obj.label!r}) has no vertices")
