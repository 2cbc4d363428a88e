"""Host-side entry points of the refinement: one frame (:func:`refine_frame`) or a sequence
(:func:`refine`), their inputs validated and packed into :class:`Observations`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jax import Array

from jaxloc.camera import Camera, stride_grid
from jaxloc.geometry import uncompose_yaw, yaw_pose_to_se3
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc._sequence import FrameSequence
from jaxloc.sg2loc.refine.config import Observations, RefineConfig, RefineResult
from jaxloc.sg2loc.refine.solve import refine_pose_jit


def frame_poses_from_last(yaw_pose_last: Array, ego_motion: Array, tilt: Array) -> jaxlie.SE3:
    """``T_world_cam`` (F,) of every frame from the last frame's 4-DoF pose and the ego-motion.

    Args:
        yaw_pose_last: (4,) ``(x, y, z, yaw)`` of the last frame.
        ego_motion: (F-1, 4) motion from frame t to t+1 in frame t's body frame.
        tilt: (F, 2) known (pitch, roll) of every frame.
    """

    def back(current, motion):
        previous = uncompose_yaw(current, motion)
        return previous, previous

    _, earlier = jax.lax.scan(back, yaw_pose_last, ego_motion, reverse=True)
    yaw_poses = jnp.concatenate([earlier, yaw_pose_last[None]], axis=0)
    return jax.vmap(yaw_pose_to_se3)(yaw_poses, tilt)


def depth_samples(camera: Camera, depth_image, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ``stride``-th pixel of depth images: uv (N, 2) and depth (..., N) (host numpy).

    ``depth_image`` is (..., H, W) metres along the optical axis, 0 = invalid. Pixels are those
    of :func:`jaxloc.stride_grid` (centres at integer coordinates).
    """
    uv = np.asarray(stride_grid(camera, stride).uv)
    cols = uv[:, 0].astype(int)
    rows = uv[:, 1].astype(int)
    return uv, np.asarray(depth_image, np.float32)[..., rows, cols]


def _as_array(name: str, value, shape_tail: tuple[int, ...], ndim: int) -> np.ndarray:
    array = np.asarray(value)
    if not (np.issubdtype(array.dtype, np.floating) or np.issubdtype(array.dtype, np.integer)):
        raise TypeError(f"{name} must be a real numeric array, got dtype {array.dtype}")
    if array.ndim != ndim or array.shape[ndim - len(shape_tail) :] != shape_tail:
        tail = ", ".join(str(s) for s in shape_tail)
        lead = "(F, M, " if ndim == len(shape_tail) + 2 else "(M, "
        raise ValueError(f"{name} must have shape {lead}{tail}), got {array.shape}")
    array = array.astype(np.float32)
    if not np.all(np.isfinite(array)):
        bad = int(np.sum(~np.isfinite(array)))
        raise ValueError(
            f"{name} contains {bad} NaN/inf values (drop those correspondences or mask them)"
        )
    return array


def correspondences(uv, points_world, valid=None, *, num_frames: int | None = None):
    """Validated correspondence arrays for :func:`refine`: (F, M, 2), (F, M, 3), (F, M) bool.

    Args:
        uv: pixel coordinates (M, 2) of one frame, or (F, M, 2) for ``num_frames = F`` frames.
        points_world: the matching world points (M, 3) or (F, M, 3), metres.
        valid: optional mask (M,) or (F, M); rows whose mask is False are ignored.
        num_frames: F for per-frame arrays (``mode="sequence"``); None for one frame.

    Raises:
        ValueError: naming the argument, on a wrong shape or NaN/inf values.
    """
    ndim = 2 if num_frames is None else 3
    uv = _as_array("uv", uv, (2,), ndim)
    points = _as_array("points_world", points_world, (3,), ndim)
    if points.shape[:-1] != uv.shape[:-1]:
        raise ValueError(
            f"points_world {points.shape} must match uv {uv.shape} (one world point per pixel)"
        )
    if num_frames is not None and uv.shape[0] != num_frames:
        raise ValueError(f"uv has {uv.shape[0]} frames, expected {num_frames}")
    if valid is None:
        valid = np.ones(uv.shape[:-1], bool)
    valid = np.asarray(valid)
    if valid.shape != uv.shape[:-1] or valid.dtype != bool:
        raise ValueError(f"valid must be a bool array of shape {uv.shape[:-1]}, got {valid.shape}")
    if num_frames is None:
        uv, points, valid = uv[None], points[None], valid[None]
    return uv, points, valid


def refine_frame(
    scene: SceneGraph,
    camera: Camera,
    T_init: jaxlie.SE3,
    config: RefineConfig | None = None,
    *,
    depth=None,
    match_uv=None,
    match_points=None,
    match_valid=None,
    T_rel: jaxlie.SE3 | None = None,
) -> RefineResult:
    """Refine ``T_world_cam`` from a full SE(3) start (``config.mode`` is ignored).

    One frame by default. With ``T_rel`` (F,) (each frame's pose relative to the last one,
    ``T_last^-1 T_t``, e.g. from visual-inertial odometry) the F frames are refined jointly, as
    ``mode="sequence"`` does with the filter's 4-DoF ego-motion, and the observations are per
    frame.

    Args:
        scene: the map; camera: intrinsics.
        T_init: initial ``T_world_cam`` of the (last) frame (jaxlie.SE3, unbatched).
        config: :class:`RefineConfig`.
        depth: (H, W) depth image (metres along the optical axis, 0 = invalid), for depth residuals;
            (F, H, W) with ``T_rel``.
        match_uv: (M, 2) pixels of 2D-3D correspondences; (F, M, 2) with ``T_rel``.
        match_points: (M, 3) their world points (metres); (F, M, 3) with ``T_rel``.
        match_valid: optional (M,) bool mask of them; (F, M) with ``T_rel``.
        T_rel: optional jaxlie.SE3 with a leading (F,) axis, the last entry the identity.
    """
    config = RefineConfig() if config is None else config
    params = np.asarray(T_init.parameters())
    if params.shape != (7,) or not np.all(np.isfinite(params)):
        raise ValueError(f"T_init must be one finite jaxlie.SE3, got parameters {params!r}")
    if T_rel is None:
        rel = np.asarray(jaxlie.SE3.identity((1,)).parameters())
    else:
        rel = np.asarray(T_rel.parameters())
        if rel.ndim != 2 or rel.shape[0] < 1 or rel.shape[1] != 7 or not np.all(np.isfinite(rel)):
            raise ValueError(
                f"T_rel must be a finite jaxlie.SE3 with one leading (F,) axis, got parameters "
                f"of shape {rel.shape}"
            )
    frames = rel.shape[0]
    if config.uses_depth:
        if depth is None:
            raise ValueError(f"residuals={config.residuals!r} needs a depth image")
        depth = np.asarray(depth, np.float32)
        expected = (
            (camera.height, camera.width)
            if T_rel is None
            else (frames, camera.height, camera.width)
        )
        if depth.shape != expected:
            names = "(H, W)" if T_rel is None else "(F, H, W)"
            raise ValueError(f"depth must have shape {names} = {expected}, got {depth.shape}")
        if T_rel is None:
            depth = depth[None]
    observations = _observations(
        camera,
        config,
        frames,
        depth,
        match_uv,
        match_points,
        match_valid,
        per_frame=T_rel is not None,
    )
    return refine_pose_jit(
        scene,
        camera,
        jaxlie.SE3(jnp.asarray(params)),
        jaxlie.SE3(jnp.asarray(rel)),
        observations,
        config,
    )


def _observations(
    camera, config, frames, depth_images, match_uv, match_points, match_valid, per_frame
) -> Observations:
    """Validated :class:`Observations` of ``frames`` frames (host side)."""
    if config.uses_matches:
        if match_uv is None or match_points is None:
            raise ValueError(
                f"residuals={config.residuals!r} needs match_uv and match_points correspondences"
            )
        uv, points, valid = correspondences(
            match_uv, match_points, match_valid, num_frames=frames if per_frame else None
        )
    else:
        uv = np.zeros((frames, 0, 2), np.float32)
        points = np.zeros((frames, 0, 3), np.float32)
        valid = np.zeros((frames, 0), bool)
    if config.uses_depth:
        depth_uv, depth = depth_samples(camera, depth_images, config.depth_stride)
    else:
        depth_uv, depth = np.zeros((0, 2), np.float32), np.zeros((frames, 0), np.float32)
    return Observations(
        depth_uv=jnp.asarray(depth_uv),
        depth=jnp.asarray(depth),
        match_uv=jnp.asarray(uv),
        match_points=jnp.asarray(points),
        match_valid=jnp.asarray(valid),
    )


def refine(
    scene: SceneGraph,
    sequence: FrameSequence,
    yaw_pose: Array,
    config: RefineConfig | None = None,
    *,
    match_uv=None,
    match_points=None,
    match_valid=None,
) -> RefineResult:
    """Refine the last frame of ``sequence`` from the filter's 4-DoF estimate ``yaw_pose``.

    Validates its inputs on the host, then runs the jitted :func:`refine_pose` (one compilation
    per shape and static configuration; frames of the same shape do not retrace).

    Args:
        scene: the map.
        sequence: the query (depth is needed for depth residuals; its tilt and ego-motion place
            the frames).
        yaw_pose: (4,) ``(x, y, z, yaw)`` estimate of the last frame, e.g.
            ``localize(...).poses[-1]``.
        config: :class:`RefineConfig`.
        match_uv: pixels of the correspondences for reprojection residuals: (M, 2) of the last
            frame in ``mode="last"``, (T, M, 2) in ``mode="sequence"``.
        match_points: their world points (metres): (M, 3), or (T, M, 3).
        match_valid: optional mask of them: (M,), or (T, M).

    Returns:
        :class:`RefineResult` (``pose`` is the last frame's refined ``T_world_cam``).
    """
    config = RefineConfig() if config is None else config
    if not isinstance(scene, SceneGraph):
        raise TypeError(f"scene must be a jaxloc.SceneGraph, got {type(scene).__name__}")
    if not isinstance(sequence, FrameSequence):
        raise TypeError(f"sequence must be a jaxloc.FrameSequence, got {type(sequence).__name__}")
    yaw_pose = np.asarray(yaw_pose, np.float32)
    if yaw_pose.shape != (4,) or not np.all(np.isfinite(yaw_pose)):
        raise ValueError(f"yaw_pose must be a finite (4,) (x, y, z, yaw), got {yaw_pose!r}")
    if config.uses_depth and sequence.depth is None:
        raise ValueError(f"residuals={config.residuals!r} needs a sequence with depth")
    frames = sequence.num_frames if config.mode == "sequence" else 1
    camera = sequence.camera
    observations = _observations(
        camera,
        config,
        frames,
        None if sequence.depth is None else sequence.depth[-frames:],
        match_uv,
        match_points,
        match_valid,
        per_frame=config.mode == "sequence",
    )
    poses = frame_poses_from_last(
        jnp.asarray(yaw_pose), jnp.asarray(sequence.ego_motion), jnp.asarray(sequence.tilt)
    )
    poses = jaxlie.SE3(poses.parameters()[-frames:])
    T_init = jaxlie.SE3(poses.parameters()[-1])
    T_rel = jaxlie.SE3(
        jax.vmap(lambda p: (T_init.inverse() @ jaxlie.SE3(p)).parameters())(poses.parameters())
    )
    return refine_pose_jit(scene, camera, T_init, T_rel, observations, config)
