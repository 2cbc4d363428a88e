"""Observation scores vs straightforward numpy references, under jit and vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxloc.sg2loc import _scores as S


def random_frame(seed, num_patches=20, num_objects=7, dim=16):
    rng = np.random.default_rng(seed)
    objects = rng.normal(size=(num_objects, dim))
    objects /= np.linalg.norm(objects, axis=1, keepdims=True)
    valid = np.ones(num_objects, bool)
    valid[[2, 5]] = False
    truth = rng.choice(np.flatnonzero(valid), num_patches)
    patches = 3.0 * (objects[truth] + 0.6 * rng.normal(size=(num_patches, dim)))
    patches[4] = 0.0  # a patch with no embedding
    return patches.astype(np.float32), objects.astype(np.float32), valid


def numpy_semantic(patches, objects, valid, rendered, variant):
    patches = np.asarray(patches, np.float64)
    norms = np.linalg.norm(patches, axis=1)
    total = 0.0
    for p in range(len(patches)):
        o = rendered[p]
        if o < 0 or norms[p] == 0 or not valid[o]:
            continue
        cos = patches[p] @ objects[o] / norms[p]
        sims = [
            patches[p] @ objects[j] / norms[p] if valid[j] else -np.inf for j in range(len(objects))
        ]
        if variant == "soft" or int(np.argmax(sims)) == o:
            total += cos + 1.0
    return total / len(patches)


@pytest.mark.parametrize("variant", ["gated", "soft"])
def test_semantic_score_matches_numpy_under_jit_and_vmap(variant):
    patches, objects, valid = random_frame(0)
    rng = np.random.default_rng(1)
    rendered = rng.integers(-1, 7, size=(5, 20)).astype(np.int32)
    match = jax.jit(S.match_patches)(patches, objects, valid)
    truth = np.argmax(np.where(valid, patches @ objects.T, -np.inf), axis=1)
    rendered[0] = truth  # a particle that sees what the patches predict
    score = jax.jit(jax.vmap(S.semantic_score, (None, 0, None)), static_argnums=2)
    batched = np.asarray(score(match, rendered, variant))
    for i in range(len(rendered)):
        expected = numpy_semantic(patches, objects, valid, rendered[i], variant)
        np.testing.assert_allclose(batched[i], expected, atol=1e-5)
        eager = float(S.semantic_score(match, rendered[i], variant))
        np.testing.assert_allclose(eager, batched[i], atol=1e-6)
    assert 0.0 <= batched.min() and batched.max() <= 2.0
    assert batched[0] == batched.max()


def test_match_patches_handles_zero_patches_and_invalid_objects():
    patches, objects, valid = random_frame(2)
    match = S.match_patches(patches, objects, valid)
    predicted = np.asarray(match.predicted)
    assert predicted[4] == -1
    assert not np.any(np.isin(predicted, [2, 5]))
    assert np.all(np.asarray(match.cosines)[:, ~valid] == -1.0)
    none = S.match_patches(patches, objects, np.zeros(7, bool))
    assert np.all(np.asarray(none.predicted) == -1)
    assert float(S.semantic_score(none, np.zeros(20, np.int32), "soft")) == 0.0
    with pytest.raises(ValueError, match="embedding sizes"):
        S.match_patches(patches[:, :5], objects, valid)
    with pytest.raises(ValueError, match="object_valid"):
        S.match_patches(patches, objects, valid[:3])
    with pytest.raises(ValueError, match="rendered_object"):
        S.semantic_score(none, np.zeros(21, np.int32))
    with pytest.raises(ValueError, match="variant"):
        S.semantic_score(none, np.zeros(20, np.int32), "paper")


def numpy_depth(rendered, sensor, variant, clip=0.5, miss_error=1.0):
    rendered, sensor = np.asarray(rendered, np.float64), np.asarray(sensor, np.float64)
    errors = []
    for r, d in zip(rendered, sensor, strict=True):
        if not (np.isfinite(d) and d > 0):
            continue
        hit = np.isfinite(r) and r > 0
        if variant == "l1":
            errors.append(abs(r - d) if hit else miss_error)
        else:
            errors.append(abs(np.clip(d - r, -clip, clip)) if hit else clip)
    if not errors:
        return (1.0 if variant == "l1" else 2.0), 0
    e = np.mean(errors)
    return (1.0 - e if variant == "l1" else 2.0 - 2.0 * min(e, clip) / clip), len(errors)


def depth_case(seed, rays=50):
    rng = np.random.default_rng(seed)
    sensor = rng.uniform(0.5, 4.0, rays)
    sensor[rng.random(rays) < 0.2] = 0.0
    rendered = np.stack([sensor + rng.normal(0, s, rays) for s in (0.0, 0.1, 0.4, 2.0)])
    rendered[:, rng.random(rays) < 0.15] = np.inf
    return rendered.astype(np.float32), sensor.astype(np.float32)


@pytest.mark.parametrize("variant", ["l1", "clipped"])
def test_depth_score_matches_numpy_under_jit_and_vmap(variant):
    rendered, sensor = depth_case(3)
    score = jax.jit(jax.vmap(S.depth_score, (0, None, None, None, None)), static_argnums=2)
    for clip, miss in ((0.5, 1.0), (0.3, 2.5)):  # traced parameters, one compilation
        out = score(rendered, sensor, variant, clip, miss)
        for i in range(len(rendered)):
            expected, count = numpy_depth(rendered[i], sensor, variant, clip, miss)
            np.testing.assert_allclose(float(out.score[i]), expected, atol=1e-5)
            assert int(out.num_valid[i]) == count
            eager = S.depth_score(rendered[i], sensor, variant, clip, miss)
            np.testing.assert_allclose(float(eager.score), float(out.score[i]), atol=1e-6)
    assert score._cache_size() == 1


@pytest.mark.parametrize("variant", ["l1", "clipped"])
def test_depth_score_without_valid_depth_is_the_maximum_and_finite(variant):
    rendered = np.array([1.0, np.inf, 2.0], np.float32)
    for sensor in (np.zeros(3), np.array([np.nan, -1.0, np.inf])):
        out = jax.jit(S.depth_score, static_argnums=2)(rendered, sensor.astype(np.float32), variant)
        assert float(out.score) == S.DEPTH_MAX[variant] and int(out.num_valid) == 0
    # a particle that sees nothing: l1 scores 0 with the default miss error, clipped scores 0
    out = S.depth_score(np.full(3, np.inf, np.float32), np.ones(3, np.float32), variant)
    assert float(out.score) == 0.0


def test_depth_gradients_are_finite_with_misses_and_holes():
    rendered, sensor = depth_case(4)
    for variant in ("l1", "clipped"):
        grad = jax.grad(lambda r, v=variant: S.depth_score(r, sensor, v).score)(rendered[1])
        assert np.all(np.isfinite(np.asarray(grad)))
        empty = jax.grad(lambda r, v=variant: S.depth_score(r, np.zeros(50), v).score)(rendered[1])
        assert np.all(np.asarray(empty) == 0.0)


def numpy_ssim(x, y, window=7, c1=0.01**2, c2=0.03**2):
    """Textbook SSIM: every full 7x7 window, population statistics, per channel, then mean."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    h, w, c = x.shape
    values = []
    for ch in range(c):
        for i in range(h - window + 1):
            for j in range(w - window + 1):
                a = x[i : i + window, j : j + window, ch].ravel()
                b = y[i : i + window, j : j + window, ch].ravel()
                mu_a, mu_b = a.mean(), b.mean()
                var_a, var_b = a.var(), b.var()
                cov = np.mean((a - mu_a) * (b - mu_b))
                values.append(
                    (2 * mu_a * mu_b + c1)
                    * (2 * cov + c2)
                    / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
                )
    return float(np.mean(values))


def image_pair(seed, shape=(9, 12, 3)):
    rng = np.random.default_rng(seed)
    observed = rng.uniform(0, 1, shape)
    rendered = np.stack(
        [
            observed,
            np.clip(observed + rng.normal(0, 0.1, shape), 0, 1),
            rng.uniform(0, 1, shape),
            1.0 - observed,
            np.full(shape, 0.3),
        ]
    )
    return rendered.astype(np.float32), observed.astype(np.float32)


@pytest.mark.parametrize("variant", ["paper", "reference"])
def test_color_score_matches_numpy_ssim_under_jit_and_vmap(variant):
    rendered, observed = image_pair(5)
    out = jax.jit(jax.vmap(S.color_score, (0, None, None)), static_argnums=2)(
        rendered, observed, variant
    )
    for i in range(len(rendered)):
        ssim = numpy_ssim(rendered[i], observed)
        expected = np.clip(ssim, 0, 1) if variant == "paper" else 2 * ssim
        np.testing.assert_allclose(float(out[i]), expected, atol=1e-4)
        eager = float(S.color_score(rendered[i], observed, variant))
        np.testing.assert_allclose(eager, float(out[i]), atol=1e-5)
    np.testing.assert_allclose(float(out[0]), S.COLOR_MAX[variant], atol=1e-5)
    assert numpy_ssim(rendered[3], observed) < 0  # the inverted image: clipped to 0 in "paper"
    assert (float(out[3]) == 0.0) == (variant == "paper")


def test_ssim_gradient_is_finite_on_flat_images_and_rejects_small_images():
    flat = jnp.full((8, 8, 3), 0.5)
    grad = jax.grad(lambda x: S.mean_ssim(x, flat))(flat)
    assert np.all(np.isfinite(np.asarray(grad)))
    # against central differences in float64 of the numpy reference, on a textured pair
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0.2, 0.8, (2, 9, 10, 3))
    grad = np.asarray(
        jax.grad(lambda a: S.mean_ssim(a, jnp.asarray(y, jnp.float32)))(jnp.asarray(x, jnp.float32))
    )
    for index in [(0, 0, 0), (4, 5, 1), (8, 9, 2), (3, 7, 0)]:
        step = np.zeros_like(x)
        step[index] = 1e-4
        central = (numpy_ssim(x + step, y) - numpy_ssim(x - step, y)) / 2e-4
        np.testing.assert_allclose(grad[index], central, rtol=1e-2, atol=1e-4)
    with pytest.raises(ValueError, match="at least 7x7"):
        S.mean_ssim(jnp.zeros((6, 9, 3)), jnp.zeros((6, 9, 3)))
    with pytest.raises(ValueError, match="equal shape"):
        S.mean_ssim(jnp.zeros((8, 9, 3)), jnp.zeros((9, 8, 3)))


def test_max_total_for_paper_reference_and_semantic_only():
    assert float(S.ObservationConfig().max_total()) == 6.0
    assert float(S.ObservationConfig.reference().max_total()) == 6.0
    semantic_only = S.ObservationConfig(use_depth=False, use_color=False, sigma=0.2)
    assert float(semantic_only.max_total()) == 2.0
    assert float(S.ObservationConfig(lambda_depth=0.5, use_color=False).max_total()) == 2.5


def test_log_likelihood_matches_eq2_and_does_not_retrace_for_new_weights():
    traces = []

    @jax.jit
    def loglik(config, s, s_d, s_i):
        traces.append(1)
        return S.log_likelihood(config, s, s_d, s_i)

    scores = (1.4, 0.7, 0.6)
    for lam_d, lam_c, sigma in ((2.0, 2.0, 0.2), (1.0, 0.5, 0.6)):
        config = S.ObservationConfig(lambda_depth=lam_d, lambda_color=lam_c, sigma=sigma)
        total = scores[0] + lam_d * scores[1] + lam_c * scores[2]
        best = 2.0 + lam_d + lam_c
        expected = -((best - total) ** 2) / (2 * sigma**2)
        np.testing.assert_allclose(float(loglik(config, *scores)), expected, rtol=1e-5)
    assert len(traces) == 1

    reference = S.ObservationConfig.reference()
    # with clip_total a negative S counts as 0 (the worst likelihood) and S_max gives 0
    np.testing.assert_allclose(
        float(S.log_likelihood(reference, -0.5, -1.0, -2.0)), -(6.0**2) / (2 * 0.36), rtol=1e-5
    )
    assert float(S.log_likelihood(reference, 2.0, 2.0, 2.0)) == 0.0
    semantic_only = S.ObservationConfig(use_depth=False, use_color=False, sigma=0.2)
    np.testing.assert_allclose(
        float(S.log_likelihood(semantic_only, 1.5)), -(0.5**2) / (2 * 0.04), rtol=1e-5
    )
    with pytest.raises(ValueError, match="use_depth"):
        S.log_likelihood(S.ObservationConfig(), 1.0)
    # The default sigma is the paper's 0.2 scaled to eq. (2)'s threefold range (and the authors').
    assert float(S.ObservationConfig().sigma) == pytest.approx(0.6)


def test_observation_config_validates():
    with pytest.raises(ValueError, match="depth_variant"):
        S.ObservationConfig(depth_variant="L1")
    with pytest.raises(ValueError, match="sigma"):
        S.ObservationConfig(sigma=0.0)
    with pytest.raises(ValueError, match="lambda_color"):
        S.ObservationConfig(lambda_color=float("nan"))
    with pytest.raises(ValueError, match="lambda_depth"):
        S.ObservationConfig(lambda_depth=-1.0)


def test_particle_log_likelihood_combines_the_scores_under_vmap():
    patches, objects, valid = random_frame(6, num_patches=20)
    match = S.match_patches(patches, objects, valid)
    rng = np.random.default_rng(7)
    rendered_object = rng.integers(-1, 7, size=(3, 20)).astype(np.int32)
    rendered_depth, sensor = depth_case(8)
    rendered_rgb, observed = image_pair(9)
    config = S.ObservationConfig()

    def one(obj, depth, rgb):
        return S.particle_log_likelihood(config, match, obj, depth, sensor, rgb, observed)

    out = jax.jit(jax.vmap(one))(rendered_object, rendered_depth[:3], rendered_rgb[:3])
    for i in range(3):
        s = numpy_semantic(patches, objects, valid, rendered_object[i], "gated")
        s_d, _ = numpy_depth(rendered_depth[i], sensor, "l1")
        s_i = np.clip(numpy_ssim(rendered_rgb[i], observed), 0, 1)
        expected = -((6.0 - (s + 2 * s_d + 2 * s_i)) ** 2) / (2 * 0.6**2)
        np.testing.assert_allclose(float(out.log_likelihood[i]), expected, rtol=1e-4)
        np.testing.assert_allclose(float(out.depth[i]), s_d, atol=1e-5)
    with pytest.raises(ValueError, match="rendered_rgb"):
        S.particle_log_likelihood(config, match, rendered_object[0], rendered_depth[0], sensor)


def test_largest_ssim_stride_is_the_largest_whose_stride_grid_holds_the_window():
    from jaxloc.camera import Camera, stride_grid, stride_grid_shape

    for width, height in [(160, 90), (160, 120), (960, 540), (64, 48), (33, 17), (7, 7)]:
        largest = S.largest_ssim_stride(width, height)
        camera = Camera.from_fov(width, height, 60.0)
        shapes = {s: tuple(stride_grid(camera, s).shape) for s in range(1, largest + 3)}
        assert all(shapes[s] == stride_grid_shape(s, width, height) for s in shapes)
        assert min(shapes[largest]) >= S.SSIM_WINDOW
        assert all(min(shapes[s]) < S.SSIM_WINDOW for s in range(largest + 1, largest + 3))
    assert (S.largest_ssim_stride(160, 90), S.largest_ssim_stride(160, 120)) == (13, 18)
    assert S.largest_ssim_stride(6, 100) == 0


def test_check_ssim_strides_names_the_setting_in_one_line():
    S.check_ssim_strides((13, 8, 4), 160, 90)  # all fit
    with pytest.raises(ValueError) as info:
        S.check_ssim_strides((8, 20), 160, 90, "--strides", "--no-rgb")
    assert str(info.value) == (
        "--strides: stride 20 gives a 4 x 8 ray grid at 160 x 90, smaller than SSIM's 7 x 7 "
        "window; use strides of at most 13, or --no-rgb"
    )
    with pytest.raises(ValueError, match=r"^strides: stride 1 .* no stride fits an image under 7"):
        S.check_ssim_strides((1,), 6, 100)
