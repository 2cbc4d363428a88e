"""Nearest-hit engines: which triangle each ray hits first, found by JAX, Embree or Warp.

An engine only *chooses* the triangle, on stop-gradient rays; :func:`jaxloc.raycast` then computes
``t``, the barycentric coordinates, the object id and every gradient with the same JAX code for all
engines, so jit, vmap, ``lax.scan``, grads and the trace count behave identically (the DiffeRT
pattern: a fast engine picks, JAX differentiates).

* ``"jax"``: the BVH traversal of :mod:`jaxloc._raycast`; portable to any backend, no optional
  dependency, the reference.
* ``"embree"``: Intel Embree through embreex (trimesh's own binding), called from the traced
  program with ``jax.experimental.buffer_callback`` on a CPU backend (the host buffers in place,
  no copies) and :func:`jax.pure_callback` elsewhere; the rays are split over a thread pool as
  wide as the machine (``embreex``'s ``run`` releases the GIL). Host memory: on a GPU backend the
  rays make a round trip to the host.
* ``"warp"``: NVIDIA Warp's ``mesh_query_ray`` through ``warp.jax_callable`` (zero copy, CPU and
  CUDA). Warp's CPU backend runs one thread; its point is the GPU.
* ``"auto"``: Embree on a CPU backend and Warp on a GPU backend where installed, else ``"jax"``.

The engines' acceleration structures are built on first use of a map and cached, keyed by a
fingerprint of the triangles that the traced program computes (a 64-bit integer hash of their
bits): editing a map's triangles gives a new fingerprint, so a stale structure is never used. They
hold the map's real triangles only (not its all-zero padding), and only the valid rays are traced.
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
from jax.experimental.buffer_callback import buffer_callback

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


def real_triangles(triangles: np.ndarray) -> np.ndarray:
    """Indices (K,) of the real rows of ``triangles`` (T, 3, 3): padding rows are all zero.

    Engines build on these only: thousands of degenerate padding triangles at the origin would
    make one leaf that every ray passing near the origin has to test.
    """
    return np.flatnonzero(np.any(triangles.reshape(triangles.shape[0], -1) != 0, axis=1))


# ----------------------------------------------------------------------------------- Embree


class _EmbreeMap:
    """An Embree scene of a map's real triangles and their indices in the map."""

    def __init__(self, triangles: np.ndarray):
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh

        self.ids = real_triangles(triangles).astype(np.int32)
        # Maps pad at the end, so the real triangles are usually 0..K-1: no index translation.
        self.prefix = bool(np.array_equal(self.ids, np.arange(self.ids.size)))
        try:  # robust (watertight) traversal: no ray slips between two triangles sharing an edge
            self.scene = rtcore_scene.EmbreeScene(robust=True)
        except TypeError:  # embreex 2.x (Embree 2) has no robust flag
            self.scene = rtcore_scene.EmbreeScene()
        if self.ids.size:
            TriangleMesh(self.scene, np.ascontiguousarray(triangles[self.ids], np.float32))

    def nearest(
        self, origins: np.ndarray, directions: np.ndarray, faces: np.ndarray | None = None
    ) -> np.ndarray:
        """Nearest triangle (R,) int32 (map index, -1 on a miss) of finite rays (R, 3) float32,
        written into ``faces`` (R,) int32 when given (and returned).

        The rays are cut into contiguous slices (views, no copy), traced on the thread pool.
        """
        num = origins.shape[0]
        if faces is None:
            faces = np.empty(num, np.int32)
        faces[:] = -1
        if num == 0 or self.ids.size == 0:
            return faces
        parts = max(1, min(4 * embree_threads(), num // EMBREE_BATCH))
        bounds = np.linspace(0, num, parts + 1).astype(int)

        def run(part: slice) -> None:
            found = self.scene.run(origins[part], directions[part])
            faces[part] = found if self.prefix else np.where(found >= 0, self.ids[found], -1)

        if parts == 1:
            run(slice(0, num))
        else:
            slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
            list(_thread_pool().map(run, slices))
        return faces


_embree_maps = _Cache(_EmbreeMap)


def embree_threads() -> int:
    """Threads of the Embree engine: the CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


@functools.cache
def _thread_pool() -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(embree_threads(), "jaxloc-embree")


def _embree_host(key, triangles, origins, directions, valid, out=None):
    """The host side of the Embree engine, batched the ``expand_dims`` way (see pure_callback).

    Shapes: key (*L1, 2), triangles (*L2, T, 3, 3), origins and directions (*L3, R, 3) (finite),
    valid (*L4, R), with size-1 axes where an argument is not batched; returns (*L, R) int32 for
    L the broadcast batch shape, written into ``out`` when given. Only the valid rays are traced
    (the others miss).
    """
    # The callback receives jax Arrays: one explicit conversion each (zero-copy on CPU).
    key, triangles, origins, directions, valid = map(
        np.asarray, (key, triangles, origins, directions, valid)
    )
    lead = np.broadcast_shapes(
        key.shape[:-1],
        triangles.shape[:-3],
        origins.shape[:-2],
        directions.shape[:-2],
        valid.shape[:-1],
    )
    num_rays = origins.shape[-2]
    size = int(np.prod(lead))

    def flat(array, tail):
        return np.broadcast_to(array, lead + tail).reshape((size,) + tail)

    key, triangles = flat(key, key.shape[-1:]), flat(triangles, triangles.shape[-3:])
    origins = np.ascontiguousarray(flat(origins, (num_rays, 3)), np.float32).reshape(-1, 3)
    directions = np.ascontiguousarray(flat(directions, (num_rays, 3)), np.float32).reshape(-1, 3)
    valid = flat(valid, (num_rays,)).reshape(-1)
    groups: dict[bytes, list[int]] = {}
    for i in range(size):
        groups.setdefault(key[i].tobytes(), []).append(i)
    if out is None:
        out = np.empty(lead + (num_rays,), np.int32)
    faces = out.reshape(-1)  # a view: out is contiguous
    faces[:] = -1
    for fp, members in groups.items():
        embree_map = _embree_maps.get(("cpu", triangles.shape[1], fp), triangles[members[0]])
        if len(members) == size and valid.all():  # the usual case: no gather, no scatter
            embree_map.nearest(origins, directions, faces)
            continue
        rows = (np.asarray(members)[:, None] * num_rays + np.arange(num_rays)).reshape(-1)
        rays = rows[valid[rows]]
        faces[rays] = embree_map.nearest(origins[rays], directions[rays])
    return out


def _embree_fill(_context, out, *args) -> None:
    """``buffer_callback`` form of :func:`_embree_host`: writes into the output buffer."""
    _embree_host(*args, out=np.asarray(out))


def _embree_search(key, triangles, origins, directions, valid) -> Array:
    out = jax.ShapeDtypeStruct(origins.shape[:-1], jnp.int32)
    args = (key, triangles, origins, directions, valid)
    if jax.default_backend() == "cpu":
        # Host buffers in place: no copy of the rays in, none of the result out (3.24M rays:
        # ~45 ms less than pure_callback, benchmarks/results/engines_cpu.md).
        return buffer_callback(_embree_fill, out, vmap_method="expand_dims")(*args)
    return jax.pure_callback(_embree_host, out, *args, vmap_method="expand_dims")


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
        ids: wp.array(dtype=wp.int32),
        origins: wp.array(dtype=wp.vec3),
        directions: wp.array(dtype=wp.vec3),
        valid: wp.array(dtype=wp.int32),
        faces: wp.array(dtype=wp.int32),
    ):
        i = wp.tid()
        face = int(-1)  # noqa: UP018 (a Warp variable that the branches below may assign)
        if valid[i] != 0:
            query = wp.mesh_query_ray(mesh, origins[i], directions[i], 1.0e30)
            if query.result:
                face = ids[query.face]
        faces[i] = face

    def build(vertices):
        """The Warp mesh of the map's real triangles (vertices (3T, 3) on the device)."""
        triangles = vertices.numpy().reshape(-1, 3, 3)
        real = real_triangles(triangles).astype(np.int32)
        if real.size == 0:  # an empty map: one far-away degenerate triangle, never hit
            real, triangles = np.zeros(1, np.int32), np.full((1, 3, 3), 1e30, np.float32)
        device = vertices.device
        points = wp.array(triangles[real].reshape(-1, 3), dtype=wp.vec3, device=device)
        indices = wp.array(np.arange(3 * real.size, dtype=np.int32), dtype=wp.int32, device=device)
        ids = wp.array(real, dtype=wp.int32, device=device)
        return wp.Mesh(points=points, indices=indices), ids, points, indices

    meshes = _Cache(build)

    def search(
        key: wp.array(dtype=wp.uint32),
        vertices: wp.array(dtype=wp.vec3),
        origins: wp.array(dtype=wp.vec3),
        directions: wp.array(dtype=wp.vec3),
        valid: wp.array(dtype=wp.int32),
        faces: wp.array(dtype=wp.int32),
    ):
        cache_key = (str(vertices.device), vertices.shape[0], key.numpy().tobytes())
        mesh, ids = meshes.get(cache_key, vertices)[:2]
        wp.launch(
            nearest_face,
            dim=origins.shape[0],
            inputs=[mesh.id, ids, origins, directions, valid],
            outputs=[faces],
            device=origins.device,
        )

    callable_ = wp.jax_callable(
        search, graph_mode=wp.JaxCallableGraphMode.NONE, vmap_method="sequential"
    )
    return callable_, meshes


def _warp_search(key, triangles, origins, directions, valid) -> Array:
    callable_, _ = _warp()
    (faces,) = callable_(
        key,
        triangles.reshape(-1, 3),
        origins,
        directions,
        valid.astype(jnp.int32),
        output_dims={"faces": origins.shape[0]},
    )
    return faces


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
    search = _embree_search if engine == "embree" else _warp_search
    return search(fingerprint(triangles), triangles, origins, directions, valid)


def clear_caches() -> None:
    """Drop every cached Embree scene and Warp mesh (they are rebuilt on next use)."""
    _embree_maps.clear()
    if is_installed("warp") and _warp.cache_info().currsize:
        _warp()[1].clear()
