"""Particle state: initialisation, motion model, weights, estimates, injection (vs numpy)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxloc.geometry import compose_yaw, ego_motion
from jaxloc.sg2loc import _particles as P

KEY = jax.random.PRNGKey(0)
HEIGHTS = np.array(P.PAPER_HEIGHTS)


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def random_state(seed, n=64, active_count=40):
    rng = np.random.default_rng(seed)
    poses = np.concatenate(
        [rng.uniform(0, 3, (n, 3)), rng.uniform(-np.pi, np.pi, (n, 1))], axis=1
    ).astype(np.float32)
    active = np.zeros(n, bool)
    active[rng.choice(n, active_count, replace=False)] = True
    logw = rng.normal(0, 2, n).astype(np.float32)
    logw = np.where(active, logw - np.log(np.sum(np.exp(logw[active]))), -np.inf)
    return P.ParticleState(jnp.asarray(poses), jnp.asarray(logw, jnp.float32), jnp.asarray(active))


def cell_histogram(state, lo, hi, cell=0.2):
    poses = np.asarray(state.poses)[np.asarray(state.active)]
    counts = np.maximum(np.ceil((np.asarray(hi) - lo) / cell - 1e-4), 1).astype(int)
    edge = (np.asarray(hi) - lo) / counts
    ij = np.floor((poses[:, :2] - lo) / edge).astype(int)
    hist = np.zeros(tuple(counts), int)
    np.add.at(hist, (ij[:, 0], ij[:, 1]), 1)
    return hist


def test_init_region_fills_every_cell_when_capacity_allows():
    lo, hi = np.array([0.0, -1.0]), np.array([1.0, 0.6])  # 5 x 8 cells, 4 heights, 3 per cell
    state = jax.jit(P.init_region, static_argnums=1)(KEY, 600, lo, hi, 0.25)
    active = np.asarray(state.active)
    expected = 5 * 8 * 4 * 3
    assert active.sum() == expected and active[:expected].all()
    poses = np.asarray(state.poses)[active]
    assert np.all((poses[:, :2] >= lo) & (poses[:, :2] <= hi))
    assert np.all(np.min(np.abs(poses[:, 2, None] - 0.25 - HEIGHTS), axis=1) < 1e-5)
    assert np.all((poses[:, 3] >= -np.pi) & (poses[:, 3] < np.pi))
    hist = cell_histogram(state, lo, hi)
    assert np.all(hist == 4 * 3)
    np.testing.assert_allclose(np.asarray(state.log_weights)[active], -np.log(expected), rtol=1e-6)
    assert np.all(np.isneginf(np.asarray(state.log_weights)[~active]))


def test_init_region_spreads_evenly_when_over_capacity():
    lo, hi = np.array([0.0, 0.0]), np.array([4.0, 3.0])  # 20 x 15 cells -> 3600 lattice poses
    capacity = 1000
    state = jax.jit(P.init_region, static_argnums=1)(KEY, capacity, lo, hi, 0.0)
    assert bool(np.all(state.active))
    hist = cell_histogram(state, lo, hi)
    per_cell = capacity / hist.size * 1.0
    assert hist.sum() == capacity
    assert hist.min() >= np.floor(per_cell) - 1 and hist.max() <= np.ceil(per_cell) + 1
    level = np.argmin(np.abs(np.asarray(state.poses[:, 2, None]) - HEIGHTS), axis=1)
    np.testing.assert_allclose(np.bincount(level, minlength=4) / capacity, 0.25, atol=0.05)


def test_init_region_jit_matches_eager_and_vmap_matches_loop():
    lo, hi = jnp.array([0.0, 0.0]), jnp.array([1.3, 0.7])
    eager = P.init_region(KEY, 128, lo, hi, 0.1)
    jitted = jax.jit(P.init_region, static_argnums=1)(KEY, 128, lo, hi, 0.1)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(jitted), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)
    keys = jax.random.split(KEY, 3)
    one = jax.jit(lambda k: P.init_region(k, 128, lo, hi, 0.1))
    batched = jax.jit(jax.vmap(one))(keys)
    for i, k in enumerate(keys):
        single = one(k)
        np.testing.assert_allclose(np.asarray(batched.poses[i]), np.asarray(single.poses), 1e-6)


def test_init_no_retrace_for_new_regions_and_boxes():
    traces = {"region": 0, "box": 0}

    @jax.jit
    def region(key, lo, hi, floor_z):
        traces["region"] += 1
        return P.init_region(key, 256, lo, hi, floor_z)

    @jax.jit
    def box(key, centre, half_widths, yaw_range):
        traces["box"] += 1
        return P.init_box(key, 256, centre, half_widths, yaw_range)

    small = region(KEY, jnp.array([0.0, 0.0]), jnp.array([0.5, 0.5]), 0.0)
    large = region(KEY, jnp.array([-2.0, 1.0]), jnp.array([3.0, 4.0]), 1.0)
    assert traces["region"] == 1
    assert int(small.active.sum()) == 3 * 3 * 4 * 3 and int(large.active.sum()) == 256
    box(KEY, jnp.zeros(4), jnp.full(3, 0.8), 0.5)
    box(KEY, jnp.ones(4), jnp.full(3, 0.4), 1.0)
    assert traces["box"] == 1


@pytest.mark.parametrize(("half", "expected"), [(0.8, 8**3 * 3), (0.4, 4**3 * 3)])
def test_init_box_paper_boxes(half, expected):
    centre = np.array([1.0, 2.0, 1.6, 3.0], np.float32)  # yaw near +pi: the range wraps
    state = jax.jit(P.init_box, static_argnums=1)(KEY, 4096, centre, np.full(3, half), 0.3)
    active = np.asarray(state.active)
    assert active.sum() == expected
    poses = np.asarray(state.poses)[active]
    assert np.all(np.abs(poses[:, :3] - centre[:3]) <= half + 1e-5)
    yaw_gap = wrap(poses[:, 3] - centre[3])
    assert np.all(np.abs(yaw_gap) <= 0.3 + 1e-5)
    assert np.any(poses[:, 3] < 0)  # some yaws wrapped past +pi
    # every 0.2 m cell of the box holds exactly 3 poses
    ijk = np.floor((poses[:, :3] - (centre[:3] - half)) / 0.2 + 1e-6).astype(int)
    ijk = np.minimum(ijk, int(round(2 * half / 0.2)) - 1)
    _, counts = np.unique(ijk, axis=0, return_counts=True)
    assert counts.size == expected // 3 and np.all(counts == 3)


def test_init_box_around_several_modes_shares_particles_between_valid_boxes():
    centres = np.array([[0.0, 0.0, 1.5, 0.0], [9.0, 9.0, 9.0, 9.0], [3.0, 0.0, 1.6, -2.0]])
    valid = np.array([True, False, True])
    init = jax.jit(P.init_box, static_argnums=1)
    for capacity, per_box in ((1000, 192), (200, 100)):
        state = init(KEY, capacity, centres, np.full(3, 0.4), 0.2, 0.2, 3, valid)
        poses = np.asarray(state.poses)[np.asarray(state.active)]
        assert len(poses) == min(capacity, 2 * 192)
        near = np.abs(poses[:, None, :3] - centres[None, :, :3]).max(axis=-1) <= 0.4 + 1e-5
        assert not near[:, 1].any() and np.all(near[:, 0] ^ near[:, 2])
        assert np.all(np.abs(near.sum(axis=0)[[0, 2]] - per_box) <= 1)
        box = np.where(near[:, 0], 0, 2)
        assert np.all(np.abs(wrap(poses[:, 3] - centres[box, 3])) <= 0.2 + 1e-5)
    none = init(KEY, 50, centres, np.full(3, 0.4), 0.2, 0.2, 3, np.zeros(3, bool))
    assert not bool(none.active.any()) and np.all(np.isfinite(np.asarray(none.poses)))


def test_init_rejects_bad_input():
    with pytest.raises(ValueError, match="capacity"):
        P.init_region(KEY, 0, np.zeros(2), np.ones(2), 0.0)
    with pytest.raises(ValueError, match="capacity"):
        P.init_region(KEY, 10.0, np.zeros(2), np.ones(2), 0.0)
    with pytest.raises(ValueError, match="lo"):
        P.init_region(KEY, 10, np.zeros(3), np.ones(2), 0.0)
    with pytest.raises(ValueError, match="half_widths"):
        P.init_box(KEY, 10, np.zeros(4), np.ones(2))
    with pytest.raises(ValueError, match="centre"):
        P.init_box(KEY, 10, np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="centre_valid"):
        P.init_box(KEY, 10, np.zeros((2, 4)), np.ones(3), centre_valid=np.ones(3, bool))
    with pytest.raises(ValueError, match="cell_size"):
        P.init_region(KEY, 10, np.zeros(2), np.ones(2), 0.0, cell_size=0.0)
    with pytest.raises(ValueError, match="poses_per_cell"):
        P.init_box(KEY, 10, np.zeros(4), np.ones(3), poses_per_cell=0)
    with pytest.raises(ValueError, match="heights"):
        P.init_region(KEY, 10, np.zeros(2), np.ones(2), 0.0, heights=())


def test_predict_without_noise_matches_numpy_composition():
    state = random_state(1)
    motion = np.array([0.3, -0.1, 0.05, 0.4], np.float32)
    out = jax.jit(P.predict)(KEY, state, motion, 0.0, 0.0)
    eager = P.predict(KEY, state, motion, 0.0, 0.0)
    np.testing.assert_allclose(np.asarray(out.poses), np.asarray(eager.poses), atol=1e-6)
    poses = np.asarray(state.poses, np.float64)
    c, s = np.cos(poses[:, 3]), np.sin(poses[:, 3])
    expected = np.stack(
        [
            poses[:, 0] + c * motion[0] - s * motion[1],
            poses[:, 1] + s * motion[0] + c * motion[1],
            poses[:, 2] + motion[2],
            wrap(poses[:, 3] + motion[3]),
        ],
        axis=1,
    )
    np.testing.assert_allclose(np.asarray(out.poses), expected, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(out.log_weights), np.asarray(state.log_weights))


def test_predict_noise_is_body_frame_gaussian_and_deterministic():
    n = 20000
    pose = jnp.array([1.0, 2.0, 1.5, 2.0])
    state = P.ParticleState(jnp.tile(pose, (n, 1)), jnp.full(n, -np.log(n)), jnp.ones(n, bool))
    motion = jnp.array([0.5, 0.2, 0.0, 0.1])
    predict = jax.jit(P.predict)
    out = predict(KEY, state, motion, 0.05, 0.02)
    again = predict(KEY, state, motion, 0.05, 0.02)
    np.testing.assert_array_equal(np.asarray(out.poses), np.asarray(again.poses))
    other = predict(jax.random.PRNGKey(1), state, motion, 0.05, 0.02)
    assert not np.allclose(np.asarray(out.poses), np.asarray(other.poses))
    # motion recovered in the particle's body frame: motion + N(0, diag(sigmas))
    body = np.asarray(jax.jit(jax.vmap(ego_motion, (None, 0)))(pose, out.poses)) - np.asarray(
        motion
    )
    np.testing.assert_allclose(body.mean(axis=0), 0.0, atol=4 * 0.05 / np.sqrt(n))
    np.testing.assert_allclose(body.std(axis=0), [0.05, 0.05, 0.05, 0.02], rtol=0.03)
    # world displacement: forward motion at yaw 2 rad goes along (cos 2, sin 2)
    mean_step = np.asarray(out.poses[:, :2]).mean(axis=0) - np.asarray(pose[:2])
    expected = np.asarray(compose_yaw(pose, motion))[:2] - np.asarray(pose[:2])
    np.testing.assert_allclose(mean_step, expected, atol=3e-3)


def test_update_weights_matches_numpy_and_recovers_from_underflow():
    state = random_state(2)
    rng = np.random.default_rng(3)
    loglik = rng.normal(0, 30, 64).astype(np.float32)
    out, degenerate = jax.jit(P.update_weights)(state, loglik)
    active = np.asarray(state.active)
    total = np.asarray(state.log_weights, np.float64) + loglik
    expected = (
        total - np.log(np.sum(np.exp(total[active] - total[active].max()))) - total[active].max()
    )
    np.testing.assert_allclose(np.asarray(out.log_weights)[active], expected[active], atol=1e-4)
    assert np.all(np.isneginf(np.asarray(out.log_weights)[~active])) and not bool(degenerate)

    for bad in (np.full(64, -np.inf), np.full(64, np.nan), np.full(64, np.inf)):
        out, degenerate = P.update_weights(state, bad.astype(np.float32))
        logw = np.asarray(out.log_weights)
        assert bool(degenerate) and not np.any(np.isnan(logw))
        np.testing.assert_allclose(logw[active], -np.log(active.sum()), rtol=1e-6)

    # huge but finite log-likelihoods are no underflow in log space: exact, not degenerate
    out, degenerate = P.update_weights(state, loglik - 1e4)
    np.testing.assert_allclose(np.asarray(out.log_weights)[active], expected[active], atol=2e-3)
    assert not bool(degenerate)


def test_estimates_match_numpy():
    state = random_state(4)
    active = np.asarray(state.active)
    logw = np.asarray(state.log_weights)
    poses = np.asarray(state.poses, np.float64)
    pose, index = jax.jit(P.mle)(state)
    assert int(index) == int(np.argmax(np.where(active, logw, -np.inf)))
    np.testing.assert_array_equal(np.asarray(pose), poses[int(index)].astype(np.float32))

    w = np.where(active, np.exp(logw.astype(np.float64)), 0.0)
    w /= w.sum()
    mean = jax.jit(P.weighted_mean)(state)
    np.testing.assert_allclose(np.asarray(mean[:3]), w @ poses[:, :3], atol=1e-5)
    yaw = np.arctan2(w @ np.sin(poses[:, 3]), w @ np.cos(poses[:, 3]))
    np.testing.assert_allclose(float(mean[3]), yaw, atol=1e-5)

    ess = float(jax.jit(P.effective_sample_size)(state))
    np.testing.assert_allclose(ess, 1.0 / np.sum(w**2), rtol=1e-5)


def test_weighted_mean_yaw_is_circular():
    poses = jnp.array([[0, 0, 0, np.pi - 0.1], [1, 0, 0, -np.pi + 0.1]], jnp.float32)
    state = P.ParticleState(poses, jnp.log(jnp.array([0.5, 0.5])), jnp.ones(2, bool))
    mean = np.asarray(P.weighted_mean(state))
    assert abs(abs(mean[3]) - np.pi) < 1e-5 and abs(mean[0] - 0.5) < 1e-6


def nms_reference(state, k, radius, yaw_radius):
    active = np.asarray(state.active)
    logw = np.asarray(state.log_weights, np.float64)
    w = np.where(active, np.exp(logw), 0.0)
    w /= w.sum()
    poses = np.asarray(state.poses, np.float64)
    unclaimed = active.copy()
    modes = []
    for _ in range(k):
        if not unclaimed.any():
            modes.append((np.zeros(4), 0.0, False))
            continue
        i = int(np.argmax(np.where(unclaimed, w, -1.0)))
        near = np.linalg.norm(poses[:, :3] - poses[i, :3], axis=1) <= radius
        near &= np.abs(wrap(poses[:, 3] - poses[i, 3])) <= yaw_radius
        claimed = unclaimed & near
        claimed[i] = True
        modes.append((poses[i], w[claimed].sum(), True))
        unclaimed &= ~claimed
    return modes


@pytest.mark.parametrize("seed", [5, 6])
def test_top_modes_match_greedy_nms_reference(seed):
    state = random_state(seed, n=64, active_count=10)
    poses, masses, valid = jax.jit(P.top_modes, static_argnums=1)(state, 12, 1.0, 1.0)
    reference = nms_reference(state, 12, 1.0, 1.0)
    for i, (pose, mass, ok) in enumerate(reference):
        assert bool(valid[i]) == ok
        np.testing.assert_allclose(np.asarray(poses[i]), pose, atol=1e-5)
        np.testing.assert_allclose(float(masses[i]), mass, atol=1e-5)
    assert not bool(valid[-1])  # 10 particles cannot make 12 modes
    np.testing.assert_allclose(float(masses.sum()), 1.0, atol=1e-5)


def test_inject_uniform_replaces_weakest_and_fills_inactive_first():
    state = random_state(7, n=64, active_count=40)
    first_active = int(np.argmax(np.asarray(state.active)))
    # an active particle with zero weight still comes after every inactive slot
    state = P.ParticleState(
        state.poses, state.log_weights.at[first_active].set(-jnp.inf), state.active
    )
    assert first_active > 0 and not bool(state.active[0])
    lo, hi = np.array([-1.0, 5.0]), np.array([0.0, 6.0])  # far from the old particles
    traces = []

    @jax.jit
    def inject(key, state, count):
        traces.append(1)
        return P.inject_uniform(key, state, count, lo, hi, 0.0)

    for count in (0, 10, 30):
        out = inject(KEY, state, count)
        old_active = np.asarray(state.active)
        logw = np.where(old_active, np.asarray(state.log_weights), -np.inf)
        order = np.lexsort((np.arange(64), logw, old_active))
        expected = np.zeros(64, bool)
        expected[order[:count]] = True
        replaced = np.asarray(out.poses[:, 1]) >= 5.0
        np.testing.assert_array_equal(replaced, expected)
        np.testing.assert_array_equal(np.asarray(out.active), old_active | expected)
        new_logw = np.asarray(out.log_weights)
        assert np.all(np.isneginf(new_logw[~np.asarray(out.active)]))
        np.testing.assert_allclose(np.exp(new_logw[np.asarray(out.active)]).sum(), 1.0, 1e-5)
        # the new particles get the mean weight of the old active ones
        if count:
            ratio = np.exp(new_logw[expected]) / np.exp(new_logw[old_active & ~expected]).sum()
            kept = np.exp(logw[old_active & ~expected]).sum()
            mean_before = np.exp(logw[old_active]).sum() / 40
            np.testing.assert_allclose(ratio, mean_before / kept, rtol=1e-4)
    assert len(traces) == 1
