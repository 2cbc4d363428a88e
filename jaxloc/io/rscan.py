"""3RScan labelled reconstructions, checked against the dataset's documentation.

* 3RScan scan folder (WaldJohannaU/3RScan ``README.md``): ``labels.instances.annotated.v2.ply``
  (mesh with per-vertex ``objectId`` and ``NYU40`` class) and ``semseg.v2.json`` (``segGroups``
  with ``objectId``/``id`` and ``label``). Vertices whose ``objectId`` is not in ``semseg.v2.json``
  (0: unannotated) belong to no object.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxloc.io.reconstruction import (
    LabelledReconstruction,
    PathLike,
    ReconstructionObject,
    check_every_object_has_vertices,
    read_json,
    read_ply,
    seg_groups,
)


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
    vertices, faces, colors, properties = read_ply(ply_path)
    if "objectId" not in properties:
        raise ValueError(f"{ply_path}: no per-vertex 'objectId' property")
    semseg_path = scan_dir / "semseg.v2.json"
    groups = seg_groups(semseg_path, read_json(semseg_path))
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
    check_every_object_has_vertices(semseg_path, vertex_object, objects)
    return LabelledReconstruction(
        vertices, colors, faces, vertex_object, tuple(objects), semseg_path
    )
