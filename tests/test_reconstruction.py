"""Scene graphs from labelled reconstructions: ScanNet, 3RScan and generic PLY fixtures written in
the datasets' own formats (see tests/_camera_fixtures.py), decimation, embeddings, bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from _camera_fixtures import (
    NYU40,
    room_objects,
    write_3rscan_scan,
    write_binary_ply,
    write_scannet_scan,
)

from jaxloc.io.embedding_table import read_embedding_table
from jaxloc.io.ply import read_labelled_ply
from jaxloc.io.rscan import read_3rscan
from jaxloc.io.scannet import read_scannet
from jaxloc.mapping import decimate, onehot_classes, scene_graph_from_reconstruction

TARGET = 40


@pytest.fixture(scope="module")
def objects():
    return room_objects()


@pytest.fixture(scope="module")
def scannet_dir(objects, tmp_path_factory):
    return write_scannet_scan(tmp_path_factory.mktemp("scannet"), objects)


def _object_bounds(scene, index):
    triangles = np.asarray(scene.triangles)[np.asarray(scene.triangle_object) == index]
    return triangles.reshape(-1, 3).min(0), triangles.reshape(-1, 3).max(0)


def test_scannet_objects_labels_and_vertices(scannet_dir, objects):
    """Every aggregation group is one object, in file order, with its class id from the label
    table's nyu40id column (or the 'id' column) and exactly its own vertices (two segments
    each in the fixture)."""
    recon = read_scannet(scannet_dir)
    assert [o.label for o in recon.objects] == [label for label, _, _ in objects]
    assert [o.class_id for o in recon.objects] == [NYU40[label] for label, _, _ in objects]
    counts = np.bincount(recon.vertex_object, minlength=len(objects))
    assert counts.tolist() == [len(mesh.vertices) for _, _, mesh in objects]
    np.testing.assert_allclose(recon.colors[0], objects[0][1], atol=1 / 255)
    by_id = read_scannet(scannet_dir, label_column="id")
    assert [o.class_id for o in by_id.objects] == [
        list(NYU40).index(label) + 1 for label, _, _ in objects
    ]


def test_scene_graph_from_scannet_decimates_keeps_bounds_and_colours(scannet_dir, objects):
    """Each object's coarse mesh has about TARGET vertices (fewer when it had fewer), the bounds
    of the original object, and its colour; the floor and the walls are objects; the fallback
    embedding is one-hot per class."""
    recon = read_scannet(scannet_dir)
    scene = scene_graph_from_reconstruction(recon, target_vertices=TARGET)
    assert scene.num_objects == len(objects)
    labels = np.asarray(scene.labels)
    assert labels.tolist() == [NYU40[label] for label, _, _ in objects]
    for index, (_, rgb, mesh) in enumerate(objects):
        lo, hi = _object_bounds(scene, index)
        np.testing.assert_allclose(lo, mesh.bounds[0], atol=1e-5)
        np.testing.assert_allclose(hi, mesh.bounds[1], atol=1e-5)
        np.testing.assert_allclose(np.asarray(scene.colors[index]), rgb, atol=1 / 255)
        corners = np.asarray(scene.triangles)[np.asarray(scene.triangle_object) == index]
        vertices = np.unique(corners.reshape(-1, 3), axis=0).shape[0]
        assert vertices <= min(len(mesh.vertices), round(1.05 * TARGET))
        assert vertices >= 0.8 * min(len(mesh.vertices), TARGET)
    classes = onehot_classes(labels)
    np.testing.assert_array_equal(
        np.asarray(scene.embeddings), (labels[:, None] == classes[None]).astype(np.float32)
    )


def test_decimate_to_the_paper_size():
    """A 10242-vertex sphere comes down to about 860 vertices, inside its original bounds."""
    sphere = trimesh.creation.icosphere(5)
    coarse = decimate(sphere, 860)
    assert 800 <= len(coarse.vertices) <= 860
    assert np.all(coarse.bounds[0] >= sphere.bounds[0] - 0.02)
    assert np.all(coarse.bounds[1] <= sphere.bounds[1] + 0.02)
    assert decimate(sphere, 20000) is sphere


def test_3rscan_objects_and_classes(objects, tmp_path):
    """objectId per vertex; class ids from the NYU40 vertex property; unannotated (objectId 0)
    vertices belong to no object."""
    recon = read_3rscan(write_3rscan_scan(tmp_path / "scan", objects))
    assert [o.object_id for o in recon.objects] == list(range(1, len(objects) + 1))
    assert [o.class_id for o in recon.objects] == [NYU40[label] for label, _, _ in objects]
    assert np.sum(recon.vertex_object < 0) == 3
    scene = scene_graph_from_reconstruction(recon, target_vertices=TARGET)
    assert scene.num_objects == len(objects)
    assert np.asarray(scene.bounds)[1, 0] < 5.0  # the unannotated triangle at x = 9 is not in it


def _write_generic(tmp_path, with_faces: bool):
    """A PLY with a per-vertex int 'instance' (two boxes, 0 = none) and an objects file."""
    a = trimesh.creation.box(bounds=[[0, 0, 0], [1, 1, 1]]).subdivide()
    b = trimesh.creation.box(bounds=[[2, 0, 0], [3, 2, 1]]).subdivide()
    vertices = np.concatenate([a.vertices, b.vertices, [[5, 5, 5]]])
    instance = np.concatenate([np.full(len(a.vertices), 7), np.full(len(b.vertices), 9), [0]])
    faces = np.concatenate([a.faces, b.faces + len(a.vertices)]) if with_faces else None
    colors = np.tile([[255, 0, 0]], (len(vertices), 1)).astype(np.uint8)
    path = tmp_path / ("mesh.ply" if with_faces else "cloud.ply")
    write_binary_ply(path, vertices, colors, faces, extra={"instance": instance})
    objects = tmp_path / "objects.txt"
    objects.write_text("# object_id class_id label\n9 5 chair\n7 3 cabinet\n")
    return path, objects


@pytest.mark.parametrize("with_faces", [True, False])
def test_generic_mesh_and_point_cloud(tmp_path, with_faces):
    """Objects in the objects file's order; a point cloud's objects become convex hulls with
    the bounds of their points."""
    ply, objects_file = _write_generic(tmp_path, with_faces)
    recon = read_labelled_ply(ply, objects_file)
    assert [(o.object_id, o.class_id, o.label) for o in recon.objects] == [
        (9, 5, "chair"),
        (7, 3, "cabinet"),
    ]
    scene = scene_graph_from_reconstruction(recon, target_vertices=TARGET)
    lo, hi = _object_bounds(scene, 0)
    np.testing.assert_allclose(lo, [2, 0, 0], atol=1e-5)
    np.testing.assert_allclose(hi, [3, 2, 1], atol=1e-5)
    np.testing.assert_allclose(np.asarray(scene.colors[1]), [1, 0, 0], atol=1e-6)


def test_embedding_tables_by_label_and_by_object(scannet_dir, objects, tmp_path):
    recon = read_scannet(scannet_dir)
    names = sorted({label for label, _, _ in objects})
    text = tmp_path / "by_label.txt"
    text.write_text("".join(f"{n} {k + 1} 0.5 {-k}\n" for k, n in enumerate(names)))
    scene = scene_graph_from_reconstruction(recon, read_embedding_table(text), TARGET)
    k = names.index("bed") + 1
    expected = np.array([k, 0.5, -(k - 1)]) / np.linalg.norm([k, 0.5, -(k - 1)])
    np.testing.assert_allclose(np.asarray(scene.embeddings[5]), expected, rtol=1e-6)
    table = np.arange(1, 3 * len(objects) + 1, dtype=np.float64).reshape(len(objects), 3)
    np.save(tmp_path / "by_object.npy", table)
    by_object = read_embedding_table(tmp_path / "by_object.npy", by="object")
    scene = scene_graph_from_reconstruction(recon, by_object, TARGET)
    np.testing.assert_allclose(
        np.asarray(scene.embeddings[4]), table[4] / np.linalg.norm(table[4]), rtol=1e-6
    )


# ----------------------------------------------------------------------------- bad inputs


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


@pytest.fixture
def scannet_copy(objects, tmp_path):
    return write_scannet_scan(tmp_path, objects)


def test_missing_files_are_named(scannet_copy, tmp_path):
    (scannet_copy / "scene0000_00.aggregation.json").unlink()
    with pytest.raises(FileNotFoundError) as info:
        read_scannet(scannet_copy)
    assert info.value.filename.endswith("scene0000_00.aggregation.json")
    with pytest.raises(FileNotFoundError) as info:
        read_3rscan(tmp_path / "nothing")
    assert info.value.filename.endswith("labels.instances.annotated.v2.ply")


def test_aggregation_naming_segments_the_mesh_lacks(scannet_copy):
    path = scannet_copy / "scene0000_00.aggregation.json"
    _edit_json(path, lambda d: d["segGroups"][2]["segments"].append(999))
    with pytest.raises(ValueError, match=r"aggregation\.json: object 2 \('wall'\) names segments "
                       r"the mesh lacks: \[999\]"):  # fmt: skip
        read_scannet(scannet_copy)


def test_object_without_vertices(scannet_copy, objects, tmp_path):
    path = scannet_copy / "scene0000_00.aggregation.json"
    _edit_json(path, lambda d: d["segGroups"][5].update(segments=[]))
    with pytest.raises(ValueError, match=r"aggregation\.json: object 5 \('bed'\) has no vertices"):
        read_scannet(scannet_copy)
    scan = write_3rscan_scan(tmp_path / "3r", objects)
    _edit_json(
        scan / "semseg.v2.json",
        lambda d: d["segGroups"].append({"id": 77, "objectId": 77, "label": "lamp"}),
    )
    with pytest.raises(ValueError, match=r"semseg\.v2\.json: object 77 \('lamp'\) has no vertices"):
        read_3rscan(scan)


def test_unknown_label_segs_length_and_bad_tables(scannet_copy, tmp_path):
    path = scannet_copy / "scene0000_00.aggregation.json"
    _edit_json(path, lambda d: d["segGroups"][0].update(label="spaceship"))
    with pytest.raises(ValueError, match="label 'spaceship' is not in"):
        read_scannet(scannet_copy)
    segs = scannet_copy / "scene0000_00_vh_clean_2.0.010000.segs.json"
    _edit_json(segs, lambda d: d["segIndices"].pop())
    with pytest.raises(ValueError, match=r"segs\.json: 'segIndices' must hold one integer per"):
        read_scannet(scannet_copy)
    bad = tmp_path / "table.txt"
    bad.write_text("chair 1 2\nbed 1 2 3\n")
    with pytest.raises(ValueError, match=r"table\.txt:2: 3 values"):
        read_embedding_table(bad)
    pickled = tmp_path / "table.npy"
    np.save(pickled, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=r"table\.npy: not a numeric \.npy array"):
        read_embedding_table(pickled)


def _spoil_last_face(path, index: int) -> None:
    """Make the last face of a PLY whose last element is its faces (as the fixtures write them)
    name vertex ``index``."""
    data = path.read_bytes()
    if b"format ascii" in data[:64]:
        lines = data.decode().rstrip("\n").split("\n")
        lines[-1] = " ".join(lines[-1].split()[:-1] + [str(index)])
        path.write_text("\n".join(lines) + "\n")
    else:  # binary little-endian: the face's last int32
        path.write_bytes(data[:-4] + np.int32(index).tobytes())


@pytest.mark.parametrize("index", [-5, 10**6])
def test_a_face_naming_a_vertex_the_file_lacks_is_refused(scannet_copy, objects, tmp_path, index):
    """A damaged face index: a negative one would wrap around to another vertex silently, a large
    one fail as an IndexError deep inside; both are a ValueError naming the file."""
    refused = r"\.ply: face \d+ refers to vertex -?\d+, but the file has \d+ vertices"
    _spoil_last_face(scannet_copy / "scene0000_00_vh_clean_2.ply", index)
    with pytest.raises(ValueError, match=refused):
        read_scannet(scannet_copy)
    scan = write_3rscan_scan(tmp_path / "3r", objects)
    _spoil_last_face(scan / "labels.instances.annotated.v2.ply", index)
    with pytest.raises(ValueError, match=refused):
        read_3rscan(scan)
    ply, objects_file = _write_generic(tmp_path, with_faces=True)
    _spoil_last_face(ply, index)
    with pytest.raises(ValueError, match=refused):
        read_labelled_ply(ply, objects_file)


def test_missing_embedding_in_the_table_names_the_object(scannet_copy, tmp_path):
    table = tmp_path / "t.txt"
    table.write_text("floor 1 0\nwall 0 1\n")
    with pytest.raises(ValueError, match=r"t\.txt: no embedding for object 5 \('bed'"):
        scene_graph_from_reconstruction(read_scannet(scannet_copy), read_embedding_table(table))
