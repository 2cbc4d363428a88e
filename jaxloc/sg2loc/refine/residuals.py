"""Residual kernels of :mod:`jaxloc.sg2loc.refine`, one frame each: depth pixels against the map's
planes (point-to-plane, with the data association by raycasting) and reprojection errors of 2D-3D
correspondences. Pure and jit/vmap-able; see :mod:`jaxloc.sg2loc.refine` for the model.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
from jax import Array

from jaxloc.camera import Camera
from jaxloc.raycasting import raycast
from jaxloc.scene import SceneGraph


def _triangle_planes(scene: SceneGraph, triangle: Array) -> tuple[Array, Array, Array]:
    """Unit normal (..., 3), a corner (..., 3) and validity (...) of triangles (-1: none)."""
    tri = scene.triangles[jnp.maximum(triangle, 0)]
    normal = jnp.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
    squared = jnp.sum(normal * normal, axis=-1, keepdims=True)
    ok = (triangle >= 0) & (squared[..., 0] > 0)
    unit = normal * jax.lax.rsqrt(jnp.where(squared > 0, squared, 1.0))
    return unit, tri[..., 0, :], ok


class DepthPlanes(eqx.Module):
    """The planes depth pixels are compared with (data association of one frame, no gradient).

    Attributes:
        normal: (N, 3) unit normal of the triangle hit by each pixel's ray (world frame).
        corner: (N, 3) a corner of that triangle (world frame, metres).
        valid: (N,) bool: valid depth, a hit, and not grazing.
    """

    normal: Array
    corner: Array
    valid: Array


def _camera_points(camera: Camera, uv: Array, depth: Array) -> tuple[Array, Array]:
    """Back-projected points ``p_cam`` (N, 3) (metres) and the valid-depth mask (N,)."""
    depth_ok = jnp.isfinite(depth) & (depth > 0)
    safe_depth = jnp.where(depth_ok, depth, 0.0)
    x = (uv[:, 0] - camera.cx) / camera.fx
    y = (uv[:, 1] - camera.cy) / camera.fy
    return safe_depth[:, None] * jnp.stack([x, y, jnp.ones_like(x)], axis=-1), depth_ok


def associate_depth(
    T_world_cam: jaxlie.SE3,
    scene: SceneGraph,
    camera: Camera,
    uv: Array,
    depth: Array,
    min_incidence: float | Array = 0.1,
    search_radius: int = 0,
    search_spacing: float | Array = 4.0,
    *,
    engine: str = "auto",
) -> DepthPlanes:
    """The scene plane each depth pixel is compared with, found by raycasting from ``T_world_cam``.

    With ``search_radius = 0`` this is projective association: the triangle hit by the pixel's own
    ray. With ``search_radius = k`` the rays through a ``(2k+1) x (2k+1)`` window of pixels around
    it (``search_spacing`` pixels apart) are cast too and the hit closest in 3-D to the
    back-projected point wins (a local closest-point search, so a point seen across an occlusion
    edge is still compared with its own surface). No gradient flows through the association.

    Args:
        T_world_cam: the camera pose; uv: (N, 2) pixels; depth: (N,) metres (0 = invalid).
        min_incidence: candidate hits with ``|n . ray| < min_incidence`` are dropped (grazing).
        search_radius: window half-size in candidate rays (static Python int).
        search_spacing: pixels between candidate rays.
        engine: nearest-hit engine (static; see :func:`jaxloc.raycast`).
    """
    T_world_cam = jax.lax.stop_gradient(T_world_cam)
    steps = jnp.arange(-search_radius, search_radius + 1, dtype=jnp.float32) * search_spacing
    offsets = jnp.stack(jnp.meshgrid(steps, steps, indexing="ij"), axis=-1).reshape(-1, 2)
    candidates = uv[:, None, :] + offsets[None, :, :]  # (N, K, 2)
    rotation = T_world_cam.rotation().as_matrix()
    origin = T_world_cam.translation()
    rays = jnp.matmul(camera.directions(candidates), rotation.T, precision="highest")
    hit = raycast(scene, origin, rays, engine=engine)
    normal, corner, plane_ok = _triangle_planes(scene, hit.triangle_id)
    incidence = jnp.abs(jnp.sum(normal * rays, axis=-1))
    usable = hit.hit & plane_ok & (incidence >= min_incidence)
    p_cam, depth_ok = _camera_points(camera, uv, depth)
    p_world = T_world_cam @ p_cam
    p_hit = origin + jnp.where(usable, hit.t, 0.0)[..., None] * rays
    distance = jnp.where(usable, jnp.sum((p_hit - p_world[:, None, :]) ** 2, axis=-1), jnp.inf)
    best = jnp.argmin(distance, axis=1)
    pick = lambda a: jnp.take_along_axis(a, best[:, None, None], axis=1)[:, 0]  # noqa: E731
    valid = depth_ok & jnp.any(usable, axis=1)
    return DepthPlanes(pick(normal), pick(corner), valid)


def point_to_plane(
    T_world_cam: jaxlie.SE3, camera: Camera, uv: Array, depth: Array, planes: DepthPlanes
) -> tuple[Array, Array]:
    """``n . (p_world - corner)`` (N,) metres for fixed planes (0 where masked) and valid (N,)."""
    p_cam, depth_ok = _camera_points(camera, uv, depth)
    p_world = T_world_cam @ p_cam
    residual = jnp.sum(planes.normal * (p_world - planes.corner), axis=-1)
    valid = planes.valid & depth_ok & jnp.isfinite(residual)
    return jnp.where(valid, residual, 0.0), valid


def depth_residuals(
    T_world_cam: jaxlie.SE3,
    scene: SceneGraph,
    camera: Camera,
    uv: Array,
    depth: Array,
    min_incidence: float | Array = 0.1,
    search_radius: int = 0,
    search_spacing: float | Array = 4.0,
    *,
    engine: str = "auto",
) -> tuple[Array, Array]:
    """Point-to-plane residuals of depth pixels against the scene raycast, one frame.

    Args:
        T_world_cam: the camera pose.
        scene: the map.
        camera: intrinsics.
        uv: (N, 2) pixel coordinates; depth: (N,) depth along the optical axis (metres,
            0 / non-finite = invalid).
        min_incidence: hits with ``|n . ray| < min_incidence`` are masked (grazing).
        search_radius: the association window's half-size in rays (:func:`associate_depth`);
            0 uses the hit of the pixel's own ray.
        search_spacing: pixels between the window's rays (:func:`associate_depth`).
        engine: nearest-hit engine (static; see :func:`jaxloc.raycast`).

    Returns:
        residual (N,) float32 metres (``n . (p_world - p_hit)``, 0 where masked) and valid (N,).
        Differentiable in the pose; the hit triangle (the association) is piecewise constant.
    """
    planes = associate_depth(
        T_world_cam,
        scene,
        camera,
        uv,
        depth,
        min_incidence,
        search_radius,
        search_spacing,
        engine=engine,
    )
    return point_to_plane(T_world_cam, camera, uv, depth, planes)


def reprojection_residuals(
    T_world_cam: jaxlie.SE3,
    camera: Camera,
    uv: Array,
    points_world: Array,
    valid: Array,
    min_depth: float | Array = 0.05,
) -> tuple[Array, Array]:
    """Reprojection errors (pixels) of 2D-3D correspondences, one frame.

    Args:
        T_world_cam: the camera pose.
        camera: intrinsics.
        uv: (M, 2) observed pixel coordinates; points_world: (M, 3) world points (metres);
            valid: (M,) bool mask.
        min_depth: points less than this far in front of the camera (metres) are masked.

    Returns:
        residual (M, 2) float32 ``projection - uv`` in pixels (0 where masked) and valid (M,).
    """
    finite = jnp.all(jnp.isfinite(uv), axis=-1) & jnp.all(jnp.isfinite(points_world), axis=-1)
    safe_points = jnp.where(finite[:, None], points_world, 0.0)
    safe_uv = jnp.where(finite[:, None], uv, 0.0)
    p_cam = T_world_cam.inverse() @ safe_points
    in_front = p_cam[:, 2] > min_depth
    z = jnp.where(in_front, p_cam[:, 2], 1.0)
    projected = jnp.stack(
        [camera.fx * p_cam[:, 0] / z + camera.cx, camera.fy * p_cam[:, 1] / z + camera.cy], axis=-1
    )
    ok = valid & finite & in_front
    return jnp.where(ok[:, None], projected - safe_uv, 0.0), ok
