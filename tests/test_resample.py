"""Resampling on padded buffers and KLD-sampling vs numpy references (AMCL, Fox 2001)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxloc.sg2loc import _particles as P, _resampling as R

KEY = jax.random.PRNGKey(0)
METHODS = ["stratified", "systematic"]


def amcl_limit(k, eps, z, min_samples, max_samples, k_le_1="min"):
    """AMCL's pf_resample_limit, with this library's choice for k <= 1."""
    if k <= 1:
        return min_samples if k_le_1 == "min" else max_samples
    b = 2.0 / (9.0 * (k - 1))
    x = 1.0 - b + math.sqrt(b) * z
    n = math.ceil((k - 1) / (2.0 * eps) * x * x * x)
    return min(max(n, min_samples), max_samples)


def padded_state(weights, active, n_dims=4, seed=0):
    rng = np.random.default_rng(seed)
    size = len(weights)
    poses = rng.uniform(-1, 1, (size, n_dims)).astype(np.float32)
    with np.errstate(divide="ignore"):
        logw = np.where(active, np.log(weights), -np.inf).astype(np.float32)
    return P.ParticleState(jnp.asarray(poses), jnp.asarray(logw), jnp.asarray(active))


@pytest.mark.parametrize(("eps", "z"), [(0.1, 1.96), (0.05, 2.33), (0.01, 0.99)])
def test_kld_bound_matches_amcl_formula(eps, z):
    k = np.arange(0, 3000)
    out = np.asarray(jax.jit(R.kld_bound)(k, eps, z, 500, 10000))
    expected = np.array([amcl_limit(int(i), eps, z, 500, 10000) for i in k])
    mismatch = np.flatnonzero(out != expected)
    # float32 vs float64 may only differ by one where the unrounded bound is within 1e-4 of an
    # integer (ceil of a value a hair above or below it)
    for i in mismatch:
        b = 2.0 / (9.0 * (k[i] - 1))
        raw = (k[i] - 1) / (2 * eps) * (1 - b + math.sqrt(b) * z) ** 3
        assert abs(out[i] - expected[i]) == 1 and abs(raw - round(raw)) < 1e-4 * raw
    assert mismatch.size <= 3


def test_kld_bound_edge_cases():
    # k <= 1: a single occupied bin is a concentrated posterior -> min, not AMCL's max
    out = np.asarray(R.kld_bound(jnp.array([-3, 0, 1, 2]), 0.1, 1.96, 7, 10000))
    assert out[0] == out[1] == out[2] == 7
    assert out[3] == amcl_limit(2, 0.1, 1.96, 7, 10000) and out[3] >= 7
    assert amcl_limit(1, 0.1, 1.96, 7, 10000, k_le_1="amcl") == 10000  # what AMCL would give
    # the bound grows with k and saturates at the max
    grown = np.asarray(R.kld_bound(jnp.arange(2, 100000, 997), 0.1, 1.96, 1, 10000))
    assert np.all(np.diff(grown) >= 0) and grown[-1] == 10000


def numpy_fox_count(poses, bin_sizes, eps, z, min_samples, max_samples):
    """Fox's sequential rule: add draws one by one, stop once n >= bound(k)."""
    seen = set()
    size = len(poses)
    upper = min(max_samples, size)
    lower = min(min_samples, upper)
    for n, pose in enumerate(np.asarray(poses, np.float64), start=1):
        yaw = (pose[3] + np.pi) % (2 * np.pi) - np.pi
        seen.add(tuple(np.floor(np.append(pose[:3], yaw) / bin_sizes).astype(int)))
        if n >= amcl_limit(len(seen), eps, z, lower, upper):
            return n, len(seen)
    raise AssertionError("unreachable: the bound never exceeds the capacity")


@pytest.mark.parametrize("spread", [0.05, 0.5, 3.0])
def test_kld_sample_count_matches_fox_sequential_rule(spread):
    rng = np.random.default_rng(int(spread * 100))
    poses = rng.normal(0, spread, (4000, 4)).astype(np.float32)
    poses[:, 3] *= 2
    config = R.KLDConfig(epsilon=0.05, z=1.96, min_particles=50, max_particles=3000)
    n, k = jax.jit(R.kld_sample_count)(jnp.asarray(poses), config)
    expected_n, expected_k = numpy_fox_count(poses, np.full(4, 0.2), 0.05, 1.96, 50, 3000)
    assert (int(n), int(k)) == (expected_n, expected_k)
    # a small buffer caps the count at the capacity
    n_small, _ = R.kld_sample_count(jnp.asarray(poses[:40]), config)
    assert int(n_small) == numpy_fox_count(poses[:40], np.full(4, 0.2), 0.05, 1.96, 50, 3000)[0]


def test_draw_indices_never_draw_zero_weight_and_systematic_counts_are_tight():
    weights = np.zeros(32)
    weights[[3, 7, 8, 30]] = [0.5, 0.2, 0.2999, 0.0001]
    for method in METHODS:
        draws = jax.jit(jax.vmap(R.draw_indices, (0, None, None, None)), static_argnums=3)(
            jax.random.split(KEY, 200), jnp.asarray(weights, jnp.float32), 17, method
        )
        used = np.asarray(draws)[:, :17]
        assert np.all(np.isin(used, [3, 7, 8, 30]))
        assert np.all(np.asarray(draws)[:, 17:] == 0)
        if method == "systematic":  # each count is floor or ceil of n * w
            counts = np.stack([np.bincount(row, minlength=32) for row in used])
            assert np.all(counts >= np.floor(17 * weights)) and np.all(
                counts <= np.ceil(17 * weights)
            )


@pytest.mark.parametrize("method", METHODS)
def test_resampling_is_unbiased(method):
    size, n, trials = 24, 15, 4000
    rng = np.random.default_rng(11)
    active = rng.random(size) < 0.6
    weights = np.where(active, rng.gamma(0.7, size=size), 0.0)
    weights /= weights.sum()
    state = padded_state(np.where(active, weights, 1.0), active)

    @jax.jit
    def counts_for(keys):
        def one(key):
            new, _ = R.resample(key, state, n, method)
            # recover which particle each slot copied from its pose
            same = jnp.all(new.poses[:, None, :] == state.poses[None, :, :], axis=-1)
            return jnp.sum(same & new.active[:, None], axis=0)

        return jax.vmap(one)(keys)

    counts = np.asarray(counts_for(jax.random.split(KEY, trials)))
    assert np.all(counts.sum(axis=1) == n)
    assert np.all(counts[:, ~active] == 0)
    # expected count of particle i is n * w_i; per-trial std <= 0.5 for these resamplers
    np.testing.assert_allclose(counts.mean(axis=0), n * weights, atol=5 * 0.5 / np.sqrt(trials))


@pytest.mark.parametrize("method", METHODS)
def test_resample_padded_buffer_with_few_active(method):
    active = np.zeros(64, bool)
    active[[5, 40, 63]] = True
    weights = np.where(active, 1.0, 0.0)
    weights[40] = 3.0
    state = padded_state(weights, active)
    resample = jax.jit(R.resample, static_argnums=3)
    new, degenerate = resample(KEY, state, 50, method)
    eager, _ = R.resample(KEY, state, 50, method)
    np.testing.assert_array_equal(np.asarray(new.poses), np.asarray(eager.poses))
    again, _ = resample(KEY, state, 50, method)
    np.testing.assert_array_equal(np.asarray(new.poses), np.asarray(again.poses))
    assert not bool(degenerate)
    act = np.asarray(new.active)
    np.testing.assert_array_equal(act, np.arange(64) < 50)
    np.testing.assert_allclose(np.asarray(new.log_weights)[act], -np.log(50), rtol=1e-6)
    assert np.all(np.isneginf(np.asarray(new.log_weights)[~act]))
    sources = np.asarray(state.poses)[[5, 40, 63]]
    drawn = np.asarray(new.poses)[act]
    assert np.all(np.any(np.all(drawn[:, None] == sources[None], axis=-1), axis=1))
    n_big, _ = resample(KEY, state, 10**6, method)  # n is clamped to the capacity
    assert bool(np.all(n_big.active))


@pytest.mark.parametrize("bad", [-np.inf, np.nan, np.inf])
def test_resample_recovers_from_unusable_weights(bad):
    active = np.arange(16) < 10
    state = padded_state(np.ones(16), active)
    state = P.ParticleState(state.poses, jnp.where(state.active, bad, -jnp.inf), state.active)
    new, degenerate = jax.jit(R.resample)(KEY, state, 8)
    assert bool(degenerate)
    assert not np.any(np.isnan(np.asarray(new.poses))) and not np.any(
        np.isnan(np.asarray(new.log_weights))
    )
    sources = np.asarray(state.poses)[:10]
    drawn = np.asarray(new.poses)[np.asarray(new.active)]
    assert np.all(np.any(np.all(drawn[:, None] == sources[None], axis=-1), axis=1))
    new, info = jax.jit(R.kld_resample)(KEY, state, R.KLDConfig(min_particles=4))
    assert bool(info.degenerate) and 4 <= int(info.num_particles) <= 16
    assert not np.any(np.isnan(np.asarray(new.log_weights)))


def test_resample_without_active_particles_keeps_the_state():
    state = padded_state(np.ones(8), np.zeros(8, bool))
    new, degenerate = R.resample(KEY, state, 5)
    assert bool(degenerate) and not bool(np.any(new.active))
    new, info = R.kld_resample(KEY, state, R.KLDConfig(min_particles=2))
    assert int(info.num_particles) == 0 and not bool(np.any(new.active))


def test_kld_resample_adapts_count_and_does_not_retrace():
    size = 2048
    rng = np.random.default_rng(3)
    spread = np.concatenate(
        [rng.uniform(0, 6, (size, 3)), rng.uniform(-np.pi, np.pi, (size, 1))], axis=1
    )
    state = P.ParticleState(
        jnp.asarray(spread, jnp.float32), jnp.full(size, -np.log(size)), jnp.ones(size, bool)
    )
    concentrated = P.ParticleState(
        state.poses.at[:, :3].set(1.05).at[:, 3].set(0.1), state.log_weights, state.active
    )
    traces = []

    @jax.jit
    def step(key, state, config):
        traces.append(1)
        return R.kld_resample(key, state, config)

    config = R.KLDConfig(min_particles=100, max_particles=1500)
    new, info = step(KEY, state, config)
    assert int(info.num_particles) == 1500 and int(new.active.sum()) == 1500
    new, info = step(KEY, concentrated, config)
    assert int(info.num_particles) == 100 and int(info.num_bins) == 1
    medium = P.ParticleState(  # 3 x 3 x 3 position bins x 4 yaw bins
        jnp.asarray(spread * 0.1, jnp.float32), state.log_weights, state.active
    )
    medium = P.ParticleState(medium.poses.at[:, 3].add(0.4), state.log_weights, state.active)
    new, info = step(KEY, medium, R.KLDConfig(epsilon=0.5, min_particles=10, max_particles=5000))
    assert 10 < int(info.num_particles) < size and 40 <= int(info.num_bins) <= 108
    assert len(traces) == 1
    # the chosen n obeys the stopping rule for its k
    assert int(info.num_particles) >= int(R.kld_bound(info.num_bins, 0.5, 1.96, 10, size))
    # determinism for a key
    again, info_again = step(KEY, medium, R.KLDConfig(epsilon=0.5, min_particles=10))
    np.testing.assert_array_equal(np.asarray(again.poses), np.asarray(new.poses))
    assert int(info_again.num_particles) == int(info.num_particles)


def test_kld_config_validates():
    with pytest.raises(ValueError, match="min_particles"):
        R.KLDConfig(min_particles=20, max_particles=10)
    with pytest.raises(ValueError, match="positive"):
        R.KLDConfig(epsilon=0.0)
    with pytest.raises(ValueError, match="bin_sizes"):
        R.KLDConfig(bin_sizes=(0.2, 0.2, 0.2))
    with pytest.raises(ValueError, match="method"):
        R.KLDConfig(method="multinomial")


def test_pieces_compose_into_a_converging_scanned_filter_without_retrace():
    """predict -> update -> KLD resample under lax.scan, with a Gaussian stand-in likelihood."""
    from jaxloc.geometry import compose_yaw, wrap_angle

    traces = []
    start = jnp.array([1.2, 1.7, 1.6, 0.5])
    motions = jnp.tile(jnp.array([0.15, 0.0, 0.0, 0.1]), (8, 1))

    def true_poses(start):
        def move(pose, motion):
            nxt = compose_yaw(pose, motion)
            return nxt, nxt

        return jax.lax.scan(move, start, motions)[1]

    @jax.jit
    def run(key, start, lo, hi):
        traces.append(1)
        key_init, key_run = jax.random.split(key)
        state = P.init_region(key_init, 2000, lo, hi, 0.0)
        config = R.KLDConfig(min_particles=200, max_particles=2000)

        def step(state, inputs):
            key, motion, truth = inputs
            key_predict, key_resample = jax.random.split(key)
            state = P.predict(key_predict, state, motion, 0.03, 0.03)
            gap = state.poses - truth
            loglik = -jnp.sum(gap[:, :3] ** 2, -1) / (2 * 0.25**2)
            loglik = loglik - wrap_angle(gap[:, 3]) ** 2 / (2 * 0.3**2)
            state, _ = P.update_weights(state, loglik)
            estimate, _ = P.mle(state)
            state, info = R.kld_resample(key_resample, state, config)
            return state, (estimate, info.num_particles)

        keys = jax.random.split(key_run, motions.shape[0])
        return jax.lax.scan(step, state, (keys, motions, true_poses(start)))[1]

    estimates, counts = run(KEY, start, jnp.array([0.0, 0.0]), jnp.array([3.0, 3.0]))
    truth = np.asarray(true_poses(start))
    error = np.linalg.norm(np.asarray(estimates)[-1, :3] - truth[-1, :3])
    assert error < 0.25 and abs(float(wrap_angle(estimates[-1, 3] - truth[-1, 3]))) < 0.3
    assert int(counts[-1]) < int(counts[0])  # the posterior concentrates, KLD shrinks the set
    run(jax.random.PRNGKey(1), start + 0.3, jnp.array([-1.0, 0.0]), jnp.array([3.0, 4.0]))
    assert len(traces) == 1
