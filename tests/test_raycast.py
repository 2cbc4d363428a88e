"""Raycasting against independent references: a float64 brute force over all triangles, trimesh's
numpy intersector and trimesh's Embree intersector; packet sizes, metric t, invalid rays, jit/vmap
consistency and gradients.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from conftest import (
    NUM_RAYS,
    brute_force,
    cast,
    cast16,
    cast64,
    cast_padded,
    edge_margin,
    hits_triangle,
    mt_float64,
    random_scene,
    scene_mesh,
    trimesh_first,
)

from jaxloc.raycasting import raycast
from jaxloc.raycasting.bvh import build_bvh
from jaxloc.raycasting.traversal import _wide_nodes
from jaxloc.raycasting.triangle import T_MIN, triangle_hit
from jaxloc.scene import MEDIAN_DEPTH, SceneGraph

#: This module tests the pure-JAX engine (tests/test_engines.py compares the others with it).
jax_raycast = functools.partial(raycast, engine="jax")

MIN_AGREEMENT = 0.999
T_TOL = 1e-4  # metres


def _incidence_cos(scene, rays, tri):
    """|cos| between each ray and the normal of its triangle (float64); nan for -1."""
    tris = np.asarray(scene.triangles, np.float64)[np.maximum(tri, 0)]
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = rays[1].astype(np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.where(tri >= 0, np.abs(np.sum(n * d, 1)), np.nan)


def _object_of(scene, tri):
    return np.where(tri >= 0, np.asarray(scene.triangle_object)[np.maximum(tri, 0)], -1)


def _adjudicate(scene, rays, ours, ref_t, ref_tri, peer_tri):
    """For rays where a peer disagrees with us (object or hit/miss), check with the float64 brute
    force that our answer is right: the brute force agrees with us, or it is a near tie (our
    triangle is hit within a 1e-5 barycentric margin at the brute-force distance, +- 1e-4 m), or we
    missed a hit that lies within 1e-5 of a triangle edge. Returns the unexplained ray indices."""
    tris = np.asarray(scene.triangles)
    ours_obj = ours.object_id
    peer_obj = _object_of(scene, peer_tri)
    ref_obj = _object_of(scene, ref_tri)
    bad = np.flatnonzero(peer_obj != ours_obj)
    unexplained = []
    for i in bad:
        if ref_obj[i] == ours_obj[i]:
            continue
        ray = (rays[0][i : i + 1], rays[1][i : i + 1])
        if ours.triangle_id[i] >= 0:
            ok, t = hits_triangle(tris, *ray, ours.triangle_id[i : i + 1])
            if ok[0] and abs(t[0] - ref_t[i]) <= T_TOL:
                continue
        elif edge_margin(tris, *ray, ref_tri[i : i + 1])[0] < 1e-5:
            continue
        unexplained.append(int(i))
    return bad, unexplained


# ----------------------------------------------------------------------------- the kernel


def test_moller_trumbore_kernel_matches_float64_reference():
    rng = np.random.default_rng(3)
    n = 20000
    tris = rng.uniform(-1, 1, (n, 3, 3))
    origins = rng.uniform(-3, 3, (n, 3))
    # Aim at a point of the triangle's plane near it: about half the rays hit.
    w = rng.uniform(-0.4, 1.2, (n, 3))
    w /= w.sum(1, keepdims=True)
    target = np.einsum("nc,ncd->nd", w, tris)
    dirs = (target - origins) * rng.uniform(0.3, 3.0, (n, 1))
    v0, e1, e2 = tris[:, 0], tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]
    f32 = [a.astype(np.float32).T for a in (origins, dirs, v0, e1, e2)]  # (3, n) columns
    t = np.asarray(jax.jit(triangle_hit)(*f32))
    # Reference on the same float32 inputs, in float64 (t along the given direction).
    ref = [a.T.astype(np.float64) for a in f32]
    t_ref, u, v, det = mt_float64(*ref)
    hit_ref = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t_ref > T_MIN)
    margin = np.minimum(np.minimum(u, v), 1 - u - v)
    clear = np.abs(margin) > 1e-4  # not on an edge, where float32 may decide either way
    assert clear.mean() > 0.99 and 0.3 < hit_ref.mean() < 0.7
    np.testing.assert_array_equal(np.isfinite(t)[clear], hit_ref[clear])
    both = clear & hit_ref
    np.testing.assert_allclose(t[both], t_ref[both], rtol=1e-4)
    assert np.all(np.isinf(t[~np.isfinite(t)]))  # misses are +inf, never NaN
    assert not np.any(np.isnan(t))


def test_moller_trumbore_kernel_edge_cases():
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])  # in the plane z = 0
    degenerate = np.array([[0.0, 0, 0], [1, 1, 0], [2, 2, 0]])  # collinear: zero area
    cases = [  # (origin, direction, triangle, expected t)
        ([0.25, 0.25, 2.0], [0, 0, -1], tri, 2.0),  # front face, interior
        ([0.25, 0.25, -3.0], [0, 0, 2.0], tri, 1.5),  # back face (two-sided), t along d
        ([0.25, 0.25, 2.0], [0, 0, 1], tri, np.inf),  # triangle behind the origin
        ([0.25, 0.25, 0.0], [0, 0, -1], tri, np.inf),  # origin on the triangle: t = 0 < T_MIN
        ([-1.0, 0.25, 0.0], [1, 0, 0], tri, np.inf),  # parallel, in the plane
        ([0.25, 0.25, 1.0], [1, 0, 0], tri, np.inf),  # parallel, above
        ([0.8, 0.8, 1.0], [0, 0, -1], tri, np.inf),  # outside (u + v > 1)
        ([-0.1, 0.5, 1.0], [0, 0, -1], tri, np.inf),  # outside (u < 0)
        ([0.5, 0.5, 1.0], [0, 0, -1], degenerate, np.inf),  # degenerate triangle
        ([0.5, 0.5, 1.0], [0, 0, 0], tri, np.inf),  # zero direction
    ]
    cols = lambda k: np.array([np.asarray(c[k], np.float32) for c in cases]).T  # noqa: E731
    tris = np.array([c[2] for c in cases], np.float32)
    v0, e1, e2 = tris[:, 0].T, (tris[:, 1] - tris[:, 0]).T, (tris[:, 2] - tris[:, 0]).T
    t = np.asarray(triangle_hit(cols(0), cols(1), v0, e1, e2))
    np.testing.assert_allclose(t, [c[3] for c in cases], rtol=1e-6)


# ----------------------------------------------------------------------------- vs references


def test_raycast_matches_brute_force(scene, rays, hits, reference):
    t_ref, tri_ref, _ = reference
    obj_ref = _object_of(scene, tri_ref)
    assert 0.4 < hits.hit.mean() < 0.9  # the ray set mixes hits and misses
    assert scene.num_objects == 40 and scene.num_triangles > 1000
    np.testing.assert_array_equal(hits.hit, hits.triangle_id >= 0)
    np.testing.assert_array_equal(hits.hit, np.isfinite(hits.t))
    assert (hits.hit == (tri_ref >= 0)).mean() >= MIN_AGREEMENT
    assert (hits.object_id == obj_ref).mean() >= MIN_AGREEMENT
    assert (hits.triangle_id == tri_ref).mean() >= MIN_AGREEMENT
    np.testing.assert_array_equal(hits.object_id, _object_of(scene, hits.triangle_id))
    # Where we disagree, it must be a float32 near tie or an edge hit.
    _, unexplained = _adjudicate(scene, rays, hits, t_ref, tri_ref, tri_ref)
    assert unexplained == []


def test_raycast_depth_within_1e4_of_brute_force(scene, rays, hits, reference):
    t_ref, tri_ref, _ = reference
    same = (hits.triangle_id == tri_ref) & (tri_ref >= 0)
    err = np.abs(np.where(same, hits.t, 0.0) - np.where(same, t_ref, 0.0))
    cos = np.nan_to_num(_incidence_cos(scene, rays, tri_ref))
    # 1e-4 m for rays that are not grazing; grazing rays get the float32 conditioning allowance
    # (a 1e-6 rad rounding of the direction moves the hit by t * 1e-6 / cos).
    allowed = T_TOL + 1e-6 * np.where(same, t_ref, 0.0) / np.maximum(cos, 1e-12)
    assert np.all(err <= allowed), (err.max(), int(np.argmax(err - allowed)))
    assert np.all(err[same & (cos > 0.05)] <= T_TOL)


def test_raycast_t_is_close_to_brute_force(scene, rays, hits, reference):
    """A loose bound on every shared hit, and the barycentric coordinates."""
    t_ref, tri_ref, bary_ref = reference
    same = (hits.triangle_id == tri_ref) & (tri_ref >= 0)
    steep = same & (np.nan_to_num(_incidence_cos(scene, rays, tri_ref)) > 0.05)
    assert same.mean() > 0.4
    np.testing.assert_allclose(hits.t[same], t_ref[same], atol=5e-3)
    assert np.quantile(np.abs(hits.t[same] - t_ref[same]), 0.99) < T_TOL
    # Barycentric coordinates of the hit (used to interpolate colours), on non-grazing rays.
    np.testing.assert_allclose(hits.barycentric[steep], bary_ref[steep], atol=1e-3)
    assert np.all(hits.barycentric[~hits.hit] == 0) and np.all(hits.t[~hits.hit] == np.inf)
    np.testing.assert_allclose(hits.barycentric[hits.hit].sum(1), 1.0, atol=1e-5)


def test_raycast_matches_trimesh_numpy_intersector(scene, rays, hits, reference):
    peer = trimesh_first(scene_mesh(scene), *rays)
    agree = (_object_of(scene, peer) == hits.object_id).mean()
    assert agree >= MIN_AGREEMENT, agree
    _, unexplained = _adjudicate(scene, rays, hits, reference[0], reference[1], peer)
    assert unexplained == []


def test_raycast_matches_trimesh_embree(scene, rays, hits, reference):
    pytest.importorskip("embreex")
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    peer = RayMeshIntersector(scene_mesh(scene)).intersects_first(*rays)
    agree = (_object_of(scene, peer) == hits.object_id).mean()
    assert agree >= MIN_AGREEMENT, agree
    _, unexplained = _adjudicate(scene, rays, hits, reference[0], reference[1], peer)
    assert unexplained == []


def test_exact_nearest_hit_after_many_leaves(scene):
    """A ray whose path crosses the boxes of hundreds of triangles it never hits (slivers parallel
    to it) before the wall: a traversal capped at 50 leaves (the reference CUDA code) misses the
    wall; the exact traversal must find it, and the nearest of two walls."""
    slivers = []
    for i in range(400):
        x = 0.05 * i
        c = 0.002 * (1 + i % 7)  # plane y - z = c: parallel to the ray along +x at y = z = 0
        slivers.append([[x, -1, -1 - c], [x + 0.04, 1, 1 - c], [x, 1, 1 - c]])
    # Walls off-centre so that no ray runs through a face diagonal (an exact tie).
    wall = trimesh.creation.box(extents=[0.1, 4, 4]).apply_translation([25.0, 0.37, -0.21])
    far_wall = trimesh.creation.box(extents=[0.1, 4, 4]).apply_translation([27.0, 0.37, -0.21])
    sliver_mesh = trimesh.Trimesh(np.reshape(slivers, (-1, 3)), np.arange(1200).reshape(-1, 3))
    combs = SceneGraph.from_meshes(
        [sliver_mesh, far_wall, wall], [0, 1, 2], np.eye(3, 8), capacity=scene.capacity
    )
    origins = np.array([[-1.0, 0, 0], [-1.0, 0.0, 0.001], [-1.0, 0.3, 0.3], [-1, 0.0, 0.0]])
    dirs = np.array([[1.0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 1e-4, -1e-4]])
    hit = cast_padded(combs, origins, dirs)
    np.testing.assert_array_equal(hit.object_id, [2, 2, 2, 2])
    np.testing.assert_allclose(hit.t[:3], 25.95, atol=1e-4)
    tris = np.asarray(combs.triangles)[: combs.num_triangles]
    t_ref, tri_ref, _ = brute_force(tris, origins, dirs)
    np.testing.assert_array_equal(hit.triangle_id, tri_ref)


def test_wide_nodes_are_grandchildren_with_their_boxes(scene):
    """The 4-wide view of the BVH against a numpy reference built from the binary arrays."""
    refs, boxes = (np.asarray(a) for a in _wide_nodes(scene))
    children = np.asarray(scene.node_children)
    bounds = np.asarray(scene.node_bounds)
    num_nodes = children.shape[0]

    def row(ref):
        return num_nodes + (-ref - 2) if ref <= -2 else ref

    for node in range(num_nodes):
        if children[node, 0] == -1:  # capacity padding: never reached
            continue
        want = []
        for child in children[node]:
            want += list(children[child]) if child >= 0 else [child, -1]
        np.testing.assert_array_equal(refs[node], want)
        got = boxes[node].reshape(6, 4).T  # (4 children, lo xyz + hi xyz)
        for slot, ref in enumerate(want):
            if ref == -1:
                assert np.all(np.isnan(got[slot]))
            else:
                np.testing.assert_array_equal(got[slot], bounds[row(ref)])


def test_smallest_allowed_stack_gives_identical_hits(scene, rays, hits):
    """The 4-wide traversal's stack is sized from ``stack_size``; the smallest stack the scene
    accepts (tree depth + 1) must not drop any entry: the same hits as the default."""
    tris = np.asarray(scene.triangles)[: scene.num_triangles]
    depth = build_bvh(tris, leaf_size=scene.capacity.leaf_size, median_depth=MEDIAN_DEPTH).depth
    tight = random_scene(0, capacity=scene.capacity._replace(stack_size=depth + 1))
    assert tight.stack_size == depth + 1 < scene.stack_size
    other = jax.tree.map(np.asarray, cast(tight, *rays))
    np.testing.assert_array_equal(other.triangle_id, hits.triangle_id)
    np.testing.assert_array_equal(other.t, hits.t)


# ----------------------------------------------------------------------------- API behaviour


def test_packet_sizes_give_identical_results(scene, rays, hits):
    for fn in (cast16, cast64):
        other = jax.tree.map(np.asarray, fn(scene, *rays))
        np.testing.assert_array_equal(other.triangle_id, hits.triangle_id)
        np.testing.assert_array_equal(other.object_id, hits.object_id)
        np.testing.assert_array_equal(other.t, hits.t)
        np.testing.assert_array_equal(other.barycentric, hits.barycentric)


def test_non_unit_directions_give_metric_t(scene, rays, hits, reference):
    # Power-of-two scales keep the normalised direction bit-identical: t must not change.
    rng = np.random.default_rng(5)
    scale = (2.0 ** rng.integers(-12, 13, (NUM_RAYS, 1))).astype(np.float32)
    scaled = jax.tree.map(np.asarray, cast(scene, rays[0], rays[1] * scale))
    np.testing.assert_array_equal(scaled.t, hits.t)
    np.testing.assert_array_equal(scaled.triangle_id, hits.triangle_id)
    # And t is the metric distance to the hit point |p - o| (rays have lengths 0.2 .. 5 and more).
    lengths = np.linalg.norm(rays[1], axis=1)
    assert lengths.min() < 0.5 and lengths.max() > 3
    tris = np.asarray(scene.triangles, np.float64)[np.maximum(hits.triangle_id, 0)]
    point = np.einsum("rc,rcd->rd", hits.barycentric.astype(np.float64), tris)
    dist = np.linalg.norm(point - rays[0], axis=1)
    h = hits.hit & (_incidence_cos(scene, rays, hits.triangle_id) > 0.05)
    np.testing.assert_allclose(hits.t[h], dist[h], rtol=1e-3, atol=1e-3)


def test_invalid_rays_miss_without_nan(scene, rays, hits):
    o, d = rays[0].copy(), rays[1].copy()
    bad = np.arange(0, NUM_RAYS, 7)
    kinds = [
        ("zero direction", None, [0.0, 0.0, 0.0]),
        ("nan direction", None, [np.nan, 1.0, 0.0]),
        ("inf direction", None, [np.inf, 0.0, 0.0]),
        ("nan origin", [np.nan, 0.0, 0.0], None),
        ("inf origin", [0.0, -np.inf, 0.0], None),
    ]
    for j, i in enumerate(bad):
        _, origin, direction = kinds[j % len(kinds)]
        if origin is not None:
            o[i] = origin
        if direction is not None:
            d[i] = direction
    good = np.setdiff1d(np.arange(NUM_RAYS), bad)
    for fn in (cast, cast16):
        out = jax.tree.map(np.asarray, fn(scene, o, d))
        assert not np.any(np.isnan(out.t)) and not np.any(np.isnan(out.barycentric))
        assert np.all(out.t[bad] == np.inf)
        assert np.all(out.object_id[bad] == -1) and np.all(out.triangle_id[bad] == -1)
        assert not np.any(out.hit[bad]) and np.all(out.barycentric[bad] == 0)
        # The valid rays of the same packets are unaffected.
        np.testing.assert_array_equal(out.triangle_id[good], hits.triangle_id[good])
        np.testing.assert_array_equal(out.t[good], hits.t[good])


def test_bad_shapes_raise(scene):
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        raycast(scene, np.zeros((4, 2)), np.ones((4, 2)))
    empty = raycast(scene, np.zeros((0, 3)), np.ones((0, 3)))
    assert empty.t.shape == (0,) and empty.barycentric.shape == (0, 3)


def _assert_same_hits(a, b, scene, rays):
    """Two evaluations of the same rays: identical triangles/objects/hit flags (the traversal is
    exact), t and barycentric equal up to float32 re-association noise (XLA fuses the t/bary
    recomputation differently under jit/vmap), which the ill-conditioned float32 expression
    amplifies on grazing rays: 5e-5 relative for incidence cos > 0.05, looser below."""
    a, b = jax.tree.map(np.asarray, a), jax.tree.map(np.asarray, b)
    for name in ("triangle_id", "object_id", "hit"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    h = b.hit
    np.testing.assert_array_equal(a.t[~h], b.t[~h])
    np.testing.assert_array_equal(a.barycentric[~h], b.barycentric[~h])
    cos = np.nan_to_num(_incidence_cos(scene, rays, b.triangle_id))
    steep = h & (cos > 0.05)
    np.testing.assert_allclose(a.t[steep], b.t[steep], rtol=5e-5)
    np.testing.assert_allclose(a.barycentric[steep], b.barycentric[steep], atol=5e-4)
    grazing = h & ~steep
    allowed = 5e-5 * b.t + 1e-6 * b.t / np.maximum(cos, 1e-12)
    assert np.all(np.abs(a.t[grazing] - b.t[grazing]) <= allowed[grazing])


def test_jit_equals_eager(scene, rays, hits):
    _assert_same_hits(jax_raycast(scene, *rays), hits, scene, rays)


def test_vmap_equals_unbatched(scene, rays, hits):
    """vmap over 4 batches of rays equals one call on all of them (raycast is per ray, so the
    single call is the loop over batches, concatenated)."""
    o = rays[0].reshape(4, NUM_RAYS // 4, 3)
    d = rays[1].reshape(4, NUM_RAYS // 4, 3)
    vm = jax.jit(jax.vmap(jax_raycast, in_axes=(None, 0, 0)))(scene, o, d)
    flat = jax.tree.map(lambda x: np.asarray(x).reshape((NUM_RAYS,) + x.shape[2:]), vm)
    _assert_same_hits(flat, hits, scene, rays)


# ----------------------------------------------------------------------------- gradients


def _pick_clean_rays(scene, rays, hits, count):
    """Rays that hit well inside a triangle (margin > 0.05) at a steep angle (cos > 0.3)."""
    margin = edge_margin(np.asarray(scene.triangles), *rays, hits.triangle_id)
    cos = _incidence_cos(scene, rays, hits.triangle_id)
    idx = np.flatnonzero(hits.hit & (margin > 0.05) & (np.nan_to_num(cos) > 0.3))
    assert idx.size >= count
    return idx[:count]


def _sum_t(scene, o, d):
    t = jax_raycast(scene, o, d).t
    return jnp.sum(jnp.where(jnp.isfinite(t), t, 0.0))


#: d(sum of finite t)/d(origins, directions), compiled once for 64 rays and the shared capacity.
grad_t = jax.jit(jax.grad(_sum_t, argnums=(1, 2)))


def test_t_gradients_match_analytic_and_finite_differences(scene, rays, hits):
    """dt/do = -n / (n.u) and dt/dd = (I - u u^T) / |d| (-t n / (n.u)), u = d / |d|, in float64;
    and central finite differences of raycast itself."""
    idx = _pick_clean_rays(scene, rays, hits, 64)
    o, d = rays[0][idx], rays[1][idx]
    go, gd = map(np.asarray, grad_t(scene, o, d))
    tris = np.asarray(scene.triangles, np.float64)[hits.triangle_id[idx]]
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    norm = np.linalg.norm(d.astype(np.float64), axis=1, keepdims=True)
    u = d / norm
    nu = np.sum(n * u, 1, keepdims=True)
    t = hits.t[idx][:, None].astype(np.float64)
    want_o = -n / nu
    proj = np.eye(3)[None] - u[:, :, None] * u[:, None, :]
    want_d = np.einsum("rij,rj->ri", proj, -t * n / nu) / norm
    np.testing.assert_allclose(go, want_o, rtol=2e-3, atol=2e-3)
    np.testing.assert_allclose(gd, want_d, rtol=2e-3, atol=2e-3 * np.abs(want_d).max())
    # Central differences of t, all 2 x 3 x 2 perturbations of 32 rays in one padded cast.
    k = 32
    eps_o, eps_d = 1e-2, 1e-3 * norm[:k]
    po, pd = [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            step = np.zeros(3, np.float32)
            step[axis] = sign
            po += [o[:k] + eps_o * step, o[:k]]
            pd += [d[:k], d[:k] + eps_d * step]
    pert = cast_padded(scene, np.concatenate(po), np.concatenate(pd))
    t_p = pert.t.reshape(3, 2, 2, k)
    # Finite differences are only valid where every perturbed ray stays on the same triangle.
    same = np.all(pert.triangle_id.reshape(3, 2, 2, k) == hits.triangle_id[idx[:k]], axis=(0, 1))
    assert same[0].sum() >= 24 and same[1].sum() >= 24
    fd_o = (t_p[:, 0, 0] - t_p[:, 1, 0]).T / (2 * eps_o)
    fd_d = (t_p[:, 0, 1] - t_p[:, 1, 1]).T / (2 * eps_d)
    np.testing.assert_allclose(go[:k][same[0]], fd_o[same[0]], rtol=1e-2, atol=1e-2)
    scale = np.abs(fd_d[same[1]]).max()
    np.testing.assert_allclose(gd[:k][same[1]], fd_d[same[1]], rtol=2e-2, atol=2e-2 * scale)


def test_gradients_finite_for_misses_grazing_and_invalid_rays(room_scene):
    # Inside the closed 6 x 4 x 3 room: a ray grazing the floor (cos 1e-5), a clean hit, a ray
    # outside pointing away (miss), a zero direction and a NaN origin; padded to 64 rays.
    origins = np.array(
        [[1.0, 1.0, 1e-5], [3.0, 2.0, 1.5], [-5.0, 2.0, 1.5], [3.0, 2.0, 1.5], [np.nan, 0, 0]],
        np.float32,
    )
    dirs = np.array(
        [[1.0, 0.0, -1e-5], [1.0, 0.2, 0.1], [-1.0, 0, 0], [0.0, 0, 0], [1.0, 0, 0]], np.float32
    )
    o = np.concatenate([origins, np.tile(origins[2:3], (59, 1))])
    d = np.concatenate([dirs, np.tile(dirs[2:3], (59, 1))])
    hit = cast_padded(room_scene, o, d)
    np.testing.assert_array_equal(hit.hit[:5], [True, True, False, False, False])
    np.testing.assert_allclose(hit.t[0], 1.0, rtol=1e-3)  # reaches the floor at x = 2
    go, gd = map(np.asarray, grad_t(room_scene, o, d))
    assert np.all(np.isfinite(go)) and np.all(np.isfinite(gd))
    np.testing.assert_array_equal(go[2:], 0.0)
    np.testing.assert_array_equal(gd[2:], 0.0)
    # The clean ray's origin gradient is -n / (n.u): along x for the wall at x = 6.
    u = dirs[1] / np.linalg.norm(dirs[1])
    np.testing.assert_allclose(go[1], [-1.0 / u[0], 0, 0], rtol=1e-4, atol=1e-5)


def test_rays_through_shared_edges_do_not_leak(scene):
    quad = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]], process=False
    )
    floor = SceneGraph.from_meshes([quad], [0], np.eye(1, 8), capacity=scene.capacity)
    rng = np.random.default_rng(0)
    s = rng.uniform(0.1, 0.9, NUM_RAYS)
    target = np.stack([s, s, np.zeros_like(s)], 1)  # points on the shared diagonal x = y
    origins = target + rng.uniform([-2, -2, 0.5], [2, 2, 3], (NUM_RAYS, 3))
    hit = cast_padded(floor, origins, target - origins)
    assert np.all(hit.hit), f"{np.sum(~hit.hit)} of {NUM_RAYS} rays leaked through the edge"
