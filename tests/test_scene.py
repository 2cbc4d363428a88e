"""The scene-graph map: building from meshes, input validation, save/load (exact, atomic,
validated, never unpickling), no recompilation across maps of one capacity, and the mesh-file
loader (:mod:`jaxloc.io.meshes`)."""

from __future__ import annotations

import os
import pickle

import jax
import numpy as np
import pytest
import trimesh
from conftest import cast_padded, random_meshes, random_rays

from jaxloc import raycast
from jaxloc.io import MapFormatError, scene_map
from jaxloc.io.meshes import read_mesh_scene, read_objects_file
from jaxloc.io.scene_map import load_scene, save_scene
from jaxloc.scene import Capacity, SceneGraph

EMB8 = np.eye(8)


def _tri(*corners):
    return np.asarray(corners, float)


def _box(center=(0, 0, 0), size=1.0):
    return trimesh.creation.box(extents=[size] * 3).apply_translation(center)


def _assert_scenes_equal(a: SceneGraph, b: SceneGraph):
    assert a.capacity == b.capacity
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# ----------------------------------------------------------------------------- building


def test_from_meshes_packs_objects_and_normalises_embeddings():
    meshes = [_box((0, 0, 0)), _box((3, 0, 0), 0.5), trimesh.creation.icosphere(1)]
    emb = np.array([[3.0, 4.0], [0.0, -2.0], [1.0, 1.0]])
    scene = SceneGraph.from_meshes(meshes, [2, 0, 7], emb, edges=[[0, 1], [1, 2]])
    assert scene.num_objects == 3 and scene.num_triangles == 12 + 12 + 80
    np.testing.assert_array_equal(np.asarray(scene.labels), [2, 0, 7])
    np.testing.assert_allclose(
        np.asarray(scene.embeddings), emb / np.linalg.norm(emb, axis=1)[:, None], rtol=1e-6
    )
    np.testing.assert_array_equal(np.bincount(np.asarray(scene.triangle_object)), [12, 12, 80])
    np.testing.assert_array_equal(np.asarray(scene.edges), [[0, 1], [1, 2]])
    np.testing.assert_allclose(np.asarray(scene.bounds), [[-1, -1, -1], [3.25, 1, 1]], atol=1e-6)
    # Triangles are the meshes' triangles, in object order.
    np.testing.assert_allclose(
        np.asarray(scene.triangles), np.concatenate([m.triangles for m in meshes]), atol=1e-6
    )
    cap = scene.capacity
    assert (cap.objects, cap.triangles, cap.edges, cap.embedding_dim) == (3, 104, 2, 2)


def test_vertex_colours_are_kept_and_default_colours_apply():
    coloured = _box()
    coloured.visual.vertex_colors = np.tile([255, 0, 0, 255], (8, 1)).astype(np.uint8)
    plain = _box((3, 0, 0))
    scene = SceneGraph.from_meshes(
        [coloured, plain], [0, 1], np.eye(2), colors=[[0, 0, 0], [0, 0.5, 1]]
    )
    tri_obj = np.asarray(scene.triangle_object)
    corner = np.asarray(scene.triangle_colors)
    np.testing.assert_allclose(corner[tri_obj == 0], np.broadcast_to([1, 0, 0], (12, 3, 3)))
    np.testing.assert_allclose(corner[tri_obj == 1], np.broadcast_to([0, 0.5, 1], (12, 3, 3)))
    np.testing.assert_allclose(np.asarray(scene.colors), [[1, 0, 0], [0, 0.5, 1]])


def test_degenerate_triangles_are_dropped_and_harmless(scene):
    good = _box()
    bad_faces = np.array([[0, 0, 1], [2, 2, 2], [0, 1, 1]])  # repeated corners: zero area
    mesh = trimesh.Trimesh(good.vertices, np.concatenate([good.faces, bad_faces]), process=False)
    # Also collinear corners (zero area without repeated indices).
    line = trimesh.Trimesh(
        np.array([[5.0, 0, 0], [6, 0, 0], [7, 0, 0], [5, 1, 0], [6, 1, 0], [5, 1, 1]]),
        np.array([[0, 1, 2], [3, 4, 5]]),
        process=False,
    )
    degenerate_room = SceneGraph.from_meshes(
        [mesh, line], [0, 1], np.eye(2, 8), capacity=scene.capacity
    )
    assert degenerate_room.num_triangles == 12 + 1
    hit = cast_padded(
        degenerate_room,
        np.array([[-3.0, 0.1, 0.2], [5.2, 0.0, 0.3]]),
        np.array([[1.0, 0, 0], [0, 1.0, 0]]),
    )
    np.testing.assert_array_equal(hit.object_id, [0, 1])
    np.testing.assert_allclose(hit.t, [2.5, 1.0], atol=1e-5)
    assert not np.any(np.isnan(hit.t))


@pytest.mark.parametrize(
    "make, error, match",
    [
        (lambda: ([_box()], [0, 1], np.eye(2)), ValueError, "labels must have length 1"),
        (
            lambda: ([_box(), _box()], [0, 1], np.eye(3)),
            ValueError,
            r"embeddings must have shape \(n, d\) = \(2, d\)",
        ),
        (lambda: ([_box()], [0], np.ones(4)), ValueError, "embeddings must have shape"),
        (
            lambda: ([_box(), _box()], [0, 1], [[1.0, 0], [0, 0]]),
            ValueError,
            r"objects \[1\] are zero vectors",
        ),
        (lambda: ([_box()], [0], [[np.nan, 1.0]]), ValueError, "embeddings contain NaN"),
        (lambda: ([_box()], [0.5], [[1.0]]), TypeError, "labels must be integers"),
        (lambda: ([_box()], [-1], [[1.0]]), ValueError, "labels must be >= 0"),
        (lambda: ([], [], np.zeros((0, 2))), ValueError, "at least one object"),
        (lambda: (_box(), [0], [[1.0]]), TypeError, "list of trimesh.Trimesh"),
        (
            lambda: ([np.zeros((3, 3))], [0], [[1.0]]),
            TypeError,
            "object 0: expected trimesh.Trimesh",
        ),
        (
            lambda: (
                [_box(), trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int))],
                [0, 1],
                np.eye(2),
            ),
            ValueError,
            "object 1: empty mesh",
        ),
        (
            lambda: (
                [
                    trimesh.Trimesh(
                        [[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]], process=False
                    )
                ],
                [0],
                [[1.0]],
            ),
            ValueError,
            "object 0: mesh has NaN/inf vertices",
        ),
        (
            lambda: (
                [
                    trimesh.Trimesh(
                        [[0, 0, 0], [np.inf, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False
                    )
                ],
                [0],
                [[1.0]],
            ),
            ValueError,
            "NaN/inf vertices",
        ),
        (
            lambda: (
                [trimesh.Trimesh([[0, 0, 0], [1, 1, 1], [2, 2, 2]], [[0, 1, 2]], process=False)],
                [0],
                [[1.0]],
            ),
            ValueError,
            "object 0: every triangle is degenerate",
        ),
        (
            lambda: ([_box()], [0], [[1.0]], {"colors": [[0.1, 0.2]]}),
            ValueError,
            r"colors must have shape \(1, 3\)",
        ),
        (
            lambda: ([_box()], [0], [[1.0]], {"colors": [[0.1, 0.2, 1.5]]}),
            ValueError,
            r"colors must be finite and in \[0, 1\]",
        ),
        (
            lambda: ([_box()], [0], [[1.0]], {"edges": [[0, 1]]}),
            ValueError,
            r"edges must be integer object indices in \[0, 1\)",
        ),
        (
            lambda: ([_box()], [0], [[1.0]], {"edges": [0, 0, 0]}),
            ValueError,
            r"edges must have shape \(m, 2\)",
        ),
    ],
)
def test_bad_input_raises_a_clear_error(make, error, match):
    args = make()
    kwargs = args[3] if len(args) == 4 else {}
    with pytest.raises(error, match=match):
        SceneGraph.from_meshes(*args[:3], **kwargs)


def test_capacity_too_small_names_the_field_to_raise(scene):
    meshes = random_meshes(0)
    labels, emb = np.zeros(40, int), np.ones((40, 8))
    small = scene.capacity
    for field, match in (
        ("objects", "raise Capacity.objects"),
        ("triangles", "raise Capacity.triangles"),
        ("nodes", "raise Capacity.nodes"),
        ("leaves", "raise Capacity.leaves"),
    ):
        cap = small._replace(**{field: getattr(small, field) - 1})
        with pytest.raises(ValueError, match=match):
            SceneGraph.from_meshes(meshes, labels, emb, capacity=cap)
    with pytest.raises(ValueError, match="embedding dimension 8 differs from the capacity's 4"):
        SceneGraph.from_meshes(meshes, labels, emb, capacity=small._replace(embedding_dim=4))
    with pytest.raises(ValueError, match="raise Capacity.edges"):
        SceneGraph.from_meshes(meshes, labels, emb, edges=[[0, 1]], capacity=small)
    with pytest.raises(ValueError, match="stack"):
        SceneGraph.from_meshes(meshes, labels, emb, capacity=small._replace(stack_size=3))


def test_capacity_union():
    a = Capacity(3, 100, 40, 41, 2, 8)
    b = Capacity(5, 90, 50, 39, 0, 8)
    assert a.union(b) == Capacity(5, 100, 50, 41, 2, 8)
    with pytest.raises(ValueError, match="embedding_dim"):
        a.union(b._replace(embedding_dim=4))


# ----------------------------------------------------------------------------- no retrace


def test_no_retrace_for_a_second_map_of_the_same_capacity(scene, rays, tmp_path):
    traces = []

    @jax.jit
    def nearest(s, o, d):
        traces.append(1)  # runs only when jax traces (compiles) the function
        return raycast(s, o, d).object_id

    first = np.asarray(nearest(scene, *rays))
    other = SceneGraph.from_meshes(
        random_meshes(7, num_objects=30),
        np.arange(30) % 3,
        np.ones((30, 8)),
        capacity=scene.capacity,
    )
    second = np.asarray(nearest(other, *random_rays(other, 2)))
    save_scene(other, tmp_path / "other.npz")
    third = np.asarray(nearest(load_scene(tmp_path / "other.npz"), *random_rays(other, 2)))
    assert len(traces) == 1
    np.testing.assert_array_equal(second, third)
    assert np.any(first >= 0) and np.any(second >= 0)
    # The counter does count: a map of another capacity traces again (lowering only, no compile).
    bigger = SceneGraph.from_meshes(
        random_meshes(8, num_objects=50), np.zeros(50, int), np.ones((50, 8))
    )
    nearest.lower(bigger, *rays)
    assert len(traces) == 2


# ----------------------------------------------------------------------------- save / load


def test_save_load_round_trip_is_exact(scene, tmp_path):
    path = tmp_path / "maps" / "scene.npz"  # parent folders are created
    save_scene(scene, path)
    _assert_scenes_equal(load_scene(path), scene)
    assert sorted(os.listdir(path.parent)) == ["scene.npz"]  # no temp file left


def test_save_load_round_trip_keeps_padding_capacity_and_edges(scene, tmp_path):
    meshes = [_box(), _box((2, 0, 0)), trimesh.creation.icosphere(1, 0.4)]
    colored = meshes[2]
    colored.visual.vertex_colors = (
        np.random.default_rng(0).integers(0, 256, (len(colored.vertices), 4)).astype(np.uint8)
    )
    capacity = scene.capacity._replace(edges=5)
    small = SceneGraph.from_meshes(
        meshes,
        [0, 3, 1],
        np.random.default_rng(1).normal(size=(3, 8)),
        edges=[[0, 2]],
        capacity=capacity,
    )
    save_scene(small, tmp_path / "small.npz")
    back = load_scene(tmp_path / "small.npz")
    _assert_scenes_equal(back, small)
    assert back.capacity == capacity and back.num_objects == 3


def test_storage_size_is_the_saved_content(scene, tmp_path):
    save_scene(scene, tmp_path / "s.npz")
    with np.load(tmp_path / "s.npz") as data:
        content = sum(
            data[k].nbytes
            for k in (
                "labels",
                "embeddings",
                "object_colors",
                "edges",
                "triangles",
                "triangle_object",
                "triangle_colors",
            )
        )
    assert scene.storage_bytes() == content
    assert scene.storage_mb() == pytest.approx(content / 1e6)


def test_failed_save_keeps_the_existing_file_and_leaves_no_temp(scene, tmp_path, monkeypatch):
    path = tmp_path / "map.npz"
    save_scene(scene, path)
    before = path.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    other = SceneGraph.from_meshes([_box()], [0], np.ones((1, 8)))
    monkeypatch.setattr(np, "savez_compressed", boom)
    with pytest.raises(OSError, match="disk full"):
        save_scene(other, path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["map.npz"]
    _assert_scenes_equal(load_scene(path), scene)


def _rewrite(src, dst, **changes):
    """Copy the arrays of a saved map to ``dst`` with some replaced (None deletes)."""
    with np.load(src) as data:
        content = {k: data[k] for k in data.files}
    for key, value in changes.items():
        if value is None:
            content.pop(key)
        else:
            content[key] = value
    np.savez(dst, **content)
    return dst


@pytest.fixture(scope="module")
def saved(tmp_path_factory, scene):
    path = tmp_path_factory.mktemp("maps") / "good.npz"
    save_scene(scene, path)
    return path


def test_corrupt_and_truncated_files_raise_map_format_error(saved, tmp_path):
    data = saved.read_bytes()
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(np.random.default_rng(0).bytes(4096))
    empty = tmp_path / "empty.npz"
    empty.write_bytes(b"")
    flipped = bytearray(data)
    flipped[len(data) // 3 : len(data) // 3 + 64] = bytes(64)
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(bytes(flipped))
    for path in (truncated, garbage, empty, corrupt):
        with pytest.raises(MapFormatError, match="not a readable jaxloc map"):
            load_scene(path)
    with pytest.raises(FileNotFoundError):
        load_scene(tmp_path / "missing.npz")


def test_wrong_version_and_foreign_files_raise(saved, tmp_path):
    with pytest.raises(MapFormatError, match="format version 99 is not supported"):
        load_scene(_rewrite(saved, tmp_path / "v99.npz", version=np.array(99)))
    with pytest.raises(MapFormatError, match="format version"):
        load_scene(_rewrite(saved, tmp_path / "nov.npz", version=None))
    with pytest.raises(MapFormatError, match="not a jaxloc scene graph"):
        load_scene(_rewrite(saved, tmp_path / "foreign.npz", format=np.array("something.else")))
    foreign = tmp_path / "plain.npz"
    np.savez(foreign, a=np.zeros(3))
    with pytest.raises(MapFormatError, match="not a jaxloc scene graph"):
        load_scene(foreign)


class _Payload:
    """Unpickling this creates a marker file: proof that a loader ran pickle."""

    marker = ""

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_pickled_objects_are_never_loaded(saved, tmp_path):
    marker = tmp_path / "unpickled"
    _Payload.marker = str(marker)
    evil = np.empty(1, object)
    evil[0] = _Payload()
    path = _rewrite(saved, tmp_path / "evil.npz", labels=evil)
    with pytest.raises(MapFormatError):
        load_scene(path)
    assert not marker.exists()
    # A raw pickle renamed to .npz is refused too.
    raw = tmp_path / "raw.npz"
    raw.write_bytes(pickle.dumps(_Payload()))
    with pytest.raises(MapFormatError):
        load_scene(raw)
    assert not marker.exists()


@pytest.mark.parametrize(
    "change, match",
    [
        ({"triangles": None}, "missing array 'triangles'"),
        ({"labels": np.zeros(40, np.float32)}, "'labels' has dtype float32"),
        ({"triangles": np.zeros((5, 3, 2), np.float32)}, "'triangles' has shape"),
        ({"embeddings": np.full((40, 8), np.nan, np.float32)}, "'embeddings' contains NaN"),
        ({"embeddings": np.ones((40, 8), np.float32)}, "not unit-norm"),
        ({"embeddings": np.eye(39, 8, dtype=np.float32)}, "embeddings do not match labels"),
        ({"triangle_object": np.full(1440, 40, np.int32)}, "object indices out of range"),
        ({"labels": np.full(40, -3, np.int32)}, "negative labels"),
        ({"capacity": np.array([1, 2], np.int64)}, "bad capacity record"),
        (
            {"capacity": np.array([40, 10, 496, 497, 0, 8, 4, 64], np.int64)},
            "raise Capacity.triangles",
        ),
        # colours as from_meshes takes them: finite RGB in [0, 1]
        (
            {"object_colors": np.full((40, 3), 5.0, np.float32)},
            r"'object_colors' must be RGB in \[0, 1\], found \[5, 5\]",
        ),
        (
            {"object_colors": np.full((40, 3), -1.0, np.float32)},
            r"'object_colors' must be RGB in \[0, 1\], found \[-1, -1\]",
        ),
        (
            {"triangle_colors": np.full((1440, 3, 3), 300.0, np.float32)},
            r"'triangle_colors' must be RGB in \[0, 1\], found \[300, 300\]",
        ),
        # every object has a mesh, as from_meshes requires
        (
            {"triangle_object": np.zeros(1440, np.int32)},
            r"39 objects own no triangle \(first \[1, 2, 3",
        ),
    ],
)
def test_invalid_map_contents_raise(saved, tmp_path, change, match, scene):
    assert scene.num_triangles == 1440 and scene.num_objects == 40  # the sizes used above
    with pytest.raises(MapFormatError, match=match):
        load_scene(_rewrite(saved, tmp_path / "bad.npz", **change))


def _capacity_record(scene: SceneGraph, **fields) -> np.ndarray:
    """The scene's capacity as a map file stores it, with some fields replaced."""
    return np.array(tuple(scene.capacity._replace(**fields)), np.int64)


@pytest.mark.timeout(60)  # leaf_size 0 would make the BVH build split forever
@pytest.mark.parametrize(
    "fields, match",
    [
        ({"leaf_size": 0}, r"Capacity.leaf_size must be an integer in \[1, 64\], got 0"),
        ({"leaf_size": -1}, r"Capacity.leaf_size must be an integer in \[1, 64\], got -1"),
        ({"leaf_size": 65}, r"Capacity.leaf_size must be an integer in \[1, 64\], got 65"),
        ({"stack_size": 0}, r"Capacity.stack_size must be an integer in \[1, 128\], got 0"),
        ({"stack_size": 10**11}, r"Capacity.stack_size must be an integer in \[1, 128\]"),
        ({"objects": 10**15}, r"Capacity.objects must be an integer in \[1, 1073741824\]"),
        ({"objects": -1}, r"Capacity.objects must be an integer in \[1, 1073741824\], got -1"),
        ({"triangles": 0}, r"Capacity.triangles must be an integer in \[1, 1073741824\]"),
        ({"nodes": -1}, r"Capacity.nodes must be an integer in \[0, 1073741824\], got -1"),
        ({"leaves": 0}, r"Capacity.leaves must be an integer in \[1, 1073741824\], got 0"),
        ({"edges": -1}, r"Capacity.edges must be an integer in \[0, 1073741824\], got -1"),
        ({"embedding_dim": 0}, r"Capacity.embedding_dim must be an integer in \[1, 1073741824\]"),
    ],
)
def test_out_of_range_capacity_in_a_map_file_raises_at_once(saved, tmp_path, scene, fields, match):
    path = _rewrite(saved, tmp_path / "bad.npz", capacity=_capacity_record(scene, **fields))
    with pytest.raises(MapFormatError, match=match):
        load_scene(path)


@pytest.mark.timeout(60)
def test_save_refuses_a_map_the_loader_would_refuse(tmp_path, monkeypatch):
    """Padding beyond the allowance: was written, then refused by ``load_scene``."""
    scene = SceneGraph.from_meshes([_box()], [0], [[1.0]])
    padded = SceneGraph.from_meshes(
        [_box()], [0], [[1.0]], capacity=scene.capacity._replace(edges=2**18)
    )
    monkeypatch.setattr(scene_map, "MAX_PADDING_BYTES", 2**20)
    path = tmp_path / "padded.npz"
    with pytest.raises(ValueError, match=r"pads the map by 2 MiB, more than the 1 MiB .*nothing"):
        save_scene(padded, path)
    assert not path.exists()
    save_scene(scene, path)  # its own capacity pads by nothing
    _assert_scenes_equal(load_scene(path), scene)


def test_capacity_array_bytes_are_the_scene_graphs_own(scene):
    """The padding allowance is measured by ``Capacity.array_bytes``: exactly the arrays' bytes."""
    arrays = [np.asarray(leaf) for leaf in jax.tree.leaves(scene)]
    assert scene.capacity.array_bytes() == sum(a.nbytes for a in arrays)


def test_embeddings_far_from_unit_length_keep_their_direction():
    """1e200 (its square overflows: the map stored a zero embedding) and 1e-200 (its square
    underflows: it was refused as a zero vector) normalise like any other embedding."""
    scene = SceneGraph.from_meshes([_box(), _box()], [0, 1], [[1e200, 1e200], [3e-200, -4e-200]])
    np.testing.assert_allclose(
        np.asarray(scene.embeddings)[:2], [[0.5**0.5, 0.5**0.5], [0.6, -0.8]], rtol=1e-6
    )
    with pytest.raises(ValueError, match=r"embeddings of objects \[1\] are zero vectors"):
        SceneGraph.from_meshes([_box(), _box()], [0, 1], [[1.0, 0.0], [0.0, 0.0]])


def test_out_of_range_capacity_is_refused_before_the_bvh_build():
    capacity = Capacity(1, 12, 0, 1, 0, 1, leaf_size=0)
    with pytest.raises(ValueError, match=r"Capacity.leaf_size must be an integer in \[1, 64\]"):
        SceneGraph.from_meshes([_box()], [0], [[1.0]], capacity=capacity)
    with pytest.raises(ValueError, match="Capacity.objects must be an integer"):
        SceneGraph.from_meshes([_box()], [0], [[1.0]], capacity=capacity._replace(objects=2.5))


def test_map_file_capacity_may_pad_the_content_only_by_the_allowance(
    saved, tmp_path, scene, monkeypatch
):
    # in range field by field, but 32 GiB of node rows for a map of 1440 triangles
    huge = _capacity_record(scene, nodes=2**30)
    with pytest.raises(MapFormatError, match=r"pads the map by 32768 MiB, more than the 1024 MiB"):
        load_scene(_rewrite(saved, tmp_path / "huge.npz", capacity=huge))
    monkeypatch.setattr(scene_map, "MAX_PADDING_BYTES", 2**20)
    over = _capacity_record(scene, edges=2**18)  # 2 MiB of edge rows
    with pytest.raises(MapFormatError, match=r"pads the map by 2 MiB, more than the 1 MiB"):
        load_scene(_rewrite(saved, tmp_path / "over.npz", capacity=over))
    padded = _capacity_record(scene, objects=40 + 1000, edges=100)
    loaded = load_scene(_rewrite(saved, tmp_path / "padded.npz", capacity=padded))
    assert loaded.capacity == scene.capacity._replace(objects=1040, edges=100)
    _assert_scenes_equal(load_scene(saved), scene)  # a map's own capacity pads by nothing


# ----------------------------------------------------------------------------- mesh files


def _write_glb(path):
    """Three named objects with vertex colours and node transforms; returns world meshes."""
    s = trimesh.Scene()
    world = {}
    for i, name in enumerate(["chair", "table", "lamp"]):
        mesh = (
            trimesh.creation.box(extents=[1, 0.5, 0.8])
            if i < 2
            else trimesh.creation.icosphere(1, 0.3)
        )
        mesh.visual.vertex_colors = np.tile([60 * i, 200, 20, 255], (len(mesh.vertices), 1)).astype(
            np.uint8
        )
        transform = trimesh.transformations.rotation_matrix(0.3 * i, [0, 0, 1])
        transform[:3, 3] = [2.0 * i, 1.0, 0.5]
        s.add_geometry(mesh, geom_name=name, node_name=f"{name}_node", transform=transform)
        world[name] = mesh.copy().apply_transform(transform)
    s.export(path)
    return world


def test_load_scene_from_glb_and_objects_file(tmp_path):
    world = _write_glb(tmp_path / "room.glb")
    (tmp_path / "objects.txt").write_text(
        "# name label embedding\n\nlamp 4 0 0 2\ntable 1 1 1 0  # trailing comment\nchair 0 3 0 4\n"
    )
    scene = read_mesh_scene(tmp_path / "room.glb", tmp_path / "objects.txt")
    np.testing.assert_array_equal(np.asarray(scene.labels), [4, 1, 0])  # objects-file order
    np.testing.assert_allclose(
        np.asarray(scene.embeddings), [[0, 0, 1], [2**-0.5, 2**-0.5, 0], [0.6, 0, 0.8]], atol=1e-6
    )
    tri_obj = np.asarray(scene.triangle_object)
    for k, name in enumerate(["lamp", "table", "chair"]):
        tris = np.asarray(scene.triangles)[tri_obj == k]
        np.testing.assert_allclose(
            np.sort(tris.reshape(-1, 3), 0)[[0, -1]], world[name].bounds, atol=1e-5
        )
        np.testing.assert_allclose(
            np.asarray(scene.colors)[k], [60 * (2 - k) / 255, 200 / 255, 20 / 255], atol=1e-6
        )


def test_load_scene_from_a_list_of_ply_files(tmp_path):
    paths = []
    for i, name in enumerate(["wall", "sofa"]):
        mesh = _box((3.0 * i, 0, 0), 1.0 + i)
        mesh.export(tmp_path / f"{name}.ply")
        paths.append(tmp_path / f"{name}.ply")
    (tmp_path / "objects.txt").write_text("sofa 2 1 0\nwall 0 0 1\n")
    scene = read_mesh_scene(paths, tmp_path / "objects.txt")
    assert scene.num_objects == 2 and scene.num_triangles == 24
    np.testing.assert_array_equal(np.asarray(scene.labels), [2, 0])
    sofa = np.asarray(scene.triangles)[np.asarray(scene.triangle_object) == 0]
    np.testing.assert_allclose(sofa.reshape(-1, 3).min(0), [2, -1, -1], atol=1e-6)
    # A single .ply file is one object named by its stem.
    single = read_mesh_scene(paths[0], _write(tmp_path / "one.txt", "wall 5 1 2 3\n"))
    assert single.num_objects == 1 and int(single.labels[0]) == 5


def _write(path, text):
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "text, match",
    [
        (
            "chair 0 1 0\ntable 1 1\nlamp 2 0 1\n",
            r"objects.txt:2: embedding of object 'table' has 1 values, expected 2 \(as on line 1\)",
        ),
        (
            "chair 0 1 0\ntable 1 1 x\nlamp 2 0 1\n",
            r"objects.txt:2: embedding of object 'table' has a non-numeric value",
        ),
        (
            "chair 0 1 0\ntable one 1 0\nlamp 2 0 1\n",
            r"objects.txt:2: label 'one' of object 'table' is not an integer",
        ),
        (
            "chair 0 1 0\ntable -1 1 0\nlamp 2 0 1\n",
            r"objects.txt:2: label -1 of object 'table' must be >= 0",
        ),
        (
            "chair 0 1 0\n\nchair 1 1 0\n",
            r"objects.txt:3: duplicate object name 'chair' \(first on line 1\)",
        ),
        ("chair 0\n", r"objects.txt:1: expected 'name label e_1 ... e_d'"),
        ("chair 0 1 nan\n", r"objects.txt:1: embedding of object 'chair' has NaN or inf"),
        ("# nothing\n\n", r"no objects"),
        (
            "chair 0 1 0\ntable 1 1 0\n",
            r"objects without a mesh: \[\] ?|meshes not in the objects file: \['lamp'\]",
        ),
        (
            "chair 0 1 0\ntable 1 1 0\nlamp 2 0 1\nsofa 3 1 1\n",
            r"objects without a mesh: \['sofa'\]",
        ),
        ("chair 0 1 0\ntable 1 0 0\nlamp 2 0 0\n", r"objects \[1, 2\] are zero vectors"),
    ],
)
def test_objects_file_errors_are_clear(tmp_path, text, match):
    _write_glb(tmp_path / "room.glb")
    with pytest.raises(ValueError, match=match):
        read_mesh_scene(tmp_path / "room.glb", _write(tmp_path / "objects.txt", text))


def test_mesh_file_errors_name_the_object(tmp_path):
    broken = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False)
    broken.vertices[1, 0] = np.nan
    broken.export(tmp_path / "bad.ply")
    with pytest.raises(ValueError, match=r"object 0 \('bad'\): mesh has NaN/inf vertices"):
        read_mesh_scene([tmp_path / "bad.ply"], _write(tmp_path / "o.txt", "bad 0 1\n"))
    with pytest.raises(FileNotFoundError):
        read_mesh_scene(tmp_path / "missing.glb", tmp_path / "o.txt")
    names, labels, emb = read_objects_file(_write(tmp_path / "p.txt", "a 1 1e-3 -2.5E2\n"))
    assert names == ["a"] and labels.tolist() == [1] and emb.tolist() == [[1e-3, -250.0]]
