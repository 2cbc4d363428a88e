"""Robust SE(3) pose least squares, shared by the LiDAR and the camera pose refinements.

:func:`solve_pose` minimises ``sum_i rho(|r_i(T)|^2) + |p(T)|^2`` over a pose ``T`` by optimising a
perturbation ``delta = (t, omega)`` (6,) with ``T = T_init @ (SO3.exp(omega), t)`` using
``optimistix.least_squares`` (Levenberg-Marquardt or Gauss-Newton, ``throw=False``).

* ``r_i`` are residual blocks returned by the caller's ``residual_fn(T, args)``: shape (M, D) (a
  D-dimensional residual per correspondence, the robust loss acts on the block norm) or (M,) (scalar
  residuals). ``p`` is an optional prior residual vector ``prior_fn(T, args) -> (P,)`` that is never
  robustified (e.g. the road-surface-normal roll/pitch prior of TripletLoc).
* Robust losses keep optimistix on a least-squares problem: Huber and Cauchy rescale each block by
  ``sqrt(2 rho(s) ) / s`` (``s`` the block norm, ``rho`` the loss of the norm), written so the value
  and the gradient stay finite at ``s = 0``; GNC-TLS (graduated non-convexity with a truncated
  least-squares loss, Yang et al. 2020, as TripletLoc's GTSAM solver) runs a fixed number of
  weighted solves while its control parameter ``mu`` grows geometrically from the convex start to
  ``gnc_mu_final`` (a fixed count, so it jits; the weights of the last round are returned). Once
  the weights are all 0 or 1 and unchanged, every later round would repeat the same solve, so the
  remaining rounds are skipped (``lax.cond``; a clean inlier set settles after one round).

Failures are values: ``PoseSolution.ok`` is False when the residuals or the result are non-finite
or the solve did not converge. A solve that ran out of steps returns its last finite iterate (as
``scipy.optimize.least_squares`` does), so a caller that iterates (re-association rounds) keeps the
progress; non-finite input or output returns ``T_init`` (the identity when ``T_init`` is itself
non-finite). Nothing raises under jit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
from jax import Array
from jax.custom_derivatives import SymbolicZero

from jaxloc._traced import concrete, float32_leaf

#: The robust losses of :class:`RobustLoss` (``RobustLoss.kind``).
LossKind = Literal["none", "huber", "cauchy", "gnc_tls"]
#: A residual function ``fn(T, args)`` of :func:`solve_pose` (``residual_fn``, ``prior_fn``).
ResidualFn = Callable[[jaxlie.SE3, Any], Array]


class RobustLoss(eqx.Module):
    """A robust loss on residual-block norms (metres, or whatever unit the residuals carry).

    Attributes:
        kind: "none" (plain least squares), "huber", "cauchy" or "gnc_tls" (static).
        scale: the inlier threshold ``c`` (Huber/Cauchy scale, TLS truncation), residual units
            (float32, traced).
        gnc_rounds: GNC-TLS outer rounds (static Python int, >= 2).
        gnc_mu_final: the GNC control parameter reached in the last round (large = pure TLS;
            float32, traced).
    """

    kind: LossKind = eqx.field(static=True, default="none")
    scale: Array = eqx.field(default=1.0, converter=float32_leaf)
    gnc_rounds: int = eqx.field(static=True, default=10)
    gnc_mu_final: Array = eqx.field(default=1e4, converter=float32_leaf)

    def __check_init__(self) -> None:
        if self.kind not in ("none", "huber", "cauchy", "gnc_tls"):
            raise ValueError(f"unknown loss kind {self.kind!r}")
        if concrete(self.scale, self.gnc_mu_final) and not (
            self.scale > 0 and self.gnc_mu_final > 0
        ):
            raise ValueError(
                f"loss scale and gnc_mu_final must be > 0, got {self.scale}, {self.gnc_mu_final}"
            )
        if self.gnc_rounds < 2:
            raise ValueError(f"gnc_rounds must be >= 2, got {self.gnc_rounds}")


class PoseSolution(eqx.Module):
    """Result of :func:`solve_pose` (a pytree; batch axes come from vmap).

    Attributes:
        pose: the estimated pose (jaxlie.SE3): the last finite iterate (also when the step
            budget ran out, status 1), ``T_init`` when the input or the result is non-finite.
        ok: bool scalar, True when the solve succeeded and everything is finite.
        status: int32 scalar: 0 converged (optimistix reported success, or a Gauss-Newton step
            from the result would gain less than 1e-5 of the cost: float32 stalls), 1 not
            converged (step budget, non-finite iterate), 2 non-finite or empty input.
        steps: int32 scalar, optimiser steps taken (summed over GNC rounds).
        cost: float scalar, ``0.5 * sum(robustified residuals^2)`` including the prior at
            ``pose`` (``inf`` when the input or the result is non-finite).
        weights: (M,) float, per-block weights of the last GNC round (1 for other losses, 0 where
            a block was non-finite).
    """

    pose: jaxlie.SE3
    ok: Array
    status: Array
    steps: Array
    cost: Array
    weights: Array


def _blocks(residuals: Array) -> Array:
    """Residuals as blocks (M, D): a (M,) vector becomes (M, 1)."""
    return residuals[:, None] if residuals.ndim == 1 else residuals


def robust_block_scale(squared_norm: Array, loss: RobustLoss) -> Array:
    """Factor ``sqrt(2 rho(s)) / s`` for block norms ``s = sqrt(squared_norm)``; finite grads at 0.

    Multiplying a residual block by this factor makes its squared norm ``2 rho(s)``, so a
    least-squares solver minimises ``sum rho``. Huber: ``rho = s^2/2`` for ``s <= c`` else
    ``c s - c^2/2``; Cauchy: ``rho = c^2/2 log(1 + s^2/c^2)``. Other kinds give 1.
    """
    c = jnp.asarray(loss.scale, squared_norm.dtype)
    if loss.kind == "huber":
        outside = squared_norm > c * c
        s = jnp.sqrt(jnp.where(outside, squared_norm, c * c))
        return jnp.where(outside, jnp.sqrt(jnp.maximum(2.0 * c * s - c * c, 0.0)) / s, 1.0)
    if loss.kind == "cauchy":
        small = squared_norm < 1e-8 * c * c
        safe = jnp.where(small, c * c, squared_norm)
        ratio = c * c * jnp.log1p(safe / (c * c)) / safe
        return jnp.where(small, 1.0 - squared_norm / (4.0 * c * c), jnp.sqrt(ratio))
    return jnp.ones_like(squared_norm)


def gnc_tls_weights(squared_norm: Array, mu: Array, scale: float | Array) -> Array:
    """GNC-TLS weights (Yang et al. 2020) for squared block norms at control parameter ``mu``."""
    c2 = jnp.asarray(scale, squared_norm.dtype) ** 2
    lower = mu / (mu + 1.0) * c2
    upper = (mu + 1.0) / mu * c2
    safe = jnp.where(squared_norm > 0, squared_norm, c2)
    middle = jnp.sqrt(c2 * mu * (mu + 1.0) / safe) - mu
    return jnp.where(squared_norm <= lower, 1.0, jnp.where(squared_norm >= upper, 0.0, middle))


def _make_solver(method: str, rtol: float, atol: float):
    import optimistix as optx  # here, not at the top: a process whose programs come from the
    # compilation cache never traces a solve and skips optimistix's import (~0.15 s)

    if method == "lm":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol, norm=optx.rms_norm)
    if method == "gn":
        return optx.GaussNewton(rtol=rtol, atol=atol, norm=optx.rms_norm)
    raise ValueError(f"method must be 'lm' or 'gn', got {method!r}")


def _stationary(residual: Array, jacobian: Array, rtol: float = 1e-5) -> Array:
    """True when a Gauss-Newton step from where ``residual`` (R,) and its ``jacobian`` (R, 6)
    were taken would gain less than ``rtol * (cost + 1)``.

    optimistix's Cauchy test compares successive accepted iterates; in float32 the trust region
    can stall at the optimum rejecting steps whose gain is below rounding, so a converged solve
    hits ``max_steps``. This decrement test accepts it (and rejects real non-convergence). The
    caller passes the solver's own residual and Jacobian at its last accepted iterate (the
    solution), so the test adds no second linearisation to the program.
    """
    cost = 0.5 * jnp.sum(residual * residual)
    gradient = jnp.matmul(jacobian.T, residual, precision="highest")
    hessian = jnp.matmul(jacobian.T, jacobian, precision="highest")
    damping = 1e-9 * (jnp.trace(hessian) + 1.0)
    step = jnp.linalg.solve(hessian + damping * jnp.eye(6, dtype=hessian.dtype), gradient)
    decrement = 0.5 * jnp.dot(gradient, step, precision="highest")
    return jnp.isfinite(decrement) & (decrement <= rtol * (cost + 1.0))


def _is_symbolic_zero(tangent: Any) -> bool:
    return isinstance(tangent, SymbolicZero)


def _dense_jacobian(fn: Callable[..., Array]) -> Callable[..., Array]:
    """``fn(delta, operands)`` with a JVP that forms the Jacobian in ``delta`` once (``jacfwd``).

    Linearised in ``delta`` alone (as optimistix does at every step), the tangent map becomes one
    product with a dense (R, 6) matrix, so the solver's uses of it (the damped step, the gradient,
    the predicted reduction, the stationarity test) are small products instead of copies of the
    residuals' derivative graph; a smaller program that computes the same values. Tangents of
    ``operands`` (an array pytree: the caller's arguments, for implicit differentiation of the
    solution) go through ``fn``'s own JVP.
    """
    wrapped = jax.custom_jvp(fn)

    def jvp(primals, tangents):
        delta, operands = primals
        delta_tangent, operand_tangents = tangents
        jacobian, value = jax.jacfwd(lambda d: (fn(d, operands),) * 2, has_aux=True)(delta)
        out = (
            jnp.zeros_like(value)
            if _is_symbolic_zero(delta_tangent)
            else jnp.matmul(jacobian, delta_tangent, precision="highest")
        )
        leaves = jax.tree.leaves(operand_tangents, is_leaf=_is_symbolic_zero)
        if not all(_is_symbolic_zero(t) for t in leaves):
            dense = jax.tree.map(
                lambda t: np.zeros(t.aval.shape, t.aval.dtype) if _is_symbolic_zero(t) else t,
                operand_tangents,
                is_leaf=_is_symbolic_zero,
            )
            out = out + jax.jvp(lambda ops: fn(delta, ops), (operands,), (dense,))[1]
        return value, out

    wrapped.defjvp(jvp, symbolic_zeros=True)
    return wrapped


def _retraction(delta: Array) -> jaxlie.SE3:
    """The perturbation ``(SO3.exp(omega), t)`` of ``delta = (t, omega)`` (6,).

    An SO(3) x R^3 retraction: its first-order term is ``SE3.exp``'s, and without ``SE3.exp``'s V
    matrix (and its small-angle branches) the M2Loc query program is 15 % smaller (7645 -> 6464
    StableHLO operations after inlining).
    """
    return jaxlie.SE3.from_rotation_and_translation(jaxlie.SO3.exp(delta[3:]), delta[:3])


def _finite_pose(T: jaxlie.SE3) -> Array:
    return jnp.all(jnp.isfinite(T.parameters()))


# Full float32 products in jaxlie's and the optimiser's linear algebra too: XLA runs float32
# products of DEFAULT precision as TF32 on NVIDIA GPUs (tests/test_precision.py).
@jax.default_matmul_precision("highest")
def solve_pose(
    residual_fn: ResidualFn,
    T_init: jaxlie.SE3,
    args: Any = None,
    *,
    loss: RobustLoss | None = None,
    prior_fn: ResidualFn | None = None,
    max_steps: int = 50,
    rtol: float = 1e-5,
    atol: float = 1e-5,
    method: Literal["lm", "gn"] = "lm",
) -> PoseSolution:
    """Robust least-squares pose ``T = T_init @ (SO3.exp(omega), t)``, ``delta = (t, omega)``;
    pure, jit/vmap-able.

    Args:
        residual_fn: ``residual_fn(T, args) -> (M, D) or (M,)`` residual blocks; blocks that should
            not count may be zeroed by the caller (e.g. padded correspondences).
        T_init: the initial pose (jaxlie.SE3, float32 or float64).
        args: pytree passed through to ``residual_fn`` and ``prior_fn``.
        loss: the robust loss (default: plain least squares).
        prior_fn: optional ``prior_fn(T, args) -> (P,)`` prior residuals, never robustified.
        max_steps: optimiser step budget per solve (static).
        rtol: optimistix relative convergence tolerance (static).
        atol: optimistix absolute convergence tolerance (static).
        method: "lm" (Levenberg-Marquardt) or "gn" (Gauss-Newton).

    Returns:
        A :class:`PoseSolution`; on failure ``ok`` is False and ``pose`` is the last finite
        iterate (``T_init`` if there is none).
    """
    loss = RobustLoss() if loss is None else loss
    solver = _make_solver(method, rtol, atol)
    dtype = T_init.parameters().dtype
    delta0 = jnp.zeros(6, dtype)

    def pose_of(delta: Array) -> jaxlie.SE3:
        return T_init @ _retraction(delta)

    def raw_blocks(T: jaxlie.SE3, call_args: Any = args) -> Array:
        return _blocks(residual_fn(T, call_args))

    def prior_vector(T: jaxlie.SE3, call_args: Any = args) -> Array:
        if prior_fn is None:
            return jnp.zeros((0,), dtype)
        return jnp.ravel(prior_fn(T, call_args))

    # Everything traced that the residuals read is an explicit operand of the custom JVP (a
    # custom_jvp function must not close over values that are differentiated).
    dynamic, static = eqx.partition((T_init, args), eqx.is_array)

    @_dense_jacobian
    def weighted_residuals(delta: Array, operands) -> Array:
        block_weights, dynamic_part = operands
        start, call_args = eqx.combine(dynamic_part, static)
        T = start @ _retraction(delta)  # once: the residuals and the prior share it
        blocks = raw_blocks(T, call_args)
        blocks = jnp.where(jnp.isfinite(blocks), blocks, 0.0)
        squared = jnp.sum(blocks * blocks, axis=-1)
        factor = robust_block_scale(squared, loss) * jnp.sqrt(block_weights)
        return jnp.concatenate([jnp.ravel(blocks * factor[:, None]), prior_vector(T, call_args)])

    def robust_residuals(delta: Array, block_weights: Array) -> Array:
        return weighted_residuals(delta, (block_weights, dynamic))

    def solve(delta_start: Array, block_weights: Array):
        import optimistix as optx

        sol = optx.least_squares(
            lambda d, w: robust_residuals(d, w),
            solver,
            delta_start,
            args=block_weights,
            max_steps=max_steps,
            throw=False,
        )
        # The Gauss-Newton family keeps the residual and Jacobian of its last accepted iterate,
        # which is the solution it returns (every solve takes a first step, always accepted).
        at_solution = sol.state.f_info
        converged = (sol.result == optx.RESULTS.successful) | _stationary(
            at_solution.residual, at_solution.jac.as_matrix()
        )
        return sol.value, converged, sol.stats["num_steps"]

    initial_blocks = raw_blocks(T_init)
    block_finite = jnp.all(jnp.isfinite(initial_blocks), axis=-1)
    weights = block_finite.astype(dtype)
    inputs_ok = (
        jnp.all(block_finite)
        & jnp.all(jnp.isfinite(prior_vector(T_init)))
        & _finite_pose(T_init)
        & (initial_blocks.shape[0] > 0)
    )

    if loss.kind != "gnc_tls":
        delta, success, steps = solve(delta0, weights)
    else:
        # Round 0 is the plain solve on the finite blocks; rounds 1.. are GNC-TLS with mu growing
        # geometrically from the convex start (set by round 0's residuals) to gnc_mu_final. One
        # scan with one solve call site: the optimiser is traced (and compiled) once, not twice.
        c2 = jnp.asarray(loss.scale, dtype) ** 2
        mu_final = jnp.asarray(loss.gnc_mu_final, dtype)

        def convex_start(squared: Array) -> tuple[Array, Array]:
            max_sq = jnp.max(jnp.where(block_finite, squared, 0.0))
            mu0 = jnp.where(2.0 * max_sq > c2, c2 / jnp.maximum(2.0 * max_sq - c2, 1e-12), mu_final)
            mu0 = jnp.clip(mu0, 1e-9, mu_final)
            return mu0, (mu_final / mu0) ** (1.0 / (loss.gnc_rounds - 1))

        def gnc_round(carry, index):
            delta, mu, growth, steps, success, weights, settled = carry

            def run():
                sq = jnp.sum(
                    jnp.where(block_finite[:, None], raw_blocks(pose_of(delta)), 0.0) ** 2, axis=-1
                )
                mu0, growth0 = convex_start(sq)
                first_gnc = index == 1
                round_mu = jnp.where(first_gnc, mu0, mu)
                round_growth = jnp.where(first_gnc, growth0, growth)
                new_weights = jnp.where(
                    index == 0, weights, gnc_tls_weights(sq, round_mu, loss.scale) * block_finite
                )
                new_delta, new_success, new_steps = solve(delta, new_weights)
                finite = jnp.all(jnp.isfinite(new_delta))
                # Binary weights that did not change give the same weighted problem, and a
                # larger mu only narrows the band of fractional weights, so every later round
                # would return this solution again: skip them.
                binary = jnp.all((new_weights == 0.0) | (new_weights == 1.0))
                now_settled = (
                    (index > 0) & binary & jnp.all(new_weights == weights) & new_success & finite
                )
                keep = finite | (index == 0)  # round 0 reports its result as it is
                return (
                    jnp.where(keep, new_delta, delta),
                    round_mu * round_growth,
                    round_growth,
                    steps + new_steps,
                    new_success & keep,
                    new_weights,
                    now_settled,
                )

            skip = lambda: (delta, mu, growth, steps, success, weights, settled)  # noqa: E731
            return jax.lax.cond(settled, skip, run), None

        start = (
            delta0,
            jnp.ones((), dtype),
            jnp.ones((), dtype),
            jnp.int32(0),
            jnp.bool_(False),
            weights,
            jnp.bool_(False),
        )
        (delta, _, _, steps, success, weights, _), _ = jax.lax.scan(
            gnc_round, start, jnp.arange(loss.gnc_rounds + 1)
        )
    status_code = jnp.where(success, 0, 1).astype(jnp.int32)

    final = robust_residuals(delta, weights)
    cost = 0.5 * jnp.sum(final * final)
    T = pose_of(delta)
    finite = inputs_ok & jnp.isfinite(cost) & _finite_pose(T)
    ok = finite & success
    identity = jnp.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype)
    safe_init = jnp.where(_finite_pose(T_init), T_init.parameters(), identity)
    pose = jaxlie.SE3(jnp.where(finite, T.parameters(), safe_init))
    return PoseSolution(
        pose=pose,
        ok=ok,
        status=jnp.where(inputs_ok, status_code, 2).astype(jnp.int32),
        steps=jnp.asarray(steps, jnp.int32),
        cost=jnp.where(finite, cost, jnp.inf),
        weights=jnp.where(finite, weights, block_finite.astype(dtype)),
    )
