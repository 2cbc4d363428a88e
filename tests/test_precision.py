"""Every float32 matrix product in the jitted kernels asks for full float32 precision.

On NVIDIA GPUs XLA runs a float32 ``dot_general`` of DEFAULT precision as TF32 (10-bit mantissa):
on an H200 that put rendered depths 4e-4 off (mm at room scale) and patch cosines 1e-3 off, and
failed the numpy references of tests/test_scores.py and tests/test_render.py there. The CPU never
shows it (it computes float32 products exactly), so this test reads the traced programs instead:
every floating-point ``dot_general`` of the filter pass, rendering, the semantic match, the robust
pose solver and the M2Loc query, registration, matching and tracking must carry
``Precision.HIGHEST``. Tracing only: nothing here compiles.
"""

from __future__ import annotations

import functools

import _tiny_world as tiny
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from jax.extend import core as jax_core

from jaxloc import render
from jaxloc.camera import stride_grid
from jaxloc.lsq import RobustLoss, solve_pose
from jaxloc.m2loc import Tracker, build_map, m2loc_config, pad_scan
from jaxloc.m2loc._matching import match_descriptors
from jaxloc.m2loc._query import describe_query, register_query
from jaxloc.m2loc._registration import weighted_kabsch
from jaxloc.m2loc._tracking import TrackState
from jaxloc.sg2loc._filter import run_pass
from jaxloc.sg2loc._scores import match_patches
from jaxloc.sg2loc.retrieval import Gallery, retrieve
from jaxloc.synthetic.outdoor import make_outdoor_world, make_query

HIGHEST = jax.lax.Precision.HIGHEST


def _sub_jaxprs(value):
    if isinstance(value, jax_core.ClosedJaxpr):
        yield value.jaxpr
    elif isinstance(value, jax_core.Jaxpr):
        yield value
    elif isinstance(value, tuple | list):
        for item in value:
            yield from _sub_jaxprs(item)


def low_precision_dots(jaxpr: jax_core.Jaxpr) -> list[str]:
    """The floating-point ``dot_general`` equations of ``jaxpr`` (and every nested program) that
    contract a dimension and whose precision is not HIGHEST on both operands. A product without a
    contracting dimension (jaxlie's quaternion outer products) is rewritten by XLA's algebraic
    simplifier into an elementwise multiply, which is exact on every backend."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            floating = any(jnp.issubdtype(v.aval.dtype, jnp.floating) for v in eqn.invars)
            (contracting, _), _ = eqn.params["dimension_numbers"]
            precision = eqn.params.get("precision")
            if floating and len(contracting) > 0 and precision != (HIGHEST, HIGHEST):
                frames = str(eqn.source_info.traceback).splitlines()
                ours = [f for f in frames if "/jaxloc/" in f and "/tests/" not in f]
                found.append((ours or frames or [str(eqn)])[0])
        for param in eqn.params.values():
            for sub in _sub_jaxprs(param):
                found.extend(low_precision_dots(sub))
    return found


def assert_highest(fn, *args):
    jaxpr = jax.make_jaxpr(fn)(*args).jaxpr
    offenders = low_precision_dots(jaxpr)
    assert not offenders, f"{len(offenders)} float dot_general(s) below HIGHEST: {offenders[:5]}"


def test_the_check_finds_a_default_precision_product():
    """The walker is not vacuous: a plain ``@`` inside a scan is found, HIGHEST is not."""

    def plain(a):
        return jax.lax.scan(lambda c, x: (c @ x, None), a, jnp.stack([a, a]))[0]

    def highest(a):
        return jnp.matmul(a, a, precision=HIGHEST)

    a = jnp.eye(3)
    assert len(low_precision_dots(jax.make_jaxpr(plain)(a).jaxpr)) == 1
    assert low_precision_dots(jax.make_jaxpr(highest)(a).jaxpr) == []


def test_filter_pass_and_rendering():
    scene = tiny.scene()
    config = tiny.step_config(scene)
    assert_highest(
        functools.partial(run_pass, config=config),
        jax.random.key(0),
        tiny.initial_state(scene),
        tiny.frames(2),
        scene,
    )
    camera = tiny.camera()
    grid = stride_grid(camera, 4)
    pose = jnp.array([1.0, 1.0, 1.5, 0.3])
    assert_highest(lambda s, p: render(s, p, camera, grid, engine="jax"), scene, pose)
    rng = np.random.default_rng(0)
    patches = rng.normal(size=(12, tiny.EMBEDDING_DIM)).astype(np.float32)
    assert_highest(match_patches, patches, scene.embeddings, scene.object_valid)
    gallery = Gallery.from_scene_graphs([scene, tiny.scene(1)])
    assert_highest(retrieve, patches[None, :, None, :].reshape(1, 3, 4, -1), gallery)


def test_pose_solver_and_kabsch():
    rng = np.random.default_rng(1)
    source = rng.normal(size=(20, 3)).astype(np.float32)
    target = source + np.float32([1.0, 2.0, 3.0])
    weights = np.ones(20, np.float32)
    assert_highest(weighted_kabsch, source, target, weights)

    def residuals(T, args):
        src, dst = args
        return jax.vmap(T.apply)(src) - dst

    assert_highest(
        lambda T: solve_pose(residuals, T, (source, target), loss=RobustLoss("cauchy", 1.0)).pose,
        jaxlie.SE3.identity(),
    )


@pytest.fixture(scope="module")
def triplet_world():
    world = make_outdoor_world("dense", seed=3, blocks=2, bridge_length=150.0)
    config = m2loc_config(num_scales=2, scale_edges=(20.0, 30.0), query_capacity=64)
    return world, build_map(world.points, world.labels, config)


def test_m2loc_query_matching_and_tracking(triplet_world):
    world, triplet_map = triplet_world
    query = make_query(
        world.points, world.labels, world.road_normals, np.random.default_rng(2), max_kept=30
    )
    scan = pad_scan(query.points, query.labels, triplet_map.config, 64)
    descriptors, valid = describe_query(
        scan.points, scan.classes, scan.mask, triplet_map.config.descriptor
    )
    assert_highest(
        functools.partial(register_query, triplet_map),
        scan.points,
        scan.classes,
        descriptors,
        valid,
        scan.mask,
    )
    assert_highest(
        functools.partial(match_descriptors, k=5),
        descriptors[0],
        valid[0],
        scan.classes,
        triplet_map.descriptors[0],
        triplet_map.valid[0],
        triplet_map.classes,
    )
    tracker = Tracker(triplet_map)
    state = tracker.init()
    assert isinstance(state, TrackState)
    assert_highest(tracker.step, state, scan, jnp.eye(4, dtype=jnp.float32))
