"""Build a :class:`~jaxloc.scene.SceneGraph` from mesh files and a plain-text object list.

The objects file has one line per object::

    # comments and blank lines are ignored
    name label e_1 e_2 ... e_d

``name`` matches a geometry of the mesh file (or a file stem, for a list of per-object mesh files),
``label`` is a non-negative integer class, ``e_1 .. e_d`` the object's embedding (any scale; stored
unit-norm). Objects keep the file's order: object i of the scene graph is line i's object. The file
is parsed as text only (no eval, no pickle) and validated with line numbers.

Meshes: anything ``trimesh.load`` reads, loaded unprocessed (``process=False``: vertices and faces
as stored, so bad geometry reaches the checks of :meth:`SceneGraph.from_meshes`). A multi-geometry
scene file (.glb, .gltf, .obj with several objects, ...) gives one object per geometry, with its
scene-graph transform applied (world frame, metres, z up); a geometry placed by several nodes is
named by node instead. A single-mesh file (.ply, .stl, ...) is one object named by the file stem.
Vertex or face colours are kept; textured meshes are converted to vertex colours where trimesh can.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from jaxloc._lazy import renamed_names
from jaxloc.io._faces import check_face_indices
from jaxloc.io._text import data_lines, parse_finite_floats
from jaxloc.scene import Capacity, SceneGraph

#: A file path: ``str`` or ``os.PathLike``.
PathLike = str | os.PathLike


def read_objects_file(path: PathLike) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Parse an objects file (see the module docstring).

    Returns:
        names: n object names, in file order.
        labels: (n,) int64 class labels (>= 0).
        embeddings: (n, d) float64 raw embeddings (not normalised; all-zero rows are an error
            reported by :meth:`SceneGraph.from_meshes`).

    Raises:
        ValueError: naming the file and line for malformed lines, non-integer or negative labels,
            non-numeric or non-finite embedding values, embedding lengths that differ between
            lines, duplicate names, or an empty file.
    """
    path = Path(path)
    names: list[str] = []
    labels: list[int] = []
    rows: list[list[float]] = []
    first_line: dict[str, int] = {}
    dim_line = 0
    for lineno, line in data_lines(path, comments=True):
        where = f"{path}:{lineno}"
        fields = line.split()
        if len(fields) < 3:
            raise ValueError(
                f"{where}: expected 'name label e_1 ... e_d' (at least one embedding value), "
                f"got {len(fields)} field(s)"
            )
        name, label_text, values = fields[0], fields[1], fields[2:]
        if name in first_line:
            raise ValueError(
                f"{where}: duplicate object name {name!r} (first on line {first_line[name]})"
            )
        try:
            label = int(label_text)
        except ValueError:
            raise ValueError(
                f"{where}: label {label_text!r} of object {name!r} is not an integer"
            ) from None
        if label < 0:
            raise ValueError(f"{where}: label {label} of object {name!r} must be >= 0")
        embedding = parse_finite_floats(values, where, f"embedding of object {name!r}")
        if rows and len(embedding) != len(rows[0]):
            raise ValueError(
                f"{where}: embedding of object {name!r} has {len(embedding)} values, "
                f"expected {len(rows[0])} (as on line {dim_line})"
            )
        if not rows:
            dim_line = lineno
        first_line[name] = lineno
        names.append(name)
        labels.append(label)
        rows.append(embedding)
    if not names:
        raise ValueError(f"{path}: no objects (every line is blank or a comment)")
    return names, np.asarray(labels, np.int64), np.asarray(rows, np.float64)


def _as_vertex_colors(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Textured/material visuals become vertex colours where trimesh can convert them."""
    if getattr(mesh.visual, "kind", None) == "texture":
        try:
            mesh.visual = mesh.visual.to_color()
        except Exception:  # noqa: BLE001 - no usable texture: the scene's default colour applies
            mesh.visual = trimesh.visual.ColorVisuals(mesh)
    return mesh


def read_meshes(mesh_path: PathLike | Sequence[PathLike]) -> dict[str, trimesh.Trimesh]:
    """Named world-frame meshes from one mesh/scene file or a list of per-object mesh files.

    Returns an insertion-ordered dict name -> mesh (see the module docstring for naming).

    Raises:
        FileNotFoundError: a file does not exist.
        ValueError: a file holds no triangle mesh, a list of files has duplicate stems or a file
            in it holds several geometries, or two objects of a scene end up with the same name.
    """
    if isinstance(mesh_path, (str, os.PathLike)):
        path = Path(mesh_path)
        if not path.exists():
            raise FileNotFoundError(path)
        meshes = _scene_meshes(_load_file(path), path)
        if not meshes:
            raise ValueError(f"{path}: no triangle meshes in the file")
        return meshes
    out: dict[str, trimesh.Trimesh] = {}
    for item in mesh_path:
        path = Path(item)
        if not path.exists():
            raise FileNotFoundError(path)
        if path.stem in out:
            raise ValueError(
                f"two mesh files share the stem {path.stem!r}: object names must be unique"
            )
        inner = _scene_meshes(_load_file(path), path)
        if len(inner) != 1:
            raise ValueError(
                f"{path}: expected one mesh per file in a list of object files, found {len(inner)}"
            )
        out[path.stem] = next(iter(inner.values()))
    return out


def _load_file(path: Path) -> trimesh.Scene:
    """``trimesh.load`` of one file as a scene; a corrupt or truncated file raises ``ValueError``
    naming it (trimesh's own exceptions vary by format)."""
    try:
        return trimesh.load(path, force="scene", process=False)
    except Exception as err:  # noqa: BLE001 - any parser failure is a bad file
        raise ValueError(f"{path}: not a readable mesh file ({type(err).__name__}: {err})") from err


def _scene_meshes(scene: trimesh.Scene, path: Path) -> dict[str, trimesh.Trimesh]:
    """One world-frame mesh per (node, geometry) instance of a trimesh scene."""
    instances = []
    for node in scene.graph.nodes_geometry:
        transform, geometry_name = scene.graph[node]
        geometry = scene.geometry.get(geometry_name)
        if isinstance(geometry, trimesh.Trimesh):  # empty ones too: from_meshes names them
            instances.append((node, geometry_name, transform, geometry))
    uses = Counter(geometry_name for _, geometry_name, _, _ in instances)
    out: dict[str, trimesh.Trimesh] = {}
    for node, geometry_name, transform, geometry in instances:
        if len(instances) == 1:
            name = path.stem if _is_single_mesh_format(path) else geometry_name
        else:
            name = geometry_name if uses[geometry_name] == 1 else node
        if name in out:
            raise ValueError(f"{path}: two objects are named {name!r}; names must be unique")
        check_face_indices(geometry.faces, len(geometry.vertices), f"{path} (object {name!r})")
        mesh = geometry.copy()
        mesh.apply_transform(transform)
        out[name] = _as_vertex_colors(mesh)
    return out


def _is_single_mesh_format(path: Path) -> bool:
    """Formats that hold one unnamed mesh: the object is named by the file stem."""
    return path.suffix.lower() in {".ply", ".stl", ".off"}


def read_mesh_scene(
    mesh_path: PathLike | Sequence[PathLike],
    objects_path: PathLike,
    *,
    edges=None,
    capacity: Capacity | None = None,
) -> SceneGraph:
    """A scene graph from a mesh file (or a list of per-object mesh files) and an objects file.

    Args:
        mesh_path: a file ``trimesh.load`` reads (one object per geometry, transforms applied)
            or a list of per-object mesh files (objects named by file stem).
        objects_path: the plain-text objects file, ``name label e_1 ... e_d`` per line.
        edges: optional (m, 2) object index pairs (indices into the objects file's order).
        capacity: optional padding capacity (see :class:`jaxloc.scene.Capacity`).

    Returns:
        The :class:`SceneGraph`, objects in the objects file's order.

    Raises:
        ValueError: malformed objects file (with line numbers); objects listed but missing from the
            meshes, or meshes not listed in the objects file (both named); and every check of
            :meth:`SceneGraph.from_meshes` (NaN vertices, degenerate meshes, zero embeddings...).
        FileNotFoundError: a file does not exist.
    """
    names, labels, embeddings = read_objects_file(objects_path)
    meshes = read_meshes(mesh_path)
    missing = [n for n in names if n not in meshes]
    extra = [n for n in meshes if n not in set(names)]
    if missing or extra:
        parts = []
        if missing:
            parts.append(f"objects without a mesh: {missing}")
        if extra:
            parts.append(f"meshes not in the objects file: {extra}")
        raise ValueError(
            f"{objects_path} does not match the meshes of {mesh_path}: " + "; ".join(parts)
        )
    ordered = [meshes[n] for n in names]
    try:
        return SceneGraph.from_meshes(ordered, labels, embeddings, edges=edges, capacity=capacity)
    except ValueError as err:
        # from_meshes numbers objects by position: add the name.
        message = str(err)
        if message.startswith("object "):
            index = int(message.split()[1].rstrip(":"))
            message = f"object {index} ({names[index]!r}): " + message.split(":", 1)[1].strip()
        raise ValueError(message) from err


#: Names of jaxloc 0.2, kept with a DeprecationWarning for one more release.
__getattr__ = renamed_names(
    __name__,
    {
        "load_meshes": "read_meshes",
        "load_objects_file": "read_objects_file",
        "load_scene_from_files": "read_mesh_scene",
    },
)
