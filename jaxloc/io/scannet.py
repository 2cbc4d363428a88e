"""ScanNet v2 labelled reconstructions, checked against the dataset's documentation and reader code.

* ScanNet v2 scan folder ``<scene>/`` (ScanNet/ScanNet ``README.md``,
  ``BenchmarkScripts/3d_helpers/export_train_mesh_for_evaluation.py``):
  ``<scene>_vh_clean_2.ply`` (mesh with per-vertex ``red green blue``),
  ``<scene>_vh_clean_2.0.010000.segs.json`` (``segIndices``: one segment id per mesh vertex),
  ``<scene>.aggregation.json`` (``segGroups``: objects with ``objectId``, ``label`` and the
  ``segments`` they cover) and ``scannetv2-labels.combined.tsv`` (tab-separated with a header;
  ``raw_category`` is the aggregation's label, ``nyu40id`` / ``id`` the class ids).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from jaxloc.io.reconstruction import (
    LabelledReconstruction,
    PathLike,
    ReconstructionObject,
    check_every_object_has_vertices,
    read_json,
    read_ply,
    require_file,
    seg_groups,
)

#: ScanNet's label table, looked for in the scan folder and its parent when none is given.
SCANNET_LABEL_TABLE = "scannetv2-labels.combined.tsv"


def read_label_table(
    path: PathLike, column: str = "nyu40id", key: str = "raw_category"
) -> dict[str, int]:
    """ScanNet's ``scannetv2-labels.combined.tsv``: ``key`` column -> integer class id.

    Args:
        path: the tab-separated file with a header row.
        column: the class-id column (``nyu40id``, the NYU40 classes; ``id``, ScanNet's own ids).
        key: the column looked up: ``raw_category`` (the aggregation files' label names) or
            ``id`` (the raw label ids of ScanNet's 2D label images, as text).

    Raises:
        FileNotFoundError, ValueError: a missing file, a missing column, a non-integer id, not
            UTF-8 text.
    """
    path = require_file(Path(path))
    try:
        with path.open(encoding="utf-8", newline="") as handle:
            rows = list(csv.DictReader(handle, delimiter="\t"))
    except (UnicodeDecodeError, csv.Error) as err:
        raise ValueError(f"{path}: not a readable tab-separated file ({err})") from None
    table: dict[str, int] = {}
    for line, row in enumerate(rows, start=2):
        if key not in row or column not in row:
            raise ValueError(f"{path}: needs the columns {key!r} and {column!r}")
        try:
            class_id = int(row[column])
        except (TypeError, ValueError):
            raise ValueError(f"{path}:{line}: {column} {row[column]!r} is not an integer") from None
        table[str(row[key]).strip()] = class_id
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
    vertices, faces, colors, _ = read_ply(scan_dir / f"{name}_vh_clean_2.ply")
    segs_path = scan_dir / f"{name}_vh_clean_2.0.010000.segs.json"
    seg_indices = np.asarray(read_json(segs_path).get("segIndices", []))
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
    groups = seg_groups(agg_path, read_json(agg_path))
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
    check_every_object_has_vertices(agg_path, vertex_object, objects)
    return LabelledReconstruction(vertices, colors, faces, vertex_object, tuple(objects), agg_path)
