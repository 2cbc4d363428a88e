"""Simulated sensors of the synthetic indoor world: rendering, patch embeddings, depth, RGB and
ego-motion with configurable noise (host-side numpy, seeded ``numpy.random.Generator``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy import ndimage

from jaxloc.camera import Camera, stride_grid
from jaxloc.geometry import consecutive_ego_motions
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc import render


def render_views(
    meshes, object_ids: np.ndarray, camera: Camera, poses: np.ndarray, tilts: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full-resolution object ids, z-depth and colour of every pixel of every view.

    The query scene is rendered with jaxloc's own BVH raycaster (:func:`jaxloc.render`), one
    jitted view at a time, with the library's camera conventions (``rotation_world_cam``, pixel
    centres at integer coordinates).

    Args:
        meshes: world-frame trimesh meshes with per-vertex colours.
        object_ids: (n,) the id each mesh reports.
        camera: the pinhole camera.
        poses: (T, 4) camera poses (x, y, z, yaw).
        tilts: (T, 2) (pitch, roll), radians.

    Returns:
        object id (T, H, W) int32 (-1 on a miss), z-depth along the optical axis (T, H, W)
        float32 metres (+inf on a miss) and colour (T, H, W, 3) float32 in [0, 1].
    """
    scene = _bucketed_scene(list(meshes))
    grid = stride_grid(camera, 1)
    object_ids = np.asarray(object_ids, np.int32)
    views = [
        _render_view(scene, jnp.asarray(pose, jnp.float32), camera, grid, jnp.asarray(tilt))
        for pose, tilt in zip(poses, tilts, strict=True)
    ]
    index = np.stack([np.asarray(v.object_id) for v in views])
    image = (len(poses), camera.height, camera.width)
    object_id = np.where(index >= 0, object_ids[np.maximum(index, 0)], -1).astype(np.int32)
    depth = np.stack([np.asarray(v.depth) for v in views]).astype(np.float32)
    color = np.stack([np.asarray(v.color) for v in views]).astype(np.float32)
    return (
        object_id.reshape(image),
        depth.reshape(image),
        np.clip(color, 0, 1).reshape(image + (3,)),
    )


_render_view = jax.jit(render)


def _bucketed_scene(meshes: list) -> SceneGraph:
    """The meshes as a render-only scene padded to power-of-two capacities.

    Rooms differ in object and triangle counts; padding each count up to the next power of two
    lets the rooms of a dataset share a handful of compiled renderers instead of compiling one
    per room (the traversal only visits real nodes, so the padding costs memory, not time).
    """
    count = len(meshes)
    labels, embeddings = np.arange(count), np.ones((count, 1), np.float32)
    exact = SceneGraph.from_meshes(meshes, labels, embeddings).capacity
    bucket = exact._replace(
        **{
            name: 1 << max(int(getattr(exact, name)) - 1, 1).bit_length()
            for name in ("objects", "triangles", "nodes", "leaves", "edges")
        }
    )
    return SceneGraph.from_meshes(meshes, labels, embeddings, capacity=bucket)


def dominant_objects(object_images: np.ndarray, camera: Camera, rows: int, cols: int) -> np.ndarray:
    """(T, rows, cols) int32: the object covering most pixels of each patch (-1 if all miss)."""
    patch = np.asarray(stride_grid(camera, 1, rows, cols).patch)
    num_views = object_images.shape[0]
    ids = object_images.reshape(num_views, -1) + 1  # 0 = miss
    width = int(ids.max()) + 1
    keys = (np.arange(num_views)[:, None] * (rows * cols) + patch[None, :]) * width + ids
    counts = np.bincount(keys.ravel(), minlength=num_views * rows * cols * width)
    counts = counts.reshape(num_views, rows * cols, width)[..., 1:]
    best = np.where(counts.max(axis=-1) > 0, counts.argmax(axis=-1), -1)
    return best.reshape(num_views, rows, cols).astype(np.int32)


def _unit(rng: np.random.Generator, shape) -> np.ndarray:
    v = rng.normal(size=shape)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def patch_embeddings(
    rng: np.random.Generator,
    dominant: np.ndarray,
    embeddings: np.ndarray,
    confusion_rate: float,
    cosine_range: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Simulated SceneGraphLoc patch embeddings.

    A patch showing object k gets ``c e_j + sqrt(1 - c^2) u`` with ``u`` a random unit vector
    orthogonal to ``e_j`` and ``c ~ U(cosine_range)``, so its cosine with ``e_j`` is exactly c;
    ``j = k`` except with probability ``confusion_rate``, where j is another map object drawn
    uniformly. Patches showing nothing get a random unit vector.

    Args:
        dominant: (...,) int32 map object per patch, -1 for none.
        embeddings: (n, d) unit map object embeddings.

    Returns:
        (..., d) float32 unit embeddings, and (...,) bool: which patches were confused.
    """
    n, dim = embeddings.shape
    confused = (dominant >= 0) & (rng.uniform(size=dominant.shape) < confusion_rate) & (n > 1)
    other = (dominant + 1 + rng.integers(0, max(n - 1, 1), size=dominant.shape)) % n
    source = np.where(confused, other, dominant)
    target = embeddings[np.maximum(source, 0)]
    noise = rng.normal(size=dominant.shape + (dim,))
    noise -= np.sum(noise * target, axis=-1, keepdims=True) * target
    noise /= np.linalg.norm(noise, axis=-1, keepdims=True)
    cosine = rng.uniform(*cosine_range, size=dominant.shape + (1,))
    out = cosine * target + np.sqrt(1.0 - cosine**2) * noise
    out = np.where((dominant >= 0)[..., None], out, _unit(rng, dominant.shape + (dim,)))
    return out.astype(np.float32), confused


def sensor_depth(
    rng: np.random.Generator,
    depth: np.ndarray,
    relative_noise: float,
    hole_rate: float,
    model: str = "relative",
) -> np.ndarray:
    """Noisy sensor depth (T, H, W) float32 metres, 0 = invalid.

    ``"relative"``: each valid pixel is scaled by ``1 + relative_noise * N(0, 1)``. ``"kinect"``:
    each valid pixel gets axial noise of standard deviation ``0.0012 + 0.0019 (z - 0.4)^2``
    metres (Nguyen, Izadi and Lovell 2012), and pixels beyond :data:`KINECT_RANGE` or next to a
    depth edge (a neighbour more than 5 % nearer or farther) are invalid. Either way holes are
    blobs (a smoothed random field thresholded at its ``1 - hole_rate`` quantile, so each frame
    loses that fraction of pixels); pixels that see nothing are holes too.
    """
    if model == "kinect":
        sigma = 0.0012 + 0.0019 * (np.where(np.isfinite(depth), depth, 0.0) - 0.4) ** 2
        noisy = depth + sigma * rng.normal(size=depth.shape)
        finite = np.where(np.isfinite(depth), depth, 1e6)
        edge = np.zeros(depth.shape, bool)
        for axis in (1, 2):
            step = np.abs(np.diff(finite, axis=axis)) > 0.05 * np.minimum(
                finite[:, 1:] if axis == 1 else finite[:, :, 1:],
                finite[:, :-1] if axis == 1 else finite[:, :, :-1],
            )
            pad = [(0, 0)] * 3
            pad[axis] = (1, 0)
            edge |= np.pad(step, pad)
            pad[axis] = (0, 1)
            edge |= np.pad(step, pad)
        noisy = np.where(edge | (depth > KINECT_RANGE), 0.0, noisy)
    else:
        noisy = depth * (1.0 + relative_noise * rng.normal(size=depth.shape))
    num_views, height, width = depth.shape
    if hole_rate > 0:
        field = rng.normal(size=depth.shape)
        field = ndimage.gaussian_filter(
            field, sigma=(0, max(1.0, height / 60), max(1.0, width / 60))
        )
        flat = field.reshape(num_views, -1)
        count = int(round(hole_rate * height * width))
        threshold = np.partition(flat, flat.shape[1] - count, axis=1)[:, flat.shape[1] - count]
        holes = (flat >= threshold[:, None]) if count else np.zeros_like(flat, bool)
        noisy = np.where(holes.reshape(depth.shape), 0.0, noisy)
    noisy = np.where(np.isfinite(depth) & (noisy > 0), noisy, 0.0)
    return noisy.astype(np.float32)


#: The ``"kinect"`` depth model's range (metres): farther pixels are invalid.
KINECT_RANGE = 4.5


def sensor_rgb(
    rng: np.random.Generator, color: np.ndarray, noise: float, exposure_sigma: float
) -> np.ndarray:
    """Noisy RGB (T, H, W, 3) float32 in [0, 1]: a per-frame exposure gain ``exp(N(0, s))``
    times the rendered colour, plus per-pixel Gaussian noise, clipped."""
    gain = np.exp(exposure_sigma * rng.normal(size=(color.shape[0], 1, 1, 1)))
    noisy = color * gain + noise * rng.normal(size=color.shape)
    return np.clip(noisy, 0.0, 1.0).astype(np.float32)


def noisy_ego_motion(
    rng: np.random.Generator, poses: np.ndarray, translation_sigma: float, yaw_sigma: float
) -> np.ndarray:
    """(T-1, 4) ego-motion between consecutive poses plus independent Gaussian noise per frame
    (``translation_sigma`` metres on each of dx, dy, dz; ``yaw_sigma`` radians on dyaw)."""
    if len(poses) < 2:
        return np.zeros((0, 4), np.float32)
    true = np.asarray(consecutive_ego_motions(poses), np.float64)
    sigma = np.array([translation_sigma] * 3 + [yaw_sigma])
    noisy = true + sigma * rng.normal(size=true.shape)
    noisy[:, 3] = (noisy[:, 3] + np.pi) % (2 * np.pi) - np.pi
    return noisy.astype(np.float32)
