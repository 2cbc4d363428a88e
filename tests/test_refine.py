"""Tests of jaxloc.sg2loc.refine: residuals vs numpy references, gradients vs finite differences,
degenerate inputs, convergence on noise-free frames, traces, bad input.

The scene is the closed 6 x 4 x 3 m box room of conftest (analytic float64 raycasts in numpy) seen
by an 80 x 45 camera tilted down towards a corner, so three orthogonal planes (two walls and the
floor) fix all six degrees of freedom.

Compile time dominates this file, so every single-frame depth solve goes through one jitted
``SOLVE`` with one static configuration and one shape (its float settings are arrays, so changing
them does not retrace); (b) has its own, and (c) is tested with the sequence mode (one compile).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest
from conftest import BODY_CAM, ROOM, box_room, room_hits, rot_x, rot_y, rot_z

from jaxloc import Camera, FrameSequence, SceneGraph
from jaxloc.geometry import ego_motion, yaw_pose_to_se3
from jaxloc.lsq import RobustLoss
from jaxloc.sg2loc.refine import (
    STATUS_BAD_INPUT,
    STATUS_DEGENERATE,
    STATUS_DIVERGED,
    STATUS_POOR_FIT,
    STATUS_TOO_FEW_RESIDUALS,
    Observations,
    RefineConfig,
    correspondences,
    depth_residuals,
    depth_samples,
    frame_poses_from_last,
    refine,
    refine_frame,
    refine_pose,
    reprojection_residuals,
)
from jaxloc.sg2loc.refine.solve import _pose_std as pose_std

CAMERA = Camera.from_fov(80, 45, 60.0)
TILT = np.array([0.35, 0.05])
POSE = np.array([1.6, 1.2, 1.5, np.arctan2(2.8, 4.4)])  # looks towards the corner (6, 4)
STRIDE = 3
#: Pixels whose ray passes this close (metres) to a second wall are skipped in exact comparisons.
EDGE_GAP = 0.05


def numpy_rotation(yaw, tilt):
    return rot_z(yaw) @ rot_y(tilt[0]) @ rot_x(tilt[1]) @ BODY_CAM


def numpy_rays(camera: Camera, uv: np.ndarray) -> np.ndarray:
    d = np.stack(
        [(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy, np.ones(len(uv))],
        -1,
    )
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def room_depth(R: np.ndarray, origin: np.ndarray, camera: Camera) -> np.ndarray:
    """Analytic float64 z-depth image (H, W) of the box room."""
    uu, vv = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    uv = np.stack([uu.ravel(), vv.ravel()], -1).astype(np.float64)
    d_cam = numpy_rays(camera, uv)
    t, _, _ = room_hits(origin, d_cam @ R.T)
    return (t * d_cam[:, 2]).reshape(camera.height, camera.width).astype(np.float32)


def se3(R: np.ndarray, t: np.ndarray) -> jaxlie.SE3:
    return jaxlie.SE3.from_rotation_and_translation(
        jaxlie.SO3.from_matrix(jnp.asarray(R, jnp.float32)), jnp.asarray(t, jnp.float32)
    )


def perturbed(T: jaxlie.SE3, seed: int, metres: float = 0.3, degrees: float = 10.0) -> jaxlie.SE3:
    rng = np.random.default_rng(seed)
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    axis, direction = axis / np.linalg.norm(axis), direction / np.linalg.norm(direction)
    rotation = jaxlie.SO3.exp(jnp.asarray(np.deg2rad(degrees) * axis, jnp.float32))
    return jaxlie.SE3.from_rotation_and_translation(
        T.rotation() @ rotation, T.translation() + jnp.asarray(metres * direction, jnp.float32)
    )


def errors(T: jaxlie.SE3, T_ref: jaxlie.SE3) -> tuple[float, float]:
    delta = T_ref.inverse() @ T
    return (
        float(np.linalg.norm(np.asarray(T.translation() - T_ref.translation()))),
        float(np.rad2deg(np.linalg.norm(np.asarray(delta.rotation().log())))),
    )


@pytest.fixture(scope="module")
def room() -> SceneGraph:
    return SceneGraph.from_meshes(box_room(), np.arange(6), np.eye(6, 8))


@pytest.fixture(scope="module")
def truth():
    R = numpy_rotation(POSE[3], TILT)
    return R, POSE[:3], se3(R, POSE[:3])


@pytest.fixture(scope="module")
def depth_image(truth) -> np.ndarray:
    R, origin, _ = truth
    return room_depth(R, origin, CAMERA)


@pytest.fixture(scope="module")
def matches(truth):
    """60 exact 2D-3D correspondences at the true pose (world points on the room's walls)."""
    R, origin, _ = truth
    rng = np.random.default_rng(3)
    uv = np.stack([rng.uniform(0, 79, 60), rng.uniform(0, 44, 60)], -1)
    d_world = numpy_rays(CAMERA, uv) @ R.T
    t, _, _ = room_hits(origin, d_world)
    return uv.astype(np.float32), (origin + t[:, None] * d_world).astype(np.float32)


# ----------------------------------------------------------------------------- numpy references


def numpy_depth_residuals(R, origin, uv, depth):
    """Float64 point-to-plane residual against the analytic wall hit by each pixel's ray."""
    d_cam = numpy_rays(CAMERA, uv)
    d_world = d_cam @ R.T
    _, wall, gap = room_hits(origin, d_world)
    axis = np.array([2, 2, 0, 0, 1, 1])[wall]
    offset = np.array([0.0, ROOM[2], 0.0, ROOM[0], 0.0, ROOM[1]])[wall]
    p_cam = depth[:, None] * np.stack(
        [(uv[:, 0] - CAMERA.cx) / CAMERA.fx, (uv[:, 1] - CAMERA.cy) / CAMERA.fy, np.ones(len(uv))],
        -1,
    )
    p_world = p_cam @ R.T + origin
    residual = p_world[np.arange(len(uv)), axis] - offset  # the unit normal is +-e_axis
    incidence = np.abs(d_world[np.arange(len(uv)), axis])
    return residual, (depth > 0) & (incidence >= 0.1), gap


def test_depth_residuals_match_numpy(room, truth, depth_image):
    R, origin, _ = truth
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    depth = depth * (1.0 + 0.05 * np.sin(np.arange(depth.size)))  # a non-zero residual
    depth[::7] = 0.0  # invalid pixels
    R_off = R @ rot_z(0.02)
    origin_off = origin + np.array([0.05, -0.03, 0.02])
    residual, valid = jax.jit(depth_residuals)(
        se3(R_off, origin_off), room, CAMERA, jnp.asarray(uv), jnp.asarray(depth)
    )
    ref, ref_valid, gap = numpy_depth_residuals(R_off, origin_off, uv, depth)
    clear = gap > EDGE_GAP
    assert clear.sum() > 100
    np.testing.assert_array_equal(np.asarray(valid)[clear], ref_valid[clear])
    np.testing.assert_allclose(
        np.abs(np.asarray(residual))[clear], np.abs(np.where(ref_valid, ref, 0.0))[clear], atol=2e-5
    )
    assert np.all(np.asarray(residual)[~np.asarray(valid)] == 0.0)


def numpy_reprojection(R, origin, uv, points):
    p_cam = (points - origin) @ R
    front = p_cam[:, 2] > 0.05
    z = np.where(front, p_cam[:, 2], 1.0)
    projected = np.stack(
        [CAMERA.fx * p_cam[:, 0] / z + CAMERA.cx, CAMERA.fy * p_cam[:, 1] / z + CAMERA.cy], -1
    )
    return np.where(front[:, None], projected - uv, 0.0), front


def test_reprojection_residuals_match_numpy(truth, matches):
    R, origin, _ = truth
    uv, points = matches
    points = points.copy()
    points[0] = origin - 2.0 * R[:, 2]  # behind the camera
    points[1] = origin + 0.01 * R[:, 2]  # in front but closer than min_depth
    valid = np.ones(len(uv), bool)
    valid[2] = False
    R_off, origin_off = R @ rot_x(0.03), origin + np.array([0.1, 0.0, -0.05])
    residual, ok = jax.jit(reprojection_residuals)(
        se3(R_off, origin_off), CAMERA, jnp.asarray(uv), jnp.asarray(points), jnp.asarray(valid)
    )
    ref, front = numpy_reprojection(R_off, origin_off, uv.astype(np.float64), points)
    ref_ok = front & valid
    np.testing.assert_array_equal(np.asarray(ok), ref_ok)
    assert not ref_ok[0] and not ref_ok[1]
    np.testing.assert_allclose(np.asarray(residual), np.where(ref_ok[:, None], ref, 0.0), atol=2e-3)


def test_residuals_jit_equals_eager(room, truth, depth_image, matches):
    _, _, T = truth
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    args = (T, room, CAMERA, jnp.asarray(uv), jnp.asarray(depth * 1.01))
    for a, b in zip(jax.jit(depth_residuals)(*args), depth_residuals(*args), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)
    m_uv, points = matches
    args = (T, CAMERA, jnp.asarray(m_uv + 1.0), jnp.asarray(points), jnp.ones(len(m_uv), bool))
    for a, b in zip(
        jax.jit(reprojection_residuals)(*args), reprojection_residuals(*args), strict=True
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-4)


# ----------------------------------------------------------------------------- gradients


def tangent_jacobian(fn, T: jaxlie.SE3):
    """Autodiff and central finite-difference Jacobians of ``fn(T @ exp(delta))`` at delta = 0."""
    at = lambda delta: fn(T @ jaxlie.SE3.exp(delta))  # noqa: E731
    auto = np.asarray(jax.jacfwd(at)(jnp.zeros(6)))
    eps = 1e-3
    columns = []
    for k in range(6):
        step = np.zeros(6, np.float32)
        step[k] = eps
        plus, minus = np.asarray(at(jnp.asarray(step))), np.asarray(at(jnp.asarray(-step)))
        columns.append((plus.astype(np.float64) - minus) / (2 * eps))
    return auto, np.stack(columns, axis=-1)


def test_depth_residual_gradient_matches_finite_differences(room, truth, depth_image):
    R, origin, _ = truth
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    T = se3(R @ rot_y(0.01), origin + np.array([0.04, 0.02, -0.03]))
    _, ref_valid, gap = numpy_depth_residuals(
        R @ rot_y(0.01), origin + np.array([0.04, 0.02, -0.03]), uv, depth
    )
    fn = lambda pose: depth_residuals(pose, room, CAMERA, jnp.asarray(uv), jnp.asarray(depth))[0]  # noqa: E731
    auto, numeric = tangent_jacobian(jax.jit(fn), T)
    keep = (gap > EDGE_GAP) & ref_valid
    assert np.all(np.isfinite(auto))
    np.testing.assert_allclose(auto[keep], numeric[keep], atol=3e-3, rtol=1e-2)
    assert np.abs(auto[keep]).max() > 0.5  # not vacuous


def test_reprojection_gradient_matches_finite_differences(truth, matches):
    _, _, T = truth
    uv, points = matches
    fn = lambda pose: reprojection_residuals(  # noqa: E731
        pose, CAMERA, jnp.asarray(uv), jnp.asarray(points), jnp.ones(len(uv), bool)
    )[0]
    auto, numeric = tangent_jacobian(jax.jit(fn), T)
    np.testing.assert_allclose(auto, numeric, atol=0.5, rtol=2e-2)
    assert np.abs(auto).max() > 10.0


def test_gradients_finite_at_degenerate_configurations(room, truth, matches):
    _, _, T = truth
    # Grazing: a camera 1 mm above the floor looking level along it; depth all invalid or all
    # valid; correspondences on the camera centre, behind it and NaN rows.
    grazing = yaw_pose_to_se3(jnp.array([1.0, 2.0, 0.001, 0.0]))
    uv, depth = depth_samples(CAMERA, np.full((45, 80), 2.0, np.float32), STRIDE)

    @jax.jit
    def depth_jacobian(pose, d):
        return jax.jacfwd(
            lambda delta: depth_residuals(
                pose @ jaxlie.SE3.exp(delta), room, CAMERA, jnp.asarray(uv), d
            )[0]
        )(jnp.zeros(6))

    for pose, d in ((grazing, depth), (T, depth), (T, np.zeros_like(depth))):
        grad = depth_jacobian(pose, jnp.asarray(d))
        assert np.all(np.isfinite(np.asarray(grad)))
    m_uv, points = matches
    points = points[:4].copy()
    points[0] = np.asarray(T.translation())
    points[1] = np.asarray(T.translation()) - 3.0 * np.asarray(T.rotation().as_matrix())[:, 2]
    points[2] = np.nan
    grad = jax.jacfwd(
        lambda delta: reprojection_residuals(
            T @ jaxlie.SE3.exp(delta),
            CAMERA,
            jnp.asarray(m_uv[:4]),
            jnp.asarray(points),
            jnp.ones(4, bool),
        )[0]
    )(jnp.zeros(6))
    assert np.all(np.isfinite(np.asarray(grad)))
    assert np.all(np.asarray(grad)[:3] == 0.0) and np.any(np.asarray(grad)[3] != 0.0)


# ----------------------------------------------------------------------------- the solve


#: Traces of ``SOLVE`` (one expected for the whole file).
TRACES: list[int] = []


def _counted_refine_pose(*args):
    TRACES.append(1)
    return refine_pose(*args)


SOLVE = eqx.filter_jit(_counted_refine_pose)
#: The one static depth configuration of ``SOLVE``; floats as arrays so that variants share it.
DEPTH_CONFIG = RefineConfig(
    residuals="depth",
    depth_stride=STRIDE,
    max_translation=jnp.float32(1.0),
    max_position_std=jnp.float32(0.05),
    min_inlier_fraction=jnp.float32(0.0),
)
IDENTITY = jaxlie.SE3.identity((1,))


def observations(uv, depth, m_uv=None, points=None) -> Observations:
    m_uv = np.zeros((0, 2), np.float32) if m_uv is None else m_uv
    points = np.zeros((0, 3), np.float32) if points is None else points
    return Observations(
        depth_uv=jnp.asarray(uv),
        depth=jnp.asarray(depth)[None],
        match_uv=jnp.asarray(m_uv)[None],
        match_points=jnp.asarray(points)[None],
        match_valid=jnp.ones((1, len(m_uv)), bool),
    )


def test_depth_refinement_converges_without_retracing(room, truth, depth_image):
    """(a) from two 0.3 m / 10 deg perturbations; one trace for both frames; the box-room view
    constrains every direction, so it is not flagged as degenerate."""
    _, _, T_true = truth
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    results = []
    for seed in (0, 1):
        start = perturbed(T_true, seed)
        result = SOLVE(room, CAMERA, start, IDENTITY, observations(uv, depth), DEPTH_CONFIG)
        pos, rot = errors(result.pose, T_true)
        assert bool(result.ok) and int(result.status) == 0, (pos, rot, int(result.status))
        assert pos < 0.02 and rot < 0.5, (seed, pos, rot)
        assert 0 < float(result.position_std) < 0.05 and 0 < float(result.rotation_std) < 0.02
        results.append(result)
    again = SOLVE(
        room, CAMERA, perturbed(T_true, 1), IDENTITY, observations(uv, depth), DEPTH_CONFIG
    )
    np.testing.assert_array_equal(  # deterministic
        np.asarray(again.pose.parameters()), np.asarray(results[1].pose.parameters())
    )
    assert len(TRACES) == 1


def test_rounds_after_the_pose_settles_are_skipped(room, truth, depth_image):
    """Twice the association rounds give the same pose and the same step count: once a round no
    longer moves the pose, the rest are skipped (each would otherwise add solver steps)."""
    _, _, T_true = truth
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    start = perturbed(T_true, 0)
    base = SOLVE(room, CAMERA, start, IDENTITY, observations(uv, depth), DEPTH_CONFIG)
    doubled = dataclasses.replace(DEPTH_CONFIG, rounds=2 * DEPTH_CONFIG.rounds)
    longer = eqx.filter_jit(refine_pose)(
        room, CAMERA, start, IDENTITY, observations(uv, depth), doubled
    )
    assert bool(base.ok) and bool(longer.ok)
    assert int(longer.steps) == int(base.steps) < DEPTH_CONFIG.rounds * DEPTH_CONFIG.max_steps
    np.testing.assert_array_equal(
        np.asarray(longer.pose.parameters()), np.asarray(base.pose.parameters())
    )


def test_single_wall_view_is_flagged_degenerate(room):
    """A camera 1 m from the wall x = 6, looking straight at it, sees nothing else: the depth
    residuals leave the translation along the wall and the rotation about its normal free, so a
    solve that fits the depth exactly is still reported as degenerate (status 5)."""
    pose = np.array([5.0, 2.0, 1.5, 0.0])
    R = numpy_rotation(pose[3], np.zeros(2))
    depth_image = room_depth(R, pose[:3], CAMERA)
    _, wall, _ = room_hits(pose[:3], numpy_rays(CAMERA, np.array([[0.0, 0.0], [79.0, 44.0]])) @ R.T)
    assert np.all(wall == 3)  # the corner pixels see the wall x = 6 only
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    start = perturbed(se3(R, pose[:3]), 4, metres=0.05, degrees=2.0)
    result = SOLVE(room, CAMERA, start, IDENTITY, observations(uv, depth), DEPTH_CONFIG)
    assert not bool(result.ok) and int(result.status) == STATUS_DEGENERATE
    assert not np.isfinite(float(result.position_std))
    assert not np.isfinite(float(result.rotation_std))  # rotation about the wall normal is free
    np.testing.assert_array_equal(  # failure: the start pose is returned
        np.asarray(result.pose.parameters()), np.asarray(start.parameters())
    )
    assert len(TRACES) == 1


def test_joint_frames_determine_what_the_last_view_leaves_free(room, truth, depth_image):
    """The single-wall view above, refined jointly with an earlier frame that sees a corner
    (``refine_frame(..., T_rel=)``, relative poses known): converges from 0.3 m / 10 deg."""
    pose = np.array([5.0, 2.0, 1.5, 0.0])
    T_last = se3(numpy_rotation(pose[3], np.zeros(2)), pose[:3])
    _, _, T_first = truth  # looks towards the corner (6, 4)
    depth = np.stack(
        [depth_image, room_depth(np.asarray(T_last.rotation().as_matrix()), pose[:3], CAMERA)]
    )
    T_rel = jaxlie.SE3(jnp.stack([(T_last.inverse() @ T).parameters() for T in (T_first, T_last)]))
    start = perturbed(T_last, 6)
    uv, last_depth = depth_samples(CAMERA, depth[1], STRIDE)
    alone = SOLVE(room, CAMERA, start, IDENTITY, observations(uv, last_depth), DEPTH_CONFIG)
    assert not bool(alone.ok)  # the last frame alone: refused
    config = RefineConfig(residuals="depth", depth_stride=STRIDE)
    result = refine_frame(room, CAMERA, start, config, depth=depth, T_rel=T_rel)
    pos, rot = errors(result.pose, T_last)
    assert bool(result.ok) and int(result.status) == 0, int(result.status)
    assert pos < 0.02 and rot < 0.5, (pos, rot)
    assert float(result.position_std) < 0.05 and float(result.rotation_std) < 0.02
    first, _ = errors(jaxlie.SE3(result.frame_poses.parameters()[0]), T_first)
    assert first < 0.02


def test_pose_std_matches_numpy(truth, matches):
    """Worst-direction standard deviations vs a numpy covariance from finite differences, and a
    residual function blind to the rotation: rotation free (inf), position determined."""
    _, _, T = truth
    uv, points = matches
    valid = jnp.ones(len(uv), bool)

    def blocks(pose):
        return reprojection_residuals(pose, CAMERA, jnp.asarray(uv), jnp.asarray(points), valid)[0]

    position_std, rotation_std = jax.jit(lambda p: pose_std(blocks, p, RobustLoss()))(T)
    _, numeric = tangent_jacobian(lambda p: blocks(p).reshape(-1), T)
    covariance = np.linalg.inv(numeric.T @ numeric)
    np.testing.assert_allclose(
        float(position_std), np.sqrt(np.linalg.eigvalsh(covariance[:3, :3])[-1]), rtol=2e-2
    )
    np.testing.assert_allclose(
        float(rotation_std), np.sqrt(np.linalg.eigvalsh(covariance[3:, 3:])[-1]), rtol=2e-2
    )

    def position_only(pose):
        return (pose.translation() - jnp.array([1.0, 2.0, 3.0]))[:, None] / 0.1

    position_std, rotation_std = pose_std(position_only, T, RobustLoss())
    np.testing.assert_allclose(float(position_std), 0.1, rtol=1e-3)
    assert np.isinf(float(rotation_std))


def test_reprojection_refinement_converges(room, truth, matches):
    """(b) from a 0.3 m / 10 deg perturbation, exact correspondences."""
    _, _, T_true = truth
    uv, points = matches
    config = RefineConfig(residuals="reprojection", loss=RobustLoss("huber", 3.0))
    result = refine_frame(
        room, CAMERA, perturbed(T_true, 2), config, match_uv=uv, match_points=points
    )
    pos, rot = errors(result.pose, T_true)
    assert bool(result.ok) and int(result.num_matches) == len(uv)
    assert pos < 0.02 and rot < 0.5, (pos, rot)


def test_sequence_refinement_through_ego_motion(room):
    """(c) depth + reprojection, three frames refined jointly from the 4-DoF start: every frame
    lands on its truth."""
    poses = np.array([[1.2, 1.0, 1.5, 0.45], [1.4, 1.1, 1.5, 0.55], [1.6, 1.2, 1.5, 0.6]])
    tilts = np.array([[0.3, 0.0], [0.35, 0.05], [0.35, 0.05]])
    rotations = [numpy_rotation(p[3], s) for p, s in zip(poses, tilts, strict=True)]
    depth = np.stack([room_depth(R, p[:3], CAMERA) for R, p in zip(rotations, poses, strict=True)])
    rng = np.random.default_rng(5)
    match_uv = np.stack([rng.uniform(0, 79, (3, 20)), rng.uniform(0, 44, (3, 20))], -1)
    match_points = []
    for R, p, frame_uv in zip(rotations, poses, match_uv, strict=True):
        d_world = numpy_rays(CAMERA, frame_uv) @ R.T
        t, _, _ = room_hits(p[:3], d_world)
        match_points.append(p[:3] + t[:, None] * d_world)
    motion = np.stack(
        [
            np.asarray(ego_motion(jnp.asarray(a), jnp.asarray(b)))
            for a, b in zip(poses[:-1], poses[1:], strict=True)
        ]
    )
    sequence = FrameSequence(CAMERA, np.ones((3, 9, 16, 8)), motion, depth=depth, tilt=tilts)
    start = poses[-1] + np.array([0.2, -0.15, 0.1, np.deg2rad(8.0)])
    config = RefineConfig(residuals="both", mode="sequence", depth_stride=4)
    result = refine(
        room,
        sequence,
        start,
        config,
        match_uv=match_uv.astype(np.float32),
        match_points=np.stack(match_points).astype(np.float32),
    )
    assert bool(result.ok) and int(result.num_matches) == 60
    for t in range(3):
        T_true = se3(numpy_rotation(poses[t, 3], tilts[t]), poses[t, :3])
        pos, rot = errors(jaxlie.SE3(result.frame_poses.parameters()[t]), T_true)
        assert pos < 0.02 and rot < 0.5, (t, pos, rot)
    np.testing.assert_allclose(np.asarray(result.yaw_pose), poses[-1], atol=0.02)
    # the same solve from a full SE(3) start and the frames' relative poses (e.g. from VIO)
    chain = frame_poses_from_last(jnp.asarray(start, jnp.float32), motion, tilts)
    T_start = jaxlie.SE3(chain.parameters()[-1])
    T_rel = jaxlie.SE3(
        jax.vmap(lambda q: (T_start.inverse() @ jaxlie.SE3(q)).parameters())(chain.parameters())
    )
    joint = refine_frame(
        room,
        CAMERA,
        T_start,
        config,
        depth=depth,
        match_uv=match_uv,
        match_points=np.stack(match_points),
        T_rel=T_rel,
    )
    np.testing.assert_array_equal(
        np.asarray(joint.pose.parameters()), np.asarray(result.pose.parameters())
    )


def test_failures_are_values(room, truth, depth_image):
    _, _, T_true = truth
    config = DEPTH_CONFIG
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    identity = IDENTITY
    solve = SOLVE
    start = perturbed(T_true, 0)
    cases = {
        STATUS_TOO_FEW_RESIDUALS: (
            room,
            CAMERA,
            start,
            identity,
            observations(uv, 0 * depth),
            config,
        ),
        STATUS_BAD_INPUT: (
            room,
            CAMERA,
            jaxlie.SE3(jnp.full(7, jnp.nan, jnp.float32)),  # not weak-typed: no retrace
            identity,
            observations(uv, depth),
            config,
        ),
    }
    for status, args in cases.items():
        result = solve(*args)
        assert not bool(result.ok) and int(result.status) == status
        assert np.all(np.isfinite(np.asarray(result.pose.parameters())))
    diverging = eqx.tree_at(lambda c: c.max_translation, config, jnp.float32(0.01))
    result = solve(room, CAMERA, start, identity, observations(uv, depth), diverging)
    assert not bool(result.ok) and int(result.status) == STATUS_DIVERGED
    np.testing.assert_array_equal(
        np.asarray(result.pose.parameters()), np.asarray(start.parameters())
    )
    assert np.isinf(float(result.cost))
    # The box-room view is well determined, but not to 1 mm: a demanding threshold flags it.
    strict = eqx.tree_at(lambda c: c.max_position_std, config, jnp.float32(1e-3))
    result = solve(room, CAMERA, start, identity, observations(uv, depth), strict)
    assert not bool(result.ok) and int(result.status) == STATUS_DEGENERATE
    assert len(TRACES) == 1


def test_poor_fit_is_flagged(room, truth, depth_image):
    """A phantom surface the map lacks (every fifth depth pixel at 0.8 of its depth) leaves a
    fifth of the observations unexplained: status 6 when the fit check asks for more."""
    _, _, T_true = truth
    uv, depth = depth_samples(CAMERA, depth_image, STRIDE)
    clean = SOLVE(room, CAMERA, T_true, IDENTITY, observations(uv, depth), DEPTH_CONFIG)
    assert bool(clean.ok) and float(clean.inlier_fraction) > 0.95
    phantom = observations(uv, np.where(np.arange(depth.size) % 5 == 0, 0.8 * depth, depth))
    lenient = eqx.tree_at(lambda c: c.min_inlier_fraction, DEPTH_CONFIG, jnp.float32(0.5))
    result = SOLVE(room, CAMERA, T_true, IDENTITY, phantom, lenient)
    assert bool(result.ok), int(result.status)
    assert 0.5 <= float(result.inlier_fraction) < 0.9
    strict = eqx.tree_at(lambda c: c.min_inlier_fraction, DEPTH_CONFIG, jnp.float32(0.9))
    result = SOLVE(room, CAMERA, T_true, IDENTITY, phantom, strict)
    assert not bool(result.ok) and int(result.status) == STATUS_POOR_FIT
    np.testing.assert_array_equal(
        np.asarray(result.pose.parameters()), np.asarray(T_true.parameters())
    )
    assert len(TRACES) == 1


def test_bad_input_raises_clear_errors(room, truth, depth_image, matches):
    _, _, T = truth
    uv, points = matches
    with pytest.raises(ValueError, match="points_world"):
        correspondences(uv, points[:, :2])
    with pytest.raises(ValueError, match="must match uv"):
        correspondences(uv, points[:-1])
    bad = uv.copy()
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="uv contains 1 NaN"):
        correspondences(bad, points)
    with pytest.raises(ValueError, match="valid must be a bool"):
        correspondences(uv, points, np.ones(3, bool))
    with pytest.raises(ValueError, match="depth must have shape"):
        refine_frame(room, CAMERA, T, RefineConfig(), depth=depth_image[:, :10])
    with pytest.raises(ValueError, match="needs match_uv"):
        refine_frame(room, CAMERA, T, RefineConfig(residuals="reprojection"))
    with pytest.raises(ValueError, match=r"depth must have shape \(F, H, W\)"):
        refine_frame(room, CAMERA, T, RefineConfig(), depth=depth_image, T_rel=IDENTITY)
    with pytest.raises(ValueError, match="T_rel must be a finite"):
        refine_frame(room, CAMERA, T, RefineConfig(), depth=depth_image[None], T_rel=T)
    with pytest.raises(ValueError, match="residuals must be"):
        RefineConfig(residuals="lidar")
    with pytest.raises(ValueError, match="yaw_pose"):
        sequence = FrameSequence(
            CAMERA, np.ones((1, 9, 16, 8)), np.zeros((0, 4)), depth=depth_image[None]
        )
        refine(room, sequence, np.array([1.0, 2.0, np.nan, 0.0]))
