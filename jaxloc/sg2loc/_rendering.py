"""Render what a camera at a 4-DoF pose sees: per-ray object, depth and colour, per-patch majority.

:func:`render` handles one pose (vmap it for a batch); :func:`render_batch` renders many poses in
one raycast, which is faster because the traversal's chunks then span particles. Both give the same
values.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.camera import Camera, RayGrid
from jaxloc.geometry import rotation_world_cam
from jaxloc.raycasting import RayHit, raycast, resolve_engine
from jaxloc.scene import SceneGraph

#: Rays of one camera traverse the BVH in packets of this many neighbouring rays (half a 4 x 4
#: tile: 2 rows x 4 columns). 8 beat 4 and 16 on the benchmark room for both the patch and the
#: stride-20 grid (benchmarks/results/raycast_cpu.md).
PACKET_SIZE = 8


class Render(eqx.Module):
    """One view rendered on a :class:`~jaxloc.camera.RayGrid` of R rays and P patches.

    Attributes:
        object_id: (R,) int32 object hit by each ray, -1 on a miss.
        depth: (R,) float32 z-depth along the optical axis in metres (as a depth sensor reports
            it); +inf on a miss.
        t: (R,) float32 range along the ray in metres; +inf on a miss.
        color: (R, 3) float32 RGB in [0, 1] interpolated from the mesh's corner colours; 0 on a
            miss.
        valid: (R,) bool, the ray hit something.
        patch_object: (P,) int32 the majority label among the patch's rays, counting a miss as a
            candidate: -1 when misses are the majority or the patch has no ray.
        patch_fraction: (P,) float32 share of the patch's rays that hit ``patch_object``.
    """

    object_id: Array
    depth: Array
    t: Array
    color: Array
    valid: Array
    patch_object: Array
    patch_fraction: Array


def _tile_order(grid: RayGrid, engine: str) -> np.ndarray | None:
    """The order the rays of ``grid`` are cast in, or None for their own order.

    The ``"jax"`` engine traverses packets of neighbouring rays, so a full ray image is cast tile
    by tile (4 x 4) and put back in row-major order afterwards; Embree and Warp trace ray by ray,
    and the two permutations would only cost gathers.
    """
    if resolve_engine(engine) != "jax" or np.prod(grid.shape) != grid.uv.shape[0]:
        return None
    return _tiles(grid.shape)


def _tiles(shape: tuple[int, int], tile: int = 4) -> np.ndarray:
    """A permutation of a row-major (h, w) ray image that lists it tile by tile (tile x tile)."""
    h, w = shape
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    key = (rows // tile) * ((w + tile - 1) // tile) + cols // tile
    return np.lexsort((cols.ravel(), rows.ravel(), key.ravel()))


def _rotate(R_world_cam: Array, d_cam: Array) -> Array:
    """Directions (R, 3) in the camera frame turned into the world frame by rotations
    (..., 3, 3): (..., R, 3). Written as three products and sums rather than a matmul, so that XLA
    fuses the turn with what consumes it (raycast's normalisation) in one pass over the rays."""
    column = R_world_cam[..., None, :, :]  # (..., 1, 3, 3)
    return sum(column[..., j] * d_cam[:, j : j + 1] for j in range(3))


def _world_rays(pose: Array, camera: Camera, grid: RayGrid, tilt: Array | None):
    """Unit directions in the camera frame (R, 3) and world frame (R, 3) of one view."""
    d_cam = camera.directions(grid.uv)
    return d_cam, _rotate(rotation_world_cam(pose[3], tilt), d_cam)


def _views(scene: SceneGraph, hit: RayHit, d_cam: Array, grid: RayGrid) -> Render:
    """Depth, colour and patch majority of one view from its rays' hits."""
    depth = jnp.where(hit.hit, hit.t * d_cam[:, 2], jnp.inf)
    # Corner colours as 9 columns, weighted sums written out: on XLA:CPU ~5x faster than an
    # einsum over (R, 3, 3) corners (benchmarks/results/filter_profile_cpu.md).
    corner = scene.triangle_colors.reshape(-1, 9)[jnp.maximum(hit.triangle_id, 0)]  # (R, 9)
    weight = hit.barycentric
    color = jnp.stack(
        [sum(weight[:, c] * corner[:, 3 * c + k] for c in range(3)) for k in range(3)], -1
    )
    color = jnp.where(hit.hit[:, None], color, 0.0)
    num_objects = scene.labels.shape[0]
    bins = grid.patch * (num_objects + 1) + hit.object_id + 1
    counts = jnp.zeros(grid.num_patches * (num_objects + 1), jnp.int32).at[bins].add(1)
    counts = counts.reshape(grid.num_patches, num_objects + 1)
    winner = jnp.argmax(counts, axis=1)
    total = jnp.sum(counts, axis=1)
    fraction = counts[jnp.arange(grid.num_patches), winner] / jnp.maximum(total, 1)
    patch_object = jnp.where(total > 0, winner - 1, -1).astype(jnp.int32)
    patch_fraction = jnp.where(patch_object >= 0, fraction, 0.0).astype(jnp.float32)
    return Render(
        object_id=hit.object_id,
        depth=depth,
        t=hit.t,
        color=color,
        valid=hit.hit,
        patch_object=patch_object,
        patch_fraction=patch_fraction,
    )


def _check_pose(pose: Array, tilt: Array | None, batch: bool) -> None:
    want = "(N, 4)" if batch else "(4,)"
    if jnp.ndim(pose) != (2 if batch else 1) or jnp.shape(pose)[-1] != 4:
        raise ValueError(f"pose must have shape {want} = (x, y, z, yaw), got {jnp.shape(pose)}")
    if tilt is not None and jnp.shape(tilt)[-1:] != (2,):
        raise ValueError(f"tilt must be (pitch, roll) with shape (..., 2), got {jnp.shape(tilt)}")


def render(
    scene: SceneGraph,
    pose: Array,
    camera: Camera,
    grid: RayGrid,
    tilt: Array | None = None,
    *,
    engine: str = "auto",
    differentiable: bool = True,
) -> Render:
    """Render one view from ``pose = (x, y, z, yaw)`` (4,) with an optional known tilt (2,).

    Rays follow ``grid`` (see :func:`jaxloc.stride_grid` / :func:`jaxloc.patch_grid`); the frame
    conventions are those of :mod:`jaxloc.geometry`. Differentiable in ``pose`` through ``depth``
    and ``t`` (the hit triangle itself is piecewise constant). ``engine`` (static) picks the
    nearest-hit engine of :func:`jaxloc.raycast`; ``differentiable=False`` (static) takes its
    values-only path (the engine's own distances and barycentric coordinates, no gradient).
    """
    _check_pose(pose, tilt, batch=False)
    d_cam, d_world = _world_rays(pose, camera, grid, tilt)
    order = _tile_order(grid, engine)
    if order is not None:
        d_world = d_world[order]
    hit = raycast(
        scene,
        pose[:3],
        d_world,
        engine=engine,
        differentiable=differentiable,
        packet_size=PACKET_SIZE,
    )
    if order is not None:
        inverse = np.argsort(order)
        hit = jax.tree.map(lambda a: a[inverse], hit)
    return _views(scene, hit, d_cam, grid)


def render_batch(
    scene: SceneGraph,
    poses: Array,
    camera: Camera,
    grid: RayGrid,
    tilt: Array | None = None,
    *,
    engine: str = "auto",
    differentiable: bool = True,
) -> Render:
    """Render N views (``poses`` (N, 4), ``tilt`` None, (2,) shared or (N, 2)) in one raycast.

    Returns a :class:`Render` whose arrays have a leading N axis; equal to ``jax.vmap(render)``.
    ``engine`` and ``differentiable`` (static) are those of :func:`render`.
    """
    _check_pose(poses, tilt, batch=True)
    num = poses.shape[0]
    tilts = None if tilt is None else jnp.broadcast_to(tilt, (num, 2))
    d_cam = camera.directions(grid.uv)
    rotations = (
        jax.vmap(rotation_world_cam)(poses[:, 3], tilts)
        if tilts is not None
        else (jax.vmap(rotation_world_cam)(poses[:, 3]))
    )
    order = _tile_order(grid, engine)
    num_rays = grid.uv.shape[0]
    rays = d_cam if order is None else d_cam[order]
    with jax.named_scope("rays"):
        d_world = _rotate(rotations, rays)  # (N, R, 3)
    if order is None:  # cast in the grid's own order, nothing to permute
        origins = jnp.broadcast_to(poses[:, None, :3], d_world.shape)
        hits = raycast(scene, origins, d_world, engine=engine, differentiable=differentiable)
        with jax.named_scope("views"):
            return jax.vmap(lambda h: _views(scene, h, d_cam, grid))(hits)
    # The "jax" engine: whole packets of neighbouring rays (NaN-origin padding rays miss).
    padded = -(-num_rays // PACKET_SIZE) * PACKET_SIZE
    d_world = jnp.pad(d_world, ((0, 0), (0, padded - num_rays), (0, 0)), constant_values=1.0)
    origins = jnp.broadcast_to(poses[:, None, :3], d_world.shape)
    origins = jnp.where(jnp.arange(padded)[None, :, None] < num_rays, origins, jnp.nan)
    hits = raycast(
        scene,
        origins,
        d_world,
        engine=engine,
        differentiable=differentiable,
        packet_size=PACKET_SIZE,
    )
    inverse = np.argsort(order)
    with jax.named_scope("views"):
        hits = jax.tree.map(lambda a: a[:, :num_rays][:, inverse], hits)
        return jax.vmap(lambda h: _views(scene, h, d_cam, grid))(hits)
