"""The observations of one query sequence: what a user hands to :func:`jaxloc.sg2loc.localize`."""

from __future__ import annotations

import equinox as eqx
import numpy as np
from jax import Array

from jaxloc.camera import Camera


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
