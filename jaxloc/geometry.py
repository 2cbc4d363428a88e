"""Poses and frames: 4-DoF yaw poses, full SE(3) via jaxlie, the camera/body conventions.

Conventions (a contract of the whole library):

* World z is up (gravity along -z).
* A camera pose ``(x, y, z, yaw)``: ``(x, y, z)`` is the camera centre in the world (metres);
  ``yaw`` (radians) is the azimuth of the level optical axis, counter-clockwise about world +z
  from world +x.
* Camera frame: OpenCV (x right, y down, z forward).
* Gravity-aligned body frame: x forward (the level optical axis), y left, z up.
  ``R_body_cam`` maps camera z to body +x, camera x to body -y, camera y to body -z.
* A tilted camera with known gravity: ``R_world_cam = R_z(yaw) R_y(pitch) R_x(roll) R_body_cam``,
  so ``pitch > 0`` tilts the optical axis down and ``roll > 0`` raises the camera's left side.
* Ego-motion from frame t to t+1: ``(R_z(-yaw_t) (p_{t+1} - p_t), wrap(yaw_{t+1} - yaw_t))``.

Every function works on one pose; leading batch axes come from ``jax.vmap`` (or jaxlie's own
broadcasting for SE(3) objects). :func:`consecutive_ego_motions` is the one batched, jitted helper
(a recording's ego-motion in one program, not one eager dispatch per operation).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jax import Array

#: ``R_body_cam`` (3, 3) float32: its columns are the camera axes (OpenCV) in the body frame.
#: (A numpy constant: a JAX one would start the backend and compile a conversion at import.)
R_BODY_CAM = np.array(
    [
        [0.0, 0.0, 1.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
    ],
    dtype=np.float32,
)


def wrap_angle(angle: Array) -> Array:
    """Wrap angles (radians) to ``[-pi, pi)``."""
    return (angle + jnp.pi) % (2.0 * jnp.pi) - jnp.pi


def rotation_world_cam(yaw: Array, tilt: Array | None = None) -> Array:
    """``R_world_cam`` (3, 3) of a camera with a yaw and an optional ``tilt = (pitch, roll)``."""
    r_world_body = jaxlie.SO3.from_z_radians(yaw)
    if tilt is not None:
        r_world_body = (
            r_world_body @ jaxlie.SO3.from_y_radians(tilt[0]) @ jaxlie.SO3.from_x_radians(tilt[1])
        )
    return jnp.matmul(
        r_world_body.as_matrix(), R_BODY_CAM.astype(r_world_body.wxyz.dtype), precision="highest"
    )


def yaw_pose_to_se3(pose: Array, tilt: Array | None = None) -> jaxlie.SE3:
    """``T_world_cam`` of a 4-DoF pose ``(x, y, z, yaw)`` (4,), with an optional known tilt (2,)."""
    rotation = jaxlie.SO3.from_matrix(rotation_world_cam(pose[3], tilt))
    return jaxlie.SE3.from_rotation_and_translation(rotation, pose[:3])


def se3_to_yaw_pose(T_world_cam: jaxlie.SE3) -> Array:
    """The 4-DoF pose ``(x, y, z, yaw)`` of a camera pose: yaw is the azimuth of the optical axis.

    Pitch and roll are dropped; for a tilted camera the optical axis' azimuth is still its yaw
    (the azimuth is undefined for a camera looking straight up or down, where this returns 0).
    """
    axis = T_world_cam.rotation().as_matrix()[:, 2]
    yaw = jnp.arctan2(axis[1], axis[0])
    return jnp.concatenate([T_world_cam.translation(), yaw[None]])


def compose_yaw(pose: Array, delta: Array) -> Array:
    """Apply a body-frame 4-DoF motion ``delta = (dx, dy, dz, dyaw)`` to ``pose = (x, y, z, yaw)``.

    ``p' = p + R_z(yaw) d``, ``yaw' = wrap(yaw + dyaw)``: the inverse of :func:`ego_motion`.
    """
    c, s = jnp.cos(pose[3]), jnp.sin(pose[3])
    dx = c * delta[0] - s * delta[1]
    dy = s * delta[0] + c * delta[1]
    return jnp.stack(
        [pose[0] + dx, pose[1] + dy, pose[2] + delta[2], wrap_angle(pose[3] + delta[3])]
    )


def ego_motion(pose_a: Array, pose_b: Array) -> Array:
    """Motion ``(dx, dy, dz, dyaw)`` from ``pose_a`` to ``pose_b`` in a's gravity-aligned frame.

    The inverse of :func:`compose_yaw`: ``compose_yaw(a, ego_motion(a, b)) == b``.
    """
    c, s = jnp.cos(pose_a[3]), jnp.sin(pose_a[3])
    d = pose_b[:3] - pose_a[:3]
    return jnp.stack(
        [c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2], wrap_angle(pose_b[3] - pose_a[3])]
    )


@jax.jit
def consecutive_ego_motions(poses: Array) -> Array:
    """(T-1, 4) :func:`ego_motion` between consecutive poses of (T, 4) ``(x, y, z, yaw)`` poses
    (T >= 1), one compiled program per T."""
    return jax.vmap(ego_motion)(poses[:-1], poses[1:])


def uncompose_yaw(pose_b: Array, delta: Array) -> Array:
    """The pose a with ``compose_yaw(a, delta) == pose_b``: carries a pose back through a motion."""
    yaw_a = wrap_angle(pose_b[3] - delta[3])
    c, s = jnp.cos(yaw_a), jnp.sin(yaw_a)
    dx = c * delta[0] - s * delta[1]
    dy = s * delta[0] + c * delta[1]
    return jnp.stack([pose_b[0] - dx, pose_b[1] - dy, pose_b[2] - delta[2], yaw_a])


def transform_points(T: jaxlie.SE3, points: Array) -> Array:
    """Apply a rigid transform to points (..., 3)."""
    return jnp.matmul(points, T.rotation().as_matrix().T, precision="highest") + T.translation()
