"""The streaming SG2Loc filter (:mod:`jaxloc.sg2loc.online`) on the tiny world of
tests/_tiny_world.py: equal to one round of :func:`~jaxloc.sg2loc.localize`, one compiled program
for a whole stream, relocalization, deterministic, and clear errors for bad frames."""

from __future__ import annotations

import _tiny_world as tiny
import jax
import numpy as np
import pytest
from _compilations import compilations

from jaxloc.sg2loc import SG2LocConfig, localize, online
from jaxloc.sg2loc._particles import PAPER_HEIGHTS
from jaxloc.sg2loc._resampling import KLDConfig
from jaxloc.sg2loc._verdict import VerdictConfig

NUM_FRAMES = 5
KLD = KLDConfig(min_particles=4, max_particles=tiny.CAPACITY)
#: stride 2 on the 32x18 camera: 16 x 9 rays, 3 x 4 patches (SSIM needs at least 7 x 7 rays).
STREAM = SG2LocConfig(capacity=tiny.CAPACITY, strides=(2,), kld=KLD, relocalize_after=0)
PATCHES = (3, 4)


def start(seed, scene, sequence, config=STREAM):
    """A stream of ``config`` on the tiny world's camera and 3 x 4 patches."""
    return online.init(jax.random.key(seed), scene, sequence.camera, config, patch_shape=PATCHES)


def stream(state, sequence, frames=range(NUM_FRAMES), **given):
    estimates = []
    for t in frames:
        motion = np.zeros(4, np.float32) if t == 0 else sequence.ego_motion[t - 1]
        inputs = {"depth": sequence.depth[t], "rgb": sequence.rgb[t]}
        inputs.update(given)
        state, estimate = online.update(state, sequence.patch_embeddings[t], motion, **inputs)
        estimates.append(estimate)
    return state, jax.tree.map(lambda *xs: np.stack(xs), *estimates)


@pytest.fixture(scope="module")
def world():
    return tiny.scene(), tiny.sequence(NUM_FRAMES)


def test_stream_equals_one_round_of_localize(world):
    scene, sequence = world
    state = start(3, scene, sequence)
    state, est = stream(state, sequence)
    config = SG2LocConfig(capacity=tiny.CAPACITY, strides=(2,), kld=KLD)
    located = localize(jax.random.key(3), scene, sequence, config)
    np.testing.assert_array_equal(est.pose, np.asarray(located.poses))
    np.testing.assert_array_equal(est.localized, np.asarray(located.localized))
    # reductions fused differently in the scan and the one-frame program: float32 rounding
    np.testing.assert_allclose(est.spread, np.asarray(located.info.verdict.spread), rtol=1e-5)
    np.testing.assert_array_equal(est.num_particles, np.asarray(located.num_particles[0]))
    assert int(state.index) == NUM_FRAMES and not est.relocalized.any()


def test_one_program_for_the_whole_stream(world):
    scene, sequence = world
    state = start(4, scene, sequence)
    state, _ = stream(state, sequence, range(1))
    with compilations() as compiled:
        stream(state, sequence, range(1, NUM_FRAMES))
        other = start(5, scene, sequence)
        stream(other, sequence, range(2))  # a new stream of the same shapes: no new program
    assert not [c for c in compiled if "_update" in c], compiled
    with compilations() as compiled:
        stream(other, sequence, range(1), depth=None)  # no depth: the one other program
    assert len([c for c in compiled if "_update" in c]) == 1, compiled


def test_deterministic_and_nan_motion_is_survived(world):
    scene, sequence = world
    runs = [
        stream(
            start(6, scene, sequence),
            sequence,
        )[1]
        for _ in range(2)
    ]
    for a, b in zip(jax.tree.leaves(runs[0]), jax.tree.leaves(runs[1]), strict=True):
        np.testing.assert_array_equal(a, b)
    state = start(6, scene, sequence)
    state, _ = stream(state, sequence, range(1))
    state, est = online.update(
        state, sequence.patch_embeddings[1], np.full(4, np.nan), sequence.depth[1], sequence.rgb[1]
    )
    assert not bool(est.motion_valid) and np.all(np.isfinite(np.asarray(est.pose)))


def test_relocalization_after_frames_without_the_verdict(world):
    scene, sequence = world
    never = VerdictConfig(min_semantic_fraction=2.0)  # no frame can be flagged
    config = SG2LocConfig(
        capacity=tiny.CAPACITY,
        strides=(2,),
        kld=KLD,
        verdict=never,
        relocalize_after=2,
        relocalize_count=tiny.CAPACITY,
    )
    state = start(7, scene, sequence, config)
    states, relocalized = [], []
    for t in range(NUM_FRAMES):
        state, est = stream(state, sequence, [t])
        states.append(state)
        relocalized.append(bool(est.relocalized[0]))
    assert relocalized == [False, True, False, True, False]
    # every particle replaced: the new ones lie on the region's floor heights, uniform in yaw
    fresh = states[1].particles
    assert bool(fresh.active.all())
    region = states[1].config.region
    heights = np.asarray(fresh.poses[:, 2]) - float(region.floor_z)
    gaps = np.abs(heights[:, None] - np.asarray(PAPER_HEIGHTS)[None, :]).min(axis=1)
    assert np.all(gaps < 1e-5)
    assert int(states[1].unlocalized) == 0 and int(states[2].unlocalized) == 1


def test_bad_frames_and_configs_are_clear_errors(world):
    scene, sequence = world
    state = start(8, scene, sequence)
    patches, depth, rgb = sequence.patch_embeddings[0], sequence.depth[0], sequence.rgb[0]
    zero = np.zeros(4, np.float32)
    cases = [
        ((patches[:2], zero), {}, "patch_embeddings must have shape"),
        ((patches, np.zeros(3)), {}, r"ego_motion must have shape \(4,\)"),
        ((patches, zero), {"depth": depth[:5]}, "depth must have shape"),
        ((patches, zero), {"depth": -depth}, "depth must be >= 0"),
        ((patches, zero), {"rgb": np.full_like(rgb, np.nan)}, "rgb contains NaN"),
    ]
    for args, kwargs, message in cases:
        with pytest.raises(ValueError, match=message):
            online.update(state, *args, **kwargs)
    with pytest.raises(TypeError, match="OnlineState"):
        online.update(None, patches, zero)
    with pytest.raises(ValueError, match="strides must be positive ints"):
        SG2LocConfig(strides=(0,))
    with pytest.raises(ValueError, match="relocalize_after must be an int >= 0, got -1"):
        SG2LocConfig(relocalize_after=-1)
    with pytest.raises(ValueError, match="patch_shape must be two positive ints"):
        online.init(jax.random.key(0), scene, sequence.camera, STREAM, patch_shape=(3, 0))
    with pytest.raises(ValueError, match=r"^SG2LocConfig\(strides=\.\.\.\): stride 4 gives a 4 x"):
        online.init(
            jax.random.key(0),
            scene,
            sequence.camera,
            SG2LocConfig(capacity=16, strides=(4,)),
            patch_shape=PATCHES,
        )


def test_the_config_of_jaxloc_0_2_still_works_with_a_warning(world):
    """``OnlineConfig`` (deprecated) stands for the SG2LocConfig of its stride: the same stream."""
    scene, sequence = world
    with pytest.warns(DeprecationWarning, match="OnlineConfig is deprecated"):
        old = online.OnlineConfig(
            capacity=tiny.CAPACITY, stride=2, patch_shape=PATCHES, kld=KLD, relocalize_after=0
        )
    _, expected = stream(
        start(3, scene, sequence),
        sequence,
        range(2),
    )
    _, got = stream(online.init(jax.random.key(3), scene, sequence.camera, old), sequence, range(2))
    np.testing.assert_array_equal(got.pose, expected.pose)


def test_filter_sequence_is_the_stream(world):
    scene, sequence = world
    _, by_hand = stream(
        start(9, scene, sequence),
        sequence,
    )
    seen = []
    whole = online.filter_sequence(jax.random.key(9), scene, sequence, STREAM, progress=seen.append)
    assert seen == list(range(NUM_FRAMES))
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(by_hand), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(TypeError, match="jaxloc.FrameSequence"):
        online.filter_sequence(jax.random.key(0), scene, None)


def test_a_stride_too_coarse_for_ssim_names_the_setting_that_fixes_it(world):
    """At 160 x 90 the coarse stride 20 casts 4 x 8 rays, below SSIM's 7 x 7 window: the stream
    and the offline filter refuse it in one line naming the setting (the one config both take)
    and the largest stride that fits (13); without colour either runs."""
    from jaxloc.camera import Camera
    from jaxloc.sg2loc import (
        FrameSequence,
        ObservationConfig,
        _localization as localization,
        warm_up,
    )

    scene = world[0]
    camera = Camera.from_fov(160, 90, 60.0)
    fix = "smaller than SSIM's 7 x 7 window; use strides of at most 13"
    with pytest.raises(
        ValueError, match=r"^SG2LocConfig\(strides=\.\.\.\): stride 20 gives a 4 x 8"
    ) as info:
        online.init(jax.random.key(0), scene, camera)
    assert fix in str(info.value) and "\n" not in str(info.value)
    dim = scene.embeddings.shape[1]
    frames = FrameSequence.zeros(camera, 2, (9, 16), dim)
    with pytest.raises(
        ValueError, match=r"^SG2LocConfig\(strides=\.\.\.\): stride 20 gives a 4 x 8"
    ) as info:
        warm_up(jax.random.key(0), scene, frames, SG2LocConfig(capacity=8))
    assert fix in str(info.value) and "ObservationConfig(use_color=False)" in str(info.value)
    no_color = ObservationConfig(use_color=False)
    online.init(jax.random.key(0), scene, camera, SG2LocConfig(observation=no_color))
    without_rgb = FrameSequence.zeros(camera, 2, (9, 16), dim, rgb=False)
    assert len(localization._checked(scene, without_rgb, SG2LocConfig(capacity=8), None)) == 3
