"""The Warp engine: NVIDIA Warp's ``mesh_query_ray`` through ``warp.jax_callable`` (zero copy,
CPU and CUDA). Warp's CPU backend runs one thread; its point is the GPU. The Warp mesh holds the
map's real triangles only (not its all-zero padding), and only the valid rays are traced.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.raycasting._cache import StructureCache, fingerprint, real_triangles


@functools.cache
def _warp():
    """Warp, initialised quietly, the one-ray kernel and its JAX callable, and the mesh cache."""
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
        distances: wp.array(dtype=wp.float32),
        first: wp.array(dtype=wp.float32),
        second: wp.array(dtype=wp.float32),
    ):
        i = wp.tid()
        face = int(-1)  # noqa: UP018 (Warp variables that the branches below may assign)
        distance = float(0.0)  # noqa: UP018
        u = float(0.0)  # noqa: UP018
        v = float(0.0)  # noqa: UP018
        if valid[i] != 0:
            query = wp.mesh_query_ray(mesh, origins[i], directions[i], 1.0e30)
            if query.result:
                face = ids[query.face]
                distance = query.t
                # Warp weighs the corners (u, v, 1 - u - v); jaxloc (1 - u - v, u, v) as Embree.
                u = query.v
                v = 1.0 - query.u - query.v
        faces[i] = face
        distances[i] = distance
        first[i] = u
        second[i] = v

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

    meshes = StructureCache(build)

    def launch(
        key: wp.array(dtype=wp.uint32),
        vertices: wp.array(dtype=wp.vec3),
        origins: wp.array(dtype=wp.vec3),
        directions: wp.array(dtype=wp.vec3),
        valid: wp.array(dtype=wp.int32),
        faces: wp.array(dtype=wp.int32),
        distances: wp.array(dtype=wp.float32),
        first: wp.array(dtype=wp.float32),
        second: wp.array(dtype=wp.float32),
    ):
        cache_key = (str(vertices.device), vertices.shape[0], key.numpy().tobytes())
        mesh, ids = meshes.get(cache_key, vertices)[:2]
        wp.launch(
            nearest_face,
            dim=origins.shape[0],
            inputs=[mesh.id, ids, origins, directions, valid],
            outputs=[faces, distances, first, second],
            device=origins.device,
        )

    search = wp.jax_callable(
        launch,
        num_outputs=4,
        graph_mode=wp.JaxCallableGraphMode.NONE,
        vmap_method="sequential",
    )
    return search, meshes


def nearest_triangle(triangles: Array, origins: Array, directions: Array, valid: Array) -> Array:
    """Warp's nearest triangle (R,) int32 of each ray, -1 on a miss (see
    :func:`jaxloc.raycasting.engines.nearest_triangle`); the kernel's other outputs are unused."""
    return nearest_hit(triangles, origins, directions, valid)[0]


def nearest_hit(
    triangles: Array, origins: Array, directions: Array, valid: Array
) -> tuple[Array, Array, Array, Array]:
    """Warp's nearest hit ``(triangle, t, u, v)`` of each ray with the values Warp computes (see
    :func:`jaxloc.raycasting.embree.nearest_hit`; ``u``, ``v`` in jaxloc's corner order)."""
    search = _warp()[0]
    num = origins.shape[0]
    return tuple(
        search(
            fingerprint(triangles),
            triangles.reshape(-1, 3),
            origins,
            directions,
            valid.astype(jnp.int32),
            output_dims={"faces": num, "distances": num, "first": num, "second": num},
        )
    )


def clear_cache() -> None:
    """Drop every cached Warp mesh (rebuilt on next use)."""
    if _warp.cache_info().currsize:
        _warp()[1].clear()
