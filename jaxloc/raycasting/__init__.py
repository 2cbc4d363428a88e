"""Ray casting against triangle meshes: BVH build, traversal and the nearest-hit engines.

* :mod:`~jaxloc.raycasting.bvh`: the host-side BVH build (numpy) into flat arrays, and
  :class:`BVHScene`, the fields ray casting reads from a scene.
* :mod:`~jaxloc.raycasting.triangle`: one ray against one triangle (Moller-Trumbore).
* :mod:`~jaxloc.raycasting.traversal`: the pure-JAX BVH traversal (the ``"jax"`` engine).
* :mod:`~jaxloc.raycasting.engines`: which engine runs (``"auto"``, ``"jax"``, ``"embree"``,
  ``"warp"``); the engines themselves are :mod:`~jaxloc.raycasting.embree` and
  :mod:`~jaxloc.raycasting.warp`.
* :mod:`~jaxloc.raycasting.hits`: :func:`raycast`, the one entry point: an engine picks each ray's
  triangle, JAX recomputes the distance, barycentric coordinates and object differentiably.
"""

from jaxloc._lazy import public_names
from jaxloc.raycasting.bvh import (
    BVHScene as BVHScene,
    FlatBVH as FlatBVH,
    build_bvh as build_bvh,
)
from jaxloc.raycasting.engines import (
    ENGINES as ENGINES,
    clear_caches as clear_caches,
    resolve_engine as resolve_engine,
)
from jaxloc.raycasting.hits import (
    RayHit as RayHit,
    hit_triangles as hit_triangles,
    raycast as raycast,
)

__all__ = public_names(__file__)
