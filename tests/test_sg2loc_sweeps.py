"""SG2Loc's :func:`~jaxloc.sg2loc.localize` inside a caller's ``jax.jit`` and ``jax.vmap``, with
every continuous setting of :class:`~jaxloc.sg2loc.SG2LocConfig` a traced leaf: a sweep over
values compiles once, stacked configurations, keys and sequences vmap to what a loop gives, and
the progress bar changes nothing.

Small on purpose (2 shared cores): the 160x90 room of tests/test_filter.py, 3 frames, 64
particles, two rounds (strides 10 and 8). The programs compiled here: eager ``localize``'s two
rounds (with and without the progress bar), one jitted ``localize`` with key, configuration, map
and sequence all traced (:data:`SWEEP`), and one jitted vmap each over configurations, keys and
sequences. Compilations are counted with ``jax.monitoring`` (tests/_compilations.py).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _compilations import compilations
from test_filter import EPISODE_CONFIG, assert_bitwise_equal

from jaxloc import FrameSequence
from jaxloc.camera import stride_grid
from jaxloc.sg2loc import SG2LocConfig, localize
from jaxloc.sg2loc._filter import Region
from jaxloc.sg2loc._localization import warm_up
from jaxloc.sg2loc._resampling import KLDConfig
from jaxloc.sg2loc._sequence import frames_on_grid, grid_pixels
from jaxloc.sg2loc._verdict import VerdictConfig
from jaxloc.synthetic.indoor import make_episode

NUM_FRAMES = 3
KEY = jax.random.key(0)
INF = float("inf")
#: Every frame localized unless its weights are degenerate.
PERMISSIVE = VerdictConfig(
    max_spread_xy=INF,
    max_spread_z=INF,
    max_spread_yaw=INF,
    max_ess_fraction=1.0,
    min_semantic_fraction=0.0,
    max_depth_deficit=INF,
    min_color=-INF,
)
#: No frame localized (no particle cloud has zero horizontal spread).
STRICT = dataclasses.replace(PERMISSIVE, max_spread_xy=0.0)
#: 64 particles, two rounds; no injection (``inject_count`` 0), else after frames 1, 2, ...
BASE = SG2LocConfig(
    capacity=64,
    strides=(10, 8),
    box_half_widths=(0.8,),
    kld=KLDConfig(min_particles=16, max_particles=64),
    inject_every=1,
    verdict=PERMISSIVE,
)


def replaced(config: SG2LocConfig, **observation) -> SG2LocConfig:
    """``config`` with some fields of its observation model replaced."""
    return dataclasses.replace(
        config, observation=dataclasses.replace(config.observation, **observation)
    )


#: Six settings of one compiled program: sigma, lambda_depth, heights' values, verdict thresholds.
SIX = [
    BASE,
    replaced(BASE, sigma=0.3),
    replaced(BASE, lambda_depth=0.5),
    dataclasses.replace(BASE, heights=(1.4, 1.5, 1.6, 1.7)),
    dataclasses.replace(BASE, verdict=STRICT),
    dataclasses.replace(
        replaced(BASE, sigma=1.0, lambda_depth=3.0), heights=(1.45, 1.55, 1.65, 1.75)
    ),
]


def summary(result) -> tuple:
    """What the compiled sweeps return: poses (T, 4), localized (T,), particles (R, T, N, 4)."""
    return result.poses, result.localized, result.particles


def _localized(key, config, scene, sequence) -> tuple:
    return summary(localize(key, scene, sequence, config))


#: ``localize`` in a caller's jit, with key, configuration, map and sequence traced.
SWEEP = jax.jit(_localized)
VMAP_CONFIGS = jax.jit(jax.vmap(_localized, in_axes=(None, 0, None, None)))
VMAP_KEYS = jax.jit(jax.vmap(_localized, in_axes=(0, None, None, None)))
VMAP_SEQUENCES = jax.jit(jax.vmap(_localized, in_axes=(None, None, None, 0)))


def window(sequence: FrameSequence, start: int, length: int) -> FrameSequence:
    """Frames ``start .. start + length - 1`` of ``sequence``."""
    frames = slice(start, start + length)
    return FrameSequence(
        sequence.camera,
        sequence.patch_embeddings[frames],
        sequence.ego_motion[start : start + length - 1],
        sequence.depth[frames],
        sequence.rgb[frames],
        sequence.tilt[frames],
    )


def stacked(*trees):
    """Pytrees of one structure stacked leaf by leaf on a new leading axis."""
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


@pytest.fixture(scope="module")
def world():
    """The map and two 3-frame sequences of one shape (frames 0-2 and 1-3 of one episode)."""
    episode = make_episode(0, NUM_FRAMES + 1, EPISODE_CONFIG)
    sequence = episode.sequence
    return episode.scene, window(sequence, 0, NUM_FRAMES), window(sequence, 1, NUM_FRAMES)


def test_localize_under_jit_equals_eager(world):
    """Bit for bit: the caller's program holds the same rounds as the eager calls' programs."""
    scene, sequence, _ = world
    jitted = SWEEP(KEY, BASE, scene, sequence)
    eager = summary(localize(KEY, scene, sequence, BASE))
    assert_bitwise_equal(jitted, eager)
    assert np.all(np.isfinite(np.asarray(jitted[0])))


def test_six_configurations_compile_once(world):
    """Six values of sigma, lambda_depth, the heights and the verdict's thresholds: after the
    first, neither the jitted ``localize`` nor the eager one compiles anything, and every setting
    takes effect."""
    scene, sequence, _ = world
    SWEEP(KEY, SIX[0], scene, sequence)
    localize(KEY, scene, sequence, SIX[0])
    with compilations() as compiled:
        jitted = [SWEEP(KEY, config, scene, sequence) for config in SIX]
        eager = [summary(localize(KEY, scene, sequence, config)) for config in SIX]
    assert compiled == []
    for one, other in zip(jitted, eager, strict=True):
        assert_bitwise_equal(one, other)
    base_poses, base_localized, _ = jitted[0]
    assert np.all(base_localized)
    for poses, localized, _ in jitted[1:]:
        changed = not np.array_equal(poses, base_poses)
        assert changed or not np.array_equal(localized, base_localized)
    assert not np.any(jitted[4][1])  # the strict verdict


def test_vmap_over_stacked_configurations_equals_the_loop(world):
    """Four configurations differing in every kind of traced leaf (heights, box half-widths,
    injection count, sigma), stacked: the vmapped poses within 1e-4 of the loop's."""
    scene, sequence, _ = world
    four = [
        BASE,
        dataclasses.replace(BASE, heights=(1.3, 1.45, 1.6, 1.75)),
        dataclasses.replace(BASE, box_half_widths=(0.4,)),
        replaced(dataclasses.replace(BASE, inject_count=20), sigma=0.4),
    ]
    batched = VMAP_CONFIGS(KEY, stacked(*four), scene, sequence)
    loop = [SWEEP(KEY, config, scene, sequence) for config in four]
    np.testing.assert_allclose(batched[0], np.stack([p for p, _, _ in loop]), atol=1e-4)


def test_each_traced_knob_changes_the_result(world):
    """heights set round 0's particle levels; box_half_widths round 1's box (round 0 untouched);
    inject_count the particles from the frame after the first injection on (after frame 1)."""
    scene, sequence, _ = world
    _, _, base = SWEEP(KEY, BASE, scene, sequence)
    floor = float(Region.of_scene(scene).floor_z)
    heights = (1.3, 1.45, 1.6, 1.75)
    _, _, particles = SWEEP(KEY, dataclasses.replace(BASE, heights=heights), scene, sequence)
    levels = np.unique(np.round(np.asarray(particles[0, 0, :, 2]) - floor, 4))
    np.testing.assert_allclose(levels, heights, atol=1e-4)
    assert not np.allclose(base[0, 0, :, 2], particles[0, 0, :, 2])

    _, _, boxed = SWEEP(KEY, dataclasses.replace(BASE, box_half_widths=(0.3,)), scene, sequence)
    np.testing.assert_array_equal(boxed[0], base[0])
    width = np.ptp(np.asarray(boxed[1, 0, :, :3]), axis=0)
    base_width = np.ptp(np.asarray(base[1, 0, :, :3]), axis=0)
    assert np.all(width <= 0.6 + 1e-4) and np.any(base_width > 0.6)

    _, _, injected = SWEEP(KEY, dataclasses.replace(BASE, inject_count=20), scene, sequence)
    np.testing.assert_array_equal(injected[0, :2], base[0, :2])
    assert not np.array_equal(injected[0, 2], base[0, 2])


def test_vmap_over_keys_equals_the_loop(world):
    scene, sequence, _ = world
    keys = jax.random.split(jax.random.key(1), 2)
    batched = VMAP_KEYS(keys, BASE, scene, sequence)
    loop = [SWEEP(key, BASE, scene, sequence) for key in keys]
    np.testing.assert_allclose(batched[0], np.stack([p for p, _, _ in loop]), atol=1e-4)
    assert not np.allclose(loop[0][0], loop[1][0])


def test_vmap_over_sequences_equals_the_loop(world):
    scene, first, second = world
    batched = VMAP_SEQUENCES(KEY, BASE, scene, stacked(first, second))
    loop = [SWEEP(KEY, BASE, scene, sequence) for sequence in (first, second)]
    np.testing.assert_allclose(batched[0], np.stack([p for p, _, _ in loop]), atol=1e-4)
    assert not np.allclose(loop[0][0], loop[1][0])


def test_progress_bar_after_a_warm_up(world, capsys):
    """The warm-up compiles every program of ``localize(..., progress=True)``; the bar counts
    every frame of both rounds, and the results are bit for bit those without it. A second call
    runs the same compiled scans and ticks its own bar."""
    scene, sequence, _ = world
    placeholder = FrameSequence.zeros(
        sequence.camera, NUM_FRAMES, sequence.patch_shape, scene.embeddings.shape[1]
    )
    warm_up(KEY, scene, placeholder, BASE, progress=True).result()
    capsys.readouterr()
    total = 2 * NUM_FRAMES
    with compilations() as compiled:
        shown = localize(KEY, scene, sequence, BASE, progress=True)
        for _ in range(2):
            err = capsys.readouterr().err
            assert "round 2/2 (stride 8)" in err and f"{total}/{total}" in err
            again = localize(KEY, scene, sequence, BASE, progress=True)
    assert compiled == []
    assert_bitwise_equal(again, shown)
    assert_bitwise_equal(shown, localize(KEY, scene, sequence, BASE))


def test_configurations_inside_a_trace_are_checked_by_shape_only(world):
    """Built or replaced inside jit / vmap from traced values: no value check, shapes still
    checked; concrete values still validated on construction."""

    @jax.jit
    def built(heights, boxes, count):
        config = SG2LocConfig(strides=(10, 8), heights=heights, box_half_widths=boxes)
        config = dataclasses.replace(config, inject_count=count)
        return dataclasses.replace(config, sigma_trans=config.sigma_trans * 2)

    config = built(jnp.array([1.2, 1.4]), jnp.array([0.5]), jnp.int32(3))
    np.testing.assert_allclose(config.heights, [1.2, 1.4])
    assert int(config.inject_count) == 3 and float(config.sigma_trans) == pytest.approx(0.1)
    doubled = jax.vmap(lambda c: dataclasses.replace(c, sigma_rot=c.sigma_rot * 2))(
        stacked(BASE, dataclasses.replace(BASE, sigma_rot=0.2))
    )
    np.testing.assert_allclose(doubled.sigma_rot, [0.1, 0.4])
    with pytest.raises(ValueError, match="heights must be a non-empty tuple"):
        jax.jit(lambda h: SG2LocConfig(heights=h).heights)(jnp.ones((2, 2)))
    with pytest.raises(ValueError, match=r"box_half_widths must be positive, got \(0.8, -0.4\)"):
        SG2LocConfig(box_half_widths=(0.8, -0.4))
    with pytest.raises(ValueError, match="3 rounds need 2 box_half_widths, got \\(0.8,\\)"):
        SG2LocConfig(box_half_widths=(0.8,))
    with pytest.raises(ValueError, match="inject_count must be an int >= 0, got -1"):
        SG2LocConfig(inject_count=-1)


def test_host_helpers_under_jit_equal_the_host_path(world):
    """Ray grids are concrete inside a trace; pixels, frames and the floor region computed from
    traced inputs equal the host (NumPy) path's."""
    scene, sequence, _ = world
    camera = sequence.camera

    def grid_inside(x):
        assert not isinstance(stride_grid(camera, 10).uv, jax.core.Tracer)
        return x

    jax.jit(grid_inside)(0.0)
    grid = stride_grid(camera, 10, *sequence.patch_shape)
    host = grid_pixels(camera, grid)
    assert all(isinstance(a, np.ndarray) for a in host)
    traced = jax.jit(lambda g: grid_pixels(camera, g))(grid)
    for a, b in zip(host, traced, strict=True):
        np.testing.assert_array_equal(a, b)
    assert_bitwise_equal(frames_on_grid(sequence, grid), jax.jit(frames_on_grid)(sequence, grid))
    assert_bitwise_equal(Region.of_scene(scene), jax.jit(Region.of_scene)(scene))
