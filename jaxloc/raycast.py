"""Exact nearest-hit raycasting through the scene's BVH, with differentiable hit distances.

The kernel is written for ONE ray (:func:`_traverse`) and vmapped over chunks of rays. Traversal is
a ``lax.while_loop`` with a fixed-size stack (``scene.stack_size`` >= tree depth, so it can never
overflow): at an internal node both child boxes are tested, the nearer hit child is visited first and
the farther one pushed with its entry distance; popped entries farther than the best hit so far are
skipped. There is no cap on the number of leaves visited, so the hit is the exact nearest one (up to
float32 rounding of the Moller-Trumbore test, the same test a brute force over all triangles uses).

Distances ``t`` are metric: directions are normalised first, so ``t`` is the distance in metres from
the origin along the unit direction. Differentiability: the traversal runs on stop-gradient inputs
and only chooses the triangle; ``t`` and the barycentric coordinates are then recomputed from that
triangle's Moller-Trumbore expressions, so gradients flow to origins and directions (and so to
poses) and stay finite for grazing rays (guarded denominators). Rays with non-finite or zero
directions, or non-finite origins, report a miss.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.scene import SceneGraph

#: Hits closer than this (metres) are ignored, so a ray leaving a surface does not hit it again.
T_MIN = 1e-6
#: Moller-Trumbore determinant below which a ray counts as parallel to the triangle.
DET_EPS = 1e-12
#: Rays are processed in chunks of this many lanes: small enough to keep each chunk's traversal
#: state in cache and its while loop short, large enough to amortise per-iteration overhead.
DEFAULT_CHUNK = 2048


class RayHit(eqx.Module):
    """Nearest hits of a batch of rays (leading shape ``...`` of the inputs).

    Attributes:
        t: (...,) float32 metric distance along the unit direction; +inf on a miss.
        object_id: (...,) int32 hit object; -1 on a miss.
        triangle_id: (...,) int32 hit triangle (index into ``scene.triangles``); -1 on a miss.
        barycentric: (..., 3) float32 weights of the triangle's 3 corners; zeros on a miss.
        hit: (...,) bool.
    """

    t: Array
    object_id: Array
    triangle_id: Array
    barycentric: Array
    hit: Array


def _moller_trumbore(o, d, v0, e1, e2):
    """One ray vs triangles given as (3, ...) coordinate arrays; returns t, u, v, det (...)."""
    px = d[1] * e2[2] - d[2] * e2[1]
    py = d[2] * e2[0] - d[0] * e2[2]
    pz = d[0] * e2[1] - d[1] * e2[0]
    det = e1[0] * px + e1[1] * py + e1[2] * pz
    inv = 1.0 / jnp.where(jnp.abs(det) > DET_EPS, det, 1.0)
    sx, sy, sz = o[0] - v0[0], o[1] - v0[1], o[2] - v0[2]
    u = (sx * px + sy * py + sz * pz) * inv
    qx = sy * e1[2] - sz * e1[1]
    qy = sz * e1[0] - sx * e1[2]
    qz = sx * e1[1] - sy * e1[0]
    v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv
    t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv
    return t, u, v, det


def _triangle_hit(o, d, v0, e1, e2):
    """Moller-Trumbore with the acceptance test; t is +inf where the ray misses."""
    t, u, v, det = _moller_trumbore(o, d, v0, e1, e2)
    hit = (jnp.abs(det) > DET_EPS) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > T_MIN)
    return jnp.where(hit, t, jnp.inf)


def _box_entry(box, o, inv_d):
    """Slab test of rays against one box ``[lo, hi]`` (6,), coordinates written out (structure of
    arrays: ``o`` and ``inv_d`` are lists of 3 arrays); returns (entry clipped at 0, exit)."""
    near, far = [], []
    for axis in range(3):
        t1 = (box[axis] - o[axis]) * inv_d[axis]
        t2 = (box[axis + 3] - o[axis]) * inv_d[axis]
        near.append(jnp.minimum(t1, t2))
        far.append(jnp.maximum(t1, t2))
    t_near = jnp.maximum(jnp.maximum(jnp.maximum(near[0], near[1]), near[2]), 0.0)
    t_far = jnp.minimum(jnp.minimum(far[0], far[1]), far[2])
    return t_near, t_far


def _traverse_packet(scene: SceneGraph, origins: Array, directions: Array) -> Array:
    """Nearest-hit triangle of each ray of one packet of P rays (unit directions), -1 on a miss.

    The packet walks the tree together (one node gather per step for all P rays), each ray keeping
    its own best distance: a node is entered when any ray of the packet hits its box closer than
    that ray's best hit, so each ray's result is its own exact nearest hit. Children are visited
    nearer-first along the packet's mean ray; the farther child waits on the stack. A packet of one
    ray is the classic single-ray traversal. Rays with a non-finite origin never hit.
    """
    stack_size = scene.stack_size
    num_nodes, leaf_size = scene.node_children.shape[0], scene.leaf_triangle_ids.shape[1]
    safe_d = jnp.where(
        jnp.abs(directions) < 1e-20, jnp.where(directions < 0, -1e-20, 1e-20), directions
    )
    inv_d = 1.0 / safe_d
    ray_ok = jnp.all(jnp.isfinite(origins), axis=-1) & jnp.all(jnp.isfinite(directions), axis=-1)
    origins = jnp.where(ray_ok[:, None], origins, 0.0)
    weights = ray_ok.astype(origins.dtype)[:, None]
    mean_origin = jnp.sum(origins * weights, 0) / jnp.maximum(jnp.sum(weights), 1.0)
    mean_direction = jnp.sum(directions * weights, 0)
    slots = jnp.arange(stack_size)
    o_cols = [origins[:, i] for i in range(3)]
    inv_cols = [inv_d[:, i] for i in range(3)]
    o_bcast = [c[:, None] for c in o_cols]
    d_bcast = [directions[:, i, None] for i in range(3)]

    def row_of(ref):
        return jnp.where(ref <= -2, num_nodes - ref - 2, ref)

    def cond(state):
        return state[0] != -1

    def body(state):
        cur, sp, stack, best_t, best_slot = state
        is_leaf = cur <= -2
        near, far = _box_entry(scene.node_bounds[row_of(cur)], o_cols, inv_cols)
        enter = ray_ok & (near <= far) & (near < best_t)
        # Leaf: the entering rays test the leaf's triangles.
        leaf = jnp.where(is_leaf, -cur - 2, 0)
        tris = scene.leaf_triangles[leaf]
        t = _triangle_hit(o_bcast, d_bcast, tris[0:3], tris[3:6], tris[6:9])  # (P, K)
        t = jnp.where((enter & is_leaf)[:, None], t, jnp.inf)
        t_min = t[:, 0]
        for k in range(1, leaf_size):
            t_min = jnp.minimum(t_min, t[:, k])
        first = jnp.full(t_min.shape, leaf_size - 1, jnp.int32)
        for k in reversed(range(leaf_size - 1)):
            first = jnp.where(t[:, k] == t_min, k, first)
        better = t_min < best_t
        best_t = jnp.where(better, t_min, best_t)
        best_slot = jnp.where(better, leaf * leaf_size + first, best_slot)
        # Internal node entered by any ray: go to the nearer child, push the farther one.
        children = scene.node_children[jnp.where(is_leaf, 0, cur)]
        box0 = scene.node_bounds[row_of(children[0])]
        box1 = scene.node_bounds[row_of(children[1])]
        key0 = jnp.dot(box0[:3] + box0[3:] - 2.0 * mean_origin, mean_direction)
        key1 = jnp.dot(box1[:3] + box1[3:] - 2.0 * mean_origin, mean_direction)
        first_is_0 = key0 <= key1
        near_ref = jnp.where(first_is_0, children[0], children[1])
        far_ref = jnp.where(first_is_0, children[1], children[0])
        descend = jnp.any(enter) & ~is_leaf
        popped = jnp.where(sp > 0, stack[jnp.maximum(sp - 1, 0)], -1)
        next_ref = jnp.where(descend, near_ref, popped)
        stack = jnp.where(descend & (slots == sp), far_ref, stack)
        sp = jnp.where(descend, sp + 1, jnp.maximum(sp - 1, 0))
        return next_ref, sp, stack, best_t, best_slot

    num_rays = origins.shape[0]
    init = (
        jnp.where(jnp.any(ray_ok), scene.root, -1),
        jnp.int32(0),
        jnp.full((stack_size,), -1, jnp.int32),
        jnp.full((num_rays,), jnp.inf, jnp.float32),
        jnp.full((num_rays,), -1, jnp.int32),
    )
    best_slot = jax.lax.while_loop(cond, body, init)[4]
    flat_ids = scene.leaf_triangle_ids.reshape(-1)
    return jnp.where(best_slot >= 0, flat_ids[jnp.maximum(best_slot, 0)], -1)


def _safe_normalize(v: Array) -> tuple[Array, Array]:
    """Unit vectors (..., 3) and a validity mask; zero/non-finite vectors give (0, 0, 1), False."""
    sq = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = (sq > 0) & jnp.isfinite(sq)
    safe = jnp.where(ok, v, jnp.array([0.0, 0.0, 1.0], v.dtype))
    unit = safe * jax.lax.rsqrt(jnp.sum(safe * safe, axis=-1, keepdims=True))
    return unit, ok[..., 0]


def _differentiable_hit(scene: SceneGraph, origin, direction, triangle):
    """Recompute (t, barycentric) of one ray on a known triangle, differentiably."""
    hit = triangle >= 0
    origin = jnp.where(hit, origin, 0.0)
    direction = jnp.where(hit, direction, jnp.array([0.0, 0.0, 1.0], direction.dtype))
    tri = scene.triangles[jnp.maximum(triangle, 0)]
    v0 = tri[0]
    e1, e2 = tri[1] - v0, tri[2] - v0
    t, u, v, _ = _moller_trumbore(origin, direction, v0, e1, e2)
    t = jnp.where(hit, t, jnp.inf)
    bary = jnp.where(hit, jnp.stack([1.0 - u - v, u, v]), 0.0)
    return t, bary


def raycast(
    scene: SceneGraph,
    origins: Array,
    directions: Array,
    *,
    packet_size: int = 1,
    chunk_size: int = DEFAULT_CHUNK,
) -> RayHit:
    """Nearest hits of rays against the scene's meshes.

    Args:
        scene: the map.
        origins: (..., 3) ray origins, world frame, metres.
        directions: (..., 3) ray directions, world frame, any non-zero length (normalised here).
        packet_size: consecutive rays that traverse the tree together (static). Exact for any
            value; large packets (16-64) pay off when consecutive rays are coherent, e.g. a tile
            of one camera's rays, and 1 suits unrelated rays.
        chunk_size: rays per vmapped traversal batch (static). Both are speed knobs only.

    Returns:
        :class:`RayHit` with leading shape ``...``; ``t`` is in metres along the unit direction.
    """
    origins = jnp.asarray(origins, jnp.float32)
    directions = jnp.asarray(directions, jnp.float32)
    if origins.shape[-1:] != (3,) or directions.shape[-1:] != (3,):
        raise ValueError(
            f"origins and directions must have shape (..., 3), got {origins.shape} and {directions.shape}"
        )
    shape = jnp.broadcast_shapes(origins.shape, directions.shape)
    o = jnp.broadcast_to(origins, shape).reshape(-1, 3)
    d, ok = _safe_normalize(jnp.broadcast_to(directions, shape).reshape(-1, 3))
    o_search = jax.lax.stop_gradient(jnp.where(ok[:, None], o, jnp.nan))
    d_search = jax.lax.stop_gradient(d)
    num = o.shape[0]
    if num == 0:
        triangle = jnp.zeros((0,), jnp.int32)
    else:
        num_packets = -(-num // packet_size)
        pad = num_packets * packet_size - num
        o_packets = jnp.pad(o_search, ((0, pad), (0, 0)), constant_values=jnp.nan)
        d_packets = jnp.pad(d_search, ((0, pad), (0, 0)), constant_values=1.0)
        o_packets = o_packets.reshape(num_packets, packet_size, 3)
        d_packets = d_packets.reshape(num_packets, packet_size, 3)
        trace = lambda od: _traverse_packet(scene, od[0], od[1])  # noqa: E731
        batch = max(1, min(num_packets, chunk_size // packet_size))
        triangle = jax.lax.map(trace, (o_packets, d_packets), batch_size=batch)
        triangle = triangle.reshape(-1)[:num]
    t, bary = jax.vmap(lambda a, b, c: _differentiable_hit(scene, a, b, c))(o, d, triangle)
    hit = triangle >= 0
    object_id = jnp.where(hit, scene.triangle_object[jnp.maximum(triangle, 0)], -1)
    lead = shape[:-1]
    return RayHit(
        t=t.reshape(lead),
        object_id=object_id.reshape(lead),
        triangle_id=triangle.reshape(lead),
        barycentric=bary.reshape(lead + (3,)),
        hit=hit.reshape(lead),
    )
