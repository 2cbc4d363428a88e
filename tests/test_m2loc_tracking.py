"""Tracking a drive (jaxloc.m2loc.Tracker): the association kernel against a numpy brute force,
tracked poses against global localization of the same scans, a kidnapped robot detected and
recovered, lax.scan against the Python loop, one trace for a whole drive, failures as values."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _compilations import COMPILED

from jaxloc.lsq import RobustLoss
from jaxloc.m2loc import (
    TrackConfig,
    Tracker,
    build_map,
    localization_errors,
    localize_scan,
    m2loc_config,
    pad_scan,
)
from jaxloc.m2loc._hypotheses import map_grid
from jaxloc.m2loc._tracking import (
    LOST,
    PENDING,
    RELOCALIZED,
    TRACKED,
    grid_nearest_same_class,
    track_step,
)
from jaxloc.synthetic.outdoor import make_drive, make_outdoor_world

CAPACITY = 32


@pytest.fixture(scope="module")
def world_and_map():
    # Scans of up to 24 instances; one scale and no hypotheses keep the global fallback's
    # program small (the step compiles it once per capacity).
    world = make_outdoor_world("dense", seed=3, blocks=2, bridge_length=150.0)
    config = m2loc_config(num_scales=1, query_capacity=CAPACITY, hypotheses=0)
    return world, build_map(world.points, world.labels, config, world.road_normals)


def _drive(world, seed, num_scans, max_kept=20):
    rng = np.random.default_rng(seed)
    return make_drive(
        world.points, world.labels, world.road_normals, rng, num_scans, max_kept=max_kept
    )


def _odometry(scans, first=None):
    """(S, 4, 4) float32 T_prev_scan of each scan from the ground truth (``first`` for [0])."""
    poses = [np.eye(4) if first is None else first]
    poses += [np.linalg.inv(a.T_map_scan) @ b.T_map_scan for a, b in itertools.pairwise(scans)]
    return np.stack(poses).astype(np.float32)


def _run_loop(tracker, scans, odometry):
    state, results = tracker.init(), []
    for scan, odo in zip(scans, odometry, strict=True):
        padded = pad_scan(scan.points, scan.labels, tracker.triplet_map.config, CAPACITY)
        state, result = track_step(tracker, state, padded, jnp.asarray(odo))
        results.append(jax.tree.map(np.asarray, result))
    return state, results


def test_grid_association_matches_a_numpy_brute_force():
    rng = np.random.default_rng(0)
    map_points = rng.uniform([-20, -20, 0], [20, 20, 2], (300, 3)).astype(np.float32)
    map_classes = rng.integers(0, 3, 300).astype(np.int32)
    moved = rng.uniform([-22, -22, 0], [22, 22, 2], (40, 3)).astype(np.float32)
    classes = rng.integers(0, 3, 40).astype(np.int32)
    mask = np.arange(40) < 35
    grid = map_grid(jnp.asarray(map_points), jnp.asarray(map_classes), 1.5)
    for radius in (1.5, 3.0):  # one ring of cells, two rings
        targets, found = jax.jit(grid_nearest_same_class, static_argnums=4)(
            moved, classes, mask, grid, radius
        )
        gap = np.linalg.norm(moved[:, None].astype(np.float64) - map_points[None], axis=-1)
        gap[classes[:, None] != map_classes[None]] = np.inf
        expected = mask & (gap.min(axis=1) <= radius)
        np.testing.assert_array_equal(np.asarray(found), expected)
        nearest = map_points[np.argmin(gap, axis=1)]
        np.testing.assert_array_equal(np.asarray(targets)[expected], nearest[expected])
        assert 3 < int(np.sum(found)) < 35  # both outcomes occur


def test_tracking_matches_global_localization_with_one_trace(world_and_map):
    """An easy drive: the first scan's global pose waits for the second's to confirm it, every
    next scan is tracked in a few association rounds, as accurate as global localization of the
    same scan; one trace."""
    world, triplet_map = world_and_map
    scans = _drive(world, 21, 8)
    tracker = Tracker(triplet_map)
    before = len(COMPILED)
    _, results = _run_loop(tracker, scans, _odometry(scans))
    steps = [name for name in COMPILED[before:] if "track_step" in name]
    assert len(steps) <= 1  # 0 when another test compiled it first
    assert [int(r.mode) for r in results] == [PENDING, RELOCALIZED] + [TRACKED] * 6
    assert not results[0].valid and np.all(results[0].T_map_scan == np.eye(4))
    tracked, found = [], []
    for scan, result in zip(scans[1:], results[1:], strict=True):
        errors = localization_errors(result.T_map_scan.astype(np.float64), scan.T_map_scan)
        assert errors[0] < 1.0 and errors[1] < 2.0
        alone = localize_scan(triplet_map, None, scan.points, scan.labels)
        if alone.valid:  # compared where global localization found the scan
            tracked.append(errors)
            found.append(localization_errors(alone.pose, scan.T_map_scan))
    tracked, found = np.array(tracked), np.array(found)
    assert len(found) >= 4
    assert np.median(tracked[:, 0]) <= np.median(found[:, 0]) + 0.1
    assert np.median(tracked[:, 1]) <= np.median(found[:, 1]) + 0.2


def test_kidnapped_robot_is_detected_and_recovered_and_scan_equals_the_loop(world_and_map):
    """Five scans of one drive, then the robot is carried to another drive while the odometry
    claims it kept driving: the jump is never tracked (no wrong pose); global localization
    finds the new place, the next scan confirms it, and tracking resumes. ``lax.scan`` over the
    stacked drive gives the loop's results."""
    world, triplet_map = world_and_map
    before, after = _drive(world, 22, 5), _drive(world, 23, 5)
    far = np.linalg.norm(before[-1].T_map_scan[:3, 3] - after[0].T_map_scan[:3, 3])
    assert far > 50.0
    scans = before + after
    odometry = np.concatenate([_odometry(before), _odometry(after, _odometry(before)[-1])])
    tracker = Tracker(triplet_map)
    _, results = _run_loop(tracker, scans, odometry)
    modes = [int(r.mode) for r in results]
    first_fix = modes.index(RELOCALIZED)  # the first global pose waits for a second one
    assert modes[0] == PENDING and first_fix <= 2
    assert modes[first_fix + 1 : 5] == [TRACKED] * (4 - first_fix)
    assert modes[5] in (PENDING, LOST)  # the jump is never tracked nor reported unconfirmed
    recovered = next(i for i in range(5, 10) if modes[i] == RELOCALIZED)
    assert recovered <= 7 and modes[recovered + 1 :] == [TRACKED] * (9 - recovered)
    for scan, result in zip(scans, results, strict=True):
        if result.valid:
            rte, rre = localization_errors(result.T_map_scan.astype(np.float64), scan.T_map_scan)
            assert rte < 1.5 and rre < 3.0
        else:
            np.testing.assert_array_equal(result.T_map_scan, np.eye(4))

    padded = [pad_scan(s.points, s.labels, triplet_map.config, CAPACITY) for s in scans]
    stacked = jax.tree.map(lambda *a: jnp.asarray(np.stack(a)), *padded)

    @jax.jit
    def run(tracker, scans, odometry):
        return jax.lax.scan(lambda s, x: tracker.step(s, *x), tracker.init(), (scans, odometry))

    _, scanned = run(tracker, stacked, jnp.asarray(odometry))
    np.testing.assert_array_equal(np.asarray(scanned.mode), modes)
    np.testing.assert_allclose(
        np.asarray(scanned.T_map_scan), np.stack([r.T_map_scan for r in results]), atol=1e-3
    )


def test_without_confirmation_a_lone_global_pose_is_reported_at_once(world_and_map):
    """``TrackConfig(confirm=False)``: the first scan's verified global pose is reported as it is
    found (RELOCALIZED, valid, where the default waits one scan), and tracking follows."""
    world, triplet_map = world_and_map
    scans = _drive(world, 21, 3)
    _, results = _run_loop(
        Tracker(triplet_map, TrackConfig(confirm=False)), scans, _odometry(scans)
    )
    assert [int(r.mode) for r in results] == [RELOCALIZED, TRACKED, TRACKED]
    for scan, result in zip(scans, results, strict=True):
        assert result.valid
        rte, rre = localization_errors(result.T_map_scan.astype(np.float64), scan.T_map_scan)
        assert rte < 1.0 and rre < 2.0


def test_bad_odometry_and_empty_scans_are_values_not_nans(world_and_map):
    world, triplet_map = world_and_map
    scans = _drive(world, 21, 3)
    tracker = Tracker(triplet_map)
    state, results = _run_loop(tracker, scans[:2], _odometry(scans[:2]))
    assert [int(r.mode) for r in results] == [PENDING, RELOCALIZED]
    padded = pad_scan(scans[2].points, scans[2].labels, triplet_map.config, CAPACITY)
    before = len(COMPILED)
    nan_odometry = jnp.full((4, 4), jnp.nan)  # weakly typed: must not compile the step again
    lost_state, result = track_step(tracker, state, padded, nan_odometry)
    assert int(result.mode) != TRACKED  # no prediction: the global query decides
    assert np.all(np.isfinite(np.asarray(lost_state.T_map_scan)))
    empty = pad_scan(np.zeros((0, 3)), np.zeros(0, int), triplet_map.config, CAPACITY)
    coast, result = track_step(tracker, state, empty, np.eye(4))  # float64 numpy
    assert [name for name in COMPILED[before:] if "track_step" in name] == []
    assert int(result.mode) == LOST and not bool(result.valid)
    np.testing.assert_array_equal(np.asarray(result.T_map_scan), np.eye(4))
    assert int(coast.since_fix) == 1 and np.all(np.isfinite(np.asarray(coast.T_map_scan)))


def test_bad_configuration_and_scans_raise_clear_errors(world_and_map):
    _, triplet_map = world_and_map
    with pytest.raises(ValueError, match="association_radius"):
        TrackConfig(association_radius=0.0)
    with pytest.raises(ValueError, match="max_coast"):
        TrackConfig(max_coast=-1)
    with pytest.raises(ValueError, match="confirm_angle_deg"):
        TrackConfig(confirm_angle_deg=0.0)
    many = np.random.default_rng(0).uniform(-30, 30, (CAPACITY + 1, 3))
    with pytest.raises(ValueError, match="above the capacity"):
        pad_scan(many, np.full(CAPACITY + 1, 15), triplet_map.config, CAPACITY)
    with pytest.raises(ValueError, match="not in the classes"):
        pad_scan(many[:3], np.array([15, 16, 17]), triplet_map.config, CAPACITY)


def test_tracking_settings_are_traced(world_and_map):
    """The confirmation angle, the coasting length and the loss scale change a drive's modes and
    poses on the step compiled for the default settings."""
    world, triplet_map = world_and_map
    scans = _drive(world, 21, 4)
    odometry = _odometry(scans)
    _, default = _run_loop(Tracker(triplet_map), scans, odometry)
    before = len(COMPILED)
    _, strict = _run_loop(
        Tracker(triplet_map, TrackConfig(confirm_angle_deg=1e-4, max_coast=0)), scans, odometry
    )
    _, tight = _run_loop(
        Tracker(triplet_map, TrackConfig(loss=RobustLoss("cauchy", 0.05))), scans, odometry
    )
    assert [name for name in COMPILED[before:] if "track_step" in name] == []
    assert [int(r.mode) for r in default] == [PENDING, RELOCALIZED, TRACKED, TRACKED]
    assert [int(r.mode) for r in strict] != [int(r.mode) for r in default]
    assert not np.allclose(tight[-1].T_map_scan, default[-1].T_map_scan, atol=1e-4)
