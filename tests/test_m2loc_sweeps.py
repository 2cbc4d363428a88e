"""M2Loc sweeps as JAX programs: query settings are traced, a built map takes another config's
query settings without compiling, the pure ``query`` runs under ``jit`` and ``vmap`` over stacked
configurations, and a long loop of configurations keeps the process's memory mappings flat.

Compilations are observed through ``jax.monitoring`` (tests/_compilations.py). One small world,
one map, one query capacity: the query program compiles once for the module, the vmapped one once.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _compilations import COMPILED

from jaxloc.lsq import RobustLoss
from jaxloc.m2loc import (
    build_map,
    localize_drive,
    localize_scan,
    localize_scans,
    m2loc_config,
    pad_scan,
    query,
    with_config,
)
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

CAPACITY = 32


def base_config(**overrides):
    """Two scales, M2Loc's robust options (one-to-one cliques, verified hypotheses, the uniqueness
    check) with 64 hypotheses (a smaller program than the default 256), one query capacity."""
    overrides.setdefault("hypotheses", 64)
    return m2loc_config(2, scale_edges=(20.0, 30.0), query_capacity=CAPACITY, **overrides)


@pytest.fixture(scope="module")
def world():
    return make_outdoor_world("dense", seed=3, blocks=1)


@pytest.fixture(scope="module")
def triplet_map(world):
    return build_map(world.points, world.labels, base_config(), world.road_normals)


@pytest.fixture(scope="module")
def queries(world):
    rng = np.random.default_rng(7)
    found = []
    while len(found) < 8:
        q = make_query(world.points, world.labels, world.road_normals, rng, max_kept=24)
        if len(q.points) <= CAPACITY:
            found.append(q)
    return found


def mappings() -> int:
    with open("/proc/self/maps", "rb") as maps:
        return maps.read().count(b"\n")


def outcome(result) -> tuple:
    """What a knob can change, comparable across runs."""
    return (
        bool(result.valid),
        int(result.clique_size),
        int(result.scales_used),
        round(float(result.inlier_fraction), 4),
        bool(result.ambiguous),
        tuple(np.round(np.asarray(result.pose, np.float64).ravel(), 4)),
    )


def test_a_grid_of_configs_on_a_built_map_compiles_once_and_changes_results(triplet_map, queries):
    """24 configurations (consistency_threshold x min_inlier_fraction) given to localize_scan on
    one built map: nothing compiles after the first, the mappings stay within 10 %, the results
    follow the knobs; jax.vmap of query over the 24 stacked configurations gives the loop's flags
    and poses."""
    configs = [
        base_config(consistency_threshold=t, min_inlier_fraction=f)
        for t in (0.3, 0.6, 1.0, 1.5, 2.0, 3.0)
        for f in (0.2, 0.5, 0.8, 1.0)
    ]
    q = queries[2]
    first = localize_scan(triplet_map, None, q.points, q.labels, config=configs[0])
    before, maps_before = len(COMPILED), mappings()
    loop = [first] + [
        localize_scan(triplet_map, None, q.points, q.labels, config=c) for c in configs[1:]
    ]
    assert COMPILED[before:] == []
    assert mappings() <= 1.1 * maps_before
    assert len({outcome(r) for r in loop}) > 3  # the knobs act
    assert {r.valid for r in loop} == {True, False}

    stacked = jax.tree.map(lambda *x: jnp.stack(x), *configs)
    scan = pad_scan(q.points, q.labels, triplet_map.config, CAPACITY)
    batched = jax.jit(jax.vmap(query, in_axes=(None, None, 0)))(triplet_map, scan, stacked)
    np.testing.assert_array_equal(np.asarray(batched.valid), [r.valid for r in loop])
    np.testing.assert_allclose(
        np.asarray(batched.pose), np.stack([r.pose for r in loop]), atol=1e-3
    )
    for i, want in enumerate(loop):  # the padded result holds the host result
        size = int(batched.clique_size[i])
        assert size == want.clique_size and bool(batched.ambiguous[i]) == want.ambiguous
        np.testing.assert_array_equal(np.asarray(batched.inliers[i])[:size], want.inliers)
        assert np.all(np.asarray(batched.inliers[i])[size:] == -1)
        assert float(batched.inlier_fraction[i]) == pytest.approx(want.inlier_fraction, abs=1e-6)


#: A changed value of traced settings of the base configuration, where it shows in the queries'
#: outcomes (valid, clique, scales, verification, ambiguity, pose). The search's thresholds
#: (``retry_inlier_fraction``, ``hypothesis_min_*``) act on scans whose maximum clique's pose is
#: wrong: tests/test_m2loc_options.py checks them on such a scan; the tracking settings:
#: tests/test_m2loc_tracking.py.
KNOBS = {
    "consistency_threshold": 0.1,
    "ambiguity_margin": 1.0,
    "min_clique": 1,
    "min_inliers": 60,
    "min_inlier_fraction": 1.0,
    "min_verified": 60,
    "verify_radius": 0.3,
    "rot_delta_deg": 30.0,
    "loss": RobustLoss("gnc_tls", 0.1),
}


@pytest.mark.parametrize("name", sorted(KNOBS))
def test_each_traced_setting_changes_a_result(triplet_map, queries, name):
    base = base_config()
    changed = dataclasses.replace(base, **{name: KNOBS[name]})
    assert jax.tree.structure(changed) == jax.tree.structure(base)  # a traced setting
    before = len(COMPILED)
    outcomes = [
        [outcome(localize_scan(triplet_map, None, q.points, q.labels, config=c)) for q in queries]
        for c in (base, changed)
    ]
    assert [c for c in COMPILED[before:] if "registered" in c or "describe" in c] == []
    assert outcomes[0] != outcomes[1]


def test_ambiguity_distance_and_gnc_mu_act(triplet_map, queries):
    """The uniqueness check's distance acts where a margin of 1 makes every rival count; GNC's
    final mu moves a pose."""
    plain = base_config()
    rivals = base_config(ambiguity_margin=1.0)
    far = dataclasses.replace(rivals, ambiguity_distance=1e4)
    mu = dataclasses.replace(plain, loss=RobustLoss("gnc_tls", 1.0, gnc_mu_final=1.0))
    results = {
        name: [localize_scan(triplet_map, None, q.points, q.labels, config=c) for q in queries]
        for name, c in (("plain", plain), ("rivals", rivals), ("far", far), ("mu", mu))
    }
    assert any(r.ambiguous for r in results["rivals"])
    assert not any(r.ambiguous for r in results["far"])
    assert [outcome(r) for r in results["mu"]] != [outcome(r) for r in results["plain"]]


def test_with_config_matches_a_map_built_with_it(world, triplet_map, queries):
    """Another rot_delta_deg (and a smaller radius) on a built map give what a map described with
    them gives; a larger radius gets the grid such a map has; descriptor settings that differ are
    refused, naming the settings."""
    config = base_config(verify_radius=1.0, rot_delta_deg=4.0)
    swapped = with_config(triplet_map, config)
    built = build_map(world.points, world.labels, config, world.road_normals)
    np.testing.assert_allclose(np.asarray(swapped.rsn_sigma), np.asarray(built.rsn_sigma), 1e-6)
    for q in queries[:3]:
        a = localize_scan(swapped, None, q.points, q.labels)
        b = localize_scan(built, None, q.points, q.labels)
        assert outcome(a) == outcome(b)
    wide = base_config(verify_radius=3.0)
    grids = [
        m.grid
        for m in (with_config(triplet_map, wide), build_map(world.points, world.labels, wide))
    ]
    assert grids[0].cell == grids[1].cell == 3.0
    for a, b in zip(jax.tree.leaves(grids[0]), jax.tree.leaves(grids[1]), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    other = m2loc_config(3, query_capacity=CAPACITY)
    with pytest.raises(ValueError, match="descriptor settings .* differ from the map's"):
        localize_scan(triplet_map, None, queries[0].points, queries[0].labels, config=other)
    with pytest.raises(ValueError, match="descriptor settings"):
        localize_scans(triplet_map, [(queries[0].points, queries[0].labels)], config=other)


def test_the_drive_takes_the_given_query_settings(triplet_map, queries):
    """localize_drive(query_config=) localizes each scan as localize_scan(config=) does
    (localize_scans(config=): tests/_sharding_check.py)."""
    strict = base_config(min_inlier_fraction=1.0, consistency_threshold=0.5)
    scans = [(q.points, q.labels) for q in queries[:3]]
    want = [localize_scan(triplet_map, None, p, lab, config=strict) for p, lab in scans]
    drive = localize_drive(triplet_map, scans, query_config=strict)
    np.testing.assert_array_equal(drive.valid, [r.valid for r in want])
    np.testing.assert_allclose(drive.poses, np.stack([r.pose for r in want]), atol=1e-6)
    default = [localize_scan(triplet_map, None, p, lab) for p, lab in scans]
    assert [r.valid for r in want] != [r.valid for r in default]  # the strict settings were used


def test_two_hundred_configurations_keep_mappings_flat(triplet_map, queries):
    rng = np.random.default_rng(0)
    q = queries[1]
    localize_scan(triplet_map, None, q.points, q.labels, config=base_config())
    before, maps_before = len(COMPILED), mappings()
    for _ in range(200):
        config = base_config(
            consistency_threshold=rng.uniform(0.3, 3.0),
            min_inlier_fraction=rng.uniform(0.0, 1.0),
            verify_radius=rng.uniform(0.5, 1.5),
            loss=RobustLoss("gnc_tls", rng.uniform(0.2, 2.0)),
        )
        localize_scan(triplet_map, None, q.points, q.labels, config=config)
    assert [c for c in COMPILED[before:] if "registered" in c or "describe" in c] == []
    assert mappings() - maps_before < 50
