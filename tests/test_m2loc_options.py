"""M2Loc options for small, noisy scans: the one-to-one consistency graph (against a numpy
reference), cliques that are matchings, registration retries and verified clique hypotheses (never
a worse verification, a rejected pose replaced by the right one, one compilation, the map's grid,
the closed-form pose kept against a misleading prior, ``hypothesis_min_fraction``), and
``min_verified``."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np
import pytest
from _compilations import COMPILED
from test_m2loc_hypotheses import numpy_kabsch

from jaxloc.m2loc import (
    RoadNormals,
    TripletConfig,
    build_map,
    localization_errors,
    localize_scan,
    m2loc_config,
)
from jaxloc.m2loc._hypotheses import map_grid
from jaxloc.m2loc._matching import consistency_graph
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query


def test_one_to_one_graph_matches_numpy():
    rng = np.random.default_rng(0)
    count = 60
    query_index = rng.integers(0, 15, count)
    map_index = rng.integers(0, 20, count)
    query_vertices = rng.uniform(-5, 5, (15, 3))
    map_vertices = rng.uniform(-5, 5, (20, 3))
    valid = rng.random(count) > 0.1
    got = np.asarray(
        consistency_graph(
            query_vertices[query_index],
            map_vertices[map_index],
            valid,
            1.0,
            query_index,
            map_index,
        )
    )
    want = np.zeros((count, count), bool)
    for a in range(count):
        for b in range(count):
            dq = np.linalg.norm(query_vertices[query_index[a]] - query_vertices[query_index[b]])
            dm = np.linalg.norm(map_vertices[map_index[a]] - map_vertices[map_index[b]])
            want[a, b] = (
                a != b
                and valid[a]
                and valid[b]
                and abs(dq - dm) <= 1.0
                and query_index[a] != query_index[b]
                and map_index[a] != map_index[b]
            )
    np.testing.assert_array_equal(got, want)
    plain = np.asarray(
        consistency_graph(query_vertices[query_index], map_vertices[map_index], valid, 1.0)
    )
    shared = (query_index[:, None] == query_index[None]) | (map_index[:, None] == map_index[None])
    assert np.any(plain & shared)  # the default graph does join associations of one vertex
    np.testing.assert_array_equal(got, plain & ~shared)


@pytest.fixture(scope="module")
def world():
    return make_outdoor_world("sparse", seed=3, blocks=2, bridge_length=150.0)


def config(attempts: int = 1, hypotheses: int = 0, min_verified: int = 0, **overrides):
    """The fixture's configuration; the uniqueness check off unless asked for (each test here
    looks at one option at a time)."""
    overrides.setdefault("ambiguity_margin", None)
    return m2loc_config(
        2,
        scale_edges=(20.0, 30.0),
        query_capacity=32,
        one_to_one=True,
        registration_attempts=attempts,
        hypotheses=hypotheses,
        min_inlier_fraction=0.0,
        min_verified=min_verified,
        **overrides,
    )


@pytest.fixture(scope="module")
def maps(world):
    return {a: build_map(world.points, world.labels, config(a)) for a in (1, 3)}


#: Queries of the fixture (found by a search over seed 11's first 60 queries) whose first clique is
#: a wrong hypothesis that verifies poorly, and whose retries find the right pose.
RETRY_FIXED = (0, 34, 38)


@pytest.fixture(scope="module")
def queries(world):
    rng = np.random.default_rng(11)
    return [
        make_query(world.points, world.labels, world.road_normals, rng, max_kept=20)
        for _ in range(max(RETRY_FIXED) + 1)
    ]


def fixed_queries(plain_map, option_map, queries) -> list[int]:
    """Localize every query with both maps (one-to-one cliques in both) and check what an option
    that acts on poorly verified poses must keep: never a worse verification, nothing changed
    where the plain pose verifies, cliques that are matchings, one compilation per map. Returns
    the queries whose pose the option turns from wrong (> 7.5 m) to right."""
    for m in (plain_map, option_map):
        localize_scan(m, None, queries[0].points, queries[0].labels)  # compile both
    compiled = len(COMPILED)
    fixed = []
    for index, q in enumerate(queries):
        if len(q.points) > 32:  # above the fixture's query capacity
            continue
        plain = localize_scan(plain_map, None, q.points, q.labels)
        option = localize_scan(option_map, None, q.points, q.labels)
        assert option.inlier_fraction >= plain.inlier_fraction
        if plain.inlier_fraction >= 0.5:  # verified at once: the option does not act
            np.testing.assert_array_equal(option.pose, plain.pose)
            np.testing.assert_array_equal(option.inliers, plain.inliers)
        for result in (plain, option):  # one-to-one: a clique is a matching
            assert len(np.unique(result.inliers[:, 0])) == len(result.inliers)
            assert len(np.unique(result.inliers[:, 1])) == len(result.inliers)
        before, after = (localization_errors(r.pose, q.T_map_scan)[0] for r in (plain, option))
        if before > 7.5 and after < 7.5:
            fixed.append(index)
    assert COMPILED[compiled:] == []  # one compilation per map
    return fixed


def test_retries_keep_the_best_verification_and_fix_rejected_hypotheses(maps, queries):
    assert fixed_queries(maps[1], maps[3], queries) == list(RETRY_FIXED)


#: Queries of the fixture (found by a search over seed 11's first 60 queries, the retry test's)
#: whose maximum clique gives a wrong pose, and whose verified hypotheses give the right one. The
#: search also finds right poses for queries 0, 38 and 53, but these small scans verify fewer than
#: ``hypothesis_min_support`` (6) vertices beyond the minimal set, so they are not kept.
HYPOTHESES_FIXED = (14,)


def test_hypotheses_keep_the_best_verification_and_fix_rejected_poses(world, queries):
    maps = {h: build_map(world.points, world.labels, config(hypotheses=h)) for h in (0, 64)}
    queries = queries[: max(HYPOTHESES_FIXED) + 1]
    assert fixed_queries(maps[0], maps[64], queries) == list(HYPOTHESES_FIXED)
    # The map's verification grid is an optimisation only: without it (or with cells smaller than
    # the verification radius) the query builds its own and finds the same pose.
    fine = map_grid(maps[64].points, maps[64].classes, 0.05)  # would find no neighbour
    q = queries[HYPOTHESES_FIXED[0]]
    want = localize_scan(maps[64], None, q.points, q.labels)
    for grid in (None, fine):
        other = eqx.tree_at(lambda m: m.grid, maps[64], grid, is_leaf=lambda x: x is None)
        got = localize_scan(other, None, q.points, q.labels)
        np.testing.assert_array_equal(got.pose, want.pose)
        np.testing.assert_array_equal(got.inliers, want.inliers)


def test_a_misleading_prior_cannot_spoil_a_searched_pose(world, queries):
    """Road normals tilted 10 degrees with a 0.1 degree std pull the refinement of the found clique
    off (it verifies worse than the clique's closed-form pose): the search keeps the closed-form
    pose, which is the numpy Kabsch of its inliers and the right pose."""
    normals = world.road_normals
    tilt = np.deg2rad(10.0)
    tilted = np.tile([np.sin(tilt), 0.0, np.cos(tilt)], (len(normals.xy), 1))
    misleading = RoadNormals(normals.xy, tilted, np.full(len(normals.xy), 0.1))
    triplet_map = build_map(world.points, world.labels, config(hypotheses=64), misleading)
    q = queries[HYPOTHESES_FIXED[0]]
    result = localize_scan(triplet_map, None, q.points, q.labels)
    closed_form = numpy_kabsch(q.points[result.inliers[:, 0]], world.points[result.inliers[:, 1]])
    np.testing.assert_allclose(result.pose, closed_form, atol=1e-3)
    assert localization_errors(result.pose, q.T_map_scan)[0] < 7.5
    assert result.inlier_fraction >= 0.55


def test_hypothesis_min_fraction_refuses_a_searched_pose_below_it(world, queries):
    """The fixed query's searched pose is kept at the default and refused by a
    ``hypothesis_min_fraction`` just above its verification: then the plain pose stays."""
    q = queries[HYPOTHESES_FIXED[0]]
    plain = localize_scan(build_map(world.points, world.labels, config()), None, q.points, q.labels)
    searched = localize_scan(
        build_map(world.points, world.labels, config(hypotheses=64)), None, q.points, q.labels
    )
    default = TripletConfig().hypothesis_min_fraction
    assert searched.inlier_fraction > max(plain.inlier_fraction, default)  # kept at the default
    strict = config(hypotheses=64, hypothesis_min_fraction=searched.inlier_fraction + 0.01)
    refused = localize_scan(build_map(world.points, world.labels, strict), None, q.points, q.labels)
    np.testing.assert_array_equal(refused.pose, plain.pose)
    assert refused.inlier_fraction == plain.inlier_fraction
    with pytest.raises(ValueError, match="hypothesis_min_fraction"):
        m2loc_config(3, hypothesis_min_fraction=1.5)


def test_hypotheses_must_not_be_negative():
    with pytest.raises(ValueError, match="hypotheses"):
        m2loc_config(3, hypotheses=-1)


def test_min_verified_rejects_a_pose_that_few_vertices_confirm(world):
    """``min_verified`` counts verified vertices beyond the minimal set: a right pose of a
    query whose count falls short is reported not valid, and the pose itself is unchanged."""
    rng = np.random.default_rng(11)
    loose = build_map(world.points, world.labels, config())
    for _ in range(10):  # the first query of seed 11 that localizes
        query = make_query(world.points, world.labels, world.road_normals, rng, max_kept=20)
        result = localize_scan(loose, None, query.points, query.labels)
        if result.valid and localization_errors(result.pose, query.T_map_scan)[0] < 7.5:
            break
    verified = round(result.inlier_fraction * (len(query.points) - 3))
    assert result.valid and verified >= 3
    strict = build_map(world.points, world.labels, config(min_verified=verified + 1))
    refused = localize_scan(strict, None, query.points, query.labels)
    assert not refused.valid and refused.inlier_fraction == result.inlier_fraction
    np.testing.assert_array_equal(refused.inliers, result.inliers)
    assert m2loc_config(3).min_verified == 4 and m2loc_config(3, robust=False).min_verified == 4
    with pytest.raises(ValueError, match="min_verified"):
        m2loc_config(3, min_verified=-1)


def test_a_place_that_repeats_elsewhere_is_refused_as_ambiguous(world):
    """The uniqueness check (``ambiguity_margin``): a query that localizes in the world is kept,
    right and not ambiguous; in the world with a copy of that neighbourhood 500 m away (a road
    that repeats) the copy's pose verifies as well as the right one, and the pose is refused as
    ambiguous instead of reported."""
    rng = np.random.default_rng(11)
    checked = config(hypotheses=64, ambiguity_margin=0.0)
    unique = build_map(world.points, world.labels, checked)
    for _ in range(10):  # the first query of seed 11 that localizes
        query = make_query(world.points, world.labels, world.road_normals, rng, max_kept=20)
        kept = localize_scan(unique, None, query.points, query.labels)
        if kept.valid and localization_errors(kept.pose, query.T_map_scan)[0] < 7.5:
            break
    assert kept.valid and not kept.ambiguous
    centre = query.T_map_scan[:3, 3]
    near = np.linalg.norm(world.points[:, :2] - centre[:2], axis=1) < 90.0
    offset = np.array([world.points[:, 0].max() - centre[0] + 500.0, 0.0, 0.0])
    repeated_points = np.concatenate([world.points, world.points[near] + offset])
    repeated_labels = np.concatenate([world.labels, world.labels[near]])
    repeated = build_map(repeated_points, repeated_labels, checked)
    refused = localize_scan(repeated, None, query.points, query.labels)
    assert refused.ambiguous and not refused.valid
    np.testing.assert_array_equal(refused.pose, np.eye(4))
    with pytest.raises(ValueError, match="ambiguity_margin"):
        config(hypotheses=0, ambiguity_margin=0.0)
    # on in the robust default; off where there are no hypotheses, and in the paper's M2Loc
    assert m2loc_config(3).ambiguity_margin == 0.0
    assert m2loc_config(3, hypotheses=0).ambiguity_margin is None
    assert m2loc_config(3, robust=False).ambiguity_margin is None


def test_the_search_thresholds_are_traced(world, queries):
    """retry_inlier_fraction, hypothesis_min_support and hypothesis_min_fraction decide whether the
    searched pose replaces the maximum clique's wrong one: each, changed on the built map, keeps
    the wrong pose of the fixed query, with the same compiled program."""
    triplet_map = build_map(world.points, world.labels, config(hypotheses=64))
    q = queries[HYPOTHESES_FIXED[0]]
    searched = localize_scan(triplet_map, None, q.points, q.labels)
    assert localization_errors(searched.pose, q.T_map_scan)[0] < 7.5
    before = len(COMPILED)
    for name, value in (
        ("retry_inlier_fraction", 0.0),
        ("hypothesis_min_support", 100),
        ("hypothesis_min_fraction", 1.0),
    ):
        changed = dataclasses.replace(triplet_map.config, **{name: value})
        result = localize_scan(triplet_map, None, q.points, q.labels, config=changed)
        assert localization_errors(result.pose, q.T_map_scan)[0] > 7.5, name
    assert [c for c in COMPILED[before:] if "registered" in c] == []
