"""The Embree engine: Intel Embree through embreex (trimesh's own binding), CPU.

Called from the traced program as the XLA:CPU FFI target :data:`TARGET` on a CPU backend (XLA's
buffers in place, no copies; a program that calls it goes to JAX's persistent compilation cache
like any other, see :mod:`jaxloc.raycasting._host_target`) and with :func:`jax.pure_callback`
elsewhere (on a GPU backend the rays make a round trip to the host). The rays are split over a
thread pool as wide as the machine (``embreex``'s ``run`` releases the GIL). The Embree scene holds
the map's real triangles only (not its all-zero padding), and only the valid rays are traced.

By default the same target is served by the native C++ handler instead
(:mod:`jaxloc.raycasting._native`: Embree 4 called from native threads, packets for rays that
share an origin), where it builds and passes its self-test (``JAXLOC_NATIVE=0`` keeps the Python
one); :func:`implementation` says which runs.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.raycasting import _native
from jaxloc.raycasting._cache import StructureCache, fingerprint, real_triangles
from jaxloc.raycasting._host_target import host_call, register_host_target

#: Rays per Embree call of the thread pool (smaller batches do not amortise the call).
EMBREE_BATCH = 4096


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
        self, origins: np.ndarray, directions: np.ndarray, out: tuple | None = None
    ) -> tuple:
        """Nearest hits of finite rays (R, 3) float32: ``(faces,)``, or ``(faces, t, u, v)`` when
        ``out`` holds four arrays, written into ``out`` when given (and returned).

        ``faces`` (R,) int32 map index (-1 on a miss); ``t``, ``u``, ``v`` (R,) float32 Embree's
        hit distance and barycentric coordinates (the weights of the triangle's second and third
        corners), meaningless where ``faces`` is -1. The rays are cut into contiguous slices
        (views, no copy), traced on the thread pool.
        """
        num = origins.shape[0]
        if out is None:
            out = (np.empty(num, np.int32),)
        faces = out[0]
        faces[:] = -1
        if num == 0 or self.ids.size == 0:
            return out
        parts = max(1, min(4 * embree_threads(), num // EMBREE_BATCH))
        bounds = np.linspace(0, num, parts + 1).astype(int)

        def run(part: slice) -> None:
            if len(out) == 1:
                found = self.scene.run(origins[part], directions[part])
            else:  # raw values: the caller masks the misses (faces -1)
                info = self.scene.run(origins[part], directions[part], output=1)
                found = info["primID"]
                out[1][part], out[2][part], out[3][part] = info["tfar"], info["u"], info["v"]
            faces[part] = found if self.prefix else np.where(found >= 0, self.ids[found], -1)

        if parts == 1:
            run(slice(0, num))
        else:
            slices = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
            list(_thread_pool().map(run, slices))
        return out


_embree_maps = StructureCache(_EmbreeMap)


def embree_threads() -> int:
    """Threads of the Embree engine: the CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


@functools.cache
def _thread_pool() -> concurrent.futures.ThreadPoolExecutor:
    return concurrent.futures.ThreadPoolExecutor(embree_threads(), "jaxloc-embree")


def _embree_host(key, triangles, origins, directions, valid, out=None, values=False):
    """The host side of the Embree engine, batched the ``expand_dims`` way (see pure_callback).

    Shapes: key (*L1, 2), triangles (*L2, T, 3, 3), origins and directions (*L3, R, 3) (finite),
    valid (*L4, R), with size-1 axes where an argument is not batched; L is the broadcast batch
    shape. Returns ``faces`` (*L, R) int32, or with ``values`` the tuple ``(faces, t, u, v)`` with
    (*L, R) float32 values (see :meth:`_EmbreeMap.nearest`), written into ``out`` when given.
    Only the valid rays are traced (the others miss).
    """
    # The callback receives jax Arrays: one explicit conversion each (zero-copy on CPU).
    key, triangles, origins, directions, valid = map(
        np.asarray, (key, triangles, origins, directions, valid)
    )
    key_lead, triangles_lead = key.shape[:-1], triangles.shape[:-3]
    lead = np.broadcast_shapes(
        key_lead,
        triangles_lead,
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
    groups: dict[bytes, list[int]] = {}  # map fingerprint -> the batch rows that cast on it
    if int(np.prod(np.broadcast_shapes(key_lead, triangles_lead))) == 1:  # one map for all rays
        groups[key[0].tobytes()] = list(range(size))
    else:
        for i in range(size):
            groups.setdefault(key[i].tobytes(), []).append(i)
    if out is None:
        dtypes = (np.int32, np.float32, np.float32, np.float32) if values else (np.int32,)
        out = tuple(np.empty(lead + (num_rays,), dtype) for dtype in dtypes)
    flat_out = tuple(o.reshape(-1) for o in out)  # views: out is contiguous
    flat_out[0][:] = -1
    for fp, members in groups.items():
        embree_map = _embree_maps.get(("cpu", triangles.shape[1], fp), triangles[members[0]])
        if len(members) == size and valid.all():  # the usual case: no gather, no scatter
            embree_map.nearest(origins, directions, flat_out)
            continue
        rows = (np.asarray(members)[:, None] * num_rays + np.arange(num_rays)).reshape(-1)
        rays = rows[valid[rows]]
        found = embree_map.nearest(
            origins[rays], directions[rays], _empty_like(flat_out, rays.size)
        )
        for whole, part in zip(flat_out, found, strict=True):
            whole[rays] = part
    return out if values else out[0]


def _empty_like(out: tuple, num: int) -> tuple:
    """Fresh output arrays of ``num`` rays with the dtypes of ``out``."""
    return tuple(np.empty(num, a.dtype) for a in out)


def _embree_values_host(*args):
    return _embree_host(*args, values=True)


def _fill(inputs: list, outputs: list) -> None:
    """The FFI target's body: operands and ``outputs`` (faces,) or (faces, t, u, v) with the batch
    axes of a vmapped call in front (``expand_dims``, as :func:`_embree_host` expects)."""
    _embree_host(*inputs, out=tuple(outputs), values=len(outputs) == 4)


#: The XLA:CPU FFI target of the engine: the native handler (:mod:`jaxloc.raycasting._native`)
#: where it builds and passes its self-test, else :func:`_fill` in Python; the same name and
#: signature either way, so a program in the persistent compilation cache runs with both.
TARGET = "jaxloc_embree_nearest"
#: The Python implementation under a name of its own (a process with the native engine can still
#: run the Python one, e.g. to compare them).
PYTHON_TARGET = "jaxloc_embree_nearest_python"
#: The native handler under a name of its own (see :func:`native_target`).
NATIVE_TARGET = "jaxloc_embree_nearest_native"
_registered: dict[str, str] = {}  # target name -> "native" / "python" / "" (not registrable)


def _register() -> str:
    """Register :data:`TARGET` on first use in this process (at trace time, before any program
    that calls it runs); which implementation serves it: "native", "python", or "" where this
    jaxlib cannot register one (the engine then uses a pure_callback)."""
    if TARGET not in _registered:
        engine = _native.load()
        if engine is not None:
            jax.ffi.register_ffi_target(TARGET, engine.handler(), platform="cpu")
            _registered[TARGET] = "native"
        else:
            _registered[TARGET] = "python" if register_host_target(TARGET, _fill) else ""
    return _registered[TARGET]


def implementation() -> str:
    """Which implementation casts the Embree engine's rays in this process: ``"native"`` (the C++
    FFI handler, native threads), ``"python"`` (embreex from a Python FFI target) or
    ``"callback"`` (a ``jax.pure_callback``: a non-CPU backend, or no FFI registration)."""
    if jax.default_backend() != "cpu":
        return "callback"
    return _register() or "callback"


def describe() -> str:
    """:func:`implementation` in words, with its threads (and packet width where native), e.g.
    ``"native, 2 threads, packets of 8"``."""
    kind = implementation()
    if kind == "native":
        engine = _native.load()
        return f"native, {engine.threads} threads, packets of {engine.packet_width}"
    return f"{kind}, {embree_threads()} threads" if kind == "python" else kind


def python_target() -> str:
    """:data:`PYTHON_TARGET`, registered; a process with the native engine uses it by swapping
    :func:`_target` for this (tests and benchmarks of the Python implementation)."""
    if PYTHON_TARGET not in _registered:
        register_host_target(PYTHON_TARGET, _fill)
        _registered[PYTHON_TARGET] = "python"
    return PYTHON_TARGET


def native_target() -> str:
    """:data:`NATIVE_TARGET`: the native handler under a name of its own, whatever
    ``$JAXLOC_NATIVE`` says (tests and benchmarks swap :func:`_target` for this).

    Raises:
        _native.NativeUnavailable: the native engine cannot be built or trusted here.
    """
    if NATIVE_TARGET not in _registered:
        handler = _native.engine().handler()
        jax.ffi.register_ffi_target(NATIVE_TARGET, handler, platform="cpu")
        _registered[NATIVE_TARGET] = "native"
    return NATIVE_TARGET


def _target() -> str | None:
    """The CPU target to call, or None for a pure_callback."""
    if jax.default_backend() != "cpu":
        return None
    return TARGET if _register() else None


def native_values() -> bool:
    """Whether the target this process calls is served by the native handler, whose values are
    :func:`jaxloc.raycast`'s recompute in double precision (see
    :func:`jaxloc.raycasting.engines.recomputes_hits`). At trace time."""
    target = _target()
    return target is not None and _registered.get(target) == "native"


def _call(args: tuple, out, values: bool):
    target = _target()
    if target is not None:
        found = host_call(target, out if values else (out,), *args)
        return found if values else found[0]
    host = _embree_values_host if values else _embree_host
    return jax.pure_callback(host, out, *args, vmap_method="expand_dims")


def nearest_triangle(triangles: Array, origins: Array, directions: Array, valid: Array) -> Array:
    """Embree's nearest triangle (R,) int32 of each ray, -1 on a miss (see
    :func:`jaxloc.raycasting.engines.nearest_triangle`)."""
    out = jax.ShapeDtypeStruct(origins.shape[:-1], jnp.int32)
    return _call((fingerprint(triangles), triangles, origins, directions, valid), out, False)


def nearest_hit(
    triangles: Array, origins: Array, directions: Array, valid: Array
) -> tuple[Array, Array, Array, Array]:
    """Embree's nearest hit of each ray with the values Embree computes, for code that does not
    differentiate (see :func:`jaxloc.raycasting.engines.nearest_hit`).

    Returns ``(triangle, t, u, v)``: (R,) int32 (-1 on a miss) and (R,) float32 distance along the
    direction and weights of the triangle's second and third corners, meaningless on a miss.
    """
    num = origins.shape[:-1]
    out = (jax.ShapeDtypeStruct(num, jnp.int32),) + 3 * (jax.ShapeDtypeStruct(num, jnp.float32),)
    return _call((fingerprint(triangles), triangles, origins, directions, valid), out, True)


def clear_cache() -> None:
    """Drop every cached Embree scene, native and Python (rebuilt on next use)."""
    _embree_maps.clear()
    if "native" in _registered.values():
        _native.engine().clear_cache()
