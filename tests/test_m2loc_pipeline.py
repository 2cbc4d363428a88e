"""localize_scan end to end on a synthetic world; registration; no retrace; bad inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _compilations import COMPILED

from jaxloc.lsq import RobustLoss
from jaxloc.m2loc import (
    TripletConfig,
    build_map,
    localization_errors,
    localize_scan,
    m2loc_config,
    register,
)
from jaxloc.m2loc._query import verified_fraction
from jaxloc.m2loc._registration import weighted_kabsch
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query


@pytest.fixture(scope="module")
def world():
    return make_outdoor_world("dense", seed=3, blocks=2, bridge_length=150.0)


@pytest.fixture(scope="module")
def triplet_map(world):
    # No road normals: the map then has the plain-arrays API's shapes, so every test here shares
    # one compiled query pipeline (the RSN prior is exercised by tests/test_cli.py and the
    # sharding check).
    config = m2loc_config(num_scales=2, scale_edges=(20.0, 30.0), query_capacity=64)
    return build_map(world.points, world.labels, config)


def random_transform(rng):
    yaw = rng.uniform(-np.pi, np.pi)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = rng.uniform(-100, 100, 3)
    return T


def test_weighted_kabsch_matches_numpy_svd():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(12, 3))
    T = random_transform(rng)
    dst = src @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 0.01, (12, 3))
    weights = rng.uniform(0.5, 2, 12)
    weights[:2] = 0.0
    est, ok = weighted_kabsch(jnp.asarray(src), jnp.asarray(dst), jnp.asarray(weights))
    w = weights / weights.sum()
    ms, md = w @ src, w @ dst
    u, _, vt = np.linalg.svd(((dst - md) * w[:, None]).T @ (src - ms))
    rot = u @ np.diag([1, 1, np.linalg.det(u @ vt)]) @ vt
    assert bool(ok)
    np.testing.assert_allclose(np.asarray(est.rotation().as_matrix()), rot, atol=1e-6)
    np.testing.assert_allclose(np.asarray(est.translation()), md - rot @ ms, atol=1e-6)
    _, ok = weighted_kabsch(jnp.asarray(src), jnp.asarray(dst), jnp.asarray(np.eye(12)[0] * 1.0))
    assert not bool(ok)


#: One compiled registration for both calls below (eager dispatch compiles every inner op apart).
REGISTER = jax.jit(register)


def test_register_exact_and_robust_to_half_outliers():
    rng = np.random.default_rng(1)
    src = rng.uniform(-30, 30, (40, 3)).astype(np.float32)
    T = random_transform(rng)
    dst = (src @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    mask = np.ones(40, bool)
    sol, _ = REGISTER(src, dst, mask, loss=RobustLoss("gnc_tls", 1.0))
    rte, rre = localization_errors(np.asarray(sol.pose.as_matrix()), T)
    assert bool(sol.ok) and rte < 1e-3 and rre < 1e-3
    dst_bad = dst.copy()
    dst_bad[::2] += rng.normal(0, 15, (20, 3)).astype(np.float32)
    sol, _ = REGISTER(src, dst_bad, mask, loss=RobustLoss("gnc_tls", 1.0))
    rte, rre = localization_errors(np.asarray(sol.pose.as_matrix()), T)
    # Kabsch on 50 % outliers starts far off; GNC-TLS must still find the inlier pose
    assert bool(sol.ok) and rte < 1e-2 and rre < 1e-2


def test_localizes_synthetic_queries_without_retrace(world, triplet_map):
    rng = np.random.default_rng(5)
    queries = [
        make_query(world.points, world.labels, world.road_normals, rng, max_kept=30)
        for _ in range(4)
    ]
    localize_scan(triplet_map, None, queries[0].points, queries[0].labels)  # compile
    before = len(COMPILED)
    successes = 0
    for q in queries:
        result = localize_scan(triplet_map, None, q.points, q.labels)
        rte, rre = localization_errors(result.pose, q.T_map_scan)
        successes += result.valid and rte < 7.5 and rre < 10
        assert result.clique_size == len(result.inliers)
        if result.valid:
            correct = q.map_index[result.inliers[:, 0]] == result.inliers[:, 1]
            assert correct.mean() > 0.5
    assert COMPILED[before:] == []
    assert successes >= 3


def test_noise_free_query_is_exact(world, triplet_map):
    rng = np.random.default_rng(6)
    q = make_query(
        world.points,
        world.labels,
        world.road_normals,
        rng,
        drop_range=(0.0, 0.0),
        jitter_range=(0.0, 0.0),
        spurious_range=(0.0, 0.0),
        max_kept=40,
    )
    result = localize_scan(triplet_map, None, q.points, q.labels)
    rte, rre = localization_errors(result.pose, q.T_map_scan)
    assert result.valid and rte < 0.05 and rre < 0.2


def test_deterministic(world, triplet_map):
    q = make_query(
        world.points, world.labels, world.road_normals, np.random.default_rng(7), max_kept=30
    )
    a = localize_scan(triplet_map, None, q.points, q.labels)
    b = localize_scan(triplet_map, None, q.points, q.labels)
    np.testing.assert_array_equal(a.pose, b.pose)
    np.testing.assert_array_equal(a.inliers, b.inliers)


def test_bad_inputs(world, triplet_map):
    pts = np.array([[0.0, 0, 0], [5, 0, 0], [0, 7, 1], [3, 3, 3]])
    labels = np.array([15, 17, 18, 17])
    empty = localize_scan(triplet_map, None, np.zeros((0, 3)), np.zeros(0, int))
    assert not empty.valid and empty.clique_size == 0
    assert not localize_scan(triplet_map, None, pts[:2], labels[:2]).valid
    with pytest.raises(ValueError, match="not in the classes"):
        localize_scan(triplet_map, None, pts, np.array([15, 17, 99, 17]))
    with pytest.raises(ValueError, match="NaN"):
        localize_scan(triplet_map, None, np.where(np.eye(4, 3) > 0, np.nan, pts), labels)
    with pytest.raises(ValueError, match="duplicate"):
        localize_scan(triplet_map, None, np.vstack([pts, pts[:1]]), np.append(labels, 15))
    with pytest.raises(ValueError, match="shape"):
        localize_scan(triplet_map, None, pts[:, :2], labels)
    with pytest.raises(ValueError, match="map_labels=None"):
        localize_scan(triplet_map, labels, pts, labels)
    with pytest.raises(ValueError, match="query_capacity"):
        localize_scan(
            triplet_map, None, np.random.default_rng(0).normal(size=(65, 3)) * 50, np.full(65, 17)
        )
    with pytest.raises(ValueError, match="at least 3"):
        build_map(pts[:2], labels[:2])


def test_plain_arrays_api(world, triplet_map):
    # the contract: localize_scan(map_points, map_labels, scan_points, scan_labels, config=None);
    # same config and map shapes as the fixture, so the jitted query functions are reused
    q = make_query(
        world.points, world.labels, world.road_normals, np.random.default_rng(8), max_kept=25
    )
    result = localize_scan(world.points, world.labels, q.points, q.labels, triplet_map.config)
    rte, rre = localization_errors(result.pose, q.T_map_scan)
    assert result.valid and rte < 7.5 and rre < 10
    assert result.pose.shape == (4, 4) and result.descriptor_time_ms > 0


def test_verified_fraction_matches_numpy():
    rng = np.random.default_rng(9)
    map_points = rng.uniform(-20, 20, (30, 3)).astype(np.float32)
    map_classes = rng.integers(0, 3, 30).astype(np.int32)
    T = random_transform(rng).astype(np.float32)
    T[:3, 3] = rng.uniform(-2, 2, 3)
    scan = (map_points[:12] - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 1.0, (12, 3))
    classes = map_classes[:12].copy()
    classes[:3] = (classes[:3] + 1) % 3  # wrong class: never verified by a same-class vertex
    mask = np.arange(12) < 10
    got = verified_fraction(T, scan, classes, mask, map_points, map_classes, 1.5)
    moved = scan @ T[:3, :3].T + T[:3, 3]
    distance = np.linalg.norm(moved[:, None] - map_points[None], axis=-1)
    distance[classes[:, None] != map_classes[None, :]] = np.inf
    verified = distance.min(axis=1)[mask] <= 1.5
    np.testing.assert_allclose(float(got), np.mean(verified), atol=1e-6)
    # the minimal-set discount: (verified - 3) / (real - 3), clipped at 0
    close = (map_points[:12] - T[:3, 3]) @ T[:3, :3] + rng.normal(0, 0.3, (12, 3))
    got = verified_fraction(T, close, classes, mask, map_points, map_classes, 1.5, discount=3)
    moved = close @ T[:3, :3].T + T[:3, 3]
    distance = np.linalg.norm(moved[:, None] - map_points[None], axis=-1)
    distance[classes[:, None] != map_classes[None, :]] = np.inf
    verified = distance.min(axis=1)[mask] <= 1.5
    expected = max(verified.sum() - 3, 0) / (mask.sum() - 3)
    np.testing.assert_allclose(float(got), expected, atol=1e-6)
    assert 0 < expected < np.mean(verified)
    few = np.arange(12) < 3  # no more real vertices than the discount: nothing beyond it
    assert float(verified_fraction(T, scan, classes, few, map_points, map_classes, 1.5, 3)) == 0


def test_scan_from_another_place_is_rejected(world, triplet_map):
    # a query cut from a different world: the clique is chance agreement, and under its pose
    # few scan vertices land on map vertices of their class (TripletConfig.min_inlier_fraction)
    foreign = make_outdoor_world("dense", seed=11, blocks=1, bridge_length=0.0)
    rng = np.random.default_rng(10)
    threshold = TripletConfig().min_inlier_fraction
    assert 0 < threshold < 1
    for _ in range(2):
        q = make_query(foreign.points, foreign.labels, foreign.road_normals, rng, max_kept=40)
        result = localize_scan(triplet_map, None, q.points, q.labels)
        assert result.inlier_fraction < threshold
    q = make_query(world.points, world.labels, world.road_normals, rng, max_kept=40)
    result = localize_scan(triplet_map, None, q.points, q.labels)
    rte, rre = localization_errors(result.pose, q.T_map_scan)
    assert result.valid and rte < 7.5 and rre < 10 and result.inlier_fraction >= threshold
    with pytest.raises(ValueError, match="min_inlier_fraction"):
        TripletConfig(min_inlier_fraction=1.5)


def test_the_query_program_holds_one_robust_solve(world, triplet_map, monkeypatch):
    """The robust pose solve is the largest part of the query's program; the attempts, the
    hypothesis search and their retries share one call site (a second one cost ~1-2 s of
    compilation per program; benchmarks/results/startup_cpu.md). Counted in the traced program of
    the robust configuration with retries, where every path that solves a pose is present."""
    import jaxloc.m2loc._query as query_module
    from jaxloc.m2loc._query import describe_query, register_query

    config = m2loc_config(2, scale_edges=(20.0, 30.0), query_capacity=64, registration_attempts=3)
    described = build_map(world.points, world.labels, config)
    calls = []
    solve = query_module.register

    def counted(*args, **kwargs):
        calls.append(1)
        return solve(*args, **kwargs)

    monkeypatch.setattr(query_module, "register", counted)
    rng = np.random.default_rng(8)
    q = make_query(world.points, world.labels, world.road_normals, rng, max_kept=30)
    points = np.zeros((64, 3), np.float32)
    points[: len(q.points)] = q.points
    classes = np.zeros(64, np.int32)
    classes[: len(q.points)] = [config.descriptor.classes.index(int(c)) for c in q.labels]
    mask = np.arange(64) < len(q.points)
    descriptors, valid = describe_query(points, classes, mask, config.descriptor)
    jax.eval_shape(register_query, described, points, classes, descriptors, valid, mask)
    assert len(calls) == 1
