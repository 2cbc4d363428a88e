"""Frame conventions (a contract of the whole library) and 4-DoF pose algebra, checked against
rotation matrices written out independently in numpy."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from conftest import BODY_CAM, rot_x, rot_y, rot_z
from hypothesis import given, settings, strategies as st

from jaxloc import geometry as g

# Jitted once: hypothesis calls these many times.
compose = jax.jit(g.compose_yaw)
ego = jax.jit(g.ego_motion)
uncompose = jax.jit(g.uncompose_yaw)
to_se3_and_back = jax.jit(lambda pose, tilt: g.se3_to_yaw_pose(g.yaw_pose_to_se3(pose, tilt)))
r_world_cam = jax.jit(g.rotation_world_cam)


def f32(lo: float, hi: float):
    """Finite float32 values in [lo, hi]."""
    return st.floats(lo, hi, allow_nan=False).map(np.float32)


coord = f32(-50.0, 50.0)
angle = f32(-9.0, 9.0)  # about +-3 pi
poses = st.tuples(coord, coord, coord, angle).map(lambda p: np.array(p, np.float32))
small_motion = st.tuples(f32(-5, 5), f32(-5, 5), f32(-1, 1), angle).map(
    lambda p: np.array(p, np.float32)
)


def _angle_close(a, b, atol=1e-5):
    return abs((float(a) - float(b) + np.pi) % (2 * np.pi) - np.pi) <= atol


def test_level_camera_at_yaw_zero_looks_along_plus_x():
    r = np.asarray(r_world_cam(jnp.float32(0.0), None))
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-7)  # optical axis
    np.testing.assert_allclose(r @ [1, 0, 0], [0, -1, 0], atol=1e-7)  # image right = world -y
    np.testing.assert_allclose(r @ [0, 1, 0], [0, 0, -1], atol=1e-7)  # image down = world -z
    np.testing.assert_allclose(np.asarray(g.R_BODY_CAM), BODY_CAM)


@pytest.mark.parametrize("yaw", [0.3, np.pi / 2, 2.0, -1.0, np.pi])
def test_yaw_turns_counter_clockwise(yaw):
    r = np.asarray(r_world_cam(jnp.float32(yaw), None))
    np.testing.assert_allclose(r @ [0, 0, 1], [np.cos(yaw), np.sin(yaw), 0], atol=1e-6)
    np.testing.assert_allclose(r, rot_z(yaw) @ BODY_CAM, atol=1e-6)


def test_yaw_quarter_turn_looks_along_plus_y():
    r = np.asarray(r_world_cam(jnp.float32(np.pi / 2), None))
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 1, 0], atol=1e-6)


def test_pitch_positive_looks_down_and_roll_positive_raises_left_side():
    pitch = 0.3
    r = np.asarray(r_world_cam(jnp.float32(0.0), jnp.array([pitch, 0.0])))
    axis = r @ [0, 0, 1]
    np.testing.assert_allclose(axis, [np.cos(pitch), 0, -np.sin(pitch)], atol=1e-6)
    assert axis[2] < 0  # looks down
    roll = 0.2
    r = np.asarray(r_world_cam(jnp.float32(0.0), jnp.array([0.0, roll])))
    left = r @ [-1, 0, 0]  # the camera's left is -x in the image
    assert left[2] > 0  # raised
    np.testing.assert_allclose(left, [0, np.cos(roll), np.sin(roll)], atol=1e-6)
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-6)  # roll keeps the axis


@settings(max_examples=40, deadline=None)
@given(angle, f32(-1.4, 1.4), f32(-1.0, 1.0))
def test_tilted_rotation_matches_written_out_product(yaw, pitch, roll):
    r = np.asarray(r_world_cam(jnp.float32(yaw), jnp.array([pitch, roll], jnp.float32)))
    want = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll) @ BODY_CAM
    np.testing.assert_allclose(r, want, atol=2e-6)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=2e-6)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-5)


@settings(max_examples=50, deadline=None)
@given(poses, small_motion)
def test_compose_ego_motion_uncompose_are_inverses(pose, delta):
    b = np.asarray(compose(pose, delta))
    d = np.asarray(ego(pose, b))
    np.testing.assert_allclose(d[:3], delta[:3], atol=1e-4)
    assert _angle_close(d[3], delta[3])
    a = np.asarray(uncompose(b, delta))
    np.testing.assert_allclose(a[:3], pose[:3], atol=1e-4)
    assert _angle_close(a[3], pose[3])
    # And the other way round: compose(a, ego(a, b)) == b for arbitrary pairs.
    b2 = np.asarray(compose(pose, np.asarray(ego(pose, b))))
    np.testing.assert_allclose(b2[:3], b[:3], atol=1e-4)
    assert _angle_close(b2[3], b[3])
    assert -np.pi <= b[3] < np.pi and -np.pi <= a[3] < np.pi


def test_ego_motion_is_in_the_body_frame():
    a = np.array([1.0, 2.0, 0.5, np.pi / 2], np.float32)  # facing +y
    forward = np.asarray(ego(a, np.array([1.0, 3.0, 0.5, np.pi / 2], np.float32)))
    np.testing.assert_allclose(forward, [1, 0, 0, 0], atol=1e-6)  # moved along the optical axis
    left = np.asarray(ego(a, np.array([0.0, 2.0, 0.7, np.pi / 2 + 0.1], np.float32)))
    np.testing.assert_allclose(left, [0, 1, 0.2, 0.1], atol=1e-6)  # world -x is the body's left
    # Matches R_z(-yaw) (p_b - p_a) written out.
    rng = np.random.default_rng(0)
    for _ in range(5):
        pa, pb = rng.uniform(-5, 5, 4).astype(np.float32), rng.uniform(-5, 5, 4).astype(np.float32)
        want = rot_z(-pa[3]) @ (pb[:3] - pa[:3])
        np.testing.assert_allclose(np.asarray(ego(pa, pb))[:3], want, atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(poses, f32(-1.2, 1.2), f32(-1.0, 1.0))
def test_yaw_pose_se3_round_trip(pose, pitch, roll):
    back = np.asarray(to_se3_and_back(pose, jnp.array([pitch, roll], jnp.float32)))
    np.testing.assert_allclose(back[:3], pose[:3], atol=1e-5)
    assert _angle_close(back[3], pose[3], atol=1e-5)


def test_yaw_pose_to_se3_matches_matrices_and_transforms_points():
    pose = np.array([1.0, -2.0, 1.5, 0.7], np.float32)
    tilt = np.array([0.1, -0.2], np.float32)
    T = g.yaw_pose_to_se3(jnp.asarray(pose), jnp.asarray(tilt))
    want = rot_z(0.7) @ rot_y(0.1) @ rot_x(-0.2) @ BODY_CAM
    np.testing.assert_allclose(np.asarray(T.rotation().as_matrix()), want, atol=1e-6)
    np.testing.assert_allclose(np.asarray(T.translation()), pose[:3])
    pts = np.random.default_rng(0).normal(size=(7, 3)).astype(np.float32)
    np.testing.assert_allclose(
        np.asarray(g.transform_points(T, pts)), pts @ want.T + pose[:3], atol=1e-5
    )
    np.testing.assert_allclose(
        np.asarray(g.transform_points(T, pts)), np.asarray(T @ pts), atol=1e-5
    )
    # A point on the optical axis at depth 2 lies 2 m ahead of the camera centre.
    ahead = np.asarray(g.transform_points(T, jnp.array([[0.0, 0.0, 2.0]])))[0]
    np.testing.assert_allclose(ahead, pose[:3] + 2 * want[:, 2], atol=1e-5)
    assert isinstance(T, jaxlie.SE3)


def test_se3_to_yaw_pose_of_a_camera_looking_straight_down_is_defined():
    T = g.yaw_pose_to_se3(jnp.array([0.0, 0.0, 2.0, 1.0]), jnp.array([np.pi / 2, 0.0]))
    back = np.asarray(g.se3_to_yaw_pose(T))
    assert np.all(np.isfinite(back))


def test_wrap_angle_range():
    a = np.linspace(-20, 20, 2001, dtype=np.float32)
    w = np.asarray(g.wrap_angle(jnp.asarray(a)))
    assert np.all(w >= -np.pi) and np.all(w < np.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-5)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-5)


def test_pose_functions_vmap_over_poses():
    rng = np.random.default_rng(1)
    a = rng.uniform(-3, 3, (16, 4)).astype(np.float32)
    d = rng.uniform(-1, 1, (16, 4)).astype(np.float32)
    batched = np.asarray(jax.vmap(g.compose_yaw)(a, d))
    looped = np.stack([np.asarray(compose(a[i], d[i])) for i in range(16)])
    np.testing.assert_allclose(batched, looped, atol=1e-6)
    rb = np.asarray(jax.vmap(g.rotation_world_cam)(a[:, 3], d[:, :2]))
    for i in range(16):
        np.testing.assert_allclose(
            rb[i], rot_z(a[i, 3]) @ rot_y(d[i, 0]) @ rot_x(d[i, 1]) @ BODY_CAM, atol=2e-6
        )
