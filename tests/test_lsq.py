"""jaxloc.lsq: robust SE(3) least squares vs closed form, outliers, jit/eager, finiteness."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from jaxloc.lsq import RobustLoss, gnc_tls_weights, robust_block_scale, solve_pose

TRUE_TANGENT = np.array([3.0, -2.0, 1.0, 0.1, -0.2, 1.2], np.float32)


def residuals(T, args):
    source, target = args
    return source @ T.rotation().as_matrix().T + T.translation() - target


def make_problem(outlier_fraction=0.0, noise=0.0, n=40, seed=0):
    rng = np.random.default_rng(seed)
    source = (rng.normal(size=(n, 3)) * 10).astype(np.float32)
    T = jaxlie.SE3.exp(jnp.asarray(TRUE_TANGENT))
    target = np.asarray(T @ jnp.asarray(source)) + noise * rng.normal(size=(n, 3))
    outliers = rng.random(n) < outlier_fraction
    target[outliers] += rng.normal(size=(outliers.sum(), 3)) * 20
    return source, target.astype(np.float32), T


def tangent_error(T_est, T_true):
    return float(np.max(np.abs(np.asarray((T_true.inverse() @ T_est).log()))))


IDENTITY = jaxlie.SE3(jnp.array([1.0, 0, 0, 0, 0, 0, 0], jnp.float32))

#: One jitted solver for the file: calls with the same loss kind, step budget and shapes share a
#: compilation (optimistix's Levenberg-Marquardt takes several seconds to compile on 2 cores).
SOLVE = jax.jit(solve_pose, static_argnums=0, static_argnames=("prior_fn", "max_steps", "method"))


@pytest.mark.parametrize("method", ["lm", "gn"])
def test_exact_recovery_noise_free(method):
    source, target, T = make_problem()
    sol = SOLVE(residuals, IDENTITY, (source, target), method=method)
    assert bool(sol.ok) and int(sol.status) == 0
    assert tangent_error(sol.pose, T) < 1e-4
    assert float(sol.cost) < 1e-6


def test_gnc_tls_exact_with_half_outliers_and_huber_beats_plain():
    source, target, T = make_problem(outlier_fraction=0.5, seed=1)
    tls = SOLVE(residuals, IDENTITY, (source, target), loss=RobustLoss("gnc_tls", 1.0))
    plain = SOLVE(residuals, IDENTITY, (source, target), loss=RobustLoss("none"))
    huber = SOLVE(residuals, IDENTITY, (source, target), loss=RobustLoss("huber", 1.0))
    assert bool(tls.ok)
    assert tangent_error(tls.pose, T) < 1e-3
    weights = np.asarray(tls.weights)
    inlier = np.linalg.norm(residuals(T, (source, target)), axis=1) < 1e-3
    assert np.all(weights[inlier] > 0.99) and np.all(weights[~inlier] < 0.01)
    assert tangent_error(huber.pose, T) < 0.5 * tangent_error(plain.pose, T)


def test_gnc_skips_the_rounds_after_its_weights_settle():
    # clean data: every weight is 1 from the first GNC round on, so rounds 2.. (each at least one
    # optimiser step if run) are skipped: 10 rounds take exactly the steps of 2, same answer
    source, target, T = make_problem(noise=0.01, seed=6)
    plain = SOLVE(residuals, IDENTITY, (source, target), loss=RobustLoss("none"))
    tls = SOLVE(residuals, IDENTITY, (source, target), loss=RobustLoss("gnc_tls", 1.0))
    two = SOLVE(residuals, IDENTITY, (source, target), loss=RobustLoss("gnc_tls", 1.0, 2))
    assert bool(tls.ok) and np.all(np.asarray(tls.weights) == 1.0)
    assert int(tls.steps) == int(two.steps) > int(plain.steps)
    np.testing.assert_array_equal(
        np.asarray(tls.pose.parameters()), np.asarray(two.pose.parameters())
    )
    np.testing.assert_allclose(
        np.asarray(tls.pose.parameters()), np.asarray(plain.pose.parameters()), atol=1e-5
    )


def test_jit_equals_eager_and_deterministic():
    source, target, _ = make_problem(outlier_fraction=0.2, noise=0.05, seed=2)
    loss = RobustLoss("cauchy", 1.0)
    # a short budget keeps the eager (op-by-op) side cheap; both sides take the same 8 steps
    eager = solve_pose(residuals, IDENTITY, (source, target), loss=loss, max_steps=8)
    a = SOLVE(residuals, IDENTITY, (source, target), loss=loss, max_steps=8)
    b = SOLVE(residuals, IDENTITY, (source, target), loss=loss, max_steps=8)
    assert int(a.steps) == int(eager.steps)
    np.testing.assert_allclose(eager.pose.parameters(), a.pose.parameters(), atol=1e-4)
    np.testing.assert_array_equal(a.pose.parameters(), b.pose.parameters())


def test_robust_scale_values_and_finite_gradients_at_zero():
    for kind in ("huber", "cauchy"):
        loss = RobustLoss(kind, 1.0)
        s2 = jnp.array([0.0, 0.25, 4.0, 100.0])
        factor = robust_block_scale(s2, loss)
        s = np.sqrt(np.asarray(s2))
        if kind == "huber":
            rho = np.where(s <= 1, 0.5 * s**2, s - 0.5)
        else:
            rho = 0.5 * np.log1p(s**2)
        np.testing.assert_allclose(np.asarray(factor**2 * s2), 2 * rho, rtol=1e-5, atol=1e-7)
        grad = jax.grad(
            lambda r, loss=loss: jnp.sum((r * robust_block_scale(jnp.sum(r * r), loss)) ** 2)
        )
        assert np.all(np.isfinite(np.asarray(grad(jnp.zeros(3)))))
    w = gnc_tls_weights(jnp.array([0.0, 0.5, 100.0]), jnp.asarray(1.0), 1.0)
    assert np.all(np.isfinite(np.asarray(w))) and float(w[0]) == 1.0 and float(w[2]) == 0.0


def test_gradient_of_solution_is_finite():
    source, target, _ = make_problem(noise=0.01, seed=3)

    def translation_x(t):
        return solve_pose(
            residuals, IDENTITY, (source, t), loss=RobustLoss("huber", 1.0)
        ).pose.translation()[0]

    grad = jax.jit(jax.grad(translation_x))(jnp.asarray(target))
    assert np.all(np.isfinite(np.asarray(grad)))
    assert np.abs(np.asarray(grad)).sum() > 0


def test_gradient_of_solution_matches_finite_differences():
    # Gradients of the solved pose (implicit differentiation through the solve) and of its cost
    # (the residuals' own JVP in the operands) vs central differences along a random direction.
    source, target, _ = make_problem(noise=0.01, seed=5)
    direction = np.random.default_rng(6).normal(size=target.shape).astype(np.float32)

    def solved(t):
        solution = solve_pose(residuals, IDENTITY, (source, t), rtol=1e-7, atol=1e-7)
        return solution.pose.translation()[0], solution.cost

    for output in range(2):
        f = jax.jit(lambda t, k=output: solved(t)[k])
        slope = float(jnp.vdot(jax.jit(jax.grad(f))(jnp.asarray(target)), direction))
        h = 1e-2
        finite = (float(f(target + h * direction)) - float(f(target - h * direction))) / (2 * h)
        assert abs(finite) > 0.05  # a direction both outputs move along
        assert abs(slope - finite) <= 2e-2 * abs(finite), (output, slope, finite)


def test_dense_jacobian_jvp_equals_the_plain_jvp():
    from jaxloc.lsq import _dense_jacobian

    def fn(delta, operands):
        weights, points = operands
        return jnp.ravel(
            jnp.sin(points @ delta[:3]) * weights + jnp.cos(delta[3:]).sum() * points[:, 0]
        )

    rng = np.random.default_rng(7)
    delta = jnp.asarray(rng.normal(size=6), jnp.float32)
    operands = (
        jnp.asarray(rng.random(5), jnp.float32),
        jnp.asarray(rng.normal(size=(5, 3)), jnp.float32),
    )
    t_delta = jnp.asarray(rng.normal(size=6), jnp.float32)
    t_operands = jax.tree.map(
        lambda x: jnp.asarray(rng.normal(size=x.shape), jnp.float32), operands
    )
    dense = _dense_jacobian(fn)
    zeros = jax.tree.map(jnp.zeros_like, operands)
    for tangents in [(t_delta, zeros), (jnp.zeros(6), t_operands), (t_delta, t_operands)]:
        want = jax.jvp(fn, (delta, operands), tangents)
        got = jax.jit(lambda p, t: jax.jvp(dense, p, t))((delta, operands), tangents)
        np.testing.assert_allclose(np.asarray(got[0]), np.asarray(want[0]), rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(np.asarray(got[1]), np.asarray(want[1]), rtol=1e-5, atol=1e-5)
    # Linearised in delta alone (as optimistix does): the tangent map is the dense Jacobian.
    _, linear = jax.linearize(lambda d: dense(d, operands), delta)
    np.testing.assert_allclose(
        np.asarray(linear(t_delta)),
        np.asarray(jax.jvp(lambda d: fn(d, operands), (delta,), (t_delta,))[1]),
        rtol=1e-5,
        atol=1e-5,
    )


def test_non_finite_input_gives_not_ok_and_no_nan():
    source, target, _ = make_problem(seed=4)
    target[3, 1] = np.nan
    sol = SOLVE(residuals, IDENTITY, (source, target))
    assert not bool(sol.ok) and int(sol.status) == 2
    assert np.all(np.isfinite(np.asarray(sol.pose.parameters())))
    bad_init = jaxlie.SE3(jnp.full(7, jnp.nan, jnp.float32))
    sol = SOLVE(residuals, bad_init, (source, np.nan_to_num(target)))
    assert not bool(sol.ok)
    np.testing.assert_array_equal(np.asarray(sol.pose.parameters()), [1, 0, 0, 0, 0, 0, 0])


def test_step_budget_out_returns_the_last_iterate_not_ok():
    # two LM steps from the identity cannot reach the truth: status 1, and the pose is where the
    # solver got to (cheaper than the start), so a caller iterating rounds keeps the progress
    source, target, T = make_problem(seed=5)
    sol = SOLVE(residuals, IDENTITY, (source, target), max_steps=2)
    start_cost = 0.5 * float(np.sum(np.asarray(residuals(IDENTITY, (source, target))) ** 2))
    assert not bool(sol.ok) and int(sol.status) == 1 and int(sol.steps) == 2
    assert np.isfinite(float(sol.cost)) and float(sol.cost) < start_cost
    assert tangent_error(sol.pose, T) < tangent_error(IDENTITY, T)
    full = SOLVE(residuals, sol.pose, (source, target))  # resuming from it converges
    assert bool(full.ok) and tangent_error(full.pose, T) < 1e-4


def test_prior_hook_pulls_unobservable_direction():
    # Two points leave the rotation about their common line free; a prior fixes it.
    source = np.array([[0.0, 0, 0], [1.0, 0, 0]], np.float32)
    target = source.copy()

    def prior(T, _):
        return 10.0 * (T.rotation().as_matrix()[:, 2] - jnp.array([0.0, 0.0, 1.0]))

    start = jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.from_x_radians(0.3), jnp.zeros(3))
    sol = SOLVE(residuals, start, (source, target), prior_fn=prior)
    assert bool(sol.ok)
    np.testing.assert_allclose(np.asarray(sol.pose.rotation().as_matrix()), np.eye(3), atol=1e-3)
