"""The bad-input catalogue (``docs/bad_inputs.md``): each row not already tested elsewhere is here.

Host-side checks (maps, mesh and map files, particles) run eagerly and cost nothing; the filter
rows (bad values inside a hand-built :class:`~jaxloc.sg2loc.Frame`, particles outside the
map, likelihood underflow, all-invalid depth) share the one compiled pass of
``tests/_tiny_world.py``: traced values such as sigma change without recompiling.
"""

from __future__ import annotations

import dataclasses

import _tiny_world as tiny
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxloc.io import (
    meshes as mesh_io,
    read_embedding_table,
    read_instance_map,
    read_semantickitti_scan,
)
from jaxloc.m2loc import build_map
from jaxloc.scene import Capacity, SceneGraph
from jaxloc.sg2loc._particles import ParticleState, init_box, init_region, inject_uniform, predict


def _box() -> trimesh.Trimesh:
    return trimesh.creation.box()


# ----------------------------------------------------------------------------- maps


def test_map_embeddings_of_a_non_real_dtype_are_rejected():
    with pytest.raises(TypeError, match="embeddings must be a real numeric array"):
        SceneGraph.from_meshes([_box()], [0], np.ones((1, 4)) * 1j)
    with pytest.raises(TypeError, match="embeddings must be a real numeric array"):
        SceneGraph.from_meshes([_box()], [0], [["a", "b"]])


def test_map_inf_embedding_is_rejected():
    with pytest.raises(ValueError, match="embeddings contain NaN or inf"):
        SceneGraph.from_meshes([_box()], [0], [[np.inf, 1.0]])


def test_map_inf_vertex_is_rejected():
    mesh = _box()
    vertices = np.array(mesh.vertices)
    vertices[3, 2] = -np.inf
    bad = trimesh.Trimesh(vertices, mesh.faces, process=False)
    with pytest.raises(ValueError, match="object 1: mesh has NaN/inf vertices"):
        SceneGraph.from_meshes([_box(), bad], [0, 1], np.eye(2))


def test_map_face_index_out_of_range_is_rejected():
    bad = trimesh.Trimesh(np.eye(3), [[0, 1, 5]], process=False)
    with pytest.raises(ValueError, match="object 0: a face refers to vertex 5"):
        SceneGraph.from_meshes([bad], [0], [[1.0]])


def test_map_object_of_one_point_is_rejected():
    point = trimesh.Trimesh(np.zeros((3, 3)), [[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="object 1: every triangle is degenerate"):
        SceneGraph.from_meshes([_box(), point], [0, 1], np.eye(2))


def test_map_beyond_the_object_and_embedding_capacity_names_what_to_raise():
    small = SceneGraph.from_meshes([_box()], [0], [[1.0, 0.0]])
    two = [_box(), _box().apply_translation([3, 0, 0])]
    with pytest.raises(ValueError, match="raise Capacity.objects"):
        SceneGraph.from_meshes(two, [0, 1], np.eye(2), capacity=small.capacity)
    wider = small.capacity._replace(embedding_dim=3)
    with pytest.raises(ValueError, match="embedding dimension 2 differs from the capacity's 3"):
        SceneGraph.from_meshes([_box()], [0], [[1.0, 0.0]], capacity=wider)
    assert isinstance(small.capacity, Capacity)


# ----------------------------------------------------------------------------- map files


def test_truncated_or_garbage_mesh_files_name_the_file(tmp_path):
    ply = tmp_path / "chair.ply"
    _box().export(ply)
    data = ply.read_bytes()
    ply.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"chair\.ply: not a readable mesh file"):
        mesh_io.read_meshes(ply)
    glb = tmp_path / "room.glb"
    glb.write_bytes(b"garbage!" * 16)
    with pytest.raises(ValueError, match=r"room\.glb: not a readable mesh file"):
        mesh_io.read_meshes(glb)
    with pytest.raises(ValueError, match=r"chair\.ply: not a readable mesh file"):
        mesh_io.read_meshes([ply])


def test_mesh_file_with_nan_vertex_or_no_faces(tmp_path):
    nan_obj = tmp_path / "nan.obj"
    nan_obj.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    meshes = list(mesh_io.read_meshes(nan_obj).values())
    with pytest.raises(ValueError, match="NaN/inf vertices"):
        SceneGraph.from_meshes(meshes, [0], [[1.0]])
    no_faces = tmp_path / "points.obj"
    no_faces.write_text("v 0 0 0\nv 1 0 0\n")
    with pytest.raises(ValueError, match="no triangle meshes"):
        mesh_io.read_meshes(no_faces)


@pytest.mark.parametrize("index", [-5, 99])
def test_mesh_file_whose_face_names_a_vertex_it_lacks(tmp_path, index):
    """A damaged PLY face: was an IndexError from trimesh's face colours (99) or a face on the
    wrong vertex (-5, wrapped around)."""
    ply = tmp_path / "chair.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
        f"0 0 0 9 9 9\n1 0 0 9 9 9\n0 1 0 9 9 9\n1 1 0 9 9 9\n3 0 1 2\n3 1 3 {index}\n"
    )
    refused = rf"chair\.ply \(object 'chair'\): face 1 refers to vertex {index}, but the file has 4"
    for given in (ply, [ply]):
        with pytest.raises(ValueError, match=refused):
            mesh_io.read_meshes(given)


def test_objects_file_that_is_not_utf8_or_truncated(tmp_path):
    binary = tmp_path / "objects.txt"
    binary.write_bytes(b"chair 0 \xff\xfe 1\n")
    with pytest.raises(ValueError, match=r"objects\.txt: not a UTF-8 text file"):
        mesh_io.read_objects_file(binary)
    truncated = tmp_path / "cut.txt"
    truncated.write_text("chair 0 1 2 3\ntable 1 1 2")  # the last line cut mid-embedding
    with pytest.raises(ValueError, match=r"cut\.txt:2: .* has 2 values, expected 3"):
        mesh_io.read_objects_file(truncated)


def _write_instance_map(root, text15: bytes) -> None:
    (root / "instances").mkdir()
    (root / "instances" / "15.txt").write_bytes(text15)
    (root / "instances" / "17.txt").write_text("0 1 2 3\n")
    (root / "instances" / "18.txt").write_text("0 4 5 6\n")


def test_instance_map_file_that_is_not_utf8_names_the_file(tmp_path):
    _write_instance_map(tmp_path, b"0 1 2 3\n\xff\xfe 1 2\n")
    with pytest.raises(ValueError, match=r"15\.txt"):
        read_instance_map(tmp_path)


def test_instance_map_truncated_mid_line_or_empty(tmp_path):
    cut = tmp_path / "cut"
    cut.mkdir()
    _write_instance_map(cut, b"0 1 2 3\n1 4 5")
    with pytest.raises(ValueError, match=r"15\.txt:2: expected 4 fields"):
        read_instance_map(cut)
    empty = tmp_path / "empty"
    empty.mkdir()
    _write_instance_map(empty, b"")
    instances = read_instance_map(empty)  # two vertices in all
    with pytest.raises(ValueError, match="at least 3 vertices"):
        build_map(instances.points, instances.labels)


def test_numbers_beyond_float32_in_a_file_are_refused_naming_it(tmp_path):
    """Finite in float64 but not in float32, where every value read ends up: an instance centroid
    (else a map with an infinite point), an embedding-table row (else a zero map embedding, its
    norm overflowing), an embedding table's ``.npy``, and a complex ``.npy`` (else its imaginary
    part dropped with a ComplexWarning)."""
    _write_instance_map(tmp_path, b"0 1 2 3\n1 1e39 0 0\n")
    with pytest.raises(ValueError, match=r"15\.txt:2: .* beyond float32's range \(1e\+39"):
        read_instance_map(tmp_path)
    table = tmp_path / "table.txt"
    table.write_text("chair 1e200 1e200\ntable 0 1\n")
    with pytest.raises(ValueError, match=r"table\.txt:1: embedding of 'chair' has a value beyond"):
        read_embedding_table(table)
    np.save(tmp_path / "big.npy", np.full((2, 3), 1e300))
    with pytest.raises(ValueError, match=r"big\.npy has a value beyond float32's range"):
        read_embedding_table(tmp_path / "big.npy")
    np.save(tmp_path / "complex.npy", np.eye(2) * 1j)
    complex_refused = r"complex\.npy: expected a \(K, d\) array of real numbers"
    with pytest.raises(ValueError, match=complex_refused):
        read_embedding_table(tmp_path / "complex.npy")
    np.save(tmp_path / "empty.npy", np.zeros((3, 0)))  # else a table of 0-dimensional embeddings
    with pytest.raises(ValueError, match=r"empty\.npy: expected a \(K, d\) array, got the empty"):
        read_embedding_table(tmp_path / "empty.npy")


def test_semantickitti_scan_truncated_or_mismatched(tmp_path):
    points = np.arange(40, dtype="<f4")
    bin_path, label_path = tmp_path / "a.bin", tmp_path / "a.label"
    points[:-1].tofile(bin_path)  # 39 floats: a truncated record
    np.zeros(10, "<u4").tofile(label_path)
    with pytest.raises(ValueError, match="not a multiple of 4"):
        read_semantickitti_scan(bin_path, label_path)
    points.tofile(bin_path)
    np.zeros(9, "<u4").tofile(label_path)
    with pytest.raises(ValueError, match="9 labels for 10 points"):
        read_semantickitti_scan(bin_path, label_path)


# ----------------------------------------------------------------------------- LiDAR maps


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_triplet_map_with_non_finite_points(bad):
    points = np.array([[0.0, 0, 0], [5, 0, 0], [0, 7, 1], [3, 3, bad]])
    with pytest.raises(ValueError, match="map points contain NaN or inf"):
        build_map(points, np.array([15, 17, 18, 17]))


def test_triplet_map_of_identical_points_or_float_labels():
    with pytest.raises(ValueError, match="3 duplicate point"):
        build_map(np.ones((4, 3)), np.array([15, 17, 18, 17]))
    with pytest.raises(ValueError, match="labels must be integer class ids"):
        build_map(np.eye(4, 3), np.array([15.0, 17, 18, 17]))


# ----------------------------------------------------------------------------- particles


def test_particle_regions_and_motions_must_be_finite():
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="lo must be finite"):
        init_region(key, 8, [np.nan, 0.0], [1.0, 1.0], 0.0)
    with pytest.raises(ValueError, match="hi must be finite"):
        init_region(key, 8, [0.0, 0.0], [np.inf, 1.0], 0.0)
    with pytest.raises(ValueError, match="floor_z must be finite"):
        init_region(key, 8, [0.0, 0.0], [1.0, 1.0], np.nan)
    with pytest.raises(ValueError, match="centre must be finite"):
        init_box(key, 8, [np.nan, 0.0, 1.5, 0.0], [0.5, 0.5, 0.5])
    state = init_region(key, 8, [0.0, 0.0], [1.0, 1.0], 0.0)
    with pytest.raises(ValueError, match="motion must be finite"):
        predict(key, state, [0.1, np.nan, 0.0, 0.0])
    with pytest.raises(ValueError, match="floor_z must be finite"):
        inject_uniform(key, state, 2, [0.0, 0.0], [1.0, 1.0], np.inf)
    # under jit the checks step aside (values are traced): no error, no retrace per value
    jitted = jax.jit(predict)
    assert jnp.all(jnp.isfinite(jitted(key, state, jnp.zeros(4)).poses))


# ----------------------------------------------------------------------------- filter frames


@pytest.fixture(scope="module")
def world():
    scene = tiny.scene()
    return scene, tiny.step_config(scene), tiny.initial_state(scene), tiny.frames(tiny.CHUNK)


def _run(world, frames=None, state=None, config=None):
    scene, base_config, initial, base_frames = world
    return tiny.RUN_PASS(
        jax.random.key(5),
        initial if state is None else state,
        base_frames if frames is None else frames,
        scene,
        base_config if config is None else config,
    )


def _finite(tree) -> bool:
    return all(
        bool(jnp.all(~jnp.isnan(leaf)))
        for leaf in jax.tree.leaves(tree)
        if jnp.issubdtype(leaf.dtype, jnp.floating)
    )


def test_frame_with_all_invalid_depth_runs_without_nan(world):
    frames = eqx.tree_at(lambda f: f.depth, world[3], jnp.zeros_like(world[3].depth))
    state, info = _run(world, frames)
    assert _finite(state.poses) and _finite(info.mle) and _finite(info.log_likelihood)


def test_likelihood_underflow_for_every_particle_recovers(world):
    config = world[1]
    tiny_sigma = dataclasses.replace(config.observation, sigma=jnp.float32(1e-30))
    config = eqx.tree_at(lambda c: c.observation, config, tiny_sigma)
    state, info = _run(world, config=config)
    assert bool(jnp.all(info.degenerate))
    assert _finite(state.poses) and _finite(info.mle) and _finite(info.particle_weights)
    assert bool(jnp.all(jnp.isclose(jnp.sum(info.particle_weights, axis=-1), 1.0, atol=1e-5)))


def test_particles_outside_the_map_stay_finite_and_injection_brings_some_back(world):
    scene, config, initial, _ = world
    far = ParticleState(
        initial.poses.at[:, :2].add(100.0), initial.log_weights, initial.active
    )  # every particle 100 m outside the room
    state, info = _run(world, state=far)
    assert _finite(state.poses) and _finite(info.mle) and _finite(info.log_likelihood)
    lo, hi = np.asarray(config.region.lo), np.asarray(config.region.hi)
    xy = np.asarray(state.poses[:, :2])[np.asarray(state.active)]
    inside = np.all((xy >= lo) & (xy <= hi), axis=1)
    assert inside.sum() >= 1  # frame 3 injected 2 particles into the region


@pytest.mark.parametrize("field", ["patch_embeddings", "depth", "rgb", "tilt"])
def test_nan_in_a_frame_observation_leaves_the_poses_finite(world, field):
    frames = world[3]
    value = getattr(frames, field)
    poisoned = eqx.tree_at(lambda f: getattr(f, field), frames, value.at[1].set(jnp.nan))
    state, info = _run(world, poisoned)
    assert _finite(state.poses) and _finite(info.mle), field


def test_nan_ego_motion_in_a_frame_does_not_poison_the_particles(world):
    frames = world[3]
    poisoned = eqx.tree_at(lambda f: f.motion, frames, frames.motion.at[1].set(jnp.nan))
    state, info = _run(world, poisoned)
    assert _finite(state.poses) and _finite(info.mle)
    np.testing.assert_array_equal(np.asarray(info.motion_valid), np.arange(len(frames.index)) != 1)
