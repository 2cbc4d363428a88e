"""Pinhole camera and the ray grids the filter casts: a patch grid or every ``stride``-th pixel.

Pixel centres sit at integer coordinates (OpenCV): pixel (u, v) covers ``[u - 0.5, u + 0.5)``.
A patch grid of ``rows x cols`` splits the image into equal rectangles; patch (r, c) covers
columns ``[c * W / cols, (c + 1) * W / cols)`` in continuous image coordinates (shifted by -0.5).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array


class Camera(eqx.Module):
    """A pinhole camera: focal lengths and principal point in pixels, image size static.

    Attributes:
        fx, fy: focal lengths (pixels).
        cx, cy: principal point (pixels, OpenCV: the centre of the top-left pixel is (0, 0)).
        width, height: image size in pixels (static Python ints).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __check_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, (int, float, np.floating, np.integer)) and not np.isfinite(value):
                raise ValueError(f"Camera.{name} must be finite, got {value}")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if isinstance(value, (int, float, np.floating, np.integer)) and value <= 0:
                raise ValueError(f"Camera.{name} must be positive, got {value}")
        if not (isinstance(self.width, int) and isinstance(self.height, int)):
            raise TypeError("Camera.width and Camera.height must be Python ints")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"Camera size must be positive, got {self.width}x{self.height}")

    @staticmethod
    def from_fov(width: int, height: int, hfov_deg: float) -> Camera:
        """A centred camera with the given horizontal field of view (degrees) and square pixels."""
        f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2.0)
        return Camera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height)

    def directions(self, uv: Array) -> Array:
        """Unit ray directions (..., 3), camera frame, through pixel coordinates ``uv`` (..., 2)."""
        x = (uv[..., 0] - self.cx) / self.fx
        y = (uv[..., 1] - self.cy) / self.fy
        d = jnp.stack([x, y, jnp.ones_like(x)], axis=-1)
        return d / jnp.linalg.norm(d, axis=-1, keepdims=True)


class RayGrid(eqx.Module):
    """Pixel positions of the rays one view casts, and which patch each ray falls into.

    Attributes:
        uv: (R, 2) float32 pixel coordinates of the R rays.
        patch: (R,) int32 patch index ``r * cols + c`` of each ray.
        rows, cols: the patch grid (static).
        shape: (h, w) of the ray image when the rays form a regular grid (static).
    """

    uv: Array
    patch: Array
    rows: int = eqx.field(static=True)
    cols: int = eqx.field(static=True)
    shape: tuple[int, int] = eqx.field(static=True)

    @property
    def num_patches(self) -> int:
        return self.rows * self.cols


def _patch_of(camera: Camera, uv: np.ndarray, rows: int, cols: int) -> np.ndarray:
    col = np.clip(np.floor((uv[:, 0] + 0.5) * cols / camera.width), 0, cols - 1)
    row = np.clip(np.floor((uv[:, 1] + 0.5) * rows / camera.height), 0, rows - 1)
    return (row * cols + col).astype(np.int32)


def _host_grid(
    camera: Camera, uv: np.ndarray, rows: int, cols: int, shape: tuple[int, int]
) -> RayGrid:
    """The grid of rays through ``uv`` (R, 2) on the device: concrete arrays even inside a
    caller's trace (a grid is built from static sizes only), put without a conversion program."""
    with jax.ensure_compile_time_eval():
        uv_device = jax.device_put(uv)
        patch = jax.device_put(_patch_of(camera, uv, rows, cols))
    return RayGrid(uv_device, patch, rows, cols, shape)


def stride_grid_shape(stride: int, width: int, height: int) -> tuple[int, int]:
    """(rows, cols) of the rays :func:`stride_grid` casts at ``stride`` on a width x height image
    (host ints; no camera needed)."""
    return len(range(stride // 2, height, stride)), len(range(stride // 2, width, stride))


def stride_grid(camera: Camera, stride: int, rows: int = 9, cols: int = 16) -> RayGrid:
    """Rays through every ``stride``-th pixel: u = stride // 2 + k * stride (k = 0, 1, ...).

    With a 960x540 image and stride 20 this casts 48 x 27 rays, 3 x 3 per 60 px patch.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    us = np.arange(stride // 2, camera.width, stride, dtype=np.float32)
    vs = np.arange(stride // 2, camera.height, stride, dtype=np.float32)
    uu, vv = np.meshgrid(us, vs)
    return _host_grid(camera, np.stack([uu.ravel(), vv.ravel()], axis=-1), rows, cols, uu.shape)


def patch_grid(camera: Camera, rows: int, cols: int, rays_per_side: int = 1) -> RayGrid:
    """``rays_per_side**2`` rays per patch of a ``rows x cols`` grid, evenly spread inside it.

    With ``rays_per_side = 1`` each patch gets one ray through its centre.
    """
    if rows < 1 or cols < 1 or rays_per_side < 1:
        raise ValueError("rows, cols and rays_per_side must be >= 1")
    pw, ph = camera.width / cols, camera.height / rows
    sub = (np.arange(rays_per_side) + 0.5) / rays_per_side
    us = (np.arange(cols)[:, None] + sub[None, :]).ravel() * pw - 0.5
    vs = (np.arange(rows)[:, None] + sub[None, :]).ravel() * ph - 0.5
    uu, vv = np.meshgrid(us.astype(np.float32), vs.astype(np.float32))
    return _host_grid(camera, np.stack([uu.ravel(), vv.ravel()], axis=-1), rows, cols, uu.shape)
