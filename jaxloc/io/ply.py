"""Generic labelled reconstructions: any PLY with a per-vertex instance id, and an objects file.

* Generic: a PLY mesh or point cloud with an integer per-vertex instance property (``objectId``,
  ``instance`` or ``instance_id``; 0 or negative = none) and an objects file of lines
  ``object_id class_id [label]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxloc._lazy import renamed_names
from jaxloc.io._text import data_lines
from jaxloc.io.reconstruction import (
    LabelledReconstruction,
    PathLike,
    ReconstructionObject,
    check_every_object_has_vertices,
    read_ply,
    require_file,
)

#: Per-vertex instance properties the generic reader looks for, in order.
INSTANCE_PROPERTIES = ("objectId", "instance", "instance_id")


def read_labelled_ply(
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
    vertices, faces, colors, properties = read_ply(ply_path)
    wanted = (instance_property,) if instance_property else INSTANCE_PROPERTIES
    found = next((p for p in wanted if p in properties), None)
    if found is None:
        raise ValueError(f"{ply_path}: no per-vertex instance property (looked for {wanted})")
    ids = properties[found].astype(np.int64)
    vertex_object = np.full(vertices.shape[0], -1, np.int64)
    objects: list[ReconstructionObject] = []
    for line_number, line in data_lines(require_file(objects_path), comments=True):
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
    check_every_object_has_vertices(objects_path, vertex_object, objects)
    return LabelledReconstruction(
        vertices, colors, faces, vertex_object, tuple(objects), objects_path
    )


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "read_generic": "read_labelled_ply",
    },
)
