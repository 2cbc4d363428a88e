"""The nearest-hit engines of :func:`jaxloc.raycast` ("jax", "embree", "warp"): each installed one
against the float64 brute force and against the others, gradients, jit/vmap, traces, invalid rays,
map edits (the acceleration-structure cache) and the errors for unknown or missing engines.

Optional engines are skipped when their package is absent; CI installs both (embreex is a default
dependency on x86-64, warp-lang comes with the test extra and runs on its CPU backend).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import NUM_RAYS, brute_force, random_rays, random_scene

from jaxloc import Camera, raycast, render_batch, stride_grid
from jaxloc.raycasting import embree, engines
from jaxloc.raycasting._cache import fingerprint
from jaxloc.sg2loc import SG2LocConfig
from jaxloc.sg2loc._filter import StepConfig
from jaxloc.sg2loc.refine import RefineConfig

OPTIONAL = ("embree", "warp")
INSTALLED = ["jax"] + [e for e in OPTIONAL if engines.is_installed(e)]
ALL = [
    pytest.param(e, marks=pytest.mark.skipif(e not in INSTALLED, reason=f"{e} not installed"))
    for e in ("jax",) + OPTIONAL
]
MIN_AGREEMENT = 0.999
T_TOL = 1e-4  # metres
BARY_TOL = 3e-4


@functools.cache
def _cast(engine: str):
    """One jitted raycast per engine, shared by every test of this module."""
    return jax.jit(functools.partial(raycast, engine=engine))


def _np(tree):
    return jax.tree.map(np.asarray, tree)


@pytest.fixture(scope="module")
def second_scene():
    """Another random scene (other objects, other capacity), and its rays and brute force."""
    scene = random_scene(5, num_objects=30)
    rays = random_rays(scene, 6)
    return scene, rays, brute_force(np.asarray(scene.triangles)[: scene.num_triangles], *rays)


def _steep(scene, rays, triangle):
    """Rays whose hit triangle is met at |cos| > 0.05 (not grazing), float64."""
    tris = np.asarray(scene.triangles, np.float64)[np.maximum(triangle, 0)]
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    d = rays[1] / np.linalg.norm(rays[1], axis=1, keepdims=True)
    return (triangle >= 0) & (np.abs(np.sum(normal * d, 1)) > 0.05)


def _check_against_brute_force(scene, rays, reference, hits):
    t_ref, tri_ref, _ = reference
    obj_ref = np.where(tri_ref >= 0, np.asarray(scene.triangle_object)[tri_ref], -1)
    assert 0.4 < hits.hit.mean() < 0.9
    assert (hits.hit == (tri_ref >= 0)).mean() >= MIN_AGREEMENT
    assert (hits.object_id == obj_ref).mean() >= MIN_AGREEMENT
    assert (hits.triangle_id == tri_ref).mean() >= MIN_AGREEMENT
    same = (hits.triangle_id == tri_ref) & _steep(scene, rays, tri_ref)
    assert same.mean() > 0.4
    assert np.max(np.abs(hits.t[same] - t_ref[same])) <= T_TOL


@pytest.mark.parametrize("engine", ALL)
def test_engine_matches_float64_brute_force(engine, scene, rays, reference, second_scene):
    _check_against_brute_force(scene, rays, reference, _np(_cast(engine)(scene, *rays)))
    other, other_rays, other_reference = second_scene
    hits = _np(_cast(engine)(other, *other_rays))
    _check_against_brute_force(other, other_rays, other_reference, hits)


@pytest.mark.parametrize("engine", ALL)
def test_engine_agrees_with_the_jax_engine(engine, scene, rays, hits, reference):
    """Same triangle on (nearly) every ray, and then the same t and barycentric coordinates: they
    come from the same JAX code whichever engine chose the triangle, or, for the native Embree
    engine, from the same formulas in double precision, never less accurate than JAX's float32
    (against the float64 brute force, on each ray, up to float32 rounding)."""
    ours = _np(_cast(engine)(scene, *rays))
    agree = ours.triangle_id == hits.triangle_id
    assert agree.mean() >= MIN_AGREEMENT
    np.testing.assert_array_equal(ours.object_id[agree], hits.object_id[agree])
    hit = agree & ours.hit
    if not engines.recomputes_hits(engine):
        np.testing.assert_allclose(ours.t[hit], hits.t[hit], rtol=1e-6)
        np.testing.assert_allclose(ours.barycentric[agree], hits.barycentric[agree], atol=1e-6)
        return
    t_ref, triangle_ref, bary_ref = reference
    hit &= triangle_ref == ours.triangle_id
    assert hit.mean() > 0.4
    # The reference sees the rays before float32 normalisation, so per ray either side may be
    # closer by the rounding of the direction; over all rays, native is no worse.
    error, jax_error = np.abs(ours.t[hit] - t_ref[hit]), np.abs(hits.t[hit] - t_ref[hit])
    assert (error <= jax_error + 2e-7 * t_ref[hit]).mean() >= 0.99
    assert error.mean() <= jax_error.mean() and error.max() <= 1.5 * jax_error.max() + 1e-6
    np.testing.assert_allclose(ours.t[hit], hits.t[hit], rtol=1e-3)
    bary_error = np.abs(ours.barycentric - bary_ref)[hit].max(-1)
    jax_bary_error = np.abs(hits.barycentric - bary_ref)[hit].max(-1)
    assert bary_error.mean() <= jax_bary_error.mean() + 1e-7
    assert bary_error.max() <= jax_bary_error.max() + 1e-5


@functools.cache
def _cast_values(engine: str):
    """The values-only path of :func:`raycast` (``differentiable=False``), jitted per engine."""
    return jax.jit(functools.partial(raycast, engine=engine, differentiable=False))


@pytest.mark.parametrize("engine", ALL)
def test_values_only_path_equals_the_differentiable_one(engine, scene, rays, reference):
    """The same rays through both paths: the same triangles, objects and misses (the same engine
    picks them); the engine's own t and barycentric coordinates equal JAX's recompute to float32
    rounding (both as close to the float64 brute force on rays that meet their triangle at
    |cos| > 0.05); invalid rays and padding triangles miss on both paths."""
    padded = random_scene(0, capacity=scene.capacity._replace(triangles=scene.num_triangles + 64))
    o, d = rays[0].copy(), rays[1].copy()
    o[::7] = np.nan
    d[3::11] = 0.0
    t_ref, triangle_ref, bary_ref = reference
    for world in (scene, padded):
        exact = _np(_cast(engine)(world, o, d))
        fast = _np(_cast_values(engine)(world, o, d))
        np.testing.assert_array_equal(fast.triangle_id, exact.triangle_id)
        np.testing.assert_array_equal(fast.object_id, exact.object_id)
        np.testing.assert_array_equal(fast.hit, exact.hit)
        assert 0.4 < fast.hit.mean() < 0.9 and not fast.hit[::7].any()
        assert np.all(fast.t[~fast.hit] == np.inf) and np.all(fast.barycentric[~fast.hit] == 0)
        hit = fast.hit
        close = np.isclose(fast.t[hit], exact.t[hit], rtol=1e-5, atol=1e-6)
        assert close.mean() >= 0.99
        steep = (fast.triangle_id == triangle_ref) & _steep(world, rays, triangle_ref)
        assert steep.mean() > 0.4
        for path in (fast, exact):  # float32 rounding on small triangles: ~2e-4 at worst
            assert np.max(np.abs(path.t[steep] - t_ref[steep])) <= T_TOL
            assert np.max(np.abs(path.barycentric[steep] - bary_ref[steep])) <= BARY_TOL
        near = np.all(np.abs(fast.barycentric - exact.barycentric) <= BARY_TOL, axis=-1)
        assert near[hit].mean() >= 0.99  # the rest: grazing rays, rounded apart by both paths
        np.testing.assert_allclose(fast.barycentric.sum(-1)[hit], 1.0, atol=1e-5)


@pytest.mark.parametrize("engine", ALL)
def test_values_only_renders_equal_and_carry_no_gradient(engine, room_scene):
    """``render_batch(..., differentiable=False)`` (the filter's path) gives the differentiable
    render's depth, colour and patch majority; its gradient is zero by contract, never NaN."""
    camera = Camera.from_fov(40, 30, 60.0)
    grid = stride_grid(camera, 4)
    poses = jnp.array([[0.3, -0.4, 1.5, 0.7], [-1.0, 0.5, 1.2, 2.5]])
    both = {
        flag: _np(render_batch(room_scene, poses, camera, grid, engine=engine, differentiable=flag))
        for flag in (True, False)
    }
    np.testing.assert_array_equal(both[False].patch_object, both[True].patch_object)
    np.testing.assert_array_equal(both[False].valid, both[True].valid)
    np.testing.assert_allclose(both[False].depth, both[True].depth, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(both[False].color, both[True].color, atol=1e-4)

    def total_depth(p):
        depth = render_batch(room_scene, p, camera, grid, engine=engine, differentiable=False)
        return jnp.sum(jnp.where(jnp.isfinite(depth.depth), depth.depth, 0.0))

    np.testing.assert_array_equal(np.asarray(jax.grad(total_depth)(poses)), 0.0)


@pytest.mark.parametrize("engine", ALL)
def test_engine_jit_equals_eager(engine, scene, rays):
    eager = _np(raycast(scene, *rays, engine=engine))
    jitted = _np(_cast(engine)(scene, *rays))
    np.testing.assert_array_equal(eager.triangle_id, jitted.triangle_id)
    np.testing.assert_allclose(eager.t[eager.hit], jitted.t[jitted.hit], rtol=1e-6)


@pytest.mark.parametrize("engine", ALL)
def test_engine_vmap_equals_loop(engine, scene, rays):
    """vmap over ray batches (the map shared) and over stacked maps (rays and map batched)."""
    o = rays[0][:1024].reshape(4, 256, 3)
    d = rays[1][:1024].reshape(4, 256, 3)
    cast = _cast(engine)
    batched = _np(jax.jit(jax.vmap(cast, in_axes=(None, 0, 0)))(scene, o, d))
    for i in range(4):
        np.testing.assert_array_equal(
            batched.triangle_id[i], _np(cast(scene, o[i], d[i])).triangle_id
        )
    other = random_scene(5, num_objects=30, capacity=scene.capacity)
    maps = jax.tree.map(lambda a, b: jnp.stack([a, b]), scene, other)
    both = _np(jax.jit(jax.vmap(cast))(maps, o[:2], d[:2]))
    np.testing.assert_array_equal(both.triangle_id[0], _np(cast(scene, o[0], d[0])).triangle_id)
    np.testing.assert_array_equal(both.triangle_id[1], _np(cast(other, o[1], d[1])).triangle_id)
    assert not np.array_equal(both.triangle_id[0], both.triangle_id[1])


@pytest.mark.parametrize("engine", ALL)
def test_one_trace_per_shape_and_a_new_map_is_not_stale(engine, scene, rays):
    """A second map of the same capacity reuses the compiled function (one trace), and its hits are
    its own: the engine's cached structure is keyed by the triangles, not by the shape."""
    traces = []

    @jax.jit
    def nearest(s, o, d):
        traces.append(1)
        return raycast(s, o, d, engine=engine).triangle_id

    other = random_scene(11, num_objects=30, capacity=scene.capacity)
    first = np.asarray(nearest(scene, *rays))
    second = np.asarray(nearest(other, *rays))
    again = np.asarray(nearest(scene, *rays))
    assert len(traces) == 1
    np.testing.assert_array_equal(first, again)
    reference = brute_force(np.asarray(other.triangles)[: other.num_triangles], *rays)[1]
    assert (second == reference).mean() >= MIN_AGREEMENT
    assert (first != second).mean() > 0.3


@pytest.mark.parametrize("engine", [e for e in ALL if e.values[0] != "jax"])
def test_moved_triangles_are_hit_where_they_are_now(engine, scene, rays):
    """Editing a map's triangles in place (same shape) gives a new fingerprint, so the optional
    engines rebuild their structure instead of answering from the old one (the "jax" engine
    traverses the BVH, which a user must rebuild with :meth:`SceneGraph.from_meshes`)."""
    cast = _cast(engine)
    before = _np(cast(scene, *rays))
    moved = eqx.tree_at(lambda s: s.triangles, scene, scene.triangles + jnp.array([0.7, 0, 0]))
    after = _np(cast(moved, *rays))
    reference = brute_force(np.asarray(moved.triangles)[: moved.num_triangles], *rays)[1]
    assert (after.triangle_id == reference).mean() >= MIN_AGREEMENT
    assert (after.triangle_id != before.triangle_id).mean() > 0.3


@pytest.mark.parametrize("engine", ALL)
def test_invalid_rays_miss_for_every_engine(engine, scene, rays, hits):
    o, d = rays[0].copy(), rays[1].copy()
    bad = np.arange(0, NUM_RAYS, 5)
    d[bad[0::4]] = 0.0
    d[bad[1::4]] = [np.nan, 1.0, 0.0]
    o[bad[2::4]] = [0.0, np.inf, 0.0]
    o[bad[3::4]] = np.nan
    out = _np(_cast(engine)(scene, o, d))
    assert np.all(out.triangle_id[bad] == -1) and not np.any(out.hit[bad])
    assert np.all(out.t[bad] == np.inf) and np.all(out.barycentric[bad] == 0)
    assert not np.any(np.isnan(out.t)) and not np.any(np.isnan(out.barycentric))
    good = np.setdiff1d(np.arange(NUM_RAYS), bad)
    assert (out.triangle_id[good] == hits.triangle_id[good]).mean() >= MIN_AGREEMENT


@pytest.mark.parametrize("engine", ALL)
def test_depth_gradients_w_r_t_the_pose_are_the_same_for_every_engine(engine, room_scene):
    """d(sum of depths)/d(x, y, z, yaw) of a rendered view: equal to the "jax" engine's and to
    central finite differences (the engine only picks the triangle)."""
    camera = Camera.from_fov(40, 30, 60.0)
    grid = stride_grid(camera, 4)
    poses = jnp.array([[0.3, -0.4, 1.5, 0.7], [-1.0, 0.5, 1.2, 2.5]])

    def total_depth(p, engine):
        depth = render_batch(room_scene, p, camera, grid, engine=engine).depth
        return jnp.sum(jnp.where(jnp.isfinite(depth), depth, 0.0))

    grad = jax.jit(jax.grad(total_depth), static_argnums=1)
    ours = np.asarray(grad(poses, engine))
    np.testing.assert_allclose(ours, np.asarray(grad(poses, "jax")), rtol=1e-5, atol=1e-4)
    value = jax.jit(total_depth, static_argnums=1)
    step = 1e-3
    for i, j in [(0, 0), (0, 1), (1, 2), (1, 3)]:
        delta = jnp.zeros_like(poses).at[i, j].set(step)
        fd = (value(poses + delta, engine) - value(poses - delta, engine)) / (2 * step)
        np.testing.assert_allclose(ours[i, j], fd, rtol=2e-2, atol=0.5)


def test_fingerprint_is_exact_and_sensitive(scene):
    triangles = scene.triangles
    key = np.asarray(fingerprint(triangles))
    np.testing.assert_array_equal(key, np.asarray(jax.jit(fingerprint)(triangles)))
    flipped = np.asarray(triangles).copy().view(np.uint32)
    flipped[3, 1, 2] ^= 1  # one bit of one coordinate
    other = np.asarray(fingerprint(jnp.asarray(flipped.view(np.float32))))
    assert key.dtype == np.uint32 and key.shape == (2,)
    assert np.all(key != other)


def test_unknown_and_missing_engines_raise_clear_errors(scene, rays, monkeypatch):
    with pytest.raises(ValueError, match="engine must be one of"):
        raycast(scene, *rays, engine="optix")
    for make in (StepConfig, SG2LocConfig, RefineConfig):
        with pytest.raises(ValueError, match="engine must be one of"):
            if make is StepConfig:
                StepConfig(None, None, None, None, None, engine="embre")
            else:
                make(engine="embre")
    monkeypatch.setattr(engines, "is_installed", lambda engine: False)
    with pytest.raises(ImportError, match="embreex"):
        raycast(scene, *rays, engine="embree")
    with pytest.raises(ImportError, match="warp-lang"):
        raycast(scene, *rays, engine="warp")
    assert engines.resolve_engine("auto") == "jax"  # "auto" falls back, never raises
    fallback = _np(raycast(scene, rays[0][:64], rays[1][:64], engine="auto"))
    expected = _np(raycast(scene, rays[0][:64], rays[1][:64], engine="jax"))
    np.testing.assert_array_equal(fallback.triangle_id, expected.triangle_id)


def test_auto_picks_embree_on_a_cpu_backend_where_installed():
    expected = "embree" if engines.is_installed("embree") else "jax"
    assert jax.default_backend() != "cpu" or engines.resolve_engine("auto") == expected


def test_padding_triangles_and_invalid_rays_never_reach_embree(scene, rays, monkeypatch):
    """A padded map's all-zero triangles are left out of the Embree scene (thousands of degenerate
    triangles at the origin would make every ray near the origin test them all: a filter step once
    took 44 s instead of 0.3 s so), and invalid rays are not traced at all."""
    if "embree" not in INSTALLED:
        pytest.skip("embreex not installed")
    padded = random_scene(0, capacity=scene.capacity._replace(triangles=scene.num_triangles + 500))
    traced = []
    nearest = embree._EmbreeMap.nearest

    def counting(self, origins, directions, out=None):
        traced.append((len(self.ids), origins.shape[0]))
        return nearest(self, origins, directions, out)

    monkeypatch.setattr(embree._EmbreeMap, "nearest", counting)
    monkeypatch.setattr(embree, "_target", embree.python_target)  # the Python implementation
    o = rays[0].copy()
    o[::3] = np.nan  # a third of the rays invalid
    hits = _np(jax.jit(functools.partial(raycast, engine="embree"))(padded, o, rays[1]))
    valid = int(np.sum(np.isfinite(o).all(1)))
    assert traced == [(padded.num_triangles, valid)]
    assert padded.triangles.shape[0] == padded.num_triangles + 500
    reference = _np(_cast("jax")(padded, o, rays[1]))
    np.testing.assert_array_equal(hits.triangle_id, reference.triangle_id)
