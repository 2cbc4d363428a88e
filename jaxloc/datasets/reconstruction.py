"""Readers of labelled indoor reconstructions: ScanNet, 3RScan and a generic labelled PLY.

Each reader returns a :class:`LabelledReconstruction`: the reconstruction's vertices (and faces,
for a mesh), their colours, and an object id per vertex with each object's class id and label.
:func:`jaxloc.datasets.scene_builder.scene_graph_from_reconstruction` turns it into a map.

Formats (checked against the datasets' documentation and reader code):

* ScanNet v2 scan folder ``<scene>/`` (ScanNet/ScanNet ``README.md``,
  ``BenchmarkScripts/3d_helpers/export_train_mesh_for_evaluation.py``):
  ``<scene>_vh_clean_2.ply`` (mesh with per-vertex ``red green blue``),
  ``<scene>_vh_clean_2.0.010000.segs.json`` (``segIndices``: one segment id per mesh vertex),
  ``<scene>.aggregation.json`` (``segGroups``: objects with ``objectId``, ``label`` and the
  ``segments`` they cover) and ``scannetv2-labels.combined.tsv`` (tab-separated with a header;
  ``raw_category`` is the aggregation's label, ``nyu40id`` / ``id`` the class ids).
* 3RScan scan folder (WaldJohannaU/3RScan ``README.md``): ``labels.instances.annotated.v2.ply``
  (mesh with per-vertex ``objectId`` and ``NYU40`` class) and ``semseg.v2.json`` (``segGroups``
  with ``objectId``/``id`` and ``label``). Vertices whose ``objectId`` is not in ``semseg.v2.json``
  (0: unannotated) belong to no object.
* Generic: a PLY mesh or point cloud with an integer per-vertex instance property (``objectId``,
  ``instance`` or ``instance_id``; 0 or negative = none) and an objects file of lines
  ``object_id class_id [label]``.

The world frame is the reconstruction's (metres, z up, as in both datasets). Every problem raises
``FileNotFoundError`` or ``ValueError`` naming the file.
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np
import trimesh

from jaxloc._textio import data_lines

PathLike = str | os.PathLike
#: Per-vertex instance properties the generic reader looks for, in order.
INSTANCE_PROPERTIES = ("objectId", "instance", "instance_id")
SCANNET_LABEL_TABLE = "scannetv2-labels.combined.tsv"


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


def _require(path: Path) -> Path:
    if not path.is_file():
        raise FileNotFoundError(2, "No such file", str(path))
    return path


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(_require(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{path}: not a readable JSON file ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    return data


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, dict]:
    """Vertices (V, 3), faces (F, 3) or None, colours (V, 3) or None and the raw per-vertex
    properties (name -> (V,) array) of a PLY file, loaded unprocessed."""
    _require(path)
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
    raw = geometry.metadata.get("_ply_raw", {}).get("vertex", {}).get("data", {})
    if isinstance(raw, np.ndarray):  # binary PLY: one structured array
        raw = {name: raw[name] for name in raw.dtype.names or ()}
    properties = {name: np.asarray(values).reshape(-1) for name, values in raw.items()}
    colors = None
    if all(c in properties for c in ("red", "green", "blue")):
        colors = np.stack([properties[c] for c in ("red", "green", "blue")], -1) / 255.0
    return vertices, faces, colors, properties


def _seg_groups(path: Path, data: dict) -> list[dict]:
    groups = data.get("segGroups")
    if not isinstance(groups, list):
        raise ValueError(f"{path}: no 'segGroups' list")
    for i, group in enumerate(groups):
        if not isinstance(group, dict) or "label" not in group:
            raise ValueError(f"{path}: segGroups[{i}] has no 'label'")
        if "objectId" not in group and "id" not in group:
            raise ValueError(f"{path}: segGroups[{i}] has neither 'objectId' nor 'id'")
    return groups


def read_label_table(path: PathLike, column: str = "nyu40id") -> dict[str, int]:
    """ScanNet's ``scannetv2-labels.combined.tsv``: raw category name -> integer class id.

    Args:
        path: the tab-separated file with a header row.
        column: the class-id column (``nyu40id``, the NYU40 classes; ``id``, ScanNet's own ids).

    Raises:
        FileNotFoundError, ValueError: a missing file, a missing column, a non-integer id.
    """
    path = _require(Path(path))
    with path.open(encoding="utf-8", newline="") as handle:
        rows = list(csv.DictReader(handle, delimiter="\t"))
    table: dict[str, int] = {}
    for line, row in enumerate(rows, start=2):
        if "raw_category" not in row or column not in row:
            raise ValueError(f"{path}: needs the columns 'raw_category' and {column!r}")
        try:
            class_id = int(row[column])
        except (TypeError, ValueError):
            raise ValueError(f"{path}:{line}: {column} {row[column]!r} is not an integer") from None
        table[row["raw_category"]] = class_id
    return table


def read_scannet(
    scan_dir: PathLike, label_table: PathLike | None = None, label_column: str = "nyu40id"
) -> LabelledReconstruction:
    """A ScanNet v2 scan folder (see the module docstring).

    Args:
        scan_dir: the folder ``<scene>`` holding ``<scene>_vh_clean_2.ply`` and its annotations.
        label_table: ``scannetv2-labels.combined.tsv``; by default looked for in ``scan_dir`` and
            its parent.
        label_column: the table's class-id column.

    Raises:
        FileNotFoundError: a missing file.
        ValueError: segment ids of the aggregation that no mesh vertex has, an object without
            vertices, a label not in the table, a ``segIndices`` list of another length than the
            mesh's vertices.
    """
    scan_dir = Path(scan_dir)
    name = scan_dir.name
    vertices, faces, colors, _ = _read_ply(scan_dir / f"{name}_vh_clean_2.ply")
    segs_path = scan_dir / f"{name}_vh_clean_2.0.010000.segs.json"
    seg_indices = np.asarray(_read_json(segs_path).get("segIndices", []))
    integers = np.issubdtype(seg_indices.dtype, np.integer)
    if seg_indices.shape != (vertices.shape[0],) or not integers:
        raise ValueError(
            f"{segs_path}: 'segIndices' must hold one integer per mesh vertex "
            f"({vertices.shape[0]}), got shape {seg_indices.shape}"
        )
    if label_table is None:
        candidates = [scan_dir / SCANNET_LABEL_TABLE, scan_dir.parent / SCANNET_LABEL_TABLE]
        label_table = next((p for p in candidates if p.is_file()), candidates[0])
    class_of = read_label_table(label_table, label_column)
    agg_path = scan_dir / f"{name}.aggregation.json"
    groups = _seg_groups(agg_path, _read_json(agg_path))
    known = set(np.unique(seg_indices).tolist())
    vertex_object = np.full(vertices.shape[0], -1, np.int64)
    objects = []
    for index, group in enumerate(groups):
        object_id = int(group.get("objectId", group.get("id")))
        segments = [int(s) for s in group.get("segments", [])]
        lacking = sorted(set(segments) - known)
        if lacking:
            raise ValueError(
                f"{agg_path}: object {object_id} ({group['label']!r}) names segments the mesh "
                f"lacks: {lacking[:5]}{' ...' if len(lacking) > 5 else ''}"
            )
        if group["label"] not in class_of:
            raise ValueError(f"{agg_path}: label {group['label']!r} is not in {label_table}")
        vertex_object[np.isin(seg_indices, segments)] = index
        objects.append(ReconstructionObject(object_id, class_of[group["label"]], group["label"]))
    _check_every_object_has_vertices(agg_path, vertex_object, objects)
    return LabelledReconstruction(vertices, colors, faces, vertex_object, tuple(objects), agg_path)


def read_3rscan(scan_dir: PathLike) -> LabelledReconstruction:
    """A 3RScan scan folder (see the module docstring). Class ids are each object's most common
    per-vertex ``NYU40`` value; without that property, the rank of its label among the sorted
    label names.

    Raises:
        FileNotFoundError: a missing file.
        ValueError: the PLY has no ``objectId``; an object of ``semseg.v2.json`` without vertices.
    """
    scan_dir = Path(scan_dir)
    ply_path = scan_dir / "labels.instances.annotated.v2.ply"
    vertices, faces, colors, properties = _read_ply(ply_path)
    if "objectId" not in properties:
        raise ValueError(f"{ply_path}: no per-vertex 'objectId' property")
    semseg_path = scan_dir / "semseg.v2.json"
    groups = _seg_groups(semseg_path, _read_json(semseg_path))
    ids = properties["objectId"].astype(np.int64)
    names = sorted({str(g["label"]) for g in groups})
    vertex_object = np.full(vertices.shape[0], -1, np.int64)
    objects = []
    for index, group in enumerate(groups):
        object_id = int(group.get("objectId", group.get("id")))
        mask = ids == object_id
        vertex_object[mask] = index
        if "NYU40" in properties and mask.any():
            class_id = int(np.bincount(properties["NYU40"][mask].astype(np.int64)).argmax())
        else:
            class_id = names.index(str(group["label"]))
        objects.append(ReconstructionObject(object_id, class_id, str(group["label"])))
    _check_every_object_has_vertices(semseg_path, vertex_object, objects)
    return LabelledReconstruction(
        vertices, colors, faces, vertex_object, tuple(objects), semseg_path
    )


def read_generic(
    ply_path: PathLike, objects_path: PathLike, instance_property: str | None = None
) -> LabelledReconstruction:
    """A PLY mesh or point cloud with a per-vertex instance id, and an objects file.

    Args:
        ply_path: the PLY file.
        objects_path: text lines ``object_id class_id [label]`` ('#' starts a comment); objects
            keep the file's order.
        instance_property: the per-vertex property holding instance ids (default: the first of
            ``objectId``, ``instance``, ``instance_id`` the file has).

    Raises:
        FileNotFoundError, ValueError: missing files, no instance property, malformed or duplicate
            lines, negative class ids, an object without vertices.
    """
    ply_path, objects_path = Path(ply_path), Path(objects_path)
    vertices, faces, colors, properties = _read_ply(ply_path)
    wanted = (instance_property,) if instance_property else INSTANCE_PROPERTIES
    found = next((p for p in wanted if p in properties), None)
    if found is None:
        raise ValueError(f"{ply_path}: no per-vertex instance property (looked for {wanted})")
    ids = properties[found].astype(np.int64)
    vertex_object = np.full(vertices.shape[0], -1, np.int64)
    objects: list[ReconstructionObject] = []
    for line_number, line in data_lines(_require(objects_path), comments=True):
        fields = line.split(maxsplit=2)
        where = f"{objects_path}:{line_number}"
        try:
            object_id, class_id = int(fields[0]), int(fields[1])
        except (IndexError, ValueError):
            raise ValueError(f"{where}: expected 'object_id class_id [label]'") from None
        if class_id < 0 or object_id <= 0:
            raise ValueError(f"{where}: object ids must be > 0 and class ids >= 0")
        if any(o.object_id == object_id for o in objects):
            raise ValueError(f"{where}: duplicate object id {object_id}")
        label = fields[2] if len(fields) > 2 else str(class_id)
        vertex_object[ids == object_id] = len(objects)
        objects.append(ReconstructionObject(object_id, class_id, label))
    if not objects:
        raise ValueError(f"{objects_path}: no objects")
    _check_every_object_has_vertices(objects_path, vertex_object, objects)
    return LabelledReconstruction(
        vertices, colors, faces, vertex_object, tuple(objects), objects_path
    )


def _check_every_object_has_vertices(path: Path, vertex_object: np.ndarray, objects) -> None:
    if not objects:
        raise ValueError(f"{path}: no objects")
    counts = np.bincount(vertex_object[vertex_object >= 0], minlength=len(objects))
    for index in np.flatnonzero(counts == 0):
        obj = objects[index]
        raise ValueError(f"{path}: object {obj.object_id} ({obj.label!r}) has no vertices")
