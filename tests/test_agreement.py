"""Depth agreement (:func:`jaxloc.sg2loc.depth_agreement`): its share against numpy, its rays
against the renderer's, jit/vmap against eager calls, bad arguments, and the check it is for: the
estimates of a depth-blind filter, on the test room (tests/test_filter.py) and its look-alike
wrong place, and :func:`jaxloc.sg2loc.depth_blind_check` built on it."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_filter import EPISODE_CONFIG, LOCALIZE_CONFIG

from jaxloc.camera import stride_grid
from jaxloc.metrics import yaw_pose_errors
from jaxloc.sg2loc import (
    AgreementConfig,
    depth_agreement,
    depth_blind_check,
    kld_for_capacity,
    localize,
    render_batch,
)
from jaxloc.sg2loc._agreement import agreeing_share
from jaxloc.sg2loc._check import blind_config
from jaxloc.sg2loc._sequence import frames_on_grid
from jaxloc.synthetic.indoor import make_episode, make_lookalike_episode

STRIDE = 8


def numpy_share(rendered, sensor, absolute=0.05, relative=0.05) -> float:
    rendered, sensor = np.asarray(rendered, np.float64), np.asarray(sensor, np.float64)
    valid = np.isfinite(sensor) & (sensor > 0)
    if not valid.any():
        return 0.0
    r, s = rendered[valid], sensor[valid]
    hit = np.isfinite(r)
    close = np.abs(np.where(hit, r, 0.0) - s) <= absolute + relative * s
    return float(np.mean(hit & close))


@pytest.fixture(scope="module")
def room():
    return make_episode(0, 5, EPISODE_CONFIG)


def test_share_matches_numpy_with_misses_and_missing_depth():
    rng = np.random.default_rng(0)
    sensor = rng.uniform(0.5, 6.0, (4, 300)).astype(np.float32)
    rendered = sensor + rng.normal(0, 0.2, sensor.shape).astype(np.float32)
    rendered[:, :20] = np.inf  # misses
    sensor[:, 20:50] = 0.0  # no depth
    sensor[1, 50:60] = np.nan
    sensor[3] = 0.0  # a frame without depth: 0
    config = AgreementConfig(0.1, 0.02)
    share = jax.jit(jax.vmap(agreeing_share, in_axes=(0, 0, None)))(rendered, sensor, config)
    expected = [numpy_share(r, s, 0.1, 0.02) for r, s in zip(rendered, sensor, strict=True)]
    np.testing.assert_allclose(np.asarray(share), expected, rtol=1e-6)
    assert 0.0 < expected[0] < 1.0 and expected[3] == 0.0


def test_agreement_is_the_share_of_the_rendered_rays(room):
    shifted = np.asarray(room.poses_gt, np.float32) + np.float32([0.3, -0.2, 0.0, 0.1])
    grid = stride_grid(room.sequence.camera, STRIDE, *room.sequence.patch_shape)
    frames = frames_on_grid(room.sequence, grid)
    for poses in (np.asarray(room.poses_gt, np.float32), shifted):
        views = render_batch(
            room.scene, jnp.asarray(poses), room.sequence.camera, grid, frames.tilt
        )
        expected = [
            numpy_share(r, s) for r, s in zip(views.depth, np.asarray(frames.depth), strict=True)
        ]
        got = depth_agreement(room.scene, room.sequence, poses, STRIDE)
        np.testing.assert_allclose(np.asarray(got), expected, atol=1e-6)
    at_truth = np.asarray(depth_agreement(room.scene, room.sequence, room.poses_gt, STRIDE))
    assert np.all(at_truth > 0.95)
    assert np.all(np.asarray(got) < at_truth)  # 0.36 m and 6 degrees off explain less


def test_traced_tolerance_jit_and_vmap_equal_eager_calls(room):
    poses = np.asarray(room.poses_gt, np.float32) + np.float32([0.15, 0.0, 0.0, 0.0])
    configs = [AgreementConfig(a, r) for a, r in ((0.02, 0.0), (0.05, 0.05), (0.2, 0.1))]
    eager = np.stack(
        [np.asarray(depth_agreement(room.scene, room.sequence, poses, STRIDE, c)) for c in configs]
    )
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *configs)
    run = jax.jit(lambda c: depth_agreement(room.scene, room.sequence, poses, STRIDE, c))
    np.testing.assert_allclose(np.asarray(jax.vmap(run)(stacked)), eager, atol=1e-6)
    np.testing.assert_allclose(np.asarray(run(configs[1])), eager[1], atol=1e-6)
    assert np.all(np.diff(eager, axis=0) >= 0) and eager[2].sum() > eager[0].sum()


def test_bad_arguments_are_one_line_errors(room):
    without = dataclasses.replace(room.sequence, depth=None)
    with pytest.raises(ValueError, match="needs a sequence with depth"):
        depth_agreement(room.scene, without, room.poses_gt, STRIDE)
    with pytest.raises(ValueError, match=r"poses must have shape \(5, 4\)"):
        depth_agreement(room.scene, room.sequence, room.poses_gt[:3], STRIDE)


#: The test room's filter with 1,000 particles: with the test's 400 the depth-blind filter does not
#: converge in this room (0.4-0.9 m off, nothing passes).
CHECKED_CONFIG = dataclasses.replace(LOCALIZE_CONFIG, capacity=1000, kld=kld_for_capacity(1000))


def test_depth_blind_check_flags_right_estimates_and_no_wrong_place(room):
    """The check of docs/pages/sg2loc.md: localize with depth (the estimate a user acts on) and
    check it with :func:`depth_blind_check` (a depth-blind filter's estimates against the
    recording's depth). The passed frames' estimates are within 0.5 m and 10 degrees; no frame of
    the look-alike wrong place passes."""
    wrong = make_lookalike_episode(0, 7919, 5, EPISODE_CONFIG)
    key, passed = jax.random.key(0), {}
    for name, episode in (("right", room), ("wrong", wrong)):
        check = depth_blind_check(key, episode.scene, episode.sequence, CHECKED_CONFIG)
        passed[name] = np.asarray(check.passed)
        print(f"\n{name}: depth-blind estimate's agreement {np.round(check.agreement, 3)}")
    estimate = localize(key, room.scene, room.sequence, LOCALIZE_CONFIG)
    pos, rot = yaw_pose_errors(np.asarray(estimate.poses), room.poses_gt)
    print(f"estimates' errors {np.round(pos, 3)} m {np.round(rot, 2)} deg")
    assert passed["right"].any(), "no right frame passes"
    assert np.all((pos[passed["right"]] < 0.5) & (rot[passed["right"]] < 10.0))
    assert not passed["wrong"].any()


def test_depth_blind_check_is_the_depth_blind_filter_and_its_agreement(room):
    """:func:`depth_blind_check` is ``localize`` without the depth score (and without the finest
    of three or more strides), then :func:`depth_agreement` on its last stride; the threshold is
    traced (a jitted vmap over thresholds gives the shares' comparisons); bad arguments are
    one-line errors."""
    three = dataclasses.replace(CHECKED_CONFIG, strides=(20, 10, 8), box_half_widths=(0.8, 0.4))
    assert blind_config(three).strides == (20, 10) and not blind_config(three).observation.use_depth
    assert blind_config(three, skip_finest=False).strides == (20, 10, 8)
    assert blind_config(CHECKED_CONFIG).strides == CHECKED_CONFIG.strides  # one would be left
    key = jax.random.key(3)
    check = depth_blind_check(key, room.scene, room.sequence, CHECKED_CONFIG)
    blind = dataclasses.replace(
        CHECKED_CONFIG,
        observation=dataclasses.replace(CHECKED_CONFIG.observation, use_depth=False),
    )
    reference = localize(key, room.scene, room.sequence, blind)
    assert not reference.used_depth and check.stride == CHECKED_CONFIG.strides[-1]
    share = depth_agreement(room.scene, room.sequence, reference.poses, check.stride)
    np.testing.assert_array_equal(np.asarray(check.blind_poses), np.asarray(reference.poses))
    np.testing.assert_array_equal(np.asarray(check.agreement), np.asarray(share))
    thresholds = jnp.float32([0.0, 0.5, 0.9, 1.0])
    swept = jax.jit(
        jax.vmap(
            lambda t: (
                depth_blind_check(
                    key, room.scene, room.sequence, CHECKED_CONFIG, threshold=t
                ).passed
            )
        )
    )
    np.testing.assert_array_equal(
        np.asarray(swept(thresholds)), np.asarray(share)[None] >= np.asarray(thresholds)[:, None]
    )
    assert np.asarray(swept(thresholds))[0].all()  # every share is >= 0
    without = dataclasses.replace(room.sequence, depth=None)
    with pytest.raises(ValueError, match="depth_blind_check needs a sequence with depth"):
        depth_blind_check(key, room.scene, without, CHECKED_CONFIG)
    with pytest.raises(ValueError, match=r"threshold must be in \[0, 1\], got 1.5"):
        depth_blind_check(key, room.scene, room.sequence, CHECKED_CONFIG, threshold=1.5)
