"""Nearest-hit engines: which triangle each ray hits first, found by JAX, Embree or Warp.

An engine only *chooses* the triangle, on stop-gradient rays; :func:`jaxloc.raycast` then computes
``t``, the barycentric coordinates, the object id and every gradient with the same JAX code for all
engines, so jit, vmap, ``lax.scan``, grads and the trace count behave identically (the DiffeRT
pattern: a fast engine picks, JAX differentiates). Code that never differentiates (the filter,
retrieval) asks ``raycast(..., differentiable=False)`` instead: Embree and Warp then hand back the
distance and barycentric coordinates they computed anyway (:func:`nearest_hit`), and the JAX
recompute is skipped; the ``"jax"`` engine keeps the recompute on both paths.

* ``"jax"``: the BVH traversal of :mod:`jaxloc.raycasting.traversal`; portable to any backend, no
  optional
  dependency, the reference.
* ``"embree"``: Intel Embree through embreex (trimesh's own binding), called from the traced
  program as a named XLA:CPU custom call on a CPU backend (XLA's buffers in place, no copies; the
  program can be kept in JAX's persistent compilation cache) and with :func:`jax.pure_callback`
  elsewhere; the rays are split over a thread pool as wide as the machine (``embreex``'s ``run``
  releases the GIL). Host memory: on a GPU backend the rays make a round trip to the host.
* ``"warp"``: NVIDIA Warp's ``mesh_query_ray`` through ``warp.jax_callable`` (zero copy, CPU and
  CUDA). Warp's CPU backend runs one thread; its point is the GPU.
* ``"auto"``: Embree on a CPU backend and Warp on a GPU backend where installed, else ``"jax"``.

The engines' acceleration structures are built on first use of a map and cached
(:mod:`jaxloc.raycasting._cache`); the engines live in :mod:`jaxloc.raycasting.embree` and
:mod:`jaxloc.raycasting.warp`, and this module is the one place that picks one.
"""

from __future__ import annotations

import functools
import importlib.util

import jax
from jax import Array

from jaxloc.raycasting import embree, warp

#: Every engine name :func:`jaxloc.raycast` accepts.
ENGINES = ("auto", "jax", "embree", "warp")
#: The package that provides each optional engine, and how to install it.
_PACKAGES = {
    "embree": ("embreex", "pip install embreex (a jaxloc dependency where wheels exist)"),
    "warp": ("warp", 'pip install "jaxloc[gpu]" (or: pip install warp-lang)'),
}


@functools.cache
def is_installed(engine: str) -> bool:
    """Whether the package of ``engine`` ("embree" or "warp") can be imported."""
    return importlib.util.find_spec(_PACKAGES[engine][0]) is not None


def check_engine_name(engine: str) -> None:
    """Raise a ValueError unless ``engine`` is one of :data:`ENGINES` (for configs)."""
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, got {engine!r}")


def resolve_engine(engine: str) -> str:
    """The concrete engine ("jax", "embree" or "warp") that ``engine`` names; static.

    Raises:
        ValueError: an unknown name.
        ImportError: an optional engine asked for by name whose package is not installed (naming
            the package to install). ``"auto"`` never raises.
    """
    check_engine_name(engine)
    if engine == "auto":
        backend = jax.default_backend()
        if backend == "cpu" and is_installed("embree"):
            return "embree"
        if backend in ("gpu", "cuda") and is_installed("warp"):
            return "warp"
        return "jax"
    if engine != "jax" and not is_installed(engine):
        package, hint = _PACKAGES[engine]
        raise ImportError(f'engine="{engine}" needs the {package} package: {hint}')
    return engine


def recomputes_hits(engine: str) -> bool:
    """Whether ``engine``'s values (:func:`nearest_hit`) are the JAX recompute of
    :func:`jaxloc.raycast` or better (the same formulas on the hit triangle, in double
    precision): true of the native Embree engine, which :func:`jaxloc.raycast` then trusts on its
    differentiable path too (the hit paid for once, derivatives from the JAX recompute). Static
    (at trace time)."""
    return engine == "embree" and embree.native_values()


def nearest_triangle(
    engine: str, triangles: Array, origins: Array, directions: Array, valid: Array
) -> Array:
    """Index (R,) int32 of the triangle each ray hits first, -1 on a miss, for "embree" / "warp".

    Args:
        engine: "embree" or "warp" (resolved; see :func:`resolve_engine`).
        triangles: (T, 3, 3) float32 vertices, world frame; all-zero padding rows are left out.
        origins: (R, 3) float32, finite.
        directions: (R, 3) float32 finite unit directions.
        valid: (R,) bool; the other rays are not traced and miss.
    """
    search = embree.nearest_triangle if engine == "embree" else warp.nearest_triangle
    return search(triangles, origins, directions, valid)


def nearest_hit(
    engine: str, triangles: Array, origins: Array, directions: Array, valid: Array
) -> tuple[Array, Array, Array, Array]:
    """The nearest hit of each ray with the distance and barycentric coordinates the engine itself
    computed, for "embree" / "warp" (the values-only path of :func:`jaxloc.raycast`).

    Arguments as :func:`nearest_triangle` (unit directions, so ``t`` is metric). Returns
    ``(triangle, t, u, v)``: (R,) int32 map index (-1 on a miss) and (R,) float32 distance and
    weights of the triangle's second and third corners, meaningless on a miss. Not
    differentiable (a host or kernel call): :func:`jaxloc.raycast` stops the gradients first.
    """
    search = embree.nearest_hit if engine == "embree" else warp.nearest_hit
    return search(triangles, origins, directions, valid)


def clear_caches() -> None:
    """Drop every cached Embree scene and Warp mesh (they are rebuilt on next use)."""
    embree.clear_cache()
    if is_installed("warp"):
        warp.clear_cache()
