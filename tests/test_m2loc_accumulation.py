"""Localizing a drive: the fused submap of a window of scans (jaxloc.m2loc.fuse_scans) against a
numpy fusion by ground-truth object, a window grown on sparse stretches (grow_window) against
fusing every prefix, and localize_window on synthetic drives of small scans (a window's pose on
the minimal set refused)."""

from __future__ import annotations

import numpy as np
import pytest
from _compilations import COMPILED

from jaxloc.m2loc import (
    LocalizationResult,
    build_map,
    fuse_scans,
    localization_errors,
    localize_scan,
    localize_window,
    m2loc_config,
)
from jaxloc.m2loc._accumulation import WINDOW_MIN_CLIQUE, grow_window, require_clique
from jaxloc.synthetic.outdoor import make_drive, make_outdoor_world


def _relative(scans):
    """(K, 4, 4) T_newest_scan of a drive given oldest first, in fuse_scans' newest-first order."""
    newest = np.linalg.inv(scans[-1].T_map_scan)
    return np.stack([newest @ s.T_map_scan for s in scans[::-1]])


def _yaw_pose(rng, shift=20.0):
    yaw = rng.uniform(-np.pi, np.pi)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = rng.uniform(-shift, shift, 3)
    return T


def test_fused_submap_matches_a_numpy_fusion_by_object():
    """Objects >= 6 m apart seen by random subsets of 4 scans with 0.2 m noise: one fused
    instance per object, at the mean of its observations, counted once per scan that saw it."""
    rng = np.random.default_rng(0)
    grid = np.stack(np.meshgrid(np.arange(6), np.arange(5)), -1).reshape(-1, 2) * 6.0
    objects = np.column_stack([grid + rng.uniform(-1, 1, grid.shape), rng.uniform(0, 4, 30)])
    classes = rng.choice([15, 17, 18], 30)
    poses = [np.eye(4)] + [_yaw_pose(rng) for _ in range(3)]  # T_newest_scan, newest first
    points, labels, seen_by = [], [], []
    for pose in poses:
        seen = np.flatnonzero(rng.random(30) < 0.6)
        seen = rng.permutation(seen)
        noisy = objects[seen] + rng.normal(0, 0.2, (seen.size, 3))
        points.append((noisy - pose[:3, 3]) @ pose[:3, :3])  # in the scan's own frame
        labels.append(classes[seen])
        seen_by.append(seen)
    fused = fuse_scans(points, labels, np.stack(poses), merge_radius=1.5)

    # Reference: group the observations by the object they came from (ground truth ids).
    sums, counts = np.zeros((30, 3)), np.zeros(30, int)
    for pose, seen, p in zip(poses, seen_by, points, strict=True):
        np.add.at(sums, seen, p @ pose[:3, :3].T + pose[:3, 3])
        np.add.at(counts, seen, 1)
    present = np.flatnonzero(counts)
    reference = sums[present] / counts[present, None]
    assert len(fused.points) == present.size
    nearest = np.argmin(np.linalg.norm(fused.points[:, None] - reference[None], axis=-1), axis=1)
    np.testing.assert_array_equal(np.sort(nearest), np.arange(present.size))
    np.testing.assert_allclose(fused.points, reference[nearest], atol=1e-9)
    np.testing.assert_array_equal(fused.labels, classes[present][nearest])
    np.testing.assert_array_equal(fused.counts, counts[present][nearest])
    assert fused.members.shape == (present.size, 4)


def test_one_scan_fuses_to_itself_and_two_instances_of_one_scan_stay_two():
    rng = np.random.default_rng(1)
    points = rng.uniform(-30, 30, (12, 3))
    labels = rng.choice([15, 17], 12)
    fused = fuse_scans([points], [labels], np.eye(4)[None])
    np.testing.assert_array_equal(fused.points, points)
    np.testing.assert_array_equal(fused.labels, labels)
    # Two poles 0.5 m apart in one scan, both seen again by the next scan: still two objects.
    pair = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0]])
    fused = fuse_scans([pair, pair + 0.05], [np.array([17, 17])] * 2, np.stack([np.eye(4)] * 2))
    assert len(fused.points) == 2 and np.all(fused.counts == 2)


def test_bad_windows_raise_clear_errors():
    p, c = np.zeros((3, 3)), np.array([15, 15, 17])
    with pytest.raises(ValueError, match="one labels array and one pose per scan"):
        fuse_scans([p, p], [c], np.stack([np.eye(4)] * 2))
    with pytest.raises(ValueError, match="finite"):
        fuse_scans([np.full((3, 3), np.nan)], [c], np.eye(4)[None])
    with pytest.raises(ValueError, match="rigid"):
        fuse_scans([p], [c], 2 * np.eye(4)[None])
    with pytest.raises(ValueError, match="integers"):
        fuse_scans([p], [c.astype(float)], np.eye(4)[None])


@pytest.fixture(scope="module")
def world_and_map():
    # The configuration of tests/test_m2loc_pipeline.py: one shared compiled query (capacity 64).
    world = make_outdoor_world("dense", seed=3, blocks=2, bridge_length=150.0)
    config = m2loc_config(num_scales=2, scale_edges=(20.0, 30.0), query_capacity=64)
    return world, build_map(world.points, world.labels, config)


def test_window_of_small_scans_localizes_the_newest_one_without_retrace(world_and_map):
    """Drives of 13-vertex scans: the fused window of 3 localizes the newest scan (RTE < 7.5 m,
    RRE < 10 deg, most inliers right), and windows of any length run one compiled program."""
    world, triplet_map = world_and_map
    rng = np.random.default_rng(11)
    drives = [
        make_drive(world.points, world.labels, world.road_normals, rng, 3, max_kept=13)
        for _ in range(4)
    ]
    first = drives[0]
    localize_scan(triplet_map, None, first[-1].points, first[-1].labels)  # compile, if needed
    before = len(COMPILED)
    good = 0
    for scans in drives:
        result, fused = localize_window(
            triplet_map, [s.points for s in scans[::-1]], [s.labels for s in scans[::-1]],
            _relative(scans),
        )  # fmt: skip
        assert len(fused.points) < sum(len(s.points) for s in scans)  # duplicates merged
        rte, rre = localization_errors(result.pose, scans[-1].T_map_scan)
        good += result.valid and rte < 7.5 and rre < 10
        assert not result.valid or (rte < 7.5 and rre < 10)
    assert good >= 3
    two = drives[1][1:]
    localize_window(
        triplet_map, [s.points for s in two[::-1]], [s.labels for s in two[::-1]], _relative(two)
    )
    assert COMPILED[before:] == []


def test_a_window_pose_on_too_small_a_clique_is_refused(world_and_map):
    """require_clique refuses a valid pose below the smallest clique (identity pose, the rest
    kept) and leaves others alone; localize_window applies it to windows of two scans or more
    (WINDOW_MIN_CLIQUE by default), never to a window of one scan."""
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    on_three = LocalizationResult(
        pose, True, 3, np.zeros((3, 2), np.int64), 1, True, 9, 0.8, 1.0, 2.0
    )  # fmt: skip
    refused = require_clique(on_three, 4)
    assert not refused.valid and np.array_equal(refused.pose, np.eye(4))
    assert refused._replace(valid=True, pose=pose) == on_three
    assert require_clique(on_three, 3) is on_three
    invalid = on_three._replace(valid=False)
    assert require_clique(invalid, 4) is invalid
    assert WINDOW_MIN_CLIQUE == 4

    world, triplet_map = world_and_map
    scans = make_drive(world.points, world.labels, world.road_normals, np.random.default_rng(5), 2)
    window = ([s.points for s in scans[::-1]], [s.labels for s in scans[::-1]], _relative(scans))
    fused = fuse_scans(*window)
    alone = localize_scan(triplet_map, None, fused.points, fused.labels)
    assert alone.valid and alone.clique_size >= WINDOW_MIN_CLIQUE
    kept, _ = localize_window(triplet_map, *window)
    assert kept.valid and np.array_equal(kept.pose, alone.pose)
    beyond = alone.clique_size + 1
    assert not localize_window(triplet_map, *window, min_clique=beyond)[0].valid
    newest = ([window[0][0]], [window[1][0]], np.eye(4)[None])  # one scan: the map's min_inliers
    single = localize_scan(triplet_map, None, window[0][0], window[1][0])
    assert localize_window(triplet_map, *newest, min_clique=10**6)[0].valid == single.valid


def _random_window(rng, num_scans=6, per_scan=(2, 9)):
    """Scans of a 30-object street, each seeing a few of them, in fuse_scans' order."""
    grid = np.stack(np.meshgrid(np.arange(6), np.arange(5)), -1).reshape(-1, 2) * 6.0
    objects = np.column_stack([grid, rng.uniform(0, 4, 30)])
    classes = rng.choice([15, 17, 18], 30)
    poses = [np.eye(4)] + [_yaw_pose(rng) for _ in range(num_scans - 1)]
    points, labels = [], []
    for pose in poses:
        seen = rng.choice(30, rng.integers(*per_scan), replace=False)
        noisy = objects[seen] + rng.normal(0, 0.1, (seen.size, 3))
        points.append((noisy - pose[:3, 3]) @ pose[:3, :3])
        labels.append(classes[seen])
    return points, labels, np.stack(poses)


def test_a_window_grows_with_older_scans_until_it_holds_enough_instances():
    """grow_window against fusing every prefix of the scans given: the shortest prefix of at least
    least_scans scans holding min_instances fused instances, else all; the same fusion."""
    rng = np.random.default_rng(7)
    for trial in range(12):
        points, labels, poses = _random_window(rng)
        held = [len(fuse_scans(points[:k], labels[:k], poses[:k]).points) for k in range(1, 7)]
        least, instances = 1 + trial % 4, int(rng.integers(0, 30))
        expected = next((k for k in range(least, 7) if held[k - 1] >= instances), 6)
        grown = grow_window(points, labels, poses, least, instances)
        assert grown.members.shape[1] == expected, (held, least, instances)
        reference = fuse_scans(points[:expected], labels[:expected], poses[:expected])
        for got, want in zip(grown, reference, strict=True):
            np.testing.assert_array_equal(got, want)
    # fewer scans than least_scans (the start of a drive): all of them; bad sizes raise
    assert grow_window(points[:2], labels[:2], poses[:2], 3, 0).members.shape[1] == 2
    with pytest.raises(ValueError, match="least_scans >= 1 and min_instances >= 0"):
        grow_window(points, labels, poses, 0, 5)
    with pytest.raises(ValueError, match="least_scans >= 1 and min_instances >= 0"):
        grow_window(points, labels, poses, 2, -1)


def test_localize_window_grows_a_sparse_window(world_and_map):
    """least_scans: localize_window fuses what grow_window would and localizes that (the clique
    rule applied to the grown window) in the program every window runs; without it every scan
    given is fused."""
    world, triplet_map = world_and_map
    scans = make_drive(
        world.points, world.labels, world.road_normals, np.random.default_rng(2), 5, max_kept=5
    )
    window = ([s.points for s in scans[::-1]], [s.labels for s in scans[::-1]], _relative(scans))
    grown = grow_window(*window, 2, 14)
    assert 2 < grown.members.shape[1] < 5  # a sparse stretch: more than 2 scans, fewer than all
    localize_scan(triplet_map, None, window[0][0], window[1][0])  # compile, if needed
    before = len(COMPILED)
    result, fused = localize_window(triplet_map, *window, least_scans=2, min_instances=14)
    assert COMPILED[before:] == []
    np.testing.assert_array_equal(fused.points, grown.points)
    expected = require_clique(
        localize_scan(triplet_map, None, grown.points, grown.labels), WINDOW_MIN_CLIQUE
    )
    assert result.valid == expected.valid and np.array_equal(result.pose, expected.pose)
    assert localize_window(triplet_map, *window)[1].members.shape[1] == 5
