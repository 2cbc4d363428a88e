"""A :class:`~jaxloc.scene.SceneGraph` from a labelled reconstruction: one coarse mesh per object.

Every object of a :class:`~jaxloc.io.reconstruction.LabelledReconstruction` (the floor and
the walls too) becomes one mesh: the reconstruction's faces whose three vertices belong to it (the
convex hull of its points for a point cloud, or an object without such faces), reduced by quadric
decimation (trimesh's ``simplify_quadric_decimation``, backed by ``fast-simplification``) to about
``target_vertices`` vertices (SG2Loc's coarse 3RScan meshes have about 860 per object). Each
decimated vertex takes the colour of the nearest original vertex of its object.

Embeddings come from an :class:`EmbeddingTable` (per label or per object id; a text file of lines
``key e_1 ... e_d`` or an ``.npy`` array whose row k belongs to class id / object id k). Without a
table the fallback is one-hot per class: dimension i stands for the i-th smallest class id of the
map (:func:`onehot_classes` lists them), so query patch embeddings can be made to match.
"""

from __future__ import annotations

import warnings

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from jaxloc.io.embedding_table import EmbeddingTable
from jaxloc.io.reconstruction import LabelledReconstruction
from jaxloc.io.scene_map import ClassEmbeddings
from jaxloc.scene import SceneGraph

#: Vertices per object of SG2Loc's coarse 3RScan meshes (about 860).
DEFAULT_TARGET_VERTICES = 860


def onehot_classes(class_ids) -> np.ndarray:
    """The class ids of the one-hot fallback, sorted: dimension i stands for the i-th of them."""
    return np.unique(np.asarray(class_ids, np.int64))


def _object_mesh(recon: LabelledReconstruction, index: int) -> tuple[trimesh.Trimesh, np.ndarray]:
    """The object's own faces (re-indexed), or the convex hull of its points; and its points."""
    members = np.flatnonzero(recon.vertex_object == index)
    points = recon.vertices[members]
    if recon.faces is not None:
        inside = np.all(recon.vertex_object[recon.faces] == index, axis=1)
        if inside.any():
            remap = np.full(recon.vertices.shape[0], -1, np.int64)
            remap[members] = np.arange(members.size)
            return trimesh.Trimesh(points, remap[recon.faces[inside]], process=False), members
    obj = recon.objects[index]
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")
            hull = trimesh.convex.convex_hull(points)
    except Exception:  # noqa: BLE001 - qhull fails on fewer than 3 points or a line
        hull = None
    if hull is None or len(hull.faces) == 0:
        raise ValueError(
            f"{recon.source}: object {obj.object_id} ({obj.label!r}) has {points.shape[0]} "
            "vertices on a point or a line: no surface to build a mesh from"
        )
    return hull, members


def decimate(mesh: trimesh.Trimesh, target_vertices: int) -> trimesh.Trimesh:
    """Quadric decimation to about ``target_vertices`` vertices (a mesh already at or below it is
    returned as is). The first face target is twice the vertex target (a closed mesh has F ~ 2V);
    an open surface keeps more vertices per face (its boundary), so the face target then shrinks
    in proportion (at most three passes; the result lands within a few vertices of the target)."""
    if target_vertices < 4:
        raise ValueError(f"target_vertices must be >= 4, got {target_vertices}")
    if len(mesh.vertices) <= target_vertices:
        return mesh
    faces = 2 * target_vertices
    for _ in range(3):
        coarse = mesh.simplify_quadric_decimation(face_count=max(faces, 4))
        if len(coarse.faces) == 0:
            return mesh
        if len(coarse.vertices) <= target_vertices:
            break
        faces = int(faces * target_vertices / len(coarse.vertices))
    return coarse


def scene_graph_from_reconstruction(
    recon: LabelledReconstruction,
    embeddings: EmbeddingTable | None = None,
    target_vertices: int = DEFAULT_TARGET_VERTICES,
) -> SceneGraph:
    """The map of a labelled reconstruction: one decimated mesh, label, colour and embedding per
    object, in the reconstruction's object order (see the module docstring).

    Args:
        recon: from :func:`~jaxloc.io.scannet.read_scannet`, ``read_3rscan`` or
            ``read_labelled_ply``.
        embeddings: object embeddings; None for the one-hot-per-class fallback.
        target_vertices: vertices per object after decimation (about).

    Raises:
        ValueError: naming the file: an object without a surface, a missing embedding; and the
            checks of :meth:`SceneGraph.from_meshes`.
    """
    meshes = []
    for index in range(len(recon.objects)):
        mesh, members = _object_mesh(recon, index)
        mesh = decimate(mesh, target_vertices)
        if recon.colors is not None:
            _, nearest = cKDTree(recon.vertices[members]).query(mesh.vertices)
            rgba = np.concatenate([recon.colors[members][nearest], np.ones((len(nearest), 1))], 1)
            mesh.visual = trimesh.visual.ColorVisuals(
                mesh, vertex_colors=np.round(rgba * 255).astype(np.uint8)
            )
        meshes.append(mesh)
    class_ids = np.asarray([o.class_id for o in recon.objects], np.int64)
    if embeddings is None:
        classes = onehot_classes(class_ids)
        vectors = (class_ids[:, None] == classes[None, :]).astype(np.float64)
    else:
        vectors = np.stack([embeddings.lookup(o) for o in recon.objects])
        zero = np.flatnonzero(np.linalg.norm(vectors, axis=1) == 0)
        if zero.size:
            obj = recon.objects[zero[0]]
            raise ValueError(f"{embeddings.source}: the embedding of {obj.label!r} is zero")
    try:
        return SceneGraph.from_meshes(meshes, class_ids, vectors)
    except ValueError as err:
        raise ValueError(f"{recon.source}: {err}") from err


def class_embeddings(
    recon: LabelledReconstruction, embeddings: EmbeddingTable | None = None
) -> ClassEmbeddings | None:
    """The embedding of each class of the map :func:`scene_graph_from_reconstruction` builds,
    what query patch embeddings from label images are made of (:mod:`jaxloc.io.label_images`).

    One-hot over the classes without a table; with a table by label, each class's vector is the
    normalised mean of its objects' vectors (exactly the table's row when keyed by class id or when
    all of the class's labels share one vector); None for a table by object (object vectors say
    nothing of a class).
    """
    class_ids = np.asarray([o.class_id for o in recon.objects], np.int64)
    if embeddings is None:
        return ClassEmbeddings.onehot(class_ids)
    if embeddings.by == "object":
        return None
    ids = np.unique(class_ids)
    vectors = np.stack([embeddings.lookup(o) for o in recon.objects])
    vectors = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)
    means = np.stack([vectors[class_ids == c].mean(axis=0) for c in ids])
    norms = np.linalg.norm(means, axis=1, keepdims=True)
    if np.any(norms == 0):
        raise ValueError(f"{embeddings.source}: a class's object embeddings cancel out")
    return ClassEmbeddings(ids, (means / norms).astype(np.float32))
