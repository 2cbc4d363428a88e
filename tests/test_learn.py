"""Learned likelihood parameters (:mod:`jaxloc.sg2loc.learn`): parameter mapping, window particles,
the loss against a float64 numpy reference, gradients against float64 finite differences,
degenerate windows, training, determinism and tracing.

A hand-made scene (a floor and three coloured boxes, 16x9 camera, one ray per pixel, 3x4 patches) is
rendered from a short trajectory to make the sequence, so the windows carry real scores from the
filter's renderer without the cost of a synthetic room; one compiled :func:`score_window` shape.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxloc import Camera, FrameSequence, render, stride_grid
from jaxloc.geometry import compose_yaw, ego_motion, wrap_angle
from jaxloc.scene import SceneGraph
from jaxloc.sg2loc import SG2LocConfig, learn, localize
from jaxloc.sg2loc._filter import Region
from jaxloc.sg2loc._resampling import KLDConfig
from jaxloc.sg2loc._scores import (
    DEPTH_MAX,
    ObservationConfig,
    match_patches,
    particle_log_likelihood,
)

CAMERA = Camera.from_fov(16, 9, 70.0)
ROWS, COLS = 3, 4
STRIDE = 1  # the ray grid is the whole image: one render shape for sequence and checks
NUM_FRAMES = 4
WINDOW = 3
NUM_PARTICLES = 16
POSES_GT = np.array(
    [[0.5, 0.4, 1.5, 0.3], [0.7, 0.45, 1.5, 0.35], [0.9, 0.5, 1.55, 0.4], [1.1, 0.6, 1.5, 0.5]],
    np.float32,
)
BASE = ObservationConfig()

#: One compiled renderer per ray grid shape.
RENDER = jax.jit(render)

#: One compiled loss gradient for every gradient check.
GRAD = jax.jit(jax.grad(learn.window_loss))

#: Parameter points (log sigma, log lambda_depth, log lambda_color) of the gradient checks, wide
#: enough that several particles share the weight (at sigma 0.6 one particle takes it all here).
GRADIENT_POINTS = (
    (np.log(4.0), np.log(2.0), np.log(2.0)),
    (np.log(2.5), np.log(0.5), np.log(1.0)),
)


def _box(extents, centre, rgb) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=extents)
    mesh.apply_translation(centre)
    colors = np.tile(np.array([*rgb, 1.0]) * 255, (len(mesh.vertices), 1))
    colors[::2, :3] *= 0.5  # some texture for SSIM
    mesh.visual.vertex_colors = colors.astype(np.uint8)
    return mesh


@pytest.fixture(scope="module")
def scene() -> SceneGraph:
    meshes = [
        _box((8.0, 8.0, 0.1), (2.0, 2.0, -0.05), (0.6, 0.6, 0.6)),
        _box((1.0, 1.0, 2.0), (4.0, 1.0, 1.0), (0.9, 0.2, 0.2)),
        _box((0.8, 1.5, 1.2), (3.5, 2.5, 0.6), (0.2, 0.8, 0.2)),
        _box((1.2, 0.6, 2.5), (4.5, -0.5, 1.25), (0.2, 0.3, 0.9)),
    ]
    embeddings = np.random.default_rng(0).normal(size=(4, 8))
    return SceneGraph.from_meshes(meshes, [0, 1, 2, 3], embeddings)


@pytest.fixture(scope="module")
def sequence(scene) -> FrameSequence:
    """The scene rendered from POSES_GT at every pixel, patch embeddings = the patch's object."""
    full = stride_grid(CAMERA, STRIDE, ROWS, COLS)
    views = [RENDER(scene, jnp.asarray(p), CAMERA, full) for p in POSES_GT]
    depth = np.stack([np.where(np.isfinite(v.depth), v.depth, 0.0) for v in views])
    rgb = np.stack([np.asarray(v.color) for v in views])
    rng = np.random.default_rng(1)
    embeddings = np.asarray(scene.embeddings)
    patch = np.stack(
        [
            np.where(
                np.asarray(v.patch_object)[:, None] >= 0,
                embeddings[np.maximum(np.asarray(v.patch_object), 0)],
                rng.normal(size=(ROWS * COLS, 8)),
            )
            for v in views
        ]
    )
    motion = np.stack(
        [np.asarray(ego_motion(POSES_GT[t], POSES_GT[t + 1])) for t in range(NUM_FRAMES - 1)]
    )
    return FrameSequence(
        CAMERA,
        patch.reshape(NUM_FRAMES, ROWS, COLS, 8),
        motion,
        depth=depth.reshape(NUM_FRAMES, 9, 16),
        rgb=rgb.reshape(NUM_FRAMES, 9, 16, 3),
    )


@pytest.fixture(scope="module")
def windows(scene, sequence) -> learn.Windows:
    grid = stride_grid(CAMERA, STRIDE, ROWS, COLS)
    return learn.sequence_windows(
        jax.random.key(0), scene, sequence, POSES_GT, grid, (0, 1), WINDOW, NUM_PARTICLES
    )


#: The default LossConfig scales (metres, radians).
SCALES = (0.1, float(np.deg2rad(5.0)))


def reference_loss(log_params, window: learn.Windows, kind: str, scales=SCALES, frames="last"):
    """Float64 numpy reference of the window loss (eq. (2), log-softmax, kernel or expectation),
    of the whole window's posterior at its last frame or averaged over the window's prefixes."""
    sigma, lambda_depth, lambda_color = np.exp(np.clip(np.asarray(log_params, np.float64), -15, 15))
    semantic, depth, color = (np.asarray(x, np.float64) for x in window[:3])
    total = semantic + lambda_depth * depth + lambda_color * color
    best = 2.0 + lambda_depth * DEPTH_MAX["l1"] + lambda_color * 1.0
    per_frame = -((best - total) ** 2) / (2.0 * sigma**2)  # (K, N)
    num_frames = per_frame.shape[0]
    prefixes = range(num_frames) if frames == "every" else [num_frames - 1]
    losses = []
    for k in prefixes:
        log_likelihood = np.sum(per_frame[: k + 1], axis=0)
        log_likelihood = np.where(np.asarray(window.valid), log_likelihood, -np.inf)
        log_weights = log_likelihood - np.max(log_likelihood)
        log_weights -= np.log(np.sum(np.exp(log_weights)))
        position = np.asarray(window.position_error, np.float64)[k] / scales[0]
        yaw = np.asarray(window.yaw_error, np.float64)[k] / scales[1]
        if kind == "nll":
            terms = log_weights - 0.5 * (position**2 + yaw**2)
            top = np.max(terms)
            losses.append(-(top + np.log(np.sum(np.exp(terms - top)))))
        else:
            losses.append(np.sum(np.exp(log_weights) * (position + yaw)))
    return float(np.mean(losses))


def as_params(log_params) -> learn.LikelihoodParams:
    return learn.LikelihoodParams(*(jnp.asarray(v, jnp.float32) for v in log_params))


def one(windows: learn.Windows, b: int) -> learn.Windows:
    return jax.tree.map(lambda a: a[b], windows)


# ----------------------------------------------------------------------------- parameters


def test_params_config_round_trip():
    config = ObservationConfig(sigma=0.37, lambda_depth=1.5, lambda_color=0.25, use_color=False)
    params = learn.LikelihoodParams.from_config(config)
    back = params.to_config(ObservationConfig(use_color=False))
    for name in ("sigma", "lambda_depth", "lambda_color"):
        np.testing.assert_allclose(getattr(back, name), getattr(config, name), rtol=1e-6)
    assert back.use_color is False
    jitted = jax.jit(lambda p: p.to_config(BASE))(params)
    np.testing.assert_allclose(jitted.sigma, 0.37, rtol=1e-6)
    big = learn.LikelihoodParams(*(jnp.float32(v) for v in (-40.0, 40.0, 0.0)))
    sigma, lambda_depth, _ = big.values()
    assert float(sigma) == pytest.approx(np.exp(-learn.LOG_BOUND), rel=1e-5)
    assert float(lambda_depth) == pytest.approx(np.exp(learn.LOG_BOUND), rel=1e-5)


def test_bad_inputs_raise(scene, sequence):
    with pytest.raises(ValueError, match="lambda_color"):
        learn.LikelihoodParams.from_config(ObservationConfig(lambda_color=0.0))
    with pytest.raises(ValueError, match="kind"):
        learn.LossConfig(kind="mse")
    with pytest.raises(ValueError, match="frames"):
        learn.LossConfig(frames="first")
    grid = stride_grid(CAMERA, STRIDE, ROWS, COLS)
    with pytest.raises(ValueError, match="window_length"):
        learn.sequence_windows(jax.random.key(0), scene, sequence, POSES_GT, grid, (2,), 3, 4)
    with pytest.raises(ValueError, match="poses_gt"):
        learn.sequence_windows(jax.random.key(0), scene, sequence, POSES_GT[:2], grid, (0,), 2, 4)


# ----------------------------------------------------------------------------- particles


def test_window_particles_box_region_and_motion():
    region = Region(jnp.array([0.0, 0.0]), jnp.array([4.0, 3.0]), jnp.float32(0.0))
    motions = np.stack([ego_motion(POSES_GT[t], POSES_GT[t + 1]) for t in range(2)])
    poses = np.asarray(
        learn.window_particles(jax.random.key(3), POSES_GT[0], motions, 64, region, 0.8, 0.5)
    )
    assert poses.shape == (3, 64, 4)
    local, spread = poses[0, :32], poses[0, 32:]
    assert np.all(np.abs(local[:, :3] - POSES_GT[0, :3]) <= 0.8 + 1e-6)
    assert np.all(np.abs(np.asarray(wrap_angle(local[:, 3] - POSES_GT[0, 3]))) <= 0.5 + 1e-6)
    assert np.all((spread[:, :2] >= 0.0) & (spread[:, :2] <= [4.0, 3.0]))
    assert np.all((spread[:, 2] >= 1.5) & (spread[:, 2] <= 1.8))
    for k in range(2):  # each frame is the previous one moved by the ego-motion (loop reference)
        for i in (0, 40):
            np.testing.assert_allclose(
                poses[k + 1, i], compose_yaw(jnp.asarray(poses[k, i]), motions[k]), atol=1e-5
            )


def test_windows_hold_the_filter_scores(scene, sequence, windows):
    """The stored scores are particle_log_likelihood of the rendered views, the errors are to each
    frame's truth."""
    assert windows.semantic.shape == (2, WINDOW, NUM_PARTICLES)
    assert windows.position_error.shape == (2, WINDOW, NUM_PARTICLES)
    assert np.all(np.isfinite(np.asarray(windows.depth)))
    grid = stride_grid(CAMERA, STRIDE, ROWS, COLS)
    region = Region.of_scene(scene)
    poses = learn.window_particles(
        jax.random.fold_in(jax.random.key(0), 1),
        POSES_GT[1],
        np.asarray(sequence.ego_motion[1:3]),
        NUM_PARTICLES,
        region,
    )
    pixels = np.rint(np.asarray(grid.uv)).astype(int)
    depth = np.asarray(sequence.depth)[2][pixels[:, 1], pixels[:, 0]]
    rgb = np.asarray(sequence.rgb)[2][pixels[:, 1], pixels[:, 0]].reshape(9, 16, 3)
    embeddings = np.asarray(sequence.patch_embeddings[2]).reshape(-1, 8)

    match = match_patches(embeddings, scene.embeddings, scene.object_valid)
    score = jax.jit(particle_log_likelihood)
    for i in (0, 3, NUM_PARTICLES - 1):  # local and spread particles
        view = RENDER(scene, poses[1, i], CAMERA, grid)
        color = view.color.reshape(9, 16, 3)
        expected = score(BASE, match, view.patch_object, view.depth, depth, color, rgb)
        np.testing.assert_allclose(windows.semantic[1, 1, i], expected.semantic, atol=1e-5)
        np.testing.assert_allclose(windows.depth[1, 1, i], expected.depth, atol=1e-4)
        np.testing.assert_allclose(windows.color[1, 1, i], expected.color, atol=1e-4)
        for k in range(WINDOW):  # window 1 covers frames 1..3
            truth = POSES_GT[1 + k]
            np.testing.assert_allclose(
                windows.position_error[1, k, i],
                np.linalg.norm(poses[k, i, :3] - truth[:3]),
                atol=1e-5,
            )
            yaw = abs(float(wrap_angle(poses[k, i, 3] - truth[3])))
            np.testing.assert_allclose(windows.yaw_error[1, k, i], yaw, atol=1e-5)


def test_filter_windows_reproduce_the_filter_update(scene, sequence):
    """One-frame windows of a localize run's particle sets: under the run's own parameters their
    posterior is the filter's weights at every round and frame (the prior is uniform)."""
    config = SG2LocConfig(
        capacity=NUM_PARTICLES,
        strides=(1, 1),  # SSIM needs a grid of at least 7x7 (the 16x9 image)
        box_half_widths=(0.8,),
        kld=KLDConfig(min_particles=4, max_particles=NUM_PARTICLES),
    )
    result = localize(jax.random.key(7), scene, sequence, config)
    observation = dataclasses.replace(
        BASE, use_depth=result.used_depth, use_color=result.used_color
    )
    windows = learn.filter_windows(
        scene,
        sequence,
        POSES_GT,
        result.particles,
        result.particle_weights,
        config.strides,
        observation,
    )
    rounds = len(config.strides)
    assert windows.semantic.shape == (rounds * NUM_FRAMES, 1, NUM_PARTICLES)
    weights = np.asarray(result.particle_weights).reshape(rounds * NUM_FRAMES, NUM_PARTICLES)
    np.testing.assert_array_equal(np.asarray(windows.valid), weights > 0)
    assert 0 < np.asarray(windows.valid).sum() < windows.valid.size  # some slots inactive
    params = learn.LikelihoodParams.from_config(BASE)
    posterior = np.exp(
        np.asarray(jax.vmap(lambda w: learn.window_log_weights(params, observation, w))(windows))
    )
    np.testing.assert_allclose(posterior, weights, atol=1e-5)
    particles = np.asarray(result.particles).reshape(rounds * NUM_FRAMES, NUM_PARTICLES, 4)
    truth = np.tile(POSES_GT, (rounds, 1))
    valid = np.asarray(windows.valid)
    expected = np.linalg.norm(particles[..., :3] - truth[:, None, :3], axis=-1)
    np.testing.assert_allclose(
        np.asarray(windows.position_error[:, 0])[valid], expected[valid], atol=1e-5
    )
    with pytest.raises(ValueError, match="particles must have shape"):
        learn.filter_windows(
            scene, sequence, POSES_GT, result.particles[:1], result.particle_weights, (1, 1)
        )


# ----------------------------------------------------------------------------- loss, gradients


@pytest.mark.parametrize("frames", learn.LOSS_FRAMES)
@pytest.mark.parametrize("kind", learn.LOSS_KINDS)
@pytest.mark.parametrize("point", GRADIENT_POINTS)
def test_loss_and_gradient_match_float64_reference(windows, kind, point, frames):
    loss_config = learn.LossConfig(kind=kind, frames=frames)
    log_params = np.array(point)
    params = as_params(log_params)
    for b in range(2):
        window = one(windows, b)
        value = learn.window_loss(params, BASE, window, loss_config)
        reference = reference_loss(log_params, window, kind, frames=frames)
        np.testing.assert_allclose(value, reference, rtol=1e-4)
        grads = GRAD(params, BASE, window, loss_config)
        grads = np.array([grads.log_sigma, grads.log_lambda_depth, grads.log_lambda_color])
        step = 1e-5
        numeric = np.array(
            [
                (
                    reference_loss(log_params + step * e, window, kind, frames=frames)
                    - reference_loss(log_params - step * e, window, kind, frames=frames)
                )
                / (2 * step)
                for e in np.eye(3)
            ]
        )
        assert np.any(np.abs(numeric) > 1e-3)  # the check is not vacuous
        np.testing.assert_allclose(grads, numeric, rtol=2e-3, atol=2e-4)


@pytest.mark.parametrize("frames", learn.LOSS_FRAMES)
def test_degenerate_windows_have_finite_gradients(windows, frames):
    grad = jax.jit(jax.value_and_grad(learn.window_loss), static_argnums=())
    loss_config = learn.LossConfig(frames=frames)
    window = one(windows, 0)

    def check(params, window):
        value, g = grad(params, BASE, window, loss_config)
        leaves = [value, *jax.tree.leaves(g)]
        assert all(np.isfinite(np.asarray(x)) for x in leaves), leaves
        return value, g

    # Every likelihood underflows (exp(log L) == 0 in float32): sigma at its lower bound and a
    # huge depth error.
    tiny = as_params([-40.0, 0.0, 0.0])
    far = window._replace(depth=jnp.full_like(window.depth, -1e3))
    assert np.all(np.exp(np.asarray(learn.config_log_likelihood(tiny.to_config(BASE), far))) == 0)
    check(tiny, far)
    # No valid particle at all.
    check(tiny, window._replace(valid=jnp.zeros_like(window.valid)))
    # Empty patches (no rendered object) and no valid sensor depth: scores from the score code.
    match = match_patches(jnp.ones((12, 8)), jnp.eye(4, 8), jnp.ones(4, bool))
    empty = jax.jit(particle_log_likelihood)(
        BASE,
        match,
        jnp.full((12,), -1, jnp.int32),
        jnp.full((144,), jnp.inf),
        jnp.zeros(144),
        jnp.zeros((9, 16, 3)),
        jnp.zeros((9, 16, 3)),
    )
    assert float(empty.semantic) == 0.0 and float(empty.depth) == DEPTH_MAX["l1"]
    blank = window._replace(
        semantic=jnp.full_like(window.semantic, empty.semantic),
        depth=jnp.full_like(window.depth, empty.depth),
        color=jnp.full_like(window.color, empty.color),
    )
    value, g = check(as_params([np.log(0.6), np.log(2.0), np.log(2.0)]), blank)
    assert float(g.log_lambda_depth) == 0.0  # no depth information: no depth gradient


# ----------------------------------------------------------------------------- training


def test_training_reduces_loss_and_is_deterministic(windows):
    # From a wide likelihood: at sigma 0.6 one particle of these tiny windows takes all the weight
    # and the gradient vanishes (see the gradient test's points).
    start = learn.LikelihoodParams.from_config(dataclasses.replace(BASE, sigma=4.0))
    params, history = learn.train(
        jax.random.key(5), start, BASE, windows, windows, num_steps=20, batch_size=2, eval_every=5
    )
    np.testing.assert_array_equal(history.step, [0, 5, 10, 15, 20])
    assert history.train_loss[-1] < history.train_loss[0] - 1e-3
    final = learn.batch_loss(params, BASE, windows, learn.LossConfig())
    np.testing.assert_allclose(final, history.train_loss[-1], rtol=1e-6)
    again, history_again = learn.train(
        jax.random.key(5), start, BASE, windows, windows, num_steps=20, batch_size=2, eval_every=5
    )
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(again), strict=True):
        assert np.asarray(a).tobytes() == np.asarray(b).tobytes()
    np.testing.assert_array_equal(history.train_loss, history_again.train_loss)


def test_train_step_traces_once(windows, monkeypatch):
    traces = {"count": 0}
    original = learn.batch_loss

    def counted(*args, **kwargs):
        traces["count"] += 1
        return original(*args, **kwargs)

    monkeypatch.setattr(learn.training, "batch_loss", counted)  # what the train step calls
    optimizer = learn.adam(0.05)
    step = learn.make_train_step(optimizer, BASE, learn.LossConfig())
    params = learn.LikelihoodParams.from_config(BASE)
    state = learn.TrainState(params, optimizer.init(params))
    for i in range(4):
        shifted = windows._replace(semantic=windows.semantic * (1.0 + 0.1 * i))
        state, value = step(state, jax.random.key(i), shifted, 3)
        assert np.isfinite(float(value))
    assert traces["count"] == 1  # batch size 3 is used nowhere else: exactly one compilation
