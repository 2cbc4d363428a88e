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

from jaxloc.raycasting.bvh import BVHScene, FlatBVH, build_bvh
from jaxloc.raycasting.engines import ENGINES, clear_caches, resolve_engine
from jaxloc.raycasting.hits import RayHit, hit_triangles, raycast

__all__ = [
    "ENGINES",
    "BVHScene",
    "FlatBVH",
    "RayHit",
    "build_bvh",
    "clear_caches",
    "hit_triangles",
    "raycast",
    "resolve_engine",
]
