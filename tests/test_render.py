"""Rendering: depth is z along the optical axis, per-patch majority, interpolated colours, tilt,
jit/vmap/batch consistency and pose gradients, against an analytic box room and numpy references.

All scenes here share the capacity of the random ``scene`` fixture and one camera and grid, so
each jitted entry point compiles once.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import (
    BODY_CAM,
    ROOM,
    box_room,
    render_batch_jit,
    render_jit,
    room_hits,
    rot_x,
    rot_y,
    rot_z,
)

from jaxloc import render, render_batch
from jaxloc.camera import Camera, stride_grid
from jaxloc.scene import SceneGraph

CAMERA = Camera.from_fov(160, 90, 60.0)
GRID = stride_grid(CAMERA, 5)  # 32 x 18 rays, 2 x 2 per patch of a 9 x 16 patch grid

#: Poses inside the 6 x 4 x 3 room and tilts (pitch, roll), some zero.
ROOM_POSES = np.array(
    [[1.0, 2.0, 1.5, 0.0], [3.0, 1.0, 1.2, 2.0], [4.5, 3.0, 2.0, -2.5], [2.0, 2.5, 0.8, 0.9]],
    np.float32,
)
ROOM_TILTS = np.array([[0.0, 0.0], [0.3, -0.2], [-0.4, 0.5], [0.1, 0.0]], np.float32)
LEVEL = np.zeros(2, np.float32)  # render_jit always gets a tilt: one compilation
SCENE_POSES = np.array(
    [[0.5, -0.3, 0.2, 1.1], [-4.0, 0.0, 0.0, 0.0], [0.0, 1.0, -1.0, -2.0], [0.0, 0.0, 0.0, -2.0]],
    np.float32,
)


def _world_rays(pose, tilt=(0.0, 0.0)):
    """Independent float64 ray directions (R, 3) in the world and the optical axis (3,)."""
    uv = np.asarray(GRID.uv, np.float64)
    d_cam = np.column_stack(
        [(uv[:, 0] - CAMERA.cx) / CAMERA.fx, (uv[:, 1] - CAMERA.cy) / CAMERA.fy, np.ones(len(uv))]
    )
    r = rot_z(pose[3]) @ rot_y(tilt[0]) @ rot_x(tilt[1]) @ BODY_CAM
    return d_cam @ r.T, r[:, 2]


def _analytic_room(pose, tilt=(0.0, 0.0)):
    """(depth, t, object, corner gap) of the box room seen from ``pose``, float64."""
    w, axis = _world_rays(np.asarray(pose, np.float64), tilt)
    t, obj, gap = room_hits(np.asarray(pose[:3], np.float64), w)
    cos = (w @ axis) / np.linalg.norm(w, axis=1)
    return t * cos, t, obj, gap


@pytest.fixture(scope="module")
def linear_room(scene) -> SceneGraph:
    """The box room with vertex colours (x / Lx, y / Ly, z / H), shared capacity."""
    return SceneGraph.from_meshes(
        box_room(colors="linear"), np.arange(6), np.eye(6, 8), capacity=scene.capacity
    )


def _np(r):
    return jax.tree.map(np.asarray, r)


# ----------------------------------------------------------------------------- analytic room


def test_render_box_room_matches_analytic(room_scene):
    """Object, range t and depth of every ray, for level and tilted cameras, via render (loop)
    and render_batch, against the analytic float64 room."""
    batch = _np(render_batch_jit(room_scene, ROOM_POSES, CAMERA, GRID, ROOM_TILTS))
    for i, (pose, tilt) in enumerate(zip(ROOM_POSES, ROOM_TILTS, strict=True)):
        depth, t, obj, gap = _analytic_room(pose, tilt)
        clear = gap > 1e-3  # not at a corner where two walls tie
        assert clear.mean() > 0.95
        for out in (
            _np(render_jit(room_scene, pose, CAMERA, GRID, tilt)),
            jax.tree.map(lambda a, i=i: a[i], batch),
        ):
            assert np.all(out.valid)  # a closed room: every ray hits
            np.testing.assert_array_equal(out.object_id[clear], obj[clear])
            np.testing.assert_allclose(out.t, t, atol=1e-4)
            np.testing.assert_allclose(out.depth, depth, atol=1e-4)


def test_camera_facing_a_wall_sees_constant_depth(room_scene):
    """A level camera at x = 1 facing the wall x = 6 sees depth D = 5 wherever it sees that wall,
    while the range t grows towards the image border (t = D / cos)."""
    out = _np(render_jit(room_scene, ROOM_POSES[0], CAMERA, GRID, ROOM_TILTS[0]))
    on_wall = out.object_id == 3
    assert on_wall.mean() > 0.5
    np.testing.assert_allclose(out.depth[on_wall], 5.0, atol=1e-4)
    assert out.t[on_wall].max() > 5.5 and out.t[on_wall].min() == pytest.approx(5.0, abs=0.05)


def test_depth_is_range_times_cos_to_optical_axis(scene):
    pose = SCENE_POSES[0]
    out = _np(render_jit(scene, pose, CAMERA, GRID, LEVEL))
    assert 0.2 < out.valid.mean() < 1.0
    w, axis = _world_rays(pose)
    cos = (w @ axis) / np.linalg.norm(w, axis=1)
    h = out.valid
    np.testing.assert_allclose(out.depth[h], out.t[h] * cos[h], rtol=1e-5)
    assert np.all(out.depth[~h] == np.inf) and np.all(out.t[~h] == np.inf)
    assert np.all(out.object_id[~h] == -1) and np.all(out.color[~h] == 0)


def test_colours_are_interpolated_from_vertex_colours(linear_room):
    """Vertex colours (x / Lx, y / Ly, z / H) interpolate exactly (linear on each triangle), so
    the colour of a hit is its position scaled; error only from the uint8 vertex colours."""
    for pose, tilt in zip(ROOM_POSES, ROOM_TILTS, strict=True):
        out = _np(render_jit(linear_room, pose, CAMERA, GRID, tilt))
        w, _ = _world_rays(pose, tilt)
        w /= np.linalg.norm(w, axis=1, keepdims=True)
        point = pose[:3] + out.t[:, None] * w
        np.testing.assert_allclose(out.color, point / np.asarray(ROOM), atol=0.5 / 255 + 1e-4)
        # Not flat: the colours vary across the image.
        assert np.ptp(out.color, axis=0).max() > 0.2


# ----------------------------------------------------------------------------- patches


def _patch_reference(object_id, patch, num_patches):
    """Per patch: the most frequent value among its rays' object ids (misses -1 included), ties
    to the smallest value; its share of the patch's rays; -1 / 0 where the winner is a miss."""
    winners, fractions = np.full(num_patches, -1), np.zeros(num_patches)
    for p in range(num_patches):
        ids = object_id[patch == p]
        values, counts = np.unique(ids, return_counts=True)
        best = values[np.argmax(counts)]  # np.unique sorts: first max is the smallest value
        winners[p] = best
        fractions[p] = counts.max() / ids.size if best >= 0 else 0.0
    return winners, fractions


def test_patch_majority_and_fraction_match_numpy(scene):
    patch = np.asarray(GRID.patch)
    mixed = 0
    for pose in SCENE_POSES:
        out = _np(render_jit(scene, pose, CAMERA, GRID, LEVEL))
        winners, fractions = _patch_reference(out.object_id, patch, GRID.num_patches)
        np.testing.assert_array_equal(out.patch_object, winners)
        np.testing.assert_allclose(out.patch_fraction, fractions, rtol=1e-6)
        mixed += np.sum((fractions > 0) & (fractions < 1))
    assert mixed > 5  # some patches mix several objects (the test is not trivial)


# ----------------------------------------------------------------------------- consistency


def test_render_jit_equals_eager(room_scene):
    eager = _np(render(room_scene, jnp.asarray(ROOM_POSES[1]), CAMERA, GRID, ROOM_TILTS[1]))
    jitted = _np(render_jit(room_scene, ROOM_POSES[1], CAMERA, GRID, ROOM_TILTS[1]))
    for name in ("object_id", "valid", "patch_object"):
        np.testing.assert_array_equal(getattr(eager, name), getattr(jitted, name))
    for name in ("depth", "t", "color", "patch_fraction"):
        np.testing.assert_allclose(
            getattr(eager, name), getattr(jitted, name), rtol=1e-5, atol=1e-6
        )


def test_vmap_render_equals_loop_and_render_batch(scene):
    """vmap(render) without tilt (the tilt=None path), render_batch with level tilts, and a loop
    of single renders agree."""
    poses = SCENE_POSES
    vmapped = jax.jit(jax.vmap(render, in_axes=(None, 0, None, None)))
    vm = _np(vmapped(scene, poses, CAMERA, GRID))
    batch = _np(render_batch_jit(scene, poses, CAMERA, GRID, np.zeros((4, 2), np.float32)))
    for i, pose in enumerate(poses):
        one = _np(render_jit(scene, pose, CAMERA, GRID, LEVEL))
        for other in (vm, batch):
            for name in ("object_id", "valid", "patch_object"):
                np.testing.assert_array_equal(getattr(other, name)[i], getattr(one, name))
            for name in ("depth", "t", "color", "patch_fraction"):
                np.testing.assert_allclose(
                    getattr(other, name)[i], getattr(one, name), rtol=1e-5, atol=1e-5
                )
    assert 0.1 < vm.valid.mean() < 0.95


def test_bad_pose_shapes_raise(scene):
    with pytest.raises(ValueError, match=r"\(4,\)"):
        render(scene, jnp.zeros(3), CAMERA, GRID)
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        render_batch(scene, jnp.zeros(4), CAMERA, GRID)
    with pytest.raises(ValueError, match="tilt"):
        render(scene, jnp.zeros(4), CAMERA, GRID, jnp.zeros(3))


# ----------------------------------------------------------------------------- gradients


def _depth(scene, pose, tilt):
    out = render(scene, pose, CAMERA, GRID, tilt)
    return jnp.where(out.valid, out.depth, 0.0)


#: (R, 4) Jacobian of every ray's depth w.r.t. (x, y, z, yaw), forward mode, compiled once.
depth_jacobian = jax.jit(jax.jacfwd(_depth, argnums=1))


def test_depth_gradient_matches_analytic_and_finite_differences(room_scene):
    pose, tilt = ROOM_POSES[1].astype(np.float64), ROOM_TILTS[1]
    jac = np.asarray(depth_jacobian(room_scene, ROOM_POSES[1], tilt))
    assert np.all(np.isfinite(jac))
    # Float64 central differences of the analytic room, on rays that stay on one wall.
    steps = np.array([1e-4, 1e-4, 1e-4, 1e-5])
    fd = np.zeros_like(jac, dtype=np.float64)
    stable = _analytic_room(pose, tilt)[3] > 1e-2
    for k in range(4):
        plus, minus = pose.copy(), pose.copy()
        plus[k] += steps[k]
        minus[k] -= steps[k]
        dp, _, op, _ = _analytic_room(plus, tilt)
        dm, _, om, _ = _analytic_room(minus, tilt)
        stable &= op == om
        fd[:, k] = (dp - dm) / (2 * steps[k])
    assert stable.mean() > 0.9
    scale = np.abs(fd[stable]).max(0)
    np.testing.assert_allclose(jac[stable], fd[stable], rtol=1e-3, atol=1e-3 * scale.max())
    # A level camera at yaw 0 moving along its optical axis (+x): the depth of the wall it faces
    # (x = 6) drops by the step, that of surfaces parallel to the motion does not change.
    level = np.asarray(depth_jacobian(room_scene, ROOM_POSES[0], ROOM_TILTS[0]))
    obj = _np(render_jit(room_scene, ROOM_POSES[0], CAMERA, GRID, ROOM_TILTS[0])).object_id
    np.testing.assert_allclose(level[obj == 3, 0], -1.0, atol=1e-4)
    np.testing.assert_allclose(level[obj != 3, 0], 0.0, atol=1e-4)
    np.testing.assert_allclose(level[:, 1:3][obj == 3], 0.0, atol=1e-4)
    # And float32 central differences of jaxloc's own render agree too.
    eps = np.array([2e-3, 2e-3, 2e-3, 2e-4], np.float32)
    for k in range(4):
        step = np.zeros(4, np.float32)
        step[k] = eps[k]
        dp = _np(render_jit(room_scene, ROOM_POSES[1] + step, CAMERA, GRID, tilt)).depth
        dm = _np(render_jit(room_scene, ROOM_POSES[1] - step, CAMERA, GRID, tilt)).depth
        own = (dp - dm) / (2 * eps[k])
        np.testing.assert_allclose(jac[stable, k], own[stable], rtol=1e-2, atol=1e-2 * scale[k])


def test_depth_gradient_finite_for_misses_and_grazing_views(room_scene, scene):
    # Outside the room looking away: every ray misses; the Jacobian is finite and zero.
    outside = np.array([-3.0, 2.0, 1.5, np.pi], np.float32)
    jac = np.asarray(depth_jacobian(room_scene, outside, LEVEL))
    assert np.all(jac == 0)
    # Camera 1e-5 m above the floor, level: the lower half of the image grazes the floor.
    grazing = np.array([3.0, 2.0, 1e-5, 0.3], np.float32)
    jac = np.asarray(depth_jacobian(room_scene, grazing, LEVEL))
    assert np.all(np.isfinite(jac))
    # A view of the random scene where some rays miss: finite everywhere, zero on misses.
    pose = SCENE_POSES[0]
    jac = np.asarray(depth_jacobian(scene, pose, LEVEL))
    out = _np(render_jit(scene, pose, CAMERA, GRID, LEVEL))
    assert np.all(np.isfinite(jac)) and np.all(jac[~out.valid] == 0)
    assert np.abs(jac[out.valid]).max() > 0
