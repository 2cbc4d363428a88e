"""The synthetic indoor world: rooms, embeddings, changes, trajectories and simulated sensors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxloc import raycast
from jaxloc.camera import stride_grid
from jaxloc.geometry import ego_motion, rotation_world_cam
from jaxloc.synthetic.indoor import (
    CLASS_NAMES,
    ChangeConfig,
    EpisodeConfig,
    RoomConfig,
    SensorConfig,
    TrajectoryConfig,
    change_room,
    frames,
    make_episode,
    make_room,
    object_embeddings,
)

SMALL = EpisodeConfig(sensor=SensorConfig(width=160, height=90))
SEEDS = (0, 1, 2, 3)


@pytest.fixture(scope="module")
def rooms():
    return {seed: make_room(seed) for seed in SEEDS}


@pytest.fixture(scope="module")
def episode():
    return make_episode(7, 8, SMALL)


def test_room_is_deterministic_for_a_seed():
    a, b, c = make_room(5), make_room(5), make_room(6)
    assert a.size == b.size and a.num_objects == b.num_objects
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.embeddings, b.embeddings)
    for ma, mb in zip(a.meshes, b.meshes, strict=True):
        np.testing.assert_array_equal(ma.vertices, mb.vertices)
        np.testing.assert_array_equal(ma.visual.vertex_colors, mb.visual.vertex_colors)
    assert a.size != c.size


def test_room_sizes_object_counts_and_classes(rooms):
    config = RoomConfig()
    seen = set()
    for room in rooms.values():
        lx, ly, h = room.size
        assert 4.0 <= lx <= 10.0 and 4.0 <= ly <= 8.0 and 2.6 <= h <= 3.0
        names = [CLASS_NAMES[k] for k in room.labels]
        assert names[:6] == ["floor", "ceiling", "wall", "wall", "wall", "wall"]
        assert 15 <= int(room.furniture.sum()) <= 40
        assert room.num_objects == len(room.labels) == len(room.embeddings) == len(room.colors)
        seen.update(names[6:])
        for mesh in room.meshes:
            assert np.all(mesh.vertices >= -1e-6)
            assert np.all(mesh.vertices <= np.array(room.size) + 1e-6)
        counts = np.array([len(m.vertices) for m in room.meshes])
        lo, hi = config.vertex_range
        assert np.all(counts[6:] >= lo) and np.all(counts[6:] <= hi + 2)  # furniture: exact target
        assert np.all(counts[:6] >= 0.8 * lo) and np.all(counts[:6] <= hi)  # planar grids
        assert np.all((room.colors >= 0) & (room.colors <= 1))
    assert len(seen) >= 15


def test_colour_texture_varies_within_objects(rooms):
    room = rooms[0]
    spread = [
        np.asarray(m.visual.vertex_colors)[:, :3].std(axis=0).mean() / 255 for m in room.meshes
    ]
    assert np.median(spread) > 0.03


def _footprint_cells(placement, step=0.02):
    corners = placement.corners()
    lo, hi = corners.min(0), corners.max(0)
    xs, ys = np.meshgrid(np.arange(lo[0], hi[0], step), np.arange(lo[1], hi[1], step))
    points = np.stack([xs.ravel(), ys.ravel()], -1)
    c, s = np.cos(placement.angle), np.sin(placement.angle)
    local = (points - placement.center) @ np.array([[c, -s], [s, c]])
    inside = np.all(np.abs(local) <= np.array(placement.half_extent), axis=1)
    return {tuple(q) for q in np.round(points[inside] / step).astype(int)}


def test_no_heavy_interpenetration(rooms):
    """Rasterised footprints of objects sharing a height interval overlap by < 0.01 m^2."""
    for room in rooms.values():
        items = [p for p in room.placements if p is not None]
        cells = [_footprint_cells(p) for p in items]
        for i in range(len(items)):
            for j in range(i + 1, len(items)):
                a, b = items[i], items[j]
                low = max(a.elevation, b.elevation)
                high = min(a.elevation + a.height, b.elevation + b.height)
                if high - low > 0.02:
                    assert len(cells[i] & cells[j]) * 0.02**2 < 0.01, (a, b)


def test_embeddings_class_and_instance_structure():
    labels = np.repeat(np.arange(10), 8)
    emb = object_embeddings(labels, np.random.default_rng(0), dim=400, class_similarity=0.5)
    assert emb.shape == (80, 400) and emb.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    cos = emb @ emb.T
    same = (labels[:, None] == labels[None, :]) & ~np.eye(80, dtype=bool)
    different = labels[:, None] != labels[None, :]
    assert abs(cos[same].mean() - 0.5) < 0.03
    assert cos[same].max() < 0.8  # similar, not identical
    assert abs(cos[different].mean()) < 0.03
    assert cos[different].max() < cos[same].mean()


def test_class_vectors_are_shared_between_rooms():
    a = object_embeddings(np.array([3, 3]), np.random.default_rng(1))
    b = object_embeddings(np.array([3, 4]), np.random.default_rng(2))
    assert a[0] @ b[0] > 0.35 and abs(a[0] @ b[1]) < 0.2


def test_scene_changes_follow_the_configured_rate(rooms):
    room = rooms[1]
    num_furniture = int(room.furniture.sum())
    for fraction, move in ((0.1, 0.5), (0.3, 1.0), (0.0, 0.5)):
        changed, changes = change_room(room, np.random.default_rng(3), ChangeConfig(fraction, move))
        touched = np.concatenate([changes.moved, changes.removed])
        assert len(touched) == round(fraction * num_furniture)
        assert len(np.unique(touched)) == len(touched)
        assert np.all(room.furniture[touched])
        assert changed.num_objects == room.num_objects - len(changes.removed)
        assert not set(changes.removed) & set(changed.object_ids.tolist())
        for position, object_id in enumerate(changed.object_ids):
            before = room.meshes[object_id].vertices
            after = changed.meshes[position].vertices
            if object_id in changes.moved:
                assert np.linalg.norm(after.mean(0) - before.mean(0)) > 0.1
                assert abs(after[:, 2].min() - before[:, 2].min()) < 1e-9  # stays on its support
            else:
                np.testing.assert_array_equal(after, before)
    _, all_moved = change_room(room, np.random.default_rng(4), ChangeConfig(0.3, 1.0))
    assert len(all_moved.moved) >= len(all_moved.removed)


def test_trajectory_is_smooth_level_and_in_free_space(episode):
    poses = episode.poses_gt
    assert poses.shape == (8, 4) and poses.dtype == np.float32
    assert np.all((poses[:, 2] >= 1.4) & (poses[:, 2] <= 1.9))
    steps = np.linalg.norm(np.diff(poses[:, :3], axis=0), axis=1)
    assert np.all((steps >= 0.09) & (steps <= 0.31))
    bend = np.linalg.norm(poses[2:, :2] - 2 * poses[1:-1, :2] + poses[:-2, :2], axis=1)
    assert np.all(bend < 0.15)
    dyaw = np.abs(np.asarray(jax.vmap(ego_motion)(poses[:-1], poses[1:]))[:, 3])
    assert np.all(dyaw < np.deg2rad(60)) and dyaw.mean() < np.deg2rad(20)
    size = np.array(episode.room.size)
    assert np.all(poses[:, :2] >= 0.45) and np.all(poses[:, :2] <= size[:2] - 0.45)
    for room in (episode.room, episode.query_room):
        for p in room.placements:
            if p is None or p.mount == "wall":
                continue
            c, s = np.cos(p.angle), np.sin(p.angle)
            local = (poses[:, :2] - p.center) @ np.array([[c, -s], [s, c]])
            outside = np.any(np.abs(local) > np.array(p.half_extent) + 0.3, axis=1)
            assert np.all(outside)
    np.testing.assert_array_equal(episode.sequence.tilt, 0.0)


def test_tilt_is_optional():
    config = EpisodeConfig(
        trajectory=TrajectoryConfig(tilt_sigma=np.deg2rad(3.0)),
        sensor=SensorConfig(width=32, height=18),
    )
    tilt = make_episode(3, 6, config).sequence.tilt
    assert tilt.shape == (6, 2) and 0.2 * np.deg2rad(3) < tilt.std() < 3 * np.deg2rad(3)


def test_episode_is_deterministic_for_a_seed(episode):
    again = make_episode(7, 8, SMALL)
    for name in ("patch_embeddings", "ego_motion", "depth", "rgb", "tilt"):
        np.testing.assert_array_equal(
            getattr(again.sequence, name), getattr(episode.sequence, name)
        )
    np.testing.assert_array_equal(again.poses_gt, episode.poses_gt)
    other = make_episode(8, 2, SMALL)  # another seed, another room and path (2 frames suffice)
    assert not np.allclose(other.poses_gt, episode.poses_gt[:2])


def test_sequence_shapes(episode):
    seq = episode.sequence
    assert seq.patch_embeddings.shape == (8, 9, 16, 400)
    assert seq.ego_motion.shape == (7, 4)
    assert seq.depth.shape == (8, 90, 160) and seq.rgb.shape == (8, 90, 160, 3)
    assert seq.camera.width == 160 and seq.camera.height == 90
    assert episode.patch_objects.shape == episode.confused.shape == (8, 9, 16)
    assert np.all(episode.patch_objects >= 0)  # a closed room: every patch sees an object


def test_patch_embedding_statistics(episode):
    emb = episode.sequence.patch_embeddings
    np.testing.assert_allclose(np.linalg.norm(emb, axis=-1), 1.0, atol=1e-5)
    truth = episode.room.embeddings[episode.patch_objects]
    cosine = np.sum(emb * truth, axis=-1)
    confused = episode.confused
    assert abs(confused.mean() - 0.2) < 0.05  # 1152 patches: std 0.012
    clean = cosine[~confused]
    assert clean.min() >= 0.7 - 1e-4 and clean.max() <= 0.9 + 1e-4
    assert abs(clean.mean() - 0.8) < 0.02
    best = np.argmax(emb @ episode.room.embeddings.T, axis=-1)
    assert np.mean(best[~confused] == episode.patch_objects[~confused]) > 0.99
    assert np.mean(best[confused] == episode.patch_objects[confused]) < 0.05


def test_patch_embedding_rates_follow_the_config():
    dominant = np.random.default_rng(0).integers(-1, 20, size=(4000,))
    table = object_embeddings(np.arange(20) % 7, np.random.default_rng(1))
    emb, confused = frames.patch_embeddings(
        np.random.default_rng(2), dominant, table, confusion_rate=0.35, cosine_range=(0.5, 0.6)
    )
    has_object = dominant >= 0
    assert not np.any(confused[~has_object])
    assert abs(confused[has_object].mean() - 0.35) < 0.03
    cosine = np.sum(emb * table[np.maximum(dominant, 0)], axis=-1)
    ok = has_object & ~confused
    assert cosine[ok].min() >= 0.5 - 1e-5 and cosine[ok].max() <= 0.6 + 1e-5
    assert np.abs(emb[~has_object] @ table.T).max() < 0.3  # empty patches: random directions


def test_depth_and_rgb_noise_match_the_config(episode):
    seq, camera = episode.sequence, episode.sequence.camera
    _, clean_depth, clean_rgb = frames.render_views(
        episode.query_room.meshes,
        episode.query_room.object_ids,
        camera,
        episode.poses_gt,
        episode.sequence.tilt,
    )
    assert np.all(np.isfinite(clean_depth))
    holes = seq.depth == 0
    np.testing.assert_allclose(holes.mean(axis=(1, 2)), 0.1, atol=1e-3)
    relative = seq.depth[~holes] / clean_depth[~holes] - 1
    assert abs(relative.std() - 0.02) < 0.002 and abs(relative.mean()) < 0.002
    assert seq.rgb.min() >= 0 and seq.rgb.max() <= 1
    gain = np.median(seq.rgb / np.maximum(clean_rgb, 1e-3), axis=(1, 2, 3))
    assert np.std(np.log(gain)) > 0.02  # exposure changes from frame to frame


def test_kinect_depth_model_noise_range_and_edges():
    """The "kinect" model: axial noise 0.0012 + 0.0019 (z - 0.4)^2 m, nothing beyond 4.5 m or
    beside a depth edge, blob holes at the configured rate on top."""
    rng = np.random.default_rng(0)
    depth = np.tile(np.linspace(1.0, 6.0, 400, dtype=np.float32), (60, 300, 1))  # (60, 300, 400)
    depth[:, 150:, :] *= np.float32(1.5)  # a depth edge between rows 149 and 150
    depth[:, :5, :5] = np.inf  # sees nothing
    noisy = frames.sensor_depth(rng, depth, 0.02, 0.0, "kinect")
    valid = noisy > 0
    assert not valid[:, 149:151].any()  # both sides of the edge
    assert not valid[:, :5, :5].any()
    assert not valid[depth > 4.5].any()
    inside = (depth <= 4.5) & np.isfinite(depth)
    inside[:, 149:151] = False
    inside[:, :6, :6] = False  # a miss's neighbours are beside an edge too
    assert valid[inside].all()
    for z in (1.5, 3.0, 4.0):
        near = inside & (np.abs(depth - z) < 0.05)
        expected = 0.0012 + 0.0019 * (z - 0.4) ** 2
        np.testing.assert_allclose((noisy - depth)[near].std(), expected, rtol=0.1)
    holes = frames.sensor_depth(np.random.default_rng(1), depth, 0.02, 0.2, "kinect") == 0
    assert 0.2 <= holes.mean(axis=(1, 2)).min() and holes.mean() < 0.2 + (~inside).mean()
    with pytest.raises(ValueError, match="depth_model"):
        SensorConfig(depth_model="tof")


def test_ego_motion_noise_matches_the_config():
    poses = np.cumsum(np.random.default_rng(0).normal(0, 0.1, (2001, 4)), axis=0).astype(np.float32)
    noisy = frames.noisy_ego_motion(np.random.default_rng(1), poses, 0.02, np.deg2rad(1.0))
    true = np.asarray(jax.vmap(ego_motion)(poses[:-1], poses[1:]))
    error = noisy - true
    error[:, 3] = (error[:, 3] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(error[:, :3].std(axis=0), 0.02, rtol=0.08)
    np.testing.assert_allclose(error[:, 3].std(), np.deg2rad(1.0), rtol=0.08)


def test_frame_renderer_agrees_with_the_bvh_raycaster(episode):
    """Object ids and z-depth of the frame renderer (jaxloc.render) equal jaxloc.raycast's."""
    room, scene = episode.room, episode.scene
    assert scene.num_objects == room.num_objects
    np.testing.assert_array_equal(np.asarray(scene.labels)[: room.num_objects], room.labels)
    camera = SensorConfig(width=32, height=18).camera()
    pose = episode.poses_gt[:1]
    tilt = np.array([[0.1, -0.05]], np.float32)
    object_id, depth, _ = frames.render_views(room.meshes, room.object_ids, camera, pose, tilt)

    rotation = rotation_world_cam(jnp.asarray(pose[0, 3]), jnp.asarray(tilt[0]))
    rays = camera.directions(stride_grid(camera, 1).uv) @ rotation.T
    hit = jax.jit(raycast)(scene, jnp.broadcast_to(jnp.asarray(pose[0, :3]), rays.shape), rays)
    z = np.asarray(hit.t) * np.asarray(rays @ rotation[:, 2])
    agree = np.asarray(hit.object_id) == object_id.ravel()
    assert agree.mean() > 0.97
    np.testing.assert_allclose(z[agree], depth.ravel()[agree], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize(
    "make",
    [
        lambda: RoomConfig(length_range=(6.0, 4.0)),
        lambda: RoomConfig(class_similarity=1.5),
        lambda: ChangeConfig(fraction=-0.1),
        lambda: TrajectoryConfig(step_range=(0.3, 0.1)),
        lambda: SensorConfig(width=8, height=4),
        lambda: SensorConfig(confusion_rate=2.0),
        lambda: SensorConfig(cosine_range=(0.9, 1.2)),
    ],
)
def test_bad_configs_raise(make):
    with pytest.raises(ValueError):
        make()


def test_bad_frame_count_raises():
    with pytest.raises(ValueError, match="num_frames"):
        make_episode(0, 0, SMALL)
