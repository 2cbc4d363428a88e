"""Merging synthetic rooms into one map (jaxloc.synthetic.indoor.merge), checked with trimesh."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import brute_force

from jaxloc.synthetic import indoor
from jaxloc.synthetic.indoor.merge import merge_rooms

SMALL = indoor.RoomConfig(
    length_range=(4.0, 5.0), width_range=(4.0, 5.0), num_objects=(15, 16), vertex_range=(100, 120)
)


@pytest.fixture(scope="module")
def rooms():
    return [indoor.make_room(seed, SMALL) for seed in (3, 4)]


def test_merge_translates_rooms_apart_and_keeps_their_content(rooms):
    merged = merge_rooms(rooms, gap=0.3)
    counts = [room.num_objects for room in rooms]
    assert len(merged.meshes) == sum(counts)
    np.testing.assert_array_equal(merged.labels, np.concatenate([r.labels for r in rooms]))
    np.testing.assert_array_equal(merged.room_of_object, np.repeat([0, 1], counts))
    np.testing.assert_allclose(merged.offsets[1], [rooms[0].size[0] + 0.3, 0.0, 0.0])
    for i, mesh in enumerate(rooms[1].meshes):  # room 1's meshes, shifted by its offset
        shifted = merged.meshes[counts[0] + i].vertices
        np.testing.assert_allclose(shifted, mesh.vertices + merged.offsets[1], atol=1e-9)
    owner = merged.room_of_object
    boxes = [
        np.concatenate([merged.meshes[i].vertices for i in np.flatnonzero(owner == k)])
        for k in range(2)
    ]
    assert boxes[0][:, 0].max() < boxes[1][:, 0].min()  # no overlap along x
    assert rooms[0].meshes[0].vertices is not merged.meshes[0].vertices  # inputs untouched


def test_rays_inside_a_merged_room_hit_what_they_hit_in_the_room_alone(rooms):
    """A float64 brute force as the peer: every ray cast from inside room 1 of the merged map hits
    at the same distance as in room 1 alone, so rooms cannot see into each other."""
    merged = merge_rooms(rooms)
    rng = np.random.default_rng(0)
    room = rooms[1]
    origins = np.column_stack(
        [rng.uniform(0.8, room.size[0] - 0.8, 64), rng.uniform(0.8, room.size[1] - 0.8, 64)]
    )
    origins = np.column_stack([origins, rng.uniform(1.2, 2.0, 64)])
    directions = rng.normal(size=(64, 3))
    alone = trimesh.util.concatenate(list(room.meshes)).triangles
    together = trimesh.util.concatenate(list(merged.meshes)).triangles
    t_alone = brute_force(alone, origins, directions)[0]
    shifted = merged.to_merged(np.column_stack([origins, np.zeros(64)]), 1)[:, :3]
    t_merged = brute_force(together, shifted, directions)[0]
    assert np.all(np.isfinite(t_alone))
    np.testing.assert_allclose(t_merged, t_alone, atol=1e-6)


def test_scene_graph_pose_mapping_and_room_lookup(rooms):
    merged = merge_rooms(rooms)
    scene = merged.scene_graph()
    assert scene.num_objects == sum(room.num_objects for room in rooms)
    bounds = np.asarray(scene.bounds)
    np.testing.assert_allclose(bounds[1, 0], merged.offsets[1, 0] + rooms[1].size[0], atol=1e-4)
    pose = np.array([1.0, 2.0, 1.5, 0.3])
    moved = merged.to_merged(pose, 1)
    np.testing.assert_allclose(moved, [1.0 + merged.offsets[1, 0], 2.0, 1.5, 0.3])
    np.testing.assert_array_equal(
        merged.room_at(np.array([pose[:2], moved[:2], [merged.offsets[1, 0] - 0.1, 1.0]])),
        [0, 1, -1],
    )


def test_merge_rejects_bad_input(rooms):
    with pytest.raises(ValueError, match="at least one room"):
        merge_rooms([])
    with pytest.raises(ValueError, match="gap must be > 0"):
        merge_rooms(rooms, gap=0.0)
