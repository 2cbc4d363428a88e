"""Nearest hits of rays against a scene's meshes, with differentiable hit distances.

:func:`raycast` is the one entry point. An engine (:mod:`jaxloc.raycasting.engines`: the JAX BVH
traversal of :mod:`jaxloc.raycasting.traversal`, Embree or Warp) only chooses each ray's triangle,
on stop-gradient inputs; ``t``, the barycentric coordinates and the object id are then recomputed
here from that triangle in JAX, so gradients flow to origins and directions (and so to poses), stay
finite for grazing rays (guarded denominators), and do not depend on the engine.

Distances ``t`` are metric: directions are normalised first, so ``t`` is the distance in metres from
the origin along the unit direction. Rays with non-finite or zero directions, or non-finite
origins, report a miss.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.raycasting.bvh import BVHScene
from jaxloc.raycasting.engines import (
    nearest_hit,
    nearest_triangle,
    recomputes_hits,
    resolve_engine,
)
from jaxloc.raycasting.traversal import DEFAULT_CHUNK, nearest_leaf_triangles
from jaxloc.raycasting.triangle import DET_EPS, moller_trumbore


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


@jax.custom_jvp
def _inverse_norm(squared: Array) -> Array:
    """``1 / sqrt(squared)`` (inf at 0, NaN at NaN, 0 at inf), whose derivative is zero wherever
    that is not a positive finite number, so a zero-length ray gets a zero gradient, not NaN."""
    return jax.lax.rsqrt(squared)


@_inverse_norm.defjvp
def _inverse_norm_jvp(primals, tangents):
    (squared,), (d_squared,) = primals, tangents
    inv = jax.lax.rsqrt(squared)
    usable = jnp.isfinite(inv) & (inv > 0)
    return inv, jnp.where(usable, -0.5 * (inv / squared), 0.0) * d_squared  # jax's rsqrt rule


def _safe_normalize(v: Array) -> tuple[Array, Array]:
    """Unit vectors (..., 3) and a validity mask; zero/non-finite vectors give (0, 0, 1), False.

    The coordinates are written out (no reduction over the last axis), so XLA:CPU normalises in
    one fused pass with whatever produced ``v``; the mask is read off the inverse norm, so that
    XLA does not compute the norm (and ``v``'s producer) once more for it: 0.12 -> 0.09 s of the
    paper-scale stride-4 filter step (``benchmarks/step_trace.py``).
    """
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    inv = _inverse_norm(x * x + y * y + z * z)
    ok = jnp.isfinite(inv) & (inv > 0)
    fill = jnp.array([0.0, 0.0, 1.0], v.dtype)
    # inv is inf or NaN where not ok: the inner where keeps the product and its gradient finite
    return jnp.where(ok[..., None], v * jnp.where(ok, inv, 0.0)[..., None], fill), ok


@jax.jit  # one compiled fusion, eager or inside a jit: the same float32 rounding either way
def _differentiable_hit(o, d, tri, hit):
    """Recompute (t, barycentric) of rays on their known triangles, differentiably (where ``hit``
    is False: t = inf, barycentric 0). Coordinates are written out (lists of 3 arrays of any
    shape ``...``), as in :func:`moller_trumbore`: on (R,) columns XLA:CPU runs this ~2x faster
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
    _, u, v, _ = moller_trumbore(o, d, v0, e1, e2)
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


def _recompute(o: Array, d: Array, corners: Array, hit: Array) -> tuple[Array, Array]:
    """:func:`_differentiable_hit` on (R, 3) rays and (R, 9) corners."""
    return _differentiable_hit(
        [o[:, a] for a in range(3)],
        [d[:, a] for a in range(3)],
        [corners[:, k] for k in range(9)],
        hit,
    )


@jax.custom_jvp
def _hit_with_gradients(o, d, corners, hit, t, bary):
    """``(t, bary)`` as an engine computed them at its hit triangles, differentiated as the JAX
    recompute (:func:`_differentiable_hit`) at the same triangles: the forward pass pays for the
    hit once, and derivatives (to origins, directions and corners) equal the recompute's.

    Args: o, d (R, 3) rays (unit directions), corners (R, 9) the hit triangles' vertices, hit (R,)
    bool, t (R,) and bary (R, 3) the engine's values (inf and 0 on a miss).
    """
    return t, bary


@_hit_with_gradients.defjvp
def _hit_with_gradients_jvp(primals, tangents):
    o, d, corners, hit, t, bary = primals
    do, dd, dcorners = tangents[:3]
    _, (dt, dbary) = jax.jvp(
        lambda o, d, c: _recompute(o, d, c, hit), (o, d, corners), (do, dd, dcorners)
    )
    return (t, bary), (dt, dbary)


def hit_triangles(
    scene: BVHScene,
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
    return nearest_leaf_triangles(scene, origins, directions, valid, packet_size, chunk_size)


def _engine_values(
    scene: BVHScene, origins: Array, directions: Array, valid: Array, engine: str
) -> tuple[Array, Array, Array, Array]:
    """The values-only hits of ``engine`` ("embree" / "warp"): triangle (R,), ``t`` (R,),
    barycentric (R, 3) as the engine computed them, and the object (R,), padding triangles
    reported as misses (one gather of the triangles' objects serves both).
    """
    with jax.named_scope("hit_search"):
        triangle, t, u, v = nearest_hit(engine, scene.triangles, origins, directions, valid)
    with jax.named_scope("hit_values"):
        obj = scene.triangle_object[jnp.clip(triangle, 0, scene.triangles.shape[0] - 1)]
        hit = valid & (triangle >= 0) & (obj >= 0)
        u, v = jnp.where(hit, u, 0.0), jnp.where(hit, v, 0.0)
        w = jnp.where(hit, 1.0 - u - v, 0.0)
        return (
            jnp.where(hit, triangle, -1),
            jnp.where(hit, t, jnp.inf),
            jnp.stack([w, u, v], -1),
            jnp.where(hit, obj, -1),
        )


def raycast(
    scene: BVHScene,
    origins: Array,
    directions: Array,
    *,
    engine: str = "auto",
    differentiable: bool = True,
    packet_size: int = 1,
    chunk_size: int = DEFAULT_CHUNK,
) -> RayHit:
    """Nearest hits of rays against the scene's meshes.

    Args:
        scene: the map (a :class:`~jaxloc.SceneGraph`, or any :class:`BVHScene`).
        origins: (..., 3) ray origins, world frame, metres.
        directions: (..., 3) ray directions, world frame, any non-zero length (normalised here).
        engine: which engine finds the hit triangle (static): ``"jax"`` (the BVH traversal of
            :mod:`jaxloc.raycasting.traversal`), ``"embree"``, ``"warp"`` or ``"auto"`` (Embree
            on a CPU backend, Warp on a GPU backend where installed, else JAX); see
            :mod:`jaxloc.raycasting.engines`. ``t``, the barycentric coordinates, the object and
            the gradients are computed by the same JAX code whatever the engine.
        differentiable: static. True (the default): ``t`` and the barycentric coordinates are
            recomputed in JAX from the hit triangle, with gradients to ``origins`` and
            ``directions``. False, for code that only needs the values (the filter, retrieval):
            the ``"embree"`` and ``"warp"`` engines hand back the values they computed and the
            recompute is skipped (``"jax"`` recomputes as before); the same hits, ``t`` and
            barycentric coordinates to float rounding, and no gradient (the inputs are
            stop-gradient: derivatives through this path are zero).
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
    with jax.named_scope("ray_prep"):
        o = jnp.broadcast_to(origins, shape).reshape(-1, 3)
        d, ok = _safe_normalize(jnp.broadcast_to(directions, shape).reshape(-1, 3))
        ok &= jnp.isfinite(o[:, 0]) & jnp.isfinite(o[:, 1]) & jnp.isfinite(o[:, 2])
        d_search = jax.lax.stop_gradient(d)
    if engine != "jax" and (not differentiable or recomputes_hits(engine)):
        # The engines never trace the invalid rays, so their origins go in unmasked.
        o_search = jax.lax.stop_gradient(o)
        triangle, t, bary, object_id = _engine_values(scene, o_search, d_search, ok, engine)
        if differentiable:  # the engine's recompute, with the derivatives of JAX's
            with jax.named_scope("hit_values"):
                rows = scene.triangles.reshape(-1, 9)
                corners = rows.at[jnp.maximum(triangle, 0)].get(mode="promise_in_bounds")
                t, bary = _hit_with_gradients(o, d, corners, triangle >= 0, t, bary)
        hit = triangle >= 0
    else:
        o_search = jax.lax.stop_gradient(jnp.where(ok[:, None], o, 0.0))
        with jax.named_scope("hit_search"):
            triangle = hit_triangles(scene, o_search, d_search, ok, engine, packet_size, chunk_size)
        with jax.named_scope("hit_values"):
            # Ids are in [-1, T), so the clamped gather is always in bounds.
            rows = scene.triangles.reshape(-1, 9)
            corners = rows.at[jnp.maximum(triangle, 0)].get(mode="promise_in_bounds")  # (R, 9)
            if not differentiable:
                o, d = o_search, d_search
            t, bary = _recompute(o, d, corners, triangle >= 0)
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
