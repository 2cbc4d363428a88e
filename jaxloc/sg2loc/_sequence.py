"""The observations of one query sequence: what a user hands to :func:`jaxloc.sg2loc.localize`;
and the same sampled on a pass's ray grid, one :class:`Frame` per step (:func:`frames_on_grid`)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc._traced import concrete
from jaxloc.camera import Camera, RayGrid


def _as_finite(name: str, value, ndim: int, dtype=np.float32) -> np.ndarray:
    array = np.asarray(value)
    if array.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {array.shape}")
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise TypeError(f"{name} must be a real numeric array, got dtype {array.dtype}")
    array = array.astype(dtype)
    if not np.all(np.isfinite(array)):
        bad = int(np.size(array) - np.count_nonzero(np.isfinite(array)))
        raise ValueError(f"{name} contains {bad} NaN/inf values")
    return array


class FrameSequence(eqx.Module):
    """A query sequence of T frames, validated on construction (host arrays, float32).

    Attributes:
        camera: the pinhole :class:`~jaxloc.Camera` of every frame.
        patch_embeddings: (T, rows, cols, d) per-patch embeddings of each image (any norm; they
            are compared by cosine). A zero vector marks a patch without an embedding (e.g. no
            known class in its label image): it adds nothing to the semantic score.
        ego_motion: (T-1, 4) motion from frame t to t+1 as (dx, dy, dz, dyaw), metres and
            radians, in frame t's gravity-aligned body frame (x forward, y left, z up).
        depth: optional (T, H, W) sensor depth in metres along the optical axis; 0 = invalid.
        rgb: optional (T, H, W, 3) colour in [0, 1].
        tilt: (T, 2) known (pitch, roll) of the camera relative to gravity in radians
            (zeros = level camera).
    """

    camera: Camera
    patch_embeddings: Array
    ego_motion: Array
    depth: Array | None
    rgb: Array | None
    tilt: Array

    def __init__(
        self,
        camera: Camera,
        patch_embeddings,
        ego_motion,
        depth=None,
        rgb=None,
        tilt=None,
    ):
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a jaxloc.Camera, got {type(camera).__name__}")
        emb = _as_finite("patch_embeddings", patch_embeddings, 4)
        num_frames = emb.shape[0]
        if num_frames < 1:
            raise ValueError("a sequence needs at least one frame")
        empty = num_frames == 1 and np.size(ego_motion) == 0
        if np.shape(ego_motion) != (num_frames - 1, 4) and not empty:
            raise ValueError(
                f"ego_motion must have shape (T-1, 4) = ({num_frames - 1}, 4) for T = {num_frames} "
                f"frames, got {np.shape(ego_motion)}"
            )
        motion = _as_finite("ego_motion", np.reshape(ego_motion, (-1, 4)), 2)
        image_shape = (num_frames, camera.height, camera.width)
        if depth is not None:
            depth = _as_finite("depth", depth, 3)
            if depth.shape != image_shape:
                raise ValueError(
                    f"depth must have shape (T, H, W) = {image_shape}, got {depth.shape}"
                )
            if np.any(depth < 0):
                raise ValueError("depth must be >= 0 (0 marks an invalid pixel)")
        if rgb is not None:
            rgb = _as_finite("rgb", rgb, 4)
            if rgb.shape != image_shape + (3,):
                raise ValueError(
                    f"rgb must have shape (T, H, W, 3) = {image_shape + (3,)}, got {rgb.shape}"
                )
            if rgb.min() < 0 or rgb.max() > 1:
                raise ValueError("rgb values must lie in [0, 1]")
        if tilt is None:
            tilt = np.zeros((num_frames, 2), np.float32)
        tilt = _as_finite("tilt", tilt, 2)
        if tilt.shape != (num_frames, 2):
            raise ValueError(f"tilt must have shape (T, 2) = ({num_frames}, 2), got {tilt.shape}")
        self.camera = camera
        self.patch_embeddings = emb
        self.ego_motion = motion
        self.depth = depth
        self.rgb = rgb
        self.tilt = tilt

    @classmethod
    def zeros(
        cls,
        camera: Camera,
        num_frames: int,
        patch_shape: tuple[int, int],
        embedding_dim: int,
        *,
        depth: bool = True,
        rgb: bool = True,
    ) -> FrameSequence:
        """A sequence of zeros with the shapes a recording of these sizes will have: a stand-in
        for :func:`jaxloc.sg2loc.warm_up`, which needs only shapes.

        Args:
            camera: the pinhole camera (its width and height size the images).
            num_frames: T.
            patch_shape: (rows, cols) of the patch grid.
            embedding_dim: d, the length of a patch embedding.
            depth: whether the recording has depth images.
            rgb: whether the recording has colour images.
        """
        rows, cols = patch_shape
        image = (num_frames, camera.height, camera.width)
        return cls(
            camera,
            np.zeros((num_frames, rows, cols, embedding_dim), np.float32),
            np.zeros((max(num_frames - 1, 0), 4), np.float32),
            depth=np.zeros(image, np.float32) if depth else None,
            rgb=np.zeros(image + (3,), np.float32) if rgb else None,
        )

    @property
    def num_frames(self) -> int:
        return self.patch_embeddings.shape[0]

    @property
    def patch_shape(self) -> tuple[int, int]:
        return self.patch_embeddings.shape[1], self.patch_embeddings.shape[2]


class Frame(eqx.Module):
    """One frame's observations, sampled on the pass's ray grid (R rays, P patches, d dims).

    Attributes:
        index: int32 frame number in the sequence.
        motion: (4,) float32 ego-motion from the previous frame (zeros for the first frame).
        patch_embeddings: (P, d) float32.
        depth: (R,) float32 sensor depth at the rays' pixels (0 = invalid).
        rgb: (h, w, 3) float32 colour at the rays' pixels, the ray image's shape.
        tilt: (2,) float32 (pitch, roll).
    """

    index: Array
    motion: Array
    patch_embeddings: Array
    depth: Array
    rgb: Array
    tilt: Array


def grid_pixels(camera: Camera, grid: RayGrid) -> tuple[np.ndarray | Array, np.ndarray | Array]:
    """The image pixel (row, column) of every ray of ``grid``: two (R,) int32 arrays, the nearest
    pixel centre, clipped to the image. NumPy arrays for a concrete grid (host side), traced ones
    for a traced grid."""
    xp = jnp if isinstance(grid.uv, jax.core.Tracer) else np
    uv = xp.asarray(grid.uv)
    cols = xp.clip(xp.rint(uv[:, 0]).astype(xp.int32), 0, camera.width - 1)
    rows = xp.clip(xp.rint(uv[:, 1]).astype(xp.int32), 0, camera.height - 1)
    return rows, cols


def frames_on_grid(sequence: FrameSequence, grid: RayGrid) -> Frame:
    """All frames of a sequence sampled on a ray grid, stacked with a leading T axis (with NumPy
    for a concrete sequence and grid, ``jax.numpy`` for traced ones)."""
    num_frames = sequence.num_frames
    rows_p, cols_p = sequence.patch_shape
    if (rows_p, cols_p) != (grid.rows, grid.cols):
        raise ValueError(
            f"the sequence has a {rows_p}x{cols_p} patch grid but the ray grid uses "
            f"{grid.rows}x{grid.cols} patches"
        )
    rows, cols = grid_pixels(sequence.camera, grid)
    xp = np if concrete(*jax.tree.leaves((sequence, rows))) else jnp
    h, w = grid.shape
    if sequence.depth is not None:
        depth = xp.asarray(sequence.depth)[:, rows, cols]
    else:
        depth = xp.zeros((num_frames, rows.shape[0]), xp.float32)
    if sequence.rgb is not None:
        rgb = xp.asarray(sequence.rgb)[:, rows, cols].reshape(num_frames, h, w, 3)
    else:
        rgb = xp.zeros((num_frames, h, w, 3), xp.float32)
    motion = xp.concatenate([xp.zeros((1, 4), xp.float32), xp.asarray(sequence.ego_motion)])
    embeddings = xp.asarray(sequence.patch_embeddings).reshape(num_frames, rows_p * cols_p, -1)
    return Frame(  # device_put: jnp.asarray would compile a conversion program per host array
        index=jax.device_put(np.arange(num_frames, dtype=np.int32)),
        motion=jax.device_put(motion),
        patch_embeddings=jax.device_put(embeddings),
        depth=jax.device_put(depth),
        rgb=jax.device_put(rgb),
        tilt=jax.device_put(sequence.tilt),
    )
