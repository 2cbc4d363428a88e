"""The training loop: Adam on the window loss, with a held-out learning curve."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax import Array

from jaxloc.sg2loc._scores import (
    ObservationConfig,
)
from jaxloc.sg2loc.learn.losses import batch_loss, expected_position_error
from jaxloc.sg2loc.learn.params import LikelihoodParams, LossConfig
from jaxloc.sg2loc.learn.windows import Windows


class TrainState(NamedTuple):
    """Parameters and optimizer state of the training loop."""

    params: LikelihoodParams
    opt_state: optax.OptState


@functools.lru_cache(maxsize=16)
def adam(learning_rate: float) -> optax.GradientTransformation:
    """``optax.adam(learning_rate)``, one object per rate (so compiled steps are reused)."""
    return optax.adam(learning_rate)


@eqx.filter_jit
def _train_step(
    optimizer: optax.GradientTransformation,
    base: ObservationConfig,
    loss: LossConfig,
    state: TrainState,
    key: Array,
    windows: Windows,
    batch_size: int,
) -> tuple[TrainState, Array]:
    count = windows.valid.shape[0]
    picks = jax.random.randint(key, (batch_size,), 0, count)
    batch = jax.tree.map(lambda a: a[picks], windows)
    value, grads = jax.value_and_grad(batch_loss)(state.params, base, batch, loss)
    updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
    return TrainState(optax.apply_updates(state.params, updates), opt_state), value


def make_train_step(
    optimizer: optax.GradientTransformation, base: ObservationConfig, loss: LossConfig
) -> Callable[[TrainState, Array, Windows, int], tuple[TrainState, Array]]:
    """A jitted ``step(state, key, windows, batch_size) -> (state, loss)``.

    Each step draws ``batch_size`` (static int) windows of ``windows`` uniformly with replacement
    using ``key`` and takes one optimizer step on their mean loss. It compiles once per
    (optimizer object, score variants, loss kind, number of windows, batch size); new window
    values, parameters or keys never recompile.
    """
    return functools.partial(_train_step, optimizer, base, loss)


@eqx.filter_jit
def _evaluate(params, base, loss, train_windows, heldout_windows):
    return (
        batch_loss(params, base, train_windows, loss),
        batch_loss(params, base, heldout_windows, loss),
        expected_position_error(params, base, heldout_windows),
        jnp.stack(params.values()),
    )


class History(NamedTuple):
    """The learning curve (host numpy arrays, one entry per evaluation).

    Attributes:
        step: (E,) int step index of each evaluation (0 = before training).
        train_loss: (E,) mean loss over all training windows.
        heldout_loss: (E,) mean loss over the held-out windows.
        heldout_position_error: (E,) held-out mean weighted position error (metres).
        sigma, lambda_depth, lambda_color: (E,) the parameters.
    """

    step: np.ndarray
    train_loss: np.ndarray
    heldout_loss: np.ndarray
    heldout_position_error: np.ndarray
    sigma: np.ndarray
    lambda_depth: np.ndarray
    lambda_color: np.ndarray


def train(
    key: Array,
    params: LikelihoodParams,
    base: ObservationConfig,
    train_windows: Windows,
    heldout_windows: Windows,
    num_steps: int,
    learning_rate: float = 0.05,
    batch_size: int = 16,
    eval_every: int = 10,
    loss: LossConfig | None = None,
) -> tuple[LikelihoodParams, History]:
    """Adam on the window loss; returns the final parameters and the learning curve.

    Deterministic for a given ``key`` and inputs.
    """
    loss = LossConfig() if loss is None else loss
    if num_steps < 0 or batch_size < 1 or eval_every < 1:
        raise ValueError(
            f"need num_steps >= 0, batch_size >= 1, eval_every >= 1; got {num_steps}, "
            f"{batch_size}, {eval_every}"
        )
    optimizer = adam(float(learning_rate))
    step = make_train_step(optimizer, base, loss)
    state = TrainState(params, optimizer.init(params))
    rows = []
    keys = jax.random.split(key, max(num_steps, 1))
    for i in range(num_steps + 1):
        if i % eval_every == 0 or i == num_steps:
            metrics = _evaluate(state.params, base, loss, train_windows, heldout_windows)
            rows.append((i, *(np.asarray(v) for v in metrics)))
        if i < num_steps:
            state, _ = step(state, keys[i], train_windows, batch_size)
    steps, train_l, held_l, held_e, values = zip(*rows, strict=True)
    values = np.stack(values)
    history = History(
        np.asarray(steps),
        np.asarray(train_l),
        np.asarray(held_l),
        np.asarray(held_e),
        values[:, 0],
        values[:, 1],
        values[:, 2],
    )
    return state.params, history
