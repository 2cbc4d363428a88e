"""Particle state of the SG2Loc filter: padded buffers, initialisation, motion model, estimates.

A :class:`ParticleState` holds a static capacity ``N`` of 4-DoF camera poses ``(x, y, z, yaw)``
(metres, radians; world frame, z up, yaw counter-clockwise about +z from +x) with log-weights and
an ``active`` mask. Inactive slots have log-weight ``-inf`` and are never estimated from or drawn.

Initialisation (SG2Loc section 3.1) places poses on a lattice of cells: the region is split into
cells of ``cell_size`` metres (0.2 m in the paper; cells tile the region exactly, so they are at
most ``cell_size`` wide), ``poses_per_cell`` poses (3) are drawn uniformly inside each cell, and
each lattice pose gets a uniform yaw. The region initialiser uses the paper's heights
(1.5, 1.6, 1.7, 1.8 m above the floor) as the vertical levels; the box initialiser (coarse-to-fine
rounds) uses 3-D cells of the same size. A lattice of ``M`` poses fills a buffer of capacity ``N``
as follows: if ``M <= N`` slot ``i < M`` holds lattice pose ``i`` and the rest are inactive; if
``M > N`` the lattice order (cell-major, the poses of one cell consecutive) is split into ``N``
equal strata and slot ``i`` holds a uniformly chosen lattice pose of stratum ``i``, so every part of
the region keeps its share of particles. Region and box sizes are traced: a new region never
recompiles.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from jaxloc.geometry import compose_yaw, wrap_angle

#: The paper's camera heights above the floor (metres).
PAPER_HEIGHTS: tuple[float, ...] = (1.5, 1.6, 1.7, 1.8)

#: Default yaw half-range (radians) of :func:`init_box`: +-45 degrees, the range SG2Loc's final
#: refinement searches around the MLE. A coarse round's MLE is usually within a few degrees when
#: its position is right, so this is generous; it is not meant to rescue a wrong mode.
DEFAULT_BOX_YAW_HALF_RANGE: float = float(jnp.pi / 4)


class ParticleState(eqx.Module):
    """Weighted particles in a padded buffer of static capacity ``N``.

    Attributes:
        poses: (N, 4) float32 camera poses ``(x, y, z, yaw)`` in the world frame (metres, radians,
            yaw in [-pi, pi)).
        log_weights: (N,) float32 log-weights, normalised over the active particles
            (``logsumexp(log_weights[active]) == 0``); ``-inf`` for inactive slots.
        active: (N,) bool, which slots hold particles.
    """

    poses: Array
    log_weights: Array
    active: Array

    @property
    def capacity(self) -> int:
        """The static buffer size ``N``."""
        return self.poses.shape[0]


def _check_shape(name: str, value: Array, shape: tuple[int, ...]) -> None:
    if jnp.shape(value) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {jnp.shape(value)}")


def _check_capacity(capacity: int) -> None:
    if not isinstance(capacity, int) or isinstance(capacity, bool) or capacity <= 0:
        raise ValueError(f"capacity must be a positive Python int, got {capacity!r}")


def _check_positive(name: str, value) -> None:
    """Reject a non-positive or non-finite scalar when it is concrete (tracers pass through)."""
    if isinstance(value, jax.core.Tracer):
        return
    array = np.asarray(value)
    if array.ndim != 0 or not np.isfinite(array) or not array > 0:
        raise ValueError(f"{name} must be a positive finite scalar, got {value!r}")


def _check_finite(name: str, value) -> None:
    """Reject NaN/inf in a concrete array (tracers pass through: under jit, bad values are the
    caller's to flag)."""
    if isinstance(value, jax.core.Tracer):
        return
    if not np.all(np.isfinite(np.asarray(value))):
        raise ValueError(f"{name} must be finite, got {np.asarray(value)}")


def _check_region(lo, hi, heights, floor_z=0.0) -> tuple[Array, Array, Array]:
    """The float32 arrays of a floor region (2,), (2,) and its camera heights (H,), validated
    (shapes; finite values when concrete, ``floor_z`` included)."""
    lo, hi = jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)
    _check_shape("lo", lo, (2,))
    _check_shape("hi", hi, (2,))
    heights = jnp.asarray(heights, jnp.float32)
    if heights.ndim != 1 or heights.shape[0] < 1:
        raise ValueError(f"heights must be a non-empty 1-D array, got shape {heights.shape}")
    for name, value in (("lo", lo), ("hi", hi), ("heights", heights), ("floor_z", floor_z)):
        _check_finite(name, value)
    return lo, hi, heights


def _check_state(state: ParticleState) -> None:
    n = state.poses.shape[0]
    _check_shape("state.poses", state.poses, (n, 4))
    _check_shape("state.log_weights", state.log_weights, (n,))
    _check_shape("state.active", state.active, (n,))


def uniform_log_weights(active: Array) -> Array:
    """(N,) float32 log-weights uniform over ``active`` (N,) bool, ``-inf`` elsewhere.

    With no active slot every entry is ``-inf`` (no NaN).
    """
    count = jnp.sum(active).astype(jnp.float32)
    return jnp.where(active, -jnp.log(jnp.maximum(count, 1.0)), -jnp.inf)


def normalized_weights(log_weights: Array, active: Array) -> tuple[Array, Array]:
    """Probabilities (N,) float32 from log-weights (N,), zero outside ``active`` (N,) bool.

    Returns ``(weights, degenerate)``: when the active log-weights carry no usable mass (all
    ``-inf``, NaN or ``+inf``) the weights are uniform over the active particles and
    ``degenerate`` (bool scalar) is True. With no active particle the weights are all zero.
    """
    usable = active & jnp.isfinite(log_weights)
    top = jnp.max(jnp.where(usable, log_weights, -jnp.inf))
    degenerate = ~jnp.any(usable) | jnp.any(active & (log_weights == jnp.inf))
    degenerate = degenerate | jnp.any(active & jnp.isnan(log_weights))
    safe_top = jnp.where(jnp.isfinite(top), top, 0.0)
    unnormalized = jnp.where(usable, jnp.exp(jnp.where(usable, log_weights - safe_top, 0.0)), 0.0)
    total = jnp.sum(unnormalized)
    weights = unnormalized / jnp.where(total > 0.0, total, 1.0)
    uniform = jnp.exp(uniform_log_weights(active))
    return jnp.where(degenerate, uniform, weights), degenerate


def _lattice_slots(
    key: Array, capacity: int, counts: Array, poses_per_cell: Array | int
) -> tuple[Array, Array, Array, Array]:
    """Fill ``capacity`` slots from a lattice of ``prod(counts) * poses_per_cell`` poses.

    Args:
        counts: (3,) int32 cells along the three lattice axes (each >= 1).
        poses_per_cell: poses drawn inside each cell.

    Returns:
        cells: (capacity, 3) int32 lattice cell of each slot.
        jitter: (capacity, 3) float32 uniform position inside the cell, in [0, 1).
        yaw: (capacity,) float32 uniform yaw in [-pi, pi).
        active: (capacity,) bool.
    """
    # one uniform draw for every slot's stratum, jitter and yaw: each call site of the random
    # number generator is compiled on its own
    u = jax.random.uniform(key, (capacity, 5))
    counts = counts.astype(jnp.int32)
    per_cell = jnp.asarray(poses_per_cell, jnp.int32)
    total = counts[0] * counts[1] * counts[2] * per_cell
    slot = jnp.arange(capacity, dtype=jnp.int32)
    stride = total.astype(jnp.float32) / capacity
    start = jnp.floor(slot * stride).astype(jnp.int32)
    end = jnp.maximum(jnp.floor((slot + 1) * stride).astype(jnp.int32), start + 1)
    stratified = jnp.minimum(start + jnp.floor(u[:, 0] * (end - start)).astype(jnp.int32), end - 1)
    index = jnp.where(total <= capacity, slot, jnp.minimum(stratified, total - 1))
    active = index < total
    cell = index // per_cell
    iz = cell % counts[2]
    iy = (cell // counts[2]) % counts[1]
    ix = cell // (counts[2] * counts[1])
    cells = jnp.stack([ix, iy, iz], axis=-1)
    jitter = u[:, 1:4]
    yaw = u[:, 4] * (2.0 * jnp.pi) - jnp.pi
    return cells, jitter, wrap_angle(yaw), active


def _cell_counts(extent: Array, cell_size: Array) -> Array:
    """Cells (int32, >= 1) of at most ``cell_size`` tiling each ``extent`` (metres)."""
    ratio = extent / jnp.maximum(cell_size, 1e-6)
    return jnp.maximum(jnp.ceil(ratio - 1e-4), 1.0).astype(jnp.int32)


def _state_from(poses: Array, active: Array) -> ParticleState:
    poses = jnp.where(active[:, None], poses, 0.0).astype(jnp.float32)
    return ParticleState(poses, uniform_log_weights(active), active)


def init_region(
    key: Array,
    capacity: int,
    lo: Array,
    hi: Array,
    floor_z: Array | float,
    cell_size: Array | float = 0.2,
    poses_per_cell: Array | int = 3,
    heights: Array | tuple[float, ...] = PAPER_HEIGHTS,
) -> ParticleState:
    """Particles spread over a floor region, as in SG2Loc section 3.1.

    The rectangle ``[lo, hi]`` (x, y in metres, world frame) is tiled by cells of at most
    ``cell_size``; each cell at each height of ``heights`` (metres above ``floor_z``) gets
    ``poses_per_cell`` poses, uniform inside the cell, with uniform yaw in [-pi, pi). That is
    ``nx * ny * len(heights) * poses_per_cell`` lattice poses, fitted into ``capacity`` slots as
    the module docstring describes. Weights are uniform over the active particles.

    Args:
        key: PRNG key.
        capacity: static buffer size N (Python int).
        lo: (2,) float lower corner of the region (metres); a degenerate side gets one cell.
        hi: (2,) float upper corner of the region (metres).
        floor_z: scalar floor height (metres).
        cell_size: cell edge (metres), traced.
        poses_per_cell: poses per cell and height, traced int.
        heights: (H,) camera heights above the floor (metres); H is static.

    Returns:
        A :class:`ParticleState` of capacity N.
    """
    _check_capacity(capacity)
    lo, hi, heights = _check_region(lo, hi, heights, floor_z)
    _check_positive("cell_size", cell_size)
    _check_positive("poses_per_cell", poses_per_cell)
    extent = jnp.maximum(hi - lo, 0.0)
    counts_xy = _cell_counts(extent, jnp.asarray(cell_size, jnp.float32))
    counts = jnp.concatenate([counts_xy, jnp.array([heights.shape[0]], jnp.int32)])
    cells, jitter, yaw, active = _lattice_slots(key, capacity, counts, poses_per_cell)
    cell_edge = extent / counts_xy
    xy = lo + (cells[:, :2] + jitter[:, :2]) * cell_edge
    z = jnp.asarray(floor_z, jnp.float32) + heights[cells[:, 2]]
    return _state_from(jnp.concatenate([xy, z[:, None], yaw[:, None]], axis=-1), active)


def init_box(
    key: Array,
    capacity: int,
    centre: Array,
    half_widths: Array,
    yaw_half_range: Array | float = DEFAULT_BOX_YAW_HALF_RANGE,
    cell_size: Array | float = 0.2,
    poses_per_cell: Array | int = 3,
    centre_valid: Array | None = None,
) -> ParticleState:
    """Particles in a box around a pose (or several), for the coarse-to-fine rounds (section 3.5).

    The box ``centre[:3] +- half_widths`` is tiled by 3-D cells of at most ``cell_size`` with
    ``poses_per_cell`` uniform poses each (the paper's 1.6^3 m box: half-widths 0.8 m, 8^3 cells,
    1536 poses; the 0.8^3 m box: 192 poses). Yaw is uniform in
    ``centre[3] +- yaw_half_range`` (default +-45 degrees, see
    :data:`DEFAULT_BOX_YAW_HALF_RANGE`). With K centres (re-seeding around the top modes of
    :func:`top_modes`) every valid centre gets the same box; the lattices are concatenated box
    by box, so over capacity each valid box keeps an equal share. Fitted into ``capacity`` slots
    as the module docstring describes; weights uniform over the active particles.

    Args:
        key: PRNG key.
        capacity: static buffer size N (Python int).
        centre: (4,) or (K, 4) float poses ``(x, y, z, yaw)`` (metres, radians).
        half_widths: (3,) float half-widths of the box along world x, y, z (metres), traced.
        yaw_half_range: yaw half-range (radians), traced; ``pi`` gives uniform yaw.
        cell_size: cell edge (metres), traced.
        poses_per_cell: poses per cell, traced int.
        centre_valid: optional (K,) bool, which centres to use (default all); with none valid
            every slot is inactive.
    """
    _check_capacity(capacity)
    centres = jnp.asarray(centre, jnp.float32)
    centres = centres[None] if centres.ndim == 1 else centres
    if centres.ndim != 2 or centres.shape[1] != 4:
        raise ValueError(f"centre must have shape (4,) or (K, 4), got {jnp.shape(centre)}")
    _check_finite("centre", centres)
    num_centres = centres.shape[0]
    valid = jnp.ones(num_centres, bool) if centre_valid is None else jnp.asarray(centre_valid)
    _check_shape("centre_valid", valid, (num_centres,))
    half_widths = jnp.asarray(half_widths, jnp.float32)
    _check_shape("half_widths", half_widths, (3,))
    _check_finite("half_widths", half_widths)
    _check_positive("cell_size", cell_size)
    _check_positive("poses_per_cell", poses_per_cell)
    extent = 2.0 * jnp.maximum(half_widths, 0.0)
    counts = _cell_counts(extent, jnp.asarray(cell_size, jnp.float32))
    num_valid = jnp.sum(valid).astype(jnp.int32)
    stacked = counts.at[0].multiply(num_valid)  # the boxes one after another along x
    cells, jitter, yaw, active = _lattice_slots(key, capacity, stacked, poses_per_cell)
    valid_centres = centres[jnp.argsort(~valid, stable=True)]
    box_centre = valid_centres[jnp.minimum(cells[:, 0] // counts[0], num_centres - 1)]
    local = cells.at[:, 0].set(cells[:, 0] % counts[0])
    position = box_centre[:, :3] - 0.5 * extent + (local + jitter) * (extent / counts)
    yaw = box_centre[:, 3] + yaw / jnp.pi * jnp.asarray(yaw_half_range, jnp.float32)
    return _state_from(jnp.concatenate([position, wrap_angle(yaw)[:, None]], axis=-1), active)


def predict(
    key: Array,
    state: ParticleState,
    motion: Array,
    sigma_trans: Array | float = 0.05,
    sigma_rot: Array | float = 0.05,
) -> ParticleState:
    """Motion model (SG2Loc eq. 1): ``s' = s (+) (motion + noise)`` for every particle.

    ``motion = (dx, dy, dz, dyaw)`` (4,) is the ego-motion from this frame to the next in the
    camera's gravity-aligned body frame (x forward, y left, z up; metres, radians). Each particle
    gets i.i.d. Gaussian noise (``sigma_trans`` metres on dx, dy, dz and ``sigma_rot`` radians on
    dyaw) in its own body frame, and the sum is composed with
    :func:`jaxloc.geometry.compose_yaw`. Weights and the active mask are unchanged.
    """
    _check_state(state)
    motion = jnp.asarray(motion, jnp.float32)
    _check_shape("motion", motion, (4,))
    _check_finite("motion", motion)
    sigmas = jnp.stack(
        [jnp.asarray(sigma_trans, jnp.float32)] * 3 + [jnp.asarray(sigma_rot, jnp.float32)]
    )
    noise = jax.random.normal(key, state.poses.shape, jnp.float32) * sigmas
    poses = jax.vmap(compose_yaw)(state.poses, motion + noise)
    return eqx.tree_at(lambda s: s.poses, state, poses)


def update_weights(state: ParticleState, log_likelihoods: Array) -> tuple[ParticleState, Array]:
    """Bayes update in log space: ``log w' = log w + log L``, renormalised over active particles.

    Args:
        state: particles.
        log_likelihoods: (N,) float32 log-likelihood of each particle's observation.

    Returns:
        ``(state, degenerate)``: when no active particle keeps a finite log-weight (every
        likelihood underflowed to ``-inf``, or NaN/``+inf`` appeared) the weights fall back to
        uniform over the active particles and ``degenerate`` (bool scalar) is True.
    """
    _check_state(state)
    _check_shape("log_likelihoods", log_likelihoods, state.log_weights.shape)
    combined = state.log_weights + log_likelihoods
    usable = state.active & jnp.isfinite(combined)
    degenerate = ~jnp.any(usable) | jnp.any(state.active & jnp.isnan(combined))
    degenerate = degenerate | jnp.any(state.active & (combined == jnp.inf))
    masked = jnp.where(usable, combined, -jnp.inf)
    total = jax.nn.logsumexp(jnp.where(degenerate, -jnp.inf, masked))
    normalized = jnp.where(usable, masked - jnp.where(jnp.isfinite(total), total, 0.0), -jnp.inf)
    log_weights = jnp.where(degenerate, uniform_log_weights(state.active), normalized)
    return eqx.tree_at(lambda s: s.log_weights, state, log_weights), degenerate


def effective_sample_size(state: ParticleState) -> Array:
    """Kish's effective sample size ``1 / sum w_i^2`` (float32; 0 with no active particle)."""
    weights, _ = normalized_weights(state.log_weights, state.active)
    squares = jnp.sum(weights**2)
    return jnp.where(squares > 0.0, 1.0 / jnp.where(squares > 0.0, squares, 1.0), 0.0)


def mle(state: ParticleState) -> tuple[Array, Array]:
    """The maximum-likelihood estimate: the active particle with the highest log-weight.

    Returns:
        ``(pose, index)``: (4,) float32 pose and int32 slot index. Ties go to the lowest index;
        with no active particle this is slot 0.
    """
    _check_state(state)
    scores = jnp.where(state.active & ~jnp.isnan(state.log_weights), state.log_weights, -jnp.inf)
    index = jnp.argmax(scores).astype(jnp.int32)
    return state.poses[index], index


def weighted_mean(state: ParticleState) -> Array:
    """Weighted mean pose (4,) float32: arithmetic mean of x, y, z, circular mean of yaw.

    Degenerate weights count as uniform over the active particles (see
    :func:`normalized_weights`); with no active particle this is all zeros. When the yaws cancel
    out exactly (zero resultant) the yaw is 0.
    """
    _check_state(state)
    weights, _ = normalized_weights(state.log_weights, state.active)
    safe_poses = jnp.where(state.active[:, None], state.poses, 0.0)
    position = jnp.matmul(weights, safe_poses[:, :3], precision="highest")
    sin, cos = jnp.sin(safe_poses[:, 3]), jnp.cos(safe_poses[:, 3])
    yaw = jnp.arctan2(
        jnp.dot(weights, sin, precision="highest"), jnp.dot(weights, cos, precision="highest")
    )
    return jnp.concatenate([position, wrap_angle(yaw)[None]])


def top_modes(
    state: ParticleState,
    num_modes: int,
    radius: Array | float = 0.8,
    yaw_radius: Array | float = DEFAULT_BOX_YAW_HALF_RANGE,
) -> tuple[Array, Array, Array]:
    """The ``num_modes`` strongest modes by greedy non-maximum suppression on the weights.

    Repeatedly: the heaviest particle not yet claimed becomes a mode; it claims every unclaimed
    active particle within ``radius`` metres (3-D distance) and ``yaw_radius`` radians of it, and
    the mode's weight is the claimed probability mass. Defaults match the first coarse-to-fine
    re-seeding box (0.8 m half-width, +-45 degrees), so boxes around distinct modes do not
    duplicate each other's core.

    Args:
        state: particles.
        num_modes: static K.
        radius: suppression radius (metres), traced.
        yaw_radius: yaw suppression radius (radians), traced.

    Returns:
        poses: (K, 4) float32, the pose of each mode's heaviest particle (zeros if invalid).
        weights: (K,) float32 probability mass claimed by each mode (0 if invalid); modes come
            in decreasing order of their heaviest particle, not necessarily of their mass.
        valid: (K,) bool, False once no unclaimed particle is left.
    """
    _check_state(state)
    if not isinstance(num_modes, int) or num_modes <= 0:
        raise ValueError(f"num_modes must be a positive Python int, got {num_modes!r}")
    weights, _ = normalized_weights(state.log_weights, state.active)
    radius = jnp.asarray(radius, jnp.float32)
    yaw_radius = jnp.asarray(yaw_radius, jnp.float32)

    def pick(unclaimed: Array, _) -> tuple[Array, tuple[Array, Array, Array]]:
        index = jnp.argmax(jnp.where(unclaimed, weights, -1.0))
        valid = unclaimed[index]
        centre = state.poses[index]
        distance = jnp.linalg.norm(state.poses[:, :3] - centre[:3], axis=-1)
        yaw_gap = jnp.abs(wrap_angle(state.poses[:, 3] - centre[3]))
        claimed = unclaimed & (distance <= radius) & (yaw_gap <= yaw_radius) & valid
        claimed = claimed.at[index].set(valid)
        mass = jnp.sum(jnp.where(claimed, weights, 0.0))
        pose = jnp.where(valid, centre, 0.0)
        return unclaimed & ~claimed, (pose, jnp.where(valid, mass, 0.0), valid)

    _, (poses, masses, valid) = jax.lax.scan(pick, state.active, None, length=num_modes)
    return poses, masses, valid


def inject_uniform(
    key: Array,
    state: ParticleState,
    count: Array | int,
    lo: Array,
    hi: Array,
    floor_z: Array | float,
    heights: Array | tuple[float, ...] = PAPER_HEIGHTS,
) -> ParticleState:
    """Recovery: replace the ``count`` weakest particles by uniform random ones over a region.

    Inactive slots are filled first, then the active particles with the lowest log-weights (ties
    to the lowest index). A new particle has x, y uniform in ``[lo, hi]``, z = ``floor_z`` plus a
    uniformly chosen height of ``heights``, yaw uniform in [-pi, pi), and the mean weight of the
    active particles before injection (if none has a finite log-weight, the new particles share
    all the mass); the weights are then renormalised. ``count`` is traced (clamped to [0, N]), so
    a schedule such as SG2Loc's reference (2000 every 5th frame, 0 otherwise) runs in one
    compiled step.

    Args:
        key: PRNG key.
        state: particles.
        count: number of particles to replace (traced int).
        lo: (2,) float lower region corner (metres).
        hi: (2,) float upper region corner (metres).
        floor_z: scalar floor height (metres).
        heights: (H,) heights above the floor (metres).
    """
    _check_state(state)
    lo, hi, heights = _check_region(lo, hi, heights, floor_z)
    n = state.capacity
    # one uniform draw for all the new particles' coordinates: each call site of the random
    # number generator is compiled on its own
    u = jax.random.uniform(key, (n, 4))
    xy = lo + u[:, :2] * (jnp.maximum(hi, lo) - lo)
    choice = jnp.minimum(
        jnp.floor(u[:, 2] * heights.shape[0]).astype(jnp.int32), heights.shape[0] - 1
    )
    z = jnp.asarray(floor_z, jnp.float32) + heights[choice]
    yaw = wrap_angle(u[:, 3] * (2.0 * jnp.pi) - jnp.pi)
    fresh = jnp.concatenate([xy, z[:, None], yaw[:, None]], axis=-1)

    usable = state.active & jnp.isfinite(state.log_weights)
    log_weights = jnp.where(usable, state.log_weights, -jnp.inf)
    # inactive slots first, then the active ones by log-weight (unusable ones lowest), ties in
    # slot order: one sort key
    lowest = jnp.finfo(jnp.float32).min
    order = jnp.argsort(
        jnp.where(state.active, jnp.maximum(log_weights, lowest), -jnp.inf), stable=True
    )
    rank = jnp.zeros(n, jnp.int32).at[order].set(jnp.arange(n, dtype=jnp.int32))
    replace = rank < jnp.clip(jnp.asarray(count, jnp.int32), 0, n)

    num_active = jnp.sum(state.active).astype(jnp.float32)
    total = jax.nn.logsumexp(log_weights)
    mean_log_weight = jnp.where(
        jnp.isfinite(total), total - jnp.log(jnp.maximum(num_active, 1.0)), 0.0
    )
    active = state.active | replace
    log_weights = jnp.where(replace, mean_log_weight, log_weights)
    total = jax.nn.logsumexp(log_weights)
    log_weights = jnp.where(
        active, log_weights - jnp.where(jnp.isfinite(total), total, 0.0), -jnp.inf
    )
    poses = jnp.where(replace[:, None], fresh, state.poses)
    return ParticleState(poses, log_weights, active)
