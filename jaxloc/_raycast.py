"""Exact nearest-hit raycasting through the scene's BVH, with differentiable hit distances.

Rays are grouped into packets of P consecutive rays that walk the tree together, and the packets
are traced by one ``lax.while_loop`` over B *lanes* (persistent lanes): each lane holds one packet,
and a lane whose packet is finished writes its result and takes the next packet from a queue in the
same loop, so the loop never waits for the slowest packet of a fixed chunk. One iteration advances
every lane by one step:

* the tree is walked 4-wide: the binary BVH's internal node n stands for its (up to) four
  grandchildren (a child that is a leaf stands for itself), whose boxes are gathered once per
  scene into one row per node (:func:`_wide_nodes`), so one iteration descends two binary levels.
  A lane at an internal node tests the four boxes for its P rays (one gather); a child is entered
  when some ray hits its box closer than that ray's best hit so far. The entered children are
  sorted by entry distance (the nearest entry over the packet's rays); the lane moves to the
  nearest and pushes the others, farthest first, on its fixed-size stack
  (3 * (``scene.stack_size`` // 2 + 1) entries >= 3 per wide level of a tree of depth <
  ``scene.stack_size``, so it can never overflow); with none entered it pops. Halving the steps
  halved the traversal time against the binary walk on the benchmark room
  (benchmarks/results/raycast_cpu.md): the loop's cost is per step, far more than per box.
* lanes at a leaf are compacted (up to B / 4 per iteration; the others wait one iteration) and only
  they test their P rays against the leaf's K triangles (Moller-Trumbore, coordinates written out),
  so the triangle test is not paid by the far more numerous internal-node steps. Each ray keeps its
  best distance and the leaf that gave it; the lane then pops.

Nothing bounds the number of leaves visited, so each ray's result is its exact nearest hit (up to
float32 rounding of the Moller-Trumbore test, the same test a brute force over all triangles uses);
the triangle within the winning leaf is picked afterwards by re-testing that leaf's K triangles.

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

from jaxloc._engines import nearest_triangle, resolve_engine
from jaxloc.scene import SceneGraph

#: Hits closer than this (metres) are ignored, so a ray leaving a surface does not hit it again.
T_MIN = 1e-6
#: Moller-Trumbore determinant below which a ray counts as parallel to the triangle.
DET_EPS = 1e-12
#: Barycentric slack of the acceptance test: float32 rounding of u and v must not let a ray through
#: an edge shared by two triangles miss both (a "leak" through a closed surface). Triangles grow by
#: this fraction of their size, which is far below the meshes' accuracy.
EDGE_EPS = 1e-5
#: Rays in flight in the traversal loop (lanes x packet size): enough lanes to amortise the loop's
#: per-iteration overhead (1024 lanes of the render's 8-ray packets beat 2048 on the benchmark
#: room), few enough that the loop state stays in cache.
DEFAULT_CHUNK = 8192
#: At most 1 / LEAF_LANE_FRACTION of the lanes test triangles in one iteration.
LEAF_LANE_FRACTION = 4


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
    inside = (u >= -EDGE_EPS) & (v >= -EDGE_EPS) & (u + v <= 1.0 + EDGE_EPS)
    hit = (jnp.abs(det) > DET_EPS) & inside & (t > T_MIN)
    return jnp.where(hit, t, jnp.inf)


def _child_entry(boxes, o, inv_d):
    """Slab test of P rays against each lane's C child boxes, coordinates written out (structure
    of arrays). ``boxes`` is a list of 6 arrays ``[lo_x, lo_y, lo_z, hi_x, hi_y, hi_z]`` (B, C, 1),
    ``o`` and ``inv_d`` lists of 3 arrays (B, 1, P). Returns (entry clipped at 0, exit) (B, C, P).
    """
    near = far = None
    for axis in range(3):
        t1 = (boxes[axis] - o[axis]) * inv_d[axis]
        t2 = (boxes[axis + 3] - o[axis]) * inv_d[axis]
        lo, hi = jnp.minimum(t1, t2), jnp.maximum(t1, t2)
        near = lo if near is None else jnp.maximum(near, lo)
        far = hi if far is None else jnp.minimum(far, hi)
    return jnp.maximum(near, 0.0), far


#: Children per node of the 4-wide tree the traversal walks (two binary levels collapsed).
WIDTH = 4


def _wide_nodes(scene: SceneGraph) -> tuple[Array, Array]:
    """The 4-wide view of the binary BVH: each internal node's grandchildren.

    Returns ``refs`` (N, 4) int32, the references (see :mod:`jaxloc.bvh`) of the node's up to four
    grandchildren (a child that is a leaf stands for itself; -1 marks an empty slot), and ``boxes``
    (N, 24) float32, their AABBs laid out ``[lo_x(4), lo_y(4), lo_z(4), hi_x(4), hi_y(4), hi_z(4)]``
    so that one gather brings a node's four child boxes as structure of arrays.
    """
    num_nodes = scene.node_children.shape[0]
    children = scene.node_children
    inner = children >= 0  # (N, 2)
    grand = children[jnp.maximum(children, 0)]  # (N, 2, 2)
    first = jnp.where(inner, grand[..., 0], children)
    second = jnp.where(inner, grand[..., 1], -1)
    refs = jnp.stack([first, second], -1).reshape(num_nodes, WIDTH)
    rows = jnp.where(refs <= -2, num_nodes - refs - 2, jnp.maximum(refs, 0))
    boxes = scene.node_bounds[rows]  # (N, 4, 6)
    boxes = jnp.where((refs == -1)[..., None], jnp.nan, boxes)  # NaN boxes are never entered
    return refs, boxes.transpose(0, 2, 1).reshape(num_nodes, 6 * WIDTH)


def _sort_children(keys: list[Array], refs: list[Array]) -> tuple[list[Array], list[Array]]:
    """Sort each lane's four (entry distance, reference) pairs by distance: a 5-exchange network."""
    keys, refs = list(keys), list(refs)
    for a, b in ((0, 1), (2, 3), (0, 2), (1, 3), (1, 2)):
        swap = keys[b] < keys[a]
        keys[a], keys[b] = jnp.where(swap, keys[b], keys[a]), jnp.where(swap, keys[a], keys[b])
        refs[a], refs[b] = jnp.where(swap, refs[b], refs[a]), jnp.where(swap, refs[a], refs[b])
    return keys, refs


def _trace_packets(scene: SceneGraph, origins: Array, directions: Array, lanes: int) -> Array:
    """Leaf holding the nearest hit of each ray, -1 on a miss: (Q, P) for Q packets of P rays.

    ``origins`` (Q, P, 3) may be NaN for invalid rays; ``directions`` (Q, P, 3) are unit vectors.
    ``lanes`` packets are in flight at once (see the module docstring for the algorithm).
    """
    num_packets, packet = origins.shape[:2]
    # Each 4-wide step pushes at most 3 references and descends two binary levels.
    stack_size = (WIDTH - 1) * (scene.stack_size // 2 + 1)
    lanes = max(1, min(lanes, num_packets))
    leaf_lanes = max(1, lanes // LEAF_LANE_FRACTION)
    wide_refs, wide_boxes = _wide_nodes(scene)

    safe_d = jnp.where(
        jnp.abs(directions) < 1e-20, jnp.where(directions < 0, -1e-20, 1e-20), directions
    )
    ray_ok = jnp.all(jnp.isfinite(origins), -1) & jnp.all(jnp.isfinite(directions), -1)
    origins = jnp.where(ray_ok[..., None], origins, 0.0)
    # (Q, 9, P): origin, direction, inverse direction, one contiguous row per packet.
    rays_all = jnp.concatenate([origins, directions, 1.0 / safe_d], -1).transpose(0, 2, 1)
    packet_ok = jnp.any(ray_ok, 1)
    lane_ids = jnp.arange(lanes)

    def step(cur, sp, stack, best_t, best_leaf, rays, ok):
        is_leaf, is_node = cur <= -2, cur >= 0
        # Internal nodes: slab test of the four grandchildren for all P rays.
        node = jnp.where(is_node, cur, 0)
        boxes = wide_boxes[node].reshape(lanes, 6, WIDTH, 1)
        o = [rays[:, None, a] for a in range(3)]
        inv_d = [rays[:, None, 6 + a] for a in range(3)]
        near, far = _child_entry([boxes[:, a] for a in range(6)], o, inv_d)
        enter = ok[:, None] & (near <= far) & (near < best_t[:, None])
        key = jnp.min(jnp.where(enter, near, jnp.inf), 2)  # (B, 4) nearest entry; inf: not entered
        key = jnp.where(is_node[:, None], key, jnp.inf)
        refs = wide_refs[node]
        keys, refs = _sort_children(
            [key[:, c] for c in range(WIDTH)], [refs[:, c] for c in range(WIDTH)]
        )
        entered = [k < jnp.inf for k in keys]
        # Leaves: compact up to leaf_lanes lanes, test their rays against the leaf's triangles.
        rank = jnp.cumsum(is_leaf) - 1
        chosen = is_leaf & (rank < leaf_lanes)
        lane_of = jnp.full((leaf_lanes,), lanes, jnp.int32)
        lane_of = lane_of.at[jnp.where(chosen, rank, leaf_lanes)].set(lane_ids, mode="drop")
        src = jnp.minimum(lane_of, lanes - 1)
        leaf = jnp.where(lane_of < lanes, -cur[src] - 2, 0)
        tri = scene.leaf_triangles[leaf]  # (M, 9, K)
        tri = [tri[:, a, None, :] for a in range(9)]
        r = rays[src]
        t = _triangle_hit(
            [r[:, a, :, None] for a in range(3)],
            [r[:, 3 + a, :, None] for a in range(3)],
            tri[0:3],
            tri[3:6],
            tri[6:9],
        )
        t_min = jnp.where(ok[src], jnp.min(t, 2), jnp.inf)  # (M, P)
        t_lane = jnp.full((lanes, packet), jnp.inf, jnp.float32)
        t_lane = t_lane.at[lane_of].set(t_min, mode="drop")  # back to the lanes
        better = t_lane < best_t
        best_t = jnp.where(better, t_lane, best_t)
        best_leaf = jnp.where(better, (-cur - 2)[:, None], best_leaf)
        # Next reference: the nearest entered child; the other entered ones go on the stack,
        # farthest first, so the nearest of them is popped first.
        pushes = entered[1] * 1 + entered[2] * 1 + entered[3] * 1
        for j in range(WIDTH - 1):
            # slot sp + j gets the (pushes - j)-th nearest of the pushed children
            value = jnp.where(
                pushes - j == 3, refs[3], jnp.where(pushes - j == 2, refs[2], refs[1])
            )
            where = jnp.where(j < pushes, sp + j, stack_size)
            stack = stack.at[lane_ids, where].set(value, mode="drop")
        wait = is_leaf & ~chosen
        top = stack[lane_ids, jnp.maximum(sp - 1, 0)]
        popped = jnp.where(sp > 0, top, -1)
        nxt = jnp.where(entered[0], refs[0], jnp.where(wait, cur, popped))
        sp = jnp.where(entered[0], sp + pushes, jnp.where(wait, sp, jnp.maximum(sp - 1, 0)))
        return nxt, sp, stack, best_t, best_leaf

    def refill(state):
        """Finished lanes write their packet's result and take the next packets of the queue."""
        cur, sp, stack, best_t, best_leaf, rays, ok, pkt, queue, out = state
        done = (cur == -1) & (pkt < num_packets)
        out = out.at[jnp.where(done, pkt, num_packets)].set(best_leaf, mode="drop")
        new = jnp.where(done, jnp.minimum(queue + jnp.cumsum(done) - 1, num_packets), pkt)
        src = jnp.minimum(new, num_packets - 1)
        rays = jnp.where(done[:, None, None], rays_all[src], rays)
        ok = jnp.where(done[:, None], ray_ok[src], ok)
        start = jnp.where((new < num_packets) & packet_ok[src], scene.root, -1)
        cur = jnp.where(done, start, cur)
        sp = jnp.where(done, 0, sp)
        best_t = jnp.where(done[:, None], jnp.inf, best_t)
        best_leaf = jnp.where(done[:, None], -1, best_leaf)
        queue = jnp.minimum(queue + jnp.sum(done), num_packets)
        return cur, sp, stack, best_t, best_leaf, rays, ok, new, queue, out

    def body(state):
        cur, sp, stack, best_t, best_leaf, rays, ok, pkt, queue, out = state
        cur, sp, stack, best_t, best_leaf = step(cur, sp, stack, best_t, best_leaf, rays, ok)
        state = (cur, sp, stack, best_t, best_leaf, rays, ok, pkt, queue, out)
        any_done = jnp.any((cur == -1) & (pkt < num_packets))
        return jax.lax.cond(any_done, refill, lambda s: s, state)

    init = (
        jnp.where(packet_ok[:lanes], scene.root, -1),
        jnp.zeros((lanes,), jnp.int32),
        jnp.full((lanes, stack_size), -1, jnp.int32),
        jnp.full((lanes, packet), jnp.inf, jnp.float32),
        jnp.full((lanes, packet), -1, jnp.int32),
        rays_all[:lanes],
        ray_ok[:lanes],
        lane_ids,
        jnp.int32(lanes),
        jnp.full((num_packets, packet), -1, jnp.int32),
    )
    return jax.lax.while_loop(lambda s: jnp.any(s[7] < num_packets), body, init)[-1]


def _leaf_triangle(scene: SceneGraph, origins: Array, directions: Array, leaf: Array) -> Array:
    """The nearest-hit triangle of each ray (R,) within its winning leaf (R,) (-1: a miss)."""
    hit = leaf >= 0
    leaf = jnp.maximum(leaf, 0)
    tri = scene.leaf_triangles[leaf]  # (R, 9, K)
    o = jnp.where(hit[:, None], origins, 0.0)
    t = _triangle_hit(
        [o[:, a, None] for a in range(3)],
        [directions[:, a, None] for a in range(3)],
        [tri[:, a] for a in range(3)],
        [tri[:, a] for a in range(3, 6)],
        [tri[:, a] for a in range(6, 9)],
    )
    slot = jnp.argmin(t, axis=1)  # first of equal distances, as the traversal's test
    triangle = jnp.take_along_axis(scene.leaf_triangle_ids[leaf], slot[:, None], 1)[:, 0]
    return jnp.where(hit, triangle, -1)


def _safe_normalize(v: Array) -> tuple[Array, Array]:
    """Unit vectors (..., 3) and a validity mask; zero/non-finite vectors give (0, 0, 1), False."""
    sq = jnp.sum(v * v, axis=-1, keepdims=True)
    ok = (sq > 0) & jnp.isfinite(sq)
    safe = jnp.where(ok, v, jnp.array([0.0, 0.0, 1.0], v.dtype))
    unit = safe * jax.lax.rsqrt(jnp.sum(safe * safe, axis=-1, keepdims=True))
    return unit, ok[..., 0]


@jax.jit  # one compiled fusion, eager or inside a jit: the same float32 rounding either way
def _differentiable_hit(o, d, tri, hit):
    """Recompute (t, barycentric) of rays on their known triangles, differentiably (where ``hit``
    is False: t = inf, barycentric 0). Coordinates are written out (lists of 3 arrays of any
    shape ``...``), as in :func:`_moller_trumbore`: on (R,) columns XLA:CPU runs this ~2x faster
    than a vmap over (R, 3) rows.

    Args:
        o, d: ray origins and unit directions, 3 arrays each. tri: the triangles' 9 coordinates
            (v0, v1, v2, x y z each). hit: (...) bool.

    Returns:
        ``t`` (...) and ``barycentric`` (..., 3). ``t`` uses the plane form
        ``n . (v0 - o) / (n . d)`` with ``n = e1 x e2``, which keeps float32 errors ~30x smaller
        than Moller-Trumbore's triple product for small, distant triangles; the barycentric
        coordinates come from Moller-Trumbore (clipped to the triangle).
    """
    o = [jnp.where(hit, c, 0.0) for c in o]
    d = [jnp.where(hit, c, fill) for c, fill in zip(d, (0.0, 0.0, 1.0), strict=True)]
    v0 = tri[0:3]
    e1 = [tri[3 + a] - v0[a] for a in range(3)]
    e2 = [tri[6 + a] - v0[a] for a in range(3)]
    _, u, v, _ = _moller_trumbore(o, d, v0, e1, e2)
    normal = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ]
    facing = sum(normal[a] * d[a] for a in range(3))
    facing = jnp.where(jnp.abs(facing) > DET_EPS, facing, 1.0)
    t = jnp.where(hit, sum(normal[a] * (v0[a] - o[a]) for a in range(3)) / facing, jnp.inf)
    u, v = jnp.clip(u, 0.0, 1.0), jnp.clip(v, 0.0, 1.0)
    bary = jnp.where(hit[..., None], jnp.stack([1.0 - u - v, u, v], -1), 0.0)
    return t, bary


def hit_triangles(
    scene: SceneGraph,
    origins: Array,
    directions: Array,
    valid: Array,
    engine: str,
    packet_size: int = 1,
    chunk_size: int = DEFAULT_CHUNK,
) -> Array:
    """The engine's hit search alone: nearest triangle (R,) int32 of each ray, -1 on a miss.

    ``origins`` (R, 3) finite, ``directions`` (R, 3) finite unit vectors (both without gradient);
    rays where ``valid`` (R,) is False miss. ``engine`` is resolved ("jax", "embree" or "warp").
    A padding triangle is never reported.
    """
    num = origins.shape[0]
    if num == 0:
        return jnp.zeros((0,), jnp.int32)
    if engine != "jax":
        triangle = nearest_triangle(engine, scene.triangles, origins, directions, valid)
        real = scene.triangle_object[jnp.clip(triangle, 0, scene.triangles.shape[0] - 1)] >= 0
        return jnp.where(valid & (triangle >= 0) & real, triangle, -1)
    origins = jnp.where(valid[:, None], origins, jnp.nan)  # the traversal retires NaN rays
    num_packets = -(-num // packet_size)
    pad = num_packets * packet_size - num
    o_packets = jnp.pad(origins, ((0, pad), (0, 0)), constant_values=jnp.nan)
    d_packets = jnp.pad(directions, ((0, pad), (0, 0)), constant_values=1.0)
    o_packets = o_packets.reshape(num_packets, packet_size, 3)
    d_packets = d_packets.reshape(num_packets, packet_size, 3)
    leaf = _trace_packets(scene, o_packets, d_packets, chunk_size // packet_size)
    return _leaf_triangle(scene, origins, directions, leaf.reshape(-1)[:num])


def raycast(
    scene: SceneGraph,
    origins: Array,
    directions: Array,
    *,
    engine: str = "auto",
    packet_size: int = 1,
    chunk_size: int = DEFAULT_CHUNK,
) -> RayHit:
    """Nearest hits of rays against the scene's meshes.

    Args:
        scene: the map.
        origins: (..., 3) ray origins, world frame, metres.
        directions: (..., 3) ray directions, world frame, any non-zero length (normalised here).
        engine: which engine finds the hit triangle (static): ``"jax"`` (this module's BVH
            traversal), ``"embree"``, ``"warp"`` or ``"auto"`` (Embree on a CPU backend, Warp on
            a GPU backend where installed, else JAX); see :mod:`jaxloc._engines`. ``t``, the
            barycentric coordinates, the object and the gradients are computed by the same JAX
            code whatever the engine.
        packet_size: consecutive rays that traverse the tree together (static, ``"jax"`` engine).
            Exact for any value; packets of 8 to 16 pay off when consecutive rays are coherent,
            e.g. a 2 x 4 or 4 x 4 tile of one camera's rays, and 1 suits unrelated rays.
        chunk_size: rays in flight in the traversal loop (static, ``"jax"`` engine):
            ``chunk_size // packet_size`` lanes. Both are speed knobs only.

    Returns:
        :class:`RayHit` with leading shape ``...``; ``t`` is in metres along the unit direction.

    Raises:
        ValueError: bad shapes or an unknown engine.
        ImportError: an engine asked for by name whose package is not installed.
    """
    engine = resolve_engine(engine)
    origins = jnp.asarray(origins, jnp.float32)
    directions = jnp.asarray(directions, jnp.float32)
    if origins.shape[-1:] != (3,) or directions.shape[-1:] != (3,):
        raise ValueError(
            "origins and directions must have shape (..., 3), "
            f"got {origins.shape} and {directions.shape}"
        )
    shape = jnp.broadcast_shapes(origins.shape, directions.shape)
    o = jnp.broadcast_to(origins, shape).reshape(-1, 3)
    d, ok = _safe_normalize(jnp.broadcast_to(directions, shape).reshape(-1, 3))
    ok &= jnp.all(jnp.isfinite(o), axis=1)
    o_search = jax.lax.stop_gradient(jnp.where(ok[:, None], o, 0.0))
    triangle = hit_triangles(
        scene, o_search, jax.lax.stop_gradient(d), ok, engine, packet_size, chunk_size
    )
    hit = triangle >= 0
    # Ids are in [-1, T), so the clamped gather is always in bounds.
    rows = scene.triangles.reshape(-1, 9)
    corners = rows.at[jnp.maximum(triangle, 0)].get(mode="promise_in_bounds")  # (R, 9)
    t, bary = _differentiable_hit(
        [o[:, a] for a in range(3)],
        [d[:, a] for a in range(3)],
        [corners[:, k] for k in range(9)],
        hit,
    )
    object_id = jnp.where(hit, scene.triangle_object[jnp.maximum(triangle, 0)], -1)
    lead = shape[:-1]
    return RayHit(
        t=t.reshape(lead),
        object_id=object_id.reshape(lead),
        triangle_id=triangle.reshape(lead),
        barycentric=bary.reshape(lead + (3,)),
        hit=hit.reshape(lead),
    )
