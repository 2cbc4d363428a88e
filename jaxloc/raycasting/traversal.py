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

The scene is anything with the BVH arrays of :class:`~jaxloc.raycasting.bvh.BVHScene` (a
:class:`~jaxloc.SceneGraph` is one); this module never differentiates: :mod:`jaxloc.raycasting.hits`
recomputes what needs gradients.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.raycasting.bvh import BVHScene
from jaxloc.raycasting.triangle import triangle_hit

#: Rays in flight in the traversal loop (lanes x packet size): enough lanes to amortise the loop's
#: per-iteration overhead (1024 lanes of the render's 8-ray packets beat 2048 on the benchmark
#: room), few enough that the loop state stays in cache.
DEFAULT_CHUNK = 8192
#: At most 1 / LEAF_LANE_FRACTION of the lanes test triangles in one iteration.
LEAF_LANE_FRACTION = 4


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


def _wide_nodes(scene: BVHScene) -> tuple[Array, Array]:
    """The 4-wide view of the binary BVH: each internal node's grandchildren.

    Returns ``refs`` (N, 4) int32, the references (see :mod:`jaxloc.raycasting.bvh`) of the node's
    up to four grandchildren (a child that is a leaf stands for itself; -1 marks an empty slot), and
    ``boxes`` (N, 24) float32, their AABBs laid out ``[lo_x(4), lo_y(4), lo_z(4), hi_x(4), hi_y(4),
    hi_z(4)]`` so that one gather brings a node's four child boxes as structure of arrays.
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


def _trace_packets(scene: BVHScene, origins: Array, directions: Array, lanes: int) -> Array:
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
        t = triangle_hit(
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


def _leaf_triangle(scene: BVHScene, origins: Array, directions: Array, leaf: Array) -> Array:
    """The nearest-hit triangle of each ray (R,) within its winning leaf (R,) (-1: a miss)."""
    hit = leaf >= 0
    leaf = jnp.maximum(leaf, 0)
    tri = scene.leaf_triangles[leaf]  # (R, 9, K)
    o = jnp.where(hit[:, None], origins, 0.0)
    t = triangle_hit(
        [o[:, a, None] for a in range(3)],
        [directions[:, a, None] for a in range(3)],
        [tri[:, a] for a in range(3)],
        [tri[:, a] for a in range(3, 6)],
        [tri[:, a] for a in range(6, 9)],
    )
    slot = jnp.argmin(t, axis=1)  # first of equal distances, as the traversal's test
    triangle = jnp.take_along_axis(scene.leaf_triangle_ids[leaf], slot[:, None], 1)[:, 0]
    return jnp.where(hit, triangle, -1)


def nearest_leaf_triangles(
    scene: BVHScene,
    origins: Array,
    directions: Array,
    valid: Array,
    packet_size: int = 1,
    chunk_size: int = DEFAULT_CHUNK,
) -> Array:
    """Nearest triangle (R,) int32 of each ray through the BVH, -1 on a miss (the "jax" engine).

    ``origins`` (R, 3) finite, ``directions`` (R, 3) finite unit vectors, no gradient; rays where
    ``valid`` (R,) is False miss. ``packet_size`` consecutive rays walk the tree together and
    ``chunk_size // packet_size`` packets are in flight (static speed knobs; exact for any value).
    """
    num = origins.shape[0]
    origins = jnp.where(valid[:, None], origins, jnp.nan)  # the traversal retires NaN rays
    num_packets = -(-num // packet_size)
    pad = num_packets * packet_size - num
    o_packets = jnp.pad(origins, ((0, pad), (0, 0)), constant_values=jnp.nan)
    d_packets = jnp.pad(directions, ((0, pad), (0, 0)), constant_values=1.0)
    o_packets = o_packets.reshape(num_packets, packet_size, 3)
    d_packets = d_packets.reshape(num_packets, packet_size, 3)
    leaf = _trace_packets(scene, o_packets, d_packets, chunk_size // packet_size)
    return _leaf_triangle(scene, origins, directions, leaf.reshape(-1)[:num])
