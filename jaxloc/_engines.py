"""Nearest-hit engines: which triangle each ray hits first, found by JAX, Embree or Warp.

An engine only *chooses* the triangle, on stop-gradient rays; :func:`jaxloc.raycast` then computes
``t``, the barycentric coordinates, the object id and every gradient with the same JAX code for all
engines, so jit, vmap, ``lax.scan``, grads and the trace count behave identically (the DiffeRT
pattern: a fast engine picks, JAX differentiates).

* ``"jax"``: the BVH traversal of :mod:`jaxloc._raycast`; portable to any backend, no optional
  dependency, the reference.
* ``"embree"``: Intel Embree through embreex (trimesh's own binding), called from the traced
  program with :func:`jax.pure_callback`; the rays are split over a thread pool as wide as the
  machine (``embreex``'s ``run`` releases the GIL). Host memory: on a GPU backend the rays make a
  round trip to the host.
* ``"warp"``: NVIDIA Warp's ``mesh_query_ray`` through ``warp.jax_callable`` (zero copy, CPU and
  CUDA). Warp's CPU backend runs one thread; its point is the GPU.
* ``"auto"``: Embree on a CPU backend and Warp on a GPU backend where installed, else ``"jax"``.

The engines' acceleration structures are built on first use of a map and cached, keyed by a
fingerprint of the triangles that the traced program computes (a 64-bit integer hash of their
bits): editing a map's triangles gives a new fingerprint, so a stale structure is never used.
"""

from __future__ import annotations

import collections
import concurrent.futures
import functools
import importlib.util
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

#: Every engine name :func:`jaxloc.raycast` accepts.
ENGINES = ("auto", "jax", "embree", "warp")
#: The package that provides each optional engine, and how to install it.
_PACKAGES = {
    "embree": ("embreex", "pip install embreex (a jaxloc dependency where wheels exist)"),
    "warp": ("warp", 'pip install "jaxloc[gpu]" (or: pip install warp-lang)'),
}
#: Acceleration structures kept per engine (least recently used first out).
CACHE_SIZE = 8
#: Rays per Embree call of the thread pool (smaller batches do not amortise the call).
EMBREE_BATCH = 4096


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


def fingerprint(triangles: Array) -> Array:
    """A 64-bit hash (2,) uint32 of ``triangles``' bits, computed in the traced program.

    Wrapping integer sums of the bits times per-position odd multipliers: exact and independent of
    the reduction order, so the same triangles always give the same key on any backend.
    """
    bits = jax.lax.bitcast_convert_type(triangles.reshape(-1).astype(jnp.float32), jnp.uint32)
    position = jnp.arange(bits.shape[0], dtype=jnp.uint32)
    bits = bits ^ (bits >> 16)
    first = jnp.sum(bits * (position * jnp.uint32(0x9E3779B1) | jnp.uint32(1)), dtype=jnp.uint32)
    second = jnp.sum(
        bits * ((position ^ jnp.uint32(0x5BD1E995)) * jnp.uint32(0x85EBCA77) | jnp.uint32(1)),
        dtype=jnp.uint32,
    )
    return jnp.stack([first, second])


class _Cache:
    """A small thread-safe LRU of acceleration structures, keyed by (device, shape, fingerprint)."""

    def __init__(self, build):
        self._build = build
        self._items: collections.OrderedDict = collections.OrderedDict()
        self._lock = threading.Lock()

    def get(self, key, triangles):
        with self._lock:
            item = self._items.get(key)
            if item is None:
                item = self._build(triangles)
                self._items[key] = item
                while len(self._items) > CACHE_SIZE:
                    self._items.popitem(last=False)
            self._items.move_to_end(key)
            return item

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


# ----------------------------------------------------------------------------------- Embree


def _build_embree(triangles: np.ndarray):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    try:  # robust (watertight) traversal: no ray slips between two triangles sharing an edge
        scene = rtcore_scene.EmbreeScene(robust=True)
    except TypeError:  # embreex 2.x (Embree 2) has no robust flag
        scene = rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(triangles, np.float32))
    return scene


_embree_scenes = _Cache(_build_embree)


def embree_threads() -> int:
    """Threads of the Embree engine: the CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


@functools.cache
def _thread_pool() -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(embree_threads(), "jaxloc-embree")


def _embree_nearest(scene, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Nearest triangle (R,) int32 of finite rays (R, 3) float32 on a built Embree scene.

    The rays are cut into contiguous slices (views, no copy), traced on the thread pool.
    """
    num = origins.shape[0]
    faces = np.empty(num, np.int32)
    parts = max(1, min(4 * embree_threads(), num // EMBREE_BATCH))
    bounds = np.linspace(0, num, parts + 1).astype(int)
    slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]

    def run(part: slice) -> None:
        faces[part] = scene.run(origins[part], directions[part])

    if parts == 1:
        run(slice(0, num))
    else:
        list(_thread_pool().map(run, slices))
    return faces


def _embree_host(key, triangles, origins, directions):
    """The host side of the Embree engine, batched the ``expand_dims`` way (see pure_callback).

    Shapes: key (*L1, 2), triangles (*L2, T, 3, 3), origins and directions (*L3, R, 3) (finite),
    with size-1 axes where an argument is not batched; returns (*L, R) int32 for L the broadcast
    batch shape.
    """
    # The callback receives jax Arrays: one explicit conversion each (zero-copy on CPU).
    key, triangles, origins, directions = map(np.asarray, (key, triangles, origins, directions))
    lead = np.broadcast_shapes(
        key.shape[:-1], triangles.shape[:-3], origins.shape[:-2], directions.shape[:-2]
    )
    num_rays = origins.shape[-2]
    size = int(np.prod(lead))
    key = np.broadcast_to(key, lead + key.shape[-1:]).reshape(size, -1)
    triangles = np.broadcast_to(triangles, lead + triangles.shape[-3:]).reshape(
        (size,) + triangles.shape[-3:]
    )
    origins = np.broadcast_to(origins, lead + origins.shape[-2:]).reshape(size, num_rays, 3)
    directions = np.broadcast_to(directions, lead + directions.shape[-2:]).reshape(
        size, num_rays, 3
    )
    origins = np.ascontiguousarray(origins, np.float32)
    directions = np.ascontiguousarray(directions, np.float32)
    groups: dict[bytes, list[int]] = {}
    for i in range(size):
        groups.setdefault(key[i].tobytes(), []).append(i)
    faces = np.empty((size, num_rays), np.int32)
    for fp, members in groups.items():
        scene = _embree_scenes.get(("cpu", triangles.shape[1], fp), triangles[members[0]])
        if len(members) == size:  # one map for the whole batch (the usual case): no gather
            rays = (origins.reshape(-1, 3), directions.reshape(-1, 3))
        else:
            rays = (origins[members].reshape(-1, 3), directions[members].reshape(-1, 3))
        found = _embree_nearest(scene, *rays)
        faces[members] = found.reshape(len(members), num_rays)
    return faces.reshape(lead + (num_rays,))


def _embree_search(key: Array, triangles: Array, origins: Array, directions: Array) -> Array:
    out = jax.ShapeDtypeStruct(origins.shape[:-1], jnp.int32)
    return jax.pure_callback(
        _embree_host, out, key, triangles, origins, directions, vmap_method="expand_dims"
    )


# ------------------------------------------------------------------------------------- Warp


@functools.cache
def _warp():
    """Warp, initialised quietly, and the one-ray kernel and JAX callable built on it."""
    import warp as wp

    level = wp.config.log_level
    wp.config.log_level = max(level, 30)  # warnings only: no start-up banner
    try:
        wp.init()
    finally:
        wp.config.log_level = level

    @wp.kernel
    def nearest_face(
        mesh: wp.uint64,
        origins: wp.array(dtype=wp.vec3),
        directions: wp.array(dtype=wp.vec3),
        faces: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        query = wp.mesh_query_ray(mesh, origins[i], directions[i], 1.0e30)
        face = int(-1)  # noqa: UP018 (a Warp variable that the branch below may assign)
        if query.result:
            face = query.face
        faces[i] = face

    def build(vertices):
        points = wp.clone(vertices)
        indices = wp.array(
            np.arange(vertices.shape[0], dtype=np.int32), dtype=wp.int32, device=vertices.device
        )
        return wp.Mesh(points=points, indices=indices), points, indices

    meshes = _Cache(build)

    def search(
        key: wp.array(dtype=wp.uint32),
        vertices: wp.array(dtype=wp.vec3),
        origins: wp.array(dtype=wp.vec3),
        directions: wp.array(dtype=wp.vec3),
        faces: wp.array(dtype=wp.int32),
    ):
        cache_key = (str(vertices.device), vertices.shape[0], key.numpy().tobytes())
        mesh = meshes.get(cache_key, vertices)[0]
        wp.launch(
            nearest_face,
            dim=origins.shape[0],
            inputs=[mesh.id, origins, directions],
            outputs=[faces],
            device=origins.device,
        )

    callable_ = wp.jax_callable(
        search, graph_mode=wp.JaxCallableGraphMode.NONE, vmap_method="sequential"
    )
    return callable_, meshes


def _warp_search(key: Array, triangles: Array, origins: Array, directions: Array) -> Array:
    callable_, _ = _warp()
    num_rays = origins.shape[0]
    (faces,) = callable_(
        key, triangles.reshape(-1, 3), origins, directions, output_dims={"faces": num_rays}
    )
    return faces


def nearest_triangle(engine: str, triangles: Array, origins: Array, directions: Array) -> Array:
    """Index (R,) int32 of the triangle each ray hits first, -1 on a miss, for "embree" / "warp".

    Args:
        engine: "embree" or "warp" (resolved; see :func:`resolve_engine`).
        triangles: (T, 3, 3) float32 vertices, world frame; padding rows never hit (all-zero, so
            degenerate) and are also rejected by the caller.
        origins: (R, 3) float32, finite (the caller masks the rays that must miss).
        directions: (R, 3) float32 finite unit directions.
    """
    search = _embree_search if engine == "embree" else _warp_search
    return search(fingerprint(triangles), triangles, origins, directions)


def clear_caches() -> None:
    """Drop every cached Embree scene and Warp mesh (they are rebuilt on next use)."""
    _embree_scenes.clear()
    if is_installed("warp") and _warp.cache_info().currsize:
        _warp()[1].clear()
