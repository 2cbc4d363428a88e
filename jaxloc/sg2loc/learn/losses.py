"""The window losses: eq. (2) on stored scores, the posterior over a fixed particle set, its
loss."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import Array

from jaxloc.sg2loc._scores import (
    ObservationConfig,
    log_likelihood,
)
from jaxloc.sg2loc.learn.params import LikelihoodParams, LossConfig
from jaxloc.sg2loc.learn.windows import Windows


def window_log_weights(params: LikelihoodParams, base: ObservationConfig, window: Windows) -> Array:
    """(N,) float32 normalised log-weights of one window's particles after all K frames.

    The log-softmax of the summed eq. (2) log-likelihoods over the valid particles, ``-inf`` for
    invalid ones (:func:`prefix_log_weights`' last row).
    """
    return _normalised(config_log_likelihood(params.to_config(base), window), window.valid)


def prefix_log_weights(params: LikelihoodParams, base: ObservationConfig, window: Windows) -> Array:
    """(K, N) float32 normalised log-weights after frames 1..k, for every k of the window.

    Row k is the log-softmax of the eq. (2) log-likelihoods summed over the first k + 1 frames,
    over the valid particles (``-inf`` for invalid ones). When no valid particle has a finite
    log-likelihood the weights are uniform over the valid particles (as
    :func:`jaxloc.sg2loc._particles.update_weights` does), and over all N when none is valid (such a
    window carries no information; its loss is constant). Values and gradients stay finite.
    """
    config = params.to_config(base)
    per_frame = log_likelihood(config, window.semantic, window.depth, window.color)
    return jax.vmap(lambda row: _normalised(row, window.valid))(jnp.cumsum(per_frame, axis=0))


def _normalised(log_likelihood: Array, valid: Array) -> Array:
    """(N,) log-softmax of ``log_likelihood`` (N,) over ``valid`` (docstring above)."""
    usable = valid & jnp.isfinite(log_likelihood)
    any_usable = jnp.any(usable)
    safe = jnp.where(usable, log_likelihood, 0.0)
    top = jax.lax.stop_gradient(jnp.max(jnp.where(usable, safe, -jnp.inf)))
    top = jnp.where(any_usable, top, 0.0)
    shifted = jnp.where(any_usable, jnp.where(usable, safe - top, -jnp.inf), 0.0)
    shifted = jnp.where(valid | ~jnp.any(valid), shifted, -jnp.inf)
    return shifted - jax.nn.logsumexp(shifted)


def config_log_likelihood(config: ObservationConfig, window: Windows) -> Array:
    """(N,) eq. (2) log-likelihood of each particle summed over the window's K frames."""
    return jnp.sum(log_likelihood(config, window.semantic, window.depth, window.color), axis=0)


def window_loss(
    params: LikelihoodParams, base: ObservationConfig, window: Windows, loss: LossConfig
) -> Array:
    """Float32 loss of one window (see :mod:`jaxloc.sg2loc.learn` and :class:`LossConfig`)."""
    if loss.frames == "last":
        log_weights = window_log_weights(params, base, window)
        return _posterior_loss(
            log_weights, window.position_error[-1], window.yaw_error[-1], window.valid, loss
        )
    per_prefix = jax.vmap(lambda lw, pos, yaw: _posterior_loss(lw, pos, yaw, window.valid, loss))(
        prefix_log_weights(params, base, window), window.position_error, window.yaw_error
    )
    return jnp.mean(per_prefix)


def _posterior_loss(
    log_weights: Array, position_error: Array, yaw_error: Array, valid: Array, loss: LossConfig
) -> Array:
    """The loss of one weighted particle set (N,) against the truth at one frame."""
    position = position_error / loss.position_scale
    yaw = yaw_error / loss.yaw_scale
    if loss.kind == "nll":
        log_kernel = -0.5 * (position**2 + yaw**2)
        terms = jnp.where(jnp.isfinite(log_weights), log_weights + log_kernel, -jnp.inf)
        return -jax.nn.logsumexp(terms)
    weights = jnp.exp(log_weights)
    return jnp.sum(jnp.where(valid, weights * (position + yaw), 0.0))


def batch_loss(
    params: LikelihoodParams, base: ObservationConfig, windows: Windows, loss: LossConfig
) -> Array:
    """Mean :func:`window_loss` over a batch of windows (leading B axis)."""
    return jnp.mean(jax.vmap(lambda w: window_loss(params, base, w, loss))(windows))


def expected_position_error(
    params: LikelihoodParams, base: ObservationConfig, windows: Windows
) -> Array:
    """Mean over windows of the weighted mean position error (metres) of the particles at the
    window's last frame."""

    def one(window):
        weights = jnp.exp(window_log_weights(params, base, window))
        return jnp.sum(jnp.where(window.valid, weights * window.position_error[-1], 0.0))

    return jnp.mean(jax.vmap(one)(windows))
