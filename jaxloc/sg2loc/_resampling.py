"""Resampling on padded particle buffers and KLD-sampling (Fox 2001) for an adaptive count.

Resampling draws ``n`` (traced, 1 <= n <= N) particles from the weights of the active slots into
the first ``n`` slots of the buffer; the rest become inactive. Inactive slots have zero weight and
are never drawn. Weights that carry no usable mass (all ``-inf``, NaN, ``+inf``) count as uniform
over the active particles, and a ``degenerate`` flag reports it.

KLD-sampling, exactly as implemented here (:func:`kld_resample`):

1. draw ``N`` (the capacity) indices from the weights with the configured resampler;
2. put them in a random order (sorted by random 32-bit keys), so each prefix is a random
   sub-sample;
3. bin every drawn pose on the grid ``floor((x, y, z, yaw) / bin_sizes)`` (yaw wrapped to
   [-pi, pi) first) and count ``k_n``, the distinct bins among the first ``n`` draws (lexsort of
   the bins with the draw order as the last key, first-occurrence flags, cumulative sum);
4. take the smallest ``n`` with ``n >= kld_bound(k_n)`` (the bound clamped to
   ``[min_particles, min(max_particles, N)]``, so ``n = min(max_particles, N)`` always qualifies);
5. draw exactly ``n`` particles with the resampler into the buffer (a fresh draw, independent of
   the counting draw); active = slot < n, log-weights uniform over the active slots.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.geometry import wrap_angle
from jaxloc.sg2loc._convert import as_float32, as_int32
from jaxloc.sg2loc._particles import ParticleState, normalized_weights, uniform_log_weights

#: The resampling schemes (the ``method`` argument of the resampling functions).
RESAMPLING_METHODS = ("stratified", "systematic")

# The largest float32 below 1: uniforms are clipped to it so a draw never runs off the end.
_BELOW_ONE = float(np.nextafter(np.float32(1.0), np.float32(0.0)))


def _check_method(method: str) -> None:
    if method not in RESAMPLING_METHODS:
        raise ValueError(f"method must be one of {RESAMPLING_METHODS}, got {method!r}")


def _unit(bits: Array) -> Array:
    """Uniforms in [0, 1) (float32, exact multiples of 2**-24) from uint32 random bits."""
    return (bits >> 8).astype(jnp.float32) * jnp.float32(2.0**-24)


def _uniforms(offsets: Array, n: Array, method: str) -> Array:
    """(size,) sorted points in [0, 1): one per stratum ``[i/n, (i+1)/n)`` for i < n, from
    ``offsets`` (size,) uniforms in [0, 1) (stratified: each its own; systematic: the first)."""
    slot = jnp.arange(offsets.shape[0], dtype=jnp.float32)
    if method == "systematic":
        offsets = jnp.full_like(offsets, offsets[0])
    return jnp.minimum((slot + offsets) / n.astype(jnp.float32), _BELOW_ONE)


def draw_indices(key: Array, weights: Array, n: Array | int, method: str = "stratified") -> Array:
    """Stratified or systematic resampling indices into a weight vector.

    Slot ``i < n`` gets the particle whose cumulative-weight interval holds
    ``u_i = (i + U_i) / n`` (stratified: independent ``U_i ~ U[0, 1)``; systematic: one shared
    ``U``). Particles with zero weight are never drawn. Slots ``i >= n`` get index 0 (unused).

    Args:
        key: PRNG key.
        weights: (N,) float32 non-negative weights (any positive total; not all zero).
        n: number of draws, traced int, 1 <= n <= N.
        method: ``"stratified"`` or ``"systematic"`` (static).

    Returns:
        (N,) int32 indices.
    """
    _check_method(method)
    return _draw(weights, n, _unit(jax.random.bits(key, weights.shape, jnp.uint32)), method)


def _draw(weights: Array, n: Array | int, offsets: Array, method: str) -> Array:
    """:func:`draw_indices` with its uniforms ``offsets`` (N,) given."""
    size = weights.shape[0]
    n = jnp.clip(jnp.asarray(n, jnp.int32), 1, size)
    cumulative = jnp.cumsum(weights)
    total = cumulative[-1]
    cumulative = cumulative / jnp.where(total > 0.0, total, 1.0)
    u = _uniforms(offsets, n, method)
    indices = jnp.searchsorted(cumulative, u, side="right").astype(jnp.int32)
    indices = jnp.minimum(indices, size - 1)
    return jnp.where(jnp.arange(size) < n, indices, 0)


def resample(
    key: Array, state: ParticleState, n: Array | int, method: str = "stratified"
) -> tuple[ParticleState, Array]:
    """Draw ``n`` particles (traced, clamped to [1, N]) from the weights into the buffer.

    Returns:
        ``(state, degenerate)``: the new state has slots ``< n`` active with uniform
        log-weights ``-log n`` and inactive slots zeroed with ``-inf``; ``degenerate`` (bool
        scalar) is True when the weights were unusable and uniform ones over the active particles
        were used. With no active particle the state is returned unchanged (and ``degenerate``
        is True).
    """
    _check_method(method)
    offsets = _unit(jax.random.bits(key, (state.capacity,), jnp.uint32))
    return _resample(state, n, offsets, method)


def _resample(
    state: ParticleState, n: Array | int, offsets: Array, method: str
) -> tuple[ParticleState, Array]:
    """:func:`resample` with its uniforms ``offsets`` (N,) given."""
    weights, degenerate = normalized_weights(state.log_weights, state.active)
    size = state.capacity
    n = jnp.clip(jnp.asarray(n, jnp.int32), 1, size)
    indices = _draw(weights, n, offsets, method)
    active = jnp.arange(size) < n
    poses = jnp.where(active[:, None], state.poses[indices], 0.0)
    resampled = ParticleState(poses, uniform_log_weights(active), active)
    any_active = jnp.any(state.active)
    new_state = jax.tree.map(lambda a, b: jnp.where(any_active, a, b), resampled, state)
    return new_state, degenerate


class KLDConfig(eqx.Module):
    """KLD-sampling settings (Fox 2001, AMCL's bound). Floats and counts traced; method static.

    Attributes:
        epsilon: bound on the KL divergence (SG2Loc's code: 0.1).
        z: upper standard-normal quantile ``z_{1-delta}`` (1.96).
        bin_sizes: (4,) float32 histogram bins over (x, y, z, yaw): 0.2 m x 3 and 0.2 rad.
        min_particles, max_particles: int32 clamp of the count (500, 10000); the count is also
            capped by the buffer capacity.
        method: ``"stratified"`` (default, as in the paper) or ``"systematic"``.
    """

    epsilon: Array = eqx.field(default=0.1, converter=as_float32)
    z: Array = eqx.field(default=1.96, converter=as_float32)
    bin_sizes: Array = eqx.field(default=(0.2, 0.2, 0.2, 0.2), converter=as_float32)
    min_particles: Array = eqx.field(default=500, converter=as_int32)
    max_particles: Array = eqx.field(default=10000, converter=as_int32)
    method: str = eqx.field(static=True, default="stratified")

    def __check_init__(self):
        _check_method(self.method)
        for name in ("epsilon", "z", "min_particles", "max_particles"):
            if jnp.shape(getattr(self, name)) != ():
                raise ValueError(f"KLDConfig.{name} must be a scalar")
        if jnp.shape(self.bin_sizes) != (4,):
            raise ValueError(f"KLDConfig.bin_sizes must have shape (4,), got {self.bin_sizes}")
        values = [
            getattr(self, f) for f in ("epsilon", "bin_sizes", "min_particles", "max_particles")
        ]
        if any(isinstance(value, jax.core.Tracer) for value in values):
            return
        epsilon, bin_sizes, lower, upper = (np.asarray(value) for value in values)
        if not (epsilon > 0 and np.all(bin_sizes > 0)):
            raise ValueError("KLDConfig.epsilon and bin_sizes must be positive")
        if not 1 <= int(lower) <= int(upper):
            raise ValueError(
                f"need 1 <= min_particles <= max_particles, got {int(lower)}, {int(upper)}"
            )


def kld_for_capacity(capacity: int, kld: KLDConfig | None = None) -> KLDConfig:
    """``kld`` (default :class:`KLDConfig`) for a buffer of ``capacity`` particles: the count may
    fill the buffer (``max_particles = capacity``) and keeps at least ``min_particles`` or the
    whole buffer where it is smaller. What an :class:`~jaxloc.sg2loc.SG2LocConfig` of that
    ``capacity`` is given by the command line."""
    kld = KLDConfig() if kld is None else kld
    lower = min(int(kld.min_particles), capacity)
    return dataclasses.replace(kld, min_particles=lower, max_particles=capacity)


def kld_bound(
    k: Array,
    epsilon: Array | float,
    z: Array | float,
    min_particles: Array | int,
    max_particles: Array | int,
) -> Array:
    """AMCL's KLD-sampling particle count for ``k`` occupied bins (``pf_resample_limit``).

    ``n = ceil((k-1)/(2 eps) * (1 - 2/(9(k-1)) + sqrt(2/(9(k-1))) z)^3)`` clamped to
    ``[min_particles, max_particles]``. For ``k <= 1`` AMCL returns ``max_particles``; here it
    returns ``min_particles``: a single occupied bin is a concentrated posterior, the bound tends
    to 0 as k -> 1, and a filter that has converged should not jump to its largest size.

    Args:
        k: int array of occupied-bin counts (any shape).

    Returns:
        int32 array of the same shape.
    """
    k = jnp.asarray(k, jnp.float32)
    dof = jnp.maximum(k - 1.0, 1.0)
    b = 2.0 / (9.0 * dof)
    x = 1.0 - b + jnp.sqrt(b) * z
    n = jnp.ceil(dof / (2.0 * jnp.asarray(epsilon, jnp.float32)) * x * x * x)
    n = jnp.where(k <= 1.0, 0.0, n)
    n = jnp.clip(
        n, jnp.asarray(min_particles, jnp.float32), jnp.asarray(max_particles, jnp.float32)
    )
    return n.astype(jnp.int32)


def _first_occurrences(bins: Array) -> Array:
    """(M,) bool: row i of ``bins`` (M, 4) int32 is the first row with its value."""
    order = jnp.lexsort((jnp.arange(bins.shape[0]),) + tuple(bins[:, j] for j in (3, 2, 1, 0)))
    sorted_bins = bins[order]
    new = jnp.concatenate(
        [jnp.array([True]), jnp.any(sorted_bins[1:] != sorted_bins[:-1], axis=-1)]
    )
    return jnp.zeros(bins.shape[0], bool).at[order].set(new)


def pose_bins(poses: Array, bin_sizes: Array) -> Array:
    """(M, 4) int32 histogram bins ``floor((x, y, z, wrap(yaw)) / bin_sizes)`` of poses (M, 4)."""
    wrapped = poses.at[:, 3].set(wrap_angle(poses[:, 3]))
    return jnp.clip(jnp.floor(wrapped / bin_sizes), -(2.0**30), 2.0**30).astype(jnp.int32)


class KLDInfo(NamedTuple):
    """Diagnostics of one KLD resampling.

    Attributes:
        num_particles: int32, the chosen count n (the active particles after resampling).
        num_bins: int32, occupied bins k_n among the first n draws.
        degenerate: bool, the weights were unusable and counted as uniform over the active ones.
    """

    num_particles: Array
    num_bins: Array
    degenerate: Array


def kld_sample_count(drawn_poses: Array, config: KLDConfig) -> tuple[Array, Array]:
    """Fox's KLD stopping rule on poses in the order they were drawn.

    Args:
        drawn_poses: (M, 4) float32 poses of M draws from the posterior, in draw order.
        config: :class:`KLDConfig`.

    Returns:
        ``(n, k)``: int32 scalars, the smallest ``n`` (1 <= n <= M) with
        ``n >= kld_bound(k_n)`` where ``k_n`` is the number of distinct bins among the first
        ``n`` draws (the bound clamped to ``[min_particles, min(max_particles, M)]``), and
        ``k = k_n``.
    """
    size = drawn_poses.shape[0]
    first = _first_occurrences(pose_bins(drawn_poses, config.bin_sizes))
    bins_in_prefix = jnp.cumsum(first).astype(jnp.int32)
    upper = jnp.minimum(config.max_particles, size)
    lower = jnp.minimum(config.min_particles, upper)
    bound = kld_bound(bins_in_prefix, config.epsilon, config.z, lower, upper)
    counts = jnp.arange(1, size + 1, dtype=jnp.int32)
    n = jnp.argmax(counts >= bound).astype(jnp.int32) + 1
    return n, bins_in_prefix[n - 1]


def kld_resample(
    key: Array, state: ParticleState, config: KLDConfig | None = None
) -> tuple[ParticleState, KLDInfo]:
    """KLD-sampling: adapt the particle count to the posterior's spread, then resample.

    The procedure is in the module docstring (steps 1-2 here, 3-4 in :func:`kld_sample_count`,
    5 in :func:`resample`). With no active particle the state is returned unchanged and
    ``num_particles`` is 0.

    Returns:
        ``(state, info)``.
    """
    config = KLDConfig() if config is None else config
    size = state.capacity
    # One draw of random bits for all three random steps (each call site of the random number
    # generator is compiled on its own): the counting draw's uniforms, the order's sort keys
    # (ties, rare among 32-bit keys, keep the draw order) and the final draw's uniforms.
    bits = jax.random.bits(key, (3, size), jnp.uint32)
    weights, degenerate = normalized_weights(state.log_weights, state.active)
    draws = _draw(weights, size, _unit(bits[0]), config.method)
    draws = draws[jnp.argsort(bits[1], stable=True)]
    n, bins = kld_sample_count(state.poses[draws], config)
    new_state, _ = _resample(state, n, _unit(bits[2]), config.method)
    any_active = jnp.any(state.active)
    info = KLDInfo(
        num_particles=jnp.where(any_active, n, 0),
        num_bins=jnp.where(any_active, bins, 0),
        degenerate=degenerate,
    )
    return new_state, info
